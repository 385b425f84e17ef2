"""Energy-based episode prioritisation (``replay_priority=energy``) against plain numpy."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rdher_jax import buffer as rb
from rdher_jax import executor
from rdher_jax.config import Config, ConfigError, resolve
from rdher_jax.relabel import HER, REAL, RelabelParams, make_her_energy, trajectory_energy
from rdher_jax.relabel.energy import draw_episodes


def energy_loop(ag: np.ndarray, clip: float) -> float:
    """The EBP authors' trajectory energy of one episode, step by step (float64)."""
    g, m, dt = 9.81, 1.0, 0.04
    total_prev, out = None, 0.0
    for t in range(1, len(ag)):
        potential = g * m * (ag[t, 2] - ag[0, 2])
        v = (ag[t] - ag[t - 1]) / dt
        total = potential + 0.5 * m * float(v @ v)
        e = total if total_prev is None else total - total_prev
        out += min(max(e, 0.0), clip)
        total_prev = total
    return out


def random_episodes(rng, n, T, resting=()):
    """Achieved goals of ``n`` episodes: a random walk of the object, or at rest."""
    start = rng.uniform(-0.2, 0.2, (n, 1, 3)) + np.array([1.3, 0.75, 0.42])
    steps = rng.normal(0, 0.01, (n, T, 3))
    ag = np.concatenate([start, start + np.cumsum(steps, axis=1)], axis=1)
    for i in resting:
        ag[i] = ag[i, :1]
    return ag.astype(np.float32)


@pytest.mark.parametrize("clip", [0.5, 0.01, 999.0])
def test_trajectory_energy_matches_the_authors_loop(clip):
    rng = np.random.default_rng(0)
    ag = random_episodes(rng, 6, 10, resting=(2,))
    got = np.asarray(trajectory_energy(jnp.asarray(ag), clip))
    want = np.array([energy_loop(ag[i].astype(np.float64), clip) for i in range(6)])
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-5)
    assert got[2] == 0.0 and (np.delete(got, 2) > 0).all()


def test_episode_draw_follows_the_weights():
    cap = 8
    w = np.array([0.0, 1.0, 3.0, 0.0, 2.0, 0, 0, 0], np.float32)
    bits = jax.random.bits(jax.random.PRNGKey(0), (200_000,), jnp.uint32)
    idx = np.asarray(draw_episodes(bits, jnp.cumsum(jnp.asarray(w)), jnp.int32(5)))
    freq = np.bincount(idx, minlength=cap) / idx.size
    np.testing.assert_allclose(freq, w / w.sum(), atol=0.005)
    assert freq[0] == 0.0 and freq[3] == 0.0 and freq[5:].sum() == 0.0


def test_episode_draw_is_uniform_while_no_episode_has_energy():
    bits = jax.random.bits(jax.random.PRNGKey(1), (100_000,), jnp.uint32)
    idx = np.asarray(draw_episodes(bits, jnp.zeros((8,), jnp.float32), jnp.int32(5)))
    freq = np.bincount(idx, minlength=8) / idx.size
    np.testing.assert_allclose(freq[:5], 0.2, atol=0.01)
    assert freq[5:].sum() == 0.0


def test_relabeller_tracks_the_ring_and_draws_only_episodes_that_moved():
    T, cap, clip = 10, 4, 0.5
    reward = lambda ag, g: -(jnp.linalg.norm(ag - g, axis=-1) > 0.05).astype(jnp.float32)  # noqa: E731
    rel = make_her_energy(reward, batch_size=512, capacity_episodes=cap, num_new=1, clip=clip)
    params = RelabelParams.default()
    buf = rb.init(cap * T, T, obs_dim=5, goal_dim=3, act_dim=2)
    state = rel.init()
    rng = np.random.default_rng(3)
    ags = random_episodes(rng, 6, T, resting=(1, 4, 5))
    for i in range(6):  # two past capacity: slots 0 and 1 are overwritten by episodes 4, 5
        ep = rb.Episode(obs=jnp.asarray(rng.normal(size=(1, T + 1, 5)), jnp.float32),
                        ag=jnp.asarray(ags[i:i + 1]), g=jnp.asarray(ags[i:i + 1] + 0.1),
                        action=jnp.zeros((1, T, 2), jnp.float32))
        buf = rb.add(buf, ep)
        state = rel.update(state, buf, params)
    # Slot k holds episode 4, 5, 2, 3: the resting ones (4, 5) weigh 0.
    want = [energy_loop(ags[i].astype(np.float64), clip) for i in (4, 5, 2, 3)]
    np.testing.assert_allclose(np.asarray(state.energy), want, rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.cumulative), np.cumsum(want), rtol=2e-4)

    batch = jax.jit(rel.sample)(jax.random.PRNGKey(0), state, buf, params, jnp.int32(0))
    ep = np.asarray(batch.ep)
    assert set(np.unique(ep)) == {2, 3}
    # The rows are HER's: relabelled ones take a strictly future achieved goal of their episode.
    her = np.asarray(batch.source) == HER
    assert 0.7 < her.mean() < 0.9 and set(np.unique(batch.source)) <= {REAL, HER}
    t = np.asarray(batch.t)
    buf_ag, goal = np.asarray(buf.ag), np.asarray(batch.goal)
    for i in np.flatnonzero(her)[:50]:
        matches = [k for k in range(t[i] + 1, T + 1) if np.array_equal(buf_ag[ep[i], k], goal[i])]
        assert matches, i
    np.testing.assert_array_equal(np.asarray(batch.obs), np.asarray(buf.obs)[ep, t])


def test_config_errors():
    with pytest.raises(ConfigError, match="applies to ddpg, her, archer, not rdher"):
        resolve(Config(algo="rdher", replay_priority="energy"))
    with pytest.raises(ConfigError, match="energy_clip must be"):
        resolve(Config(replay_priority="energy", energy_clip=0.0))
    with pytest.raises(ConfigError, match="unknown replay_priority"):
        resolve(Config(replay_priority="rank"))


def test_trainer_writes_the_stored_episodes_energies(tmp_path):
    cfg = resolve(Config(env="FetchPush", algo="her", replay_priority="energy", n_cycles=3,
                         n_batches=4, batch_size=32, buffer_size=2000, num_envs=2,
                         n_test_rollouts=2, hidden=32, progress=False, run_dir=str(tmp_path)))
    env, trainer = executor.build(cfg)
    hp = trainer.hparams
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    ts, m = jax.jit(trainer.epoch)(ts, hp)
    n = int(ts.buffer.num_episodes)
    assert n == 6
    got = np.asarray(ts.relabel.energy)
    want = np.asarray(trajectory_energy(ts.buffer.ag[:n], cfg.energy_clip))
    np.testing.assert_array_equal(got[:n], want)
    assert (got[n:] == 0).all()
    assert math.isfinite(float(m.critic_loss))
