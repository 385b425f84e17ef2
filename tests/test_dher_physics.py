"""DHER's combined rows on real FetchPushMoving episodes, checked by hand against Algorithm 1.

``tests/test_relabel.py`` checks the matcher and the combination on synthetic integer-grid
episodes. Here the buffer holds episodes of the real task: the trainer's own ``cycle`` collects
them with the native physics and its exploring initial policy, stores them and updates the DHER
state, as a training run does. The checks then read the buffer arrays in numpy:

- every live match record ``(i, p, j, q)`` pairs two distinct failed episodes with
  ``ag[i, p]`` and ``g[j, q]`` in the same ``dher_tol`` cell;
- the combined window of a record gives E_i's steps ``p - m ... p - 1`` (``m = min(p, q)``)
  E_j's goals ``g[j, q - m + t]`` in order, the next-goal column is that shifted by one, and the
  reward is ``compute_reward(ag[i, p - m + t + 1], g[j, q - m + t + 1])``;
- the DHER rows of the relabeller's ``sample`` are such rows of live records.

Why matches occur with a barely trained policy: the object starts at the gripper's x + 0.1 in
every episode and mostly stays where it is, while a goal whose x falls in that 1 cm column sweeps
along y at 5 mm per step through the objects of other episodes. A deliberate off-by-one in the
goal index must make the check fail (``test_the_check_catches_a_goal_index_off_by_one``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rdher_jax import executor
from rdher_jax.config import parse_args, resolve
from rdher_jax.relabel import dher
from rdher_jax.relabel.base import DHER

SEED = 0
NUM_ENVS, CYCLES, SLOTS = 16, 6, 64  # 96 episodes into 64 slots: records of overwritten slots die
ARGS = [
    "env=FetchPushMoving", "algo=dher", "backend=mujoco", f"num_envs={NUM_ENVS}",
    f"buffer_size={SLOTS * 50}", "batch_size=256", "n_batches=1", "hidden=16", "layers=1",
    "n_cycles=1", "n_test_rollouts=1", "run_dir=unused",
]


def sample_rows(relabeller, key, state, buffer, params):
    """The relabeller's batch, whether ``sample`` returns ``(state, Transition)`` or the
    ``Transition`` alone."""
    out = relabeller.sample(key, state, buffer, params, jnp.int32(0))
    return out[-1] if isinstance(out, tuple) else out


def reward_np(achieved, desired, threshold):
    return -(np.linalg.norm(achieved - desired, axis=-1) > threshold).astype(np.float32)


@pytest.fixture(scope="module")
def run():
    cfg = resolve(parse_args(ARGS))
    env, trainer = executor.build(cfg)
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(SEED), trainer.hparams)
    cycle = jax.jit(trainer.cycle)
    for _ in range(CYCLES):
        ts, _ = cycle(ts, trainer.hparams)
    b, st = ts.buffer, ts.relabel
    T = env.episode_length
    fns = dher.build_dher(env.compute_reward, cfg.batch_size, b.capacity_episodes, T,
                          env.goal_size, num_new=cfg.num_envs, records=cfg.dher_records,
                          partners=cfg.dher_partners)
    n = int(st.rec_count)
    gather = jax.jit(fns.gather_combined)
    rec = np.stack([np.asarray(getattr(st, f))[:n]
                    for f in ("rec_i", "rec_p", "rec_j", "rec_q", "rec_gi", "rec_gj")], 1)
    gen = np.asarray(st.slot_gen)
    live = (rec[:, 4] == gen[rec[:, 0]]) & (rec[:, 5] == gen[rec[:, 2]])
    arrays = {k: np.asarray(getattr(b, k)) for k in ("obs", "ag", "g", "action")}
    return dict(cfg=cfg, env=env, trainer=trainer, ts=ts, gather=gather, rec=rec, live=live, T=T,
                thr=float(env.distance_threshold), tol=np.float32(cfg.dher_tol), **arrays)


def failed(run, slot):
    T = run["T"]
    return reward_np(run["ag"][slot, T], run["g"][slot, T], run["thr"]) < 0


def window(run, r):
    """The combined rows of record ``r`` for every offset ``t`` in ``[0, m)``, from
    ``gather_combined`` with draws that pick exactly that record and offset (``T`` draws, one
    compiled shape; the offset draw is taken modulo ``m``, so the first ``m`` are the window)."""
    _, p, _, q = (int(x) for x in run["rec"][r, :4])
    m = min(p, q)
    T = run["T"]
    bits = jnp.stack([jnp.full((T,), r, jnp.uint32), jnp.arange(T, dtype=jnp.uint32)])
    ts = run["ts"]
    rows, ok = run["gather"](bits, ts.relabel, ts.buffer, run["trainer"].hparams.relabel)
    return jax.tree.map(lambda x: np.asarray(x)[:m], rows), np.asarray(ok)[:m]


def check_window(run, r, rows, goal_offset=0):
    """Algorithm 1 by hand for record ``r``; ``goal_offset`` shifts the goal index the check
    expects (0 is the definition; anything else must fail)."""
    i, p, j, q = (int(x) for x in run["rec"][r, :4])
    m = min(p, q)
    obs, ag, g, act, thr = run["obs"], run["ag"], run["g"], run["action"], run["thr"]
    s = p - m + np.arange(m)  # E_i's steps p - m ... p - 1
    # E_j's goal index at each of them (a shifted index is held inside E_j's episode).
    k = np.clip(q - m + np.arange(m) + goal_offset, 0, run["T"] - 1)
    np.testing.assert_array_equal(rows.ep, i)
    np.testing.assert_array_equal(rows.goal_ep, j)
    np.testing.assert_array_equal(rows.t, s)
    np.testing.assert_array_equal(rows.goal_shift, q - p)
    np.testing.assert_array_equal(rows.source, DHER)
    np.testing.assert_array_equal(rows.obs, obs[i, s])
    np.testing.assert_array_equal(rows.action, act[i, s])
    np.testing.assert_array_equal(rows.next_obs, obs[i, s + 1])
    # The cloned goal trajectory, in order, and the next-goal column one step later.
    np.testing.assert_array_equal(rows.goal, g[j, k])
    np.testing.assert_array_equal(rows.next_goal, g[j, k + 1])
    np.testing.assert_array_equal(rows.next_goal[:-1], rows.goal[1:])
    # Rewards on (E_i's next achieved goal, E_j's next desired goal), by numpy and by the env.
    want = reward_np(ag[i, s + 1], g[j, k + 1], thr)
    np.testing.assert_array_equal(rows.reward, want)
    env_r = np.asarray(run["env"].compute_reward(jnp.asarray(ag[i, s + 1]),
                                                 jnp.asarray(g[j, k + 1])))
    np.testing.assert_array_equal(rows.reward, env_r)


def chosen_records(run, n=8):
    """Up to ``n`` live records: the longest window of each goal-providing episode first, then
    the longest remaining ones."""
    rec, live = run["rec"], run["live"]
    idx = np.flatnonzero(live)
    m = np.minimum(rec[idx, 1], rec[idx, 3])
    order = idx[np.argsort(-m, kind="stable")]
    picked, seen_j = [], set()
    for r in order:
        if rec[r, 2] not in seen_j:
            picked.append(int(r))
            seen_j.add(rec[r, 2])
    picked += [int(r) for r in order if int(r) not in picked]
    return picked[:n]


def test_collection_has_live_and_dead_records(run):
    """The setting is one where DHER has work: many live records over several goal-providing
    episodes, and overwritten slots whose records died."""
    rec, live = run["rec"], run["live"]
    assert int(run["ts"].buffer.num_episodes) == SLOTS
    assert live.sum() >= 20, live.sum()
    assert len(set(rec[live, 2])) >= 2
    assert (~live).any()


def test_live_records_are_matches_of_failed_episodes(run):
    rec, live, tol, T = run["rec"], run["live"], run["tol"], run["T"]
    i, p, j, q = rec[live, :4].T
    assert np.all(i != j)
    assert np.all((p >= 1) & (p <= T) & (q >= 1) & (q <= T))
    assert all(failed(run, s) for s in np.unique(np.concatenate([i, j])))
    np.testing.assert_array_equal(np.round(run["ag"][i, p] / tol), np.round(run["g"][j, q] / tol))


def test_combined_windows_follow_algorithm_1(run):
    picked = chosen_records(run)
    assert len(picked) >= 4
    for r in picked:
        rows, ok = window(run, r)
        assert ok.all()
        check_window(run, r, rows)


def test_dead_records_give_no_rows(run):
    dead = np.flatnonzero(~run["live"])[:8]
    for r in dead:
        _, ok = window(run, int(r))
        assert not ok.any()


def test_the_check_catches_a_goal_index_off_by_one(run):
    """The same check, expecting E_j's goals one step late or early, rejects the real rows: the
    goal moves 5 mm per step, so a shifted trajectory differs."""
    for offset in (1, -1):
        caught = 0
        for r in chosen_records(run):
            rows, _ = window(run, r)
            try:
                check_window(run, r, rows, goal_offset=offset)
            except AssertionError:
                caught += 1
        assert caught >= 3, (offset, caught)


def test_sampled_dher_rows_are_rows_of_live_records(run):
    ts, trainer, rec, live = run["ts"], run["trainer"], run["rec"], run["live"]
    obs, ag, g, act, thr = run["obs"], run["ag"], run["g"], run["action"], run["thr"]
    sample = jax.jit(lambda *a: sample_rows(trainer.relabeller, *a))
    rows = jax.tree.map(np.asarray, sample(jax.random.PRNGKey(1), ts.relabel, ts.buffer,
                                           trainer.hparams.relabel))
    idx = np.flatnonzero(rows.source == DHER)
    assert idx.size >= 50, idx.size  # ~ dher_fraction * (1 - success rate) of 256 rows
    li, lp, lj, lq = rec[live, :4].T
    lm = np.minimum(lp, lq)
    for r in idx:
        i, s, j, shift = rows.ep[r], rows.t[r], rows.goal_ep[r], rows.goal_shift[r]
        hit = (li == i) & (lj == j) & (lq - lp == shift) & (lp - lm <= s) & (s < lp)
        assert hit.any(), f"row {r} is no live record's"
        np.testing.assert_array_equal(rows.obs[r], obs[i, s])
        np.testing.assert_array_equal(rows.action[r], act[i, s])
        np.testing.assert_array_equal(rows.next_obs[r], obs[i, s + 1])
        np.testing.assert_array_equal(rows.goal[r], g[j, s + shift])
        np.testing.assert_array_equal(rows.next_goal[r], g[j, s + shift + 1])
        assert rows.reward[r] == reward_np(ag[i, s + 1], g[j, s + shift + 1], thr)
