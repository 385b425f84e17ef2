"""Tests for the DDPG core: targets, losses, optimiser steps, exploration and normalisation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import update_many

from rdher_jax.ddpg import DDPGParams, DDPGState, critic_target, make_ddpg, target_subset
from rdher_jax.relabel import Transition

OBS, GOAL, ACT = 4, 3, 2
MAX_U, CLIP_OBS, NORM_EPS, NORM_CLIP = 2.0, 6.0, 0.01, 5.0
B = 32  # one batch size throughout, so each jitted function compiles once for the file

# One small configuration shared by all tests, its functions jitted once (compiles dominate the
# run time of this file).
D = make_ddpg(
    OBS,
    GOAL,
    ACT,
    hidden=(8, 8),
    max_u=MAX_U,
    clip_obs=CLIP_OBS,
    norm_eps=NORM_EPS,
    norm_clip=NORM_CLIP,
)
init = jax.jit(D.init)
update_normaliser = jax.jit(D.update_normaliser)
normalise = jax.jit(D.normalise)
act = jax.jit(D.act)
explore = jax.jit(D.explore)
update = jax.jit(D.update)
target_update = jax.jit(D.target_update)


@jax.jit
def losses(state: DDPGState, batch: Transition, h: DDPGParams) -> tuple[jax.Array, ...]:
    """(critic loss, mean Q, actor loss) at the state's online parameters."""
    c_loss, q_mean = D.critic_loss(state.critic_params, state, batch, h)
    return c_loss, q_mean, D.actor_loss(state.actor_params, state, batch, h)


def _batch(seed: int, n: int = B) -> Transition:
    """Random batch with rewards in {-1, 0} and rows of every source."""
    rng = np.random.default_rng(seed)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    return Transition(
        obs=f32(rng.normal(1.0, 2.0, (n, OBS))),
        goal=f32(rng.normal(0.0, 2.0, (n, GOAL))),
        action=f32(rng.uniform(-MAX_U, MAX_U, (n, ACT))),
        reward=f32(-(rng.random(n) < 0.5).astype(np.float32)),
        next_obs=f32(rng.normal(1.0, 2.0, (n, OBS))),
        next_goal=f32(rng.normal(0.0, 2.0, (n, GOAL))),
        # Rows cycle through the three sources: real, HER-relabelled, DHER-combined.
        source=jnp.asarray(np.arange(n) % 3, jnp.int32),
        ep=jnp.zeros(n, jnp.int32), t=jnp.zeros(n, jnp.int32),
        goal_ep=jnp.zeros(n, jnp.int32), goal_shift=jnp.zeros(n, jnp.int32),
    )


def _state(h: DDPGParams, norm_data: Transition) -> DDPGState:
    """Initialised state with distinct target networks and a non-trivial normaliser."""
    state = init(jax.random.key(0), h)
    other = init(jax.random.key(1), h)
    state = state.replace(
        target_actor_params=other.actor_params, target_critic_params=other.critic_params
    )
    return update_normaliser(state, norm_data.obs, norm_data.goal)


def _assert_trees_close(a, b, rtol: float = 1e-5, atol: float = 1e-6) -> None:
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def _np_normalise(x: np.ndarray, data: np.ndarray, clip_obs: float, eps: float, clip: float):
    """Baselines' Normalizer: std = sqrt(max(eps^2, E[x^2] - E[x]^2)), after _preprocess_og."""
    data = np.clip(np.asarray(data, np.float64), -clip_obs, clip_obs)
    mean = data.mean(0)
    std = np.sqrt(np.maximum(eps**2, (data**2).mean(0) - mean**2))
    x = np.clip(np.asarray(x, np.float64), -clip_obs, clip_obs)
    return np.clip((x - mean) / std, -clip, clip), mean, std


def _np_mlp(params, x: np.ndarray) -> np.ndarray:
    layers = params["params"]["mlp"]
    n_hidden = len(layers) - 1
    for i in range(n_hidden):
        layer = layers[f"hidden_{i}"]
        x = np.maximum(x @ np.asarray(layer["kernel"], np.float64) + np.asarray(layer["bias"]), 0)
    return x @ np.asarray(layers["out"]["kernel"], np.float64) + np.asarray(layers["out"]["bias"])


def _np_actor(params, o, g, max_u):
    return max_u * np.tanh(_np_mlp(params, np.concatenate([o, g], -1)))


def _np_critic(params, o, g, a, max_u):
    return _np_mlp(params, np.concatenate([o, g, a / max_u], -1))[:, 0]


def test_hparams_default_and_overrides():
    h = DDPGParams.default(T=50, lambda_h=0.5)
    for leaf in jax.tree.leaves(h):
        assert leaf.shape == () and leaf.dtype == jnp.float32
    assert float(h.gamma) == pytest.approx(0.98)
    assert float(h.lambda_h) == 0.5 and float(h.lambda_r) == 1.0
    assert float(DDPGParams.default(T=100).gamma) == pytest.approx(0.99)
    with pytest.raises(TypeError):
        DDPGParams.default(learning_rate=1e-3)


def test_critic_target_table():
    h = DDPGParams.default(lambda_r=1.0, lambda_h=0.5, gamma=0.9)  # bounds: real -10, hindsight -5
    table = np.array(
        # reward, q_next, hindsight, expected y
        [
            [-1.0, -2.0, 0, -2.8],
            [-1.0, -2.0, 1, -2.3],  # -0.5 - 1.8
            [0.0, 3.0, 0, 0.0],  # 2.7 clipped at the top
            [0.0, 3.0, 1, 0.0],
            [-1.0, -20.0, 0, -10.0],  # -19 clipped at -1 / (1 - 0.9)
            [-1.0, -20.0, 1, -5.0],  # -18.5 clipped at -0.5 / (1 - 0.9)
            [0.0, -8.0, 1, -5.0],  # -7.2 is inside the real range but outside the hindsight one
            [0.0, -8.0, 0, -7.2],
            [-1.0, 0.0, 1, -0.5],
            [-1.0, 0.0, 0, -1.0],
        ],
        np.float32,
    )
    reward, q_next = jnp.asarray(table[:, 0]), jnp.asarray(table[:, 1])
    hindsight = jnp.asarray(table[:, 2] > 0)
    y, grad = _target_and_grad(reward, q_next, hindsight, h)
    np.testing.assert_allclose(np.asarray(y), table[:, 3], rtol=1e-6, atol=1e-6)
    assert np.all(np.asarray(grad) == 0.0)  # the target is a constant for the critic

    # Equal lambdas reduce to baselines' clip to [-1 / (1 - gamma), 0] = [-50, 0].
    y, _ = _target_and_grad(reward, q_next - 60.0, hindsight, DDPGParams.default())
    expected = np.clip(table[:, 0] + 0.98 * (table[:, 1] - 60.0), -50.0, 0.0)
    np.testing.assert_allclose(np.asarray(y), expected, rtol=1e-5)

    # Rows with discount 0 do not bootstrap: y = lam * r, whatever q_next is.
    terminal = np.arange(len(table)) % 2 == 0
    y = critic_target(reward, q_next, hindsight, h, jnp.where(terminal, 0.0, 0.9))
    lam = np.where(table[:, 2] > 0, 0.5, 1.0)
    want = np.where(np.arange(len(table)) % 2 == 0, lam * table[:, 0], table[:, 3])
    np.testing.assert_allclose(np.asarray(y), want, rtol=1e-6, atol=1e-6)

    # n-step rows bring their own discount; the clip range stays gamma's.
    disc = jnp.full(len(table), 0.5, jnp.float32)
    y = critic_target(reward, q_next, hindsight, h, disc)
    want = np.clip(lam * table[:, 0] + 0.5 * table[:, 1], -lam / (1 - 0.9), 0.0)
    np.testing.assert_allclose(np.asarray(y), want, rtol=1e-6, atol=1e-6)


@jax.jit
def _target_and_grad(reward, q_next, hindsight, h):
    y = critic_target(reward, q_next, hindsight, h)
    grad = jax.grad(lambda q: critic_target(reward, q, hindsight, h).sum())(q_next)
    return y, grad


def test_losses_match_numpy_forward_pass():
    h = DDPGParams.default(lambda_r=1.0, lambda_h=0.5, gamma=0.9, action_l2=0.7)
    norm_data = _batch(2)
    state = _state(h, norm_data)
    batch = _batch(3)
    # An out-of-range entry exercises the raw-input clip before normalisation.
    obs = np.array(batch.obs)
    obs[0, 0] = 500.0
    batch = batch.replace(obs=jnp.asarray(obs))

    c_loss, q_mean, a_loss = losses(state, batch, h)

    def norm(x, data):
        return _np_normalise(x, data, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]

    o, g = norm(batch.obs, norm_data.obs), norm(batch.goal, norm_data.goal)
    o2, g2 = norm(batch.next_obs, norm_data.obs), norm(batch.next_goal, norm_data.goal)
    a2 = _np_actor(state.target_actor_params, o2, g2, MAX_U)
    q_next = _np_critic(state.target_critic_params, o2, g2, a2, MAX_U)
    lam = np.where(np.asarray(batch.hindsight), 0.5, 1.0)
    y = np.clip(lam * np.asarray(batch.reward) + 0.9 * q_next, -lam / 0.1, 0.0)
    q = _np_critic(state.critic_params, o, g, np.asarray(batch.action, np.float64), MAX_U)
    pi = _np_actor(state.actor_params, o, g, MAX_U)
    q_pi = _np_critic(state.critic_params, o, g, pi, MAX_U)

    assert float(c_loss) == pytest.approx(np.mean((q - y) ** 2), rel=1e-4, abs=1e-6)
    assert float(q_mean) == pytest.approx(np.mean(q), rel=1e-4, abs=1e-6)
    expected_actor = -np.mean(q_pi) + 0.7 * np.mean((pi / MAX_U) ** 2)
    assert float(a_loss) == pytest.approx(expected_actor, rel=1e-4, abs=1e-6)
    # The raw clip to clip_obs, not the normalised clip, bounds the entry set to 500.
    assert abs(o[0, 0]) < NORM_CLIP - 0.5


@jax.jit
def _reference_step(state: DDPGState, adam_states, batch: Transition, h: DDPGParams):
    """Both gradients at the same parameters, then plain optax Adam steps."""
    (c_loss, q_mean), c_g = jax.value_and_grad(D.critic_loss, has_aux=True)(
        state.critic_params, state, batch, h
    )
    a_loss, a_g = jax.value_and_grad(D.actor_loss)(state.actor_params, state, batch, h)
    a_s, c_s = adam_states
    c_u, c_s = optax.adam(h.critic_lr).update(c_g, c_s, state.critic_params)
    a_u, a_s = optax.adam(h.actor_lr).update(a_g, a_s, state.actor_params)
    state = state.replace(
        critic_params=optax.apply_updates(state.critic_params, c_u),
        actor_params=optax.apply_updates(state.actor_params, a_u),
    )
    return state, (a_s, c_s), {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": q_mean}


def test_update_applies_both_adam_steps_from_pre_update_params():
    state0 = _state(DDPGParams.default(), _batch(4))
    # Rates differ from those seen at init: the DDPGParams passed to update must be the ones used.
    h = DDPGParams.default(actor_lr=1e-2, critic_lr=3e-3)
    # Two steps: Adam's first step is about lr * sign(grad), the second depends on magnitudes.
    batches = [_batch(5 + i) for i in range(2)]

    state, ref = state0, state0
    adam_states = (
        optax.adam(1.0).init(state0.actor_params),
        optax.adam(1.0).init(state0.critic_params),
    )
    for b in batches:
        state, metrics = update(state, b, h)
        ref, adam_states, ref_metrics = _reference_step(ref, adam_states, b, h)

    _assert_trees_close(state.critic_params, ref.critic_params)
    _assert_trees_close(state.actor_params, ref.actor_params)
    _assert_trees_close(metrics, ref_metrics, rtol=1e-5, atol=1e-7)
    # Targets move only in target_update.
    _assert_trees_close(state.target_actor_params, state0.target_actor_params, 0, 0)
    _assert_trees_close(state.target_critic_params, state0.target_critic_params, 0, 0)


def test_init_targets_equal_online_and_polyak_update():
    h = DDPGParams.default(polyak=0.9)
    state = init(jax.random.key(0), h)
    _assert_trees_close(state.target_actor_params, state.actor_params, 0, 0)
    _assert_trees_close(state.target_critic_params, state.critic_params, 0, 0)

    other = init(jax.random.key(1), h)
    state = state.replace(
        target_actor_params=other.actor_params, target_critic_params=other.critic_params
    )
    new = target_update(state, h)
    mix = lambda t, o: jax.tree.map(lambda a, b: 0.9 * np.asarray(a) + 0.1 * np.asarray(b), t, o)
    _assert_trees_close(new.target_actor_params, mix(other.actor_params, state.actor_params))
    _assert_trees_close(new.target_critic_params, mix(other.critic_params, state.critic_params))
    _assert_trees_close(new.actor_params, state.actor_params, 0, 0)
    _assert_trees_close(new.critic_params, state.critic_params, 0, 0)


def test_explore():
    n = 4000
    data = _batch(7, n)
    state = _state(DDPGParams.default(), _batch(7))
    pi = np.asarray(act(state, data.obs, data.goal))
    key = jax.random.key(8)

    def sample(noise_eps: float, random_eps: float) -> np.ndarray:
        h = DDPGParams.default(noise_eps=noise_eps, random_eps=random_eps)
        return np.asarray(explore(key, state, data.obs, data.goal, h))

    np.testing.assert_array_equal(sample(0.0, 0.0), pi)

    # Large noise: every action is clipped into the box and many sit on its faces.
    a = sample(5.0, 0.0)
    assert np.all(np.abs(a) <= MAX_U)
    assert np.mean(np.abs(a) == MAX_U) > 0.5

    # No noise: rows are either exactly pi or entirely uniform random, at rate random_eps.
    p = 0.3
    a = sample(0.0, p)
    differs = a != pi
    rows = differs.any(1)
    np.testing.assert_array_equal(rows, differs.all(1))  # one coin per row
    assert abs(rows.mean() - p) < 4 * np.sqrt(p * (1 - p) / n)
    rand = a[rows]
    assert np.all(np.abs(rand) <= MAX_U)
    assert np.mean(np.abs(rand)) == pytest.approx(MAX_U / 2, abs=0.06)  # U(-max_u, max_u)


def test_normaliser_matches_baselines_formula():
    state = init(jax.random.key(0), DDPGParams.default())
    rng = np.random.default_rng(0)
    obs_all, goal_all = [], []
    for i in range(3):
        obs = rng.normal(1.0 + i, 3.0, (B, OBS)).astype(np.float32)
        obs[:, 1] = 0.5  # constant column: std falls back to eps
        obs[0, 2] = 50.0 * (-1) ** i  # beyond clip_obs
        goal = rng.normal(-1.0, 0.5 + i, (B, GOAL)).astype(np.float32)
        obs_all.append(obs)
        goal_all.append(goal)
        state = update_normaliser(state, jnp.asarray(obs), jnp.asarray(goal))
    obs_all, goal_all = np.concatenate(obs_all), np.concatenate(goal_all)

    probe_obs = np.stack([obs_all[0], obs_all[0] + 1e3, obs_all[0] - 1e3]).astype(np.float32)
    probe_obs[:, 1] = [0.5, 0.6, 0.4]  # +-0.1 / eps = +-10 std: clipped to +-norm_clip
    probe_goal = goal_all[:3]
    o_n, g_n = normalise(state, jnp.asarray(probe_obs), jnp.asarray(probe_goal))
    exp_o, mean_o, std_o = _np_normalise(probe_obs, obs_all, CLIP_OBS, NORM_EPS, NORM_CLIP)
    exp_g, mean_g, std_g = _np_normalise(probe_goal, goal_all, CLIP_OBS, NORM_EPS, NORM_CLIP)

    np.testing.assert_allclose(np.asarray(state.obs_norm.mean), mean_o, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(state.obs_norm.std), std_o, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.goal_norm.mean), mean_g, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(state.goal_norm.std), std_g, rtol=1e-5, atol=1e-6)
    assert float(state.obs_norm.std[1]) == pytest.approx(NORM_EPS)
    np.testing.assert_allclose(np.asarray(o_n), exp_o, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(g_n), exp_g, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(o_n[1:, 1]), [NORM_CLIP, -NORM_CLIP])
    assert np.all(np.abs(np.asarray(o_n)) <= NORM_CLIP)


def test_updates_reduce_critic_loss_on_toy_problem():
    h = DDPGParams.default(critic_lr=1e-2)
    batch = _batch(9)
    # Reward depends on the input so the critic has something learnable to fit.
    reward = -(np.asarray(batch.obs)[:, 0] > 1.0).astype(np.float32)
    batch = batch.replace(reward=jnp.asarray(reward))
    state = _state(h, batch)
    critic_losses = []
    for _ in range(100):
        state, metrics = update(state, batch, h)
        critic_losses.append(float(metrics["critic_loss"]))
    assert np.all(np.isfinite(critic_losses))
    assert np.mean(critic_losses[-10:]) < 0.3 * critic_losses[0]


def _run(h: DDPGParams, batches: Transition) -> tuple[DDPGState, dict[str, jax.Array]]:
    state = D.init(jax.random.key(0), h)
    state = D.update_normaliser(state, batches.obs[0], batches.goal[0])
    state, metrics = update_many(D, state, batches, h)
    return D.target_update(state, h), metrics


def test_vmap_over_hparams_matches_separate_runs():
    hs = [
        DDPGParams.default(actor_lr=1e-3, critic_lr=1e-3, polyak=0.95),
        DDPGParams.default(actor_lr=5e-3, critic_lr=2e-3, polyak=0.8, lambda_h=0.5),
    ]
    batch_list = [_batch(11 + i) for i in range(3)]
    batches = jax.tree.map(lambda *x: jnp.asarray(np.stack(x)), *batch_list)
    stacked = jax.tree.map(lambda *x: jnp.asarray(np.stack(x)), *hs)
    v_state, v_metrics = jax.jit(jax.vmap(_run, in_axes=(0, None)))(stacked, batches)
    for i, h in enumerate(hs):
        # Separate run from the shared jitted pieces; this also checks update_many == n updates.
        state = update_normaliser(init(jax.random.key(0), h), batch_list[0].obs, batch_list[0].goal)
        metrics = []
        for b in batch_list:
            state, m = update(state, b, h)
            metrics.append(m)
        state = target_update(state, h)
        metrics = jax.tree.map(lambda *x: np.stack(x), *metrics)
        member = jax.tree.map(lambda x, i=i: np.asarray(x)[i], (v_state, v_metrics))
        _assert_trees_close(member, (state, metrics), rtol=1e-5, atol=1e-6)
    # The two members really trained differently.
    diff = jax.tree.map(
        lambda x: np.abs(np.asarray(x)[0] - np.asarray(x)[1]).max(), v_state.actor_params
    )
    assert max(jax.tree.leaves(diff)) > 1e-4


# The optional learner changes (all off by default): TD3's target smoothing and delayed actor,
# target updates inside the scan, and a LayerNorm critic.
D_TD3 = make_ddpg(
    OBS, GOAL, ACT, hidden=(8, 8), max_u=MAX_U, clip_obs=CLIP_OBS, norm_eps=NORM_EPS,
    norm_clip=NORM_CLIP, target_noise=0.3, noise_clip=0.2, policy_delay=2,
)


def test_policy_delay_skips_actor_steps_and_nothing_else():
    h = DDPGParams.default()
    state0 = _state(h, _batch(4))
    batch = _batch(5)
    key = jax.random.key(3)
    upd = jax.jit(D_TD3.update)
    on, m_on = upd(state0, batch, h, key, 0)
    off, m_off = upd(state0, batch, h, key, 1)
    # Same critic step either way; the actor moves only on steps divisible by policy_delay.
    _assert_trees_close(on.critic_params, off.critic_params, 0, 0)
    _assert_trees_close(off.actor_params, state0.actor_params, 0, 0)
    _assert_trees_close(off.actor_opt_state, state0.actor_opt_state, 0, 0)
    _assert_trees_close(on.actor_params, update(state0, batch, h)[0].actor_params)
    assert np.isnan(float(m_off["actor_loss"])) and np.isfinite(float(m_on["actor_loss"]))


def test_target_smoothing_noise_is_clipped_and_keyed():
    h = DDPGParams.default()
    state = _state(h, _batch(4))
    batch = _batch(6)
    loss = jax.jit(lambda s, b, k: D_TD3.critic_loss(s.critic_params, s, b, h, k)[0])
    k1, k2 = jax.random.key(1), jax.random.key(2)
    plain = float(D.critic_loss(state.critic_params, state, batch, h)[0])
    a, a_again, b = float(loss(state, batch, k1)), float(loss(state, batch, k1)), float(
        loss(state, batch, k2))
    assert a == a_again and a != b and a != plain
    # Reference: the smoothed target action in numpy, noise drawn as the learner draws it.
    obs, goal = normalise(state, batch.next_obs, batch.next_goal)
    pi = _np_actor(state.target_actor_params, np.asarray(obs), np.asarray(goal), MAX_U)
    eps = 0.3 * MAX_U * np.asarray(jax.random.normal(k1, pi.shape))
    assert np.abs(eps).max() > 0.2 * MAX_U  # the clip below is exercised
    a_next = np.clip(pi + np.clip(eps, -0.2 * MAX_U, 0.2 * MAX_U), -MAX_U, MAX_U)
    q_next = _np_critic(state.target_critic_params, np.asarray(obs), np.asarray(goal), a_next,
                        MAX_U)
    y = np.asarray(critic_target(batch.reward, jnp.asarray(q_next, jnp.float32), batch.hindsight,
                                 h))
    o, g = normalise(state, batch.obs, batch.goal)
    q = _np_critic(state.critic_params, np.asarray(o), np.asarray(g), np.asarray(batch.action),
                   MAX_U)
    assert a == pytest.approx(np.mean((q - y) ** 2), rel=1e-4)
    with pytest.raises(ValueError, match="PRNG key"):
        D_TD3.critic_loss(state.critic_params, state, batch, h)


def test_target_update_can_be_skipped():
    h = DDPGParams.default(polyak=0.9)
    state = _state(h, _batch(4))
    kept = target_update(state, h, jnp.asarray(False))
    _assert_trees_close(kept.target_critic_params, state.target_critic_params, 0, 0)
    _assert_trees_close(kept.target_actor_params, state.target_actor_params, 0, 0)
    _assert_trees_close(target_update(state, h, jnp.asarray(True)), target_update(state, h), 0, 0)


def test_layer_norm_critic():
    d = make_ddpg(OBS, GOAL, ACT, hidden=(8, 8), layer_norm=True)
    s = d.init(jax.random.key(0), DDPGParams.default())
    assert {"norm_0", "norm_1"} <= set(s.critic_params["params"]["mlp"])
    assert not any(k.startswith("norm") for k in s.actor_params["params"]["mlp"])
    # Scaling a hidden layer's weights and bias changes nothing after a LayerNorm.
    scaled = jax.tree_util.tree_map_with_path(
        lambda p, x: x * 3.0 if "hidden_0" in jax.tree_util.keystr(p) else x, s.critic_params)
    o, g, a = jnp.ones((2, OBS)), jnp.ones((2, GOAL)), jnp.ones((2, ACT))
    np.testing.assert_allclose(d.critic.apply(scaled, o, g, a), d.critic.apply(s.critic_params,
                               o, g, a), rtol=1e-4, atol=1e-5)



def test_bfloat16_matmuls_keep_losses_and_updates_close_to_float32():
    """compute_dtype=bfloat16: the same parameters (float32 in both), the hidden matmuls in
    bfloat16. On a fixed batch at the paper's width, Q values, actions and losses stay within
    bfloat16's precision (8 bits of mantissa: about 0.4% per rounding, over three layers) of
    float32's: each Q within 2% of the batch's largest |Q|, the critic loss within 3%, the
    actor loss (a mean of Q) within 2% of the largest |Q|, actions within 1% of max_u; one
    update's parameters move no further from float32's than the update's own step."""
    h = DDPGParams.default()
    f32 = make_ddpg(OBS, GOAL, ACT, hidden=(256, 256, 256), max_u=MAX_U)
    b16 = make_ddpg(OBS, GOAL, ACT, hidden=(256, 256, 256), max_u=MAX_U,
                    compute_dtype="bfloat16")
    s = f32.init(jax.random.key(1), h)
    s = f32.update_normaliser(s, _batch(20, 256).obs, _batch(20, 256).goal)
    # Parameters and state are the same pytree of float32 arrays in both.
    s16 = b16.init(jax.random.key(1), h)
    assert jax.tree.structure(s16) == jax.tree.structure(s)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(s16.critic_params))
    batch = _batch(21, 256)

    def q_of(d):
        o, g = d.normalise(s, batch.obs, batch.goal)
        return np.asarray(jax.jit(d.critic.apply)(s.critic_params, o, g, batch.action))

    q32, q16 = q_of(f32), q_of(b16)
    assert q16.dtype == np.float32 and not np.array_equal(q32, q16)  # bf16 did run
    scale = np.abs(q32).max()
    np.testing.assert_allclose(q16, q32, atol=0.02 * scale)
    (a, ma), (b, mb) = jax.jit(f32.update)(s, batch, h), jax.jit(b16.update)(s, batch, h)
    np.testing.assert_allclose(float(mb["critic_loss"]), float(ma["critic_loss"]), rtol=3e-2)
    np.testing.assert_allclose(float(mb["actor_loss"]), float(ma["actor_loss"]),
                               atol=0.02 * scale)
    step = jax.tree.map(lambda x, y: np.abs(np.asarray(x) - np.asarray(y)).max(),
                        a.critic_params, s.critic_params)
    diff = jax.tree.map(lambda x, y: np.abs(np.asarray(x) - np.asarray(y)).max(),
                        b.critic_params, a.critic_params)
    # Adam's first step is about lr * sign(grad): the two differ only where a gradient's sign
    # flips under rounding (near-zero gradients), by at most two steps.
    assert max(jax.tree.leaves(diff)) <= 2.0 * max(jax.tree.leaves(step))
    actions = [np.asarray(jax.jit(d.act)(s, batch.obs, batch.goal)) for d in (f32, b16)]
    np.testing.assert_allclose(actions[1], actions[0], atol=0.01 * MAX_U)


def test_unknown_compute_dtype_is_refused():
    with pytest.raises(ValueError, match="compute_dtype must be float32 or bfloat16"):
        make_ddpg(OBS, GOAL, ACT, compute_dtype="float16")


def test_unweighted_target_clip():
    """target_clip=unweighted: every row's target clipped to [-1/(1-gamma), 0] whatever its
    weight (baselines' clip_return), here 4 / 0.5 at gamma 0.9: both bounds -10, where the
    weighted clip has -40 and -5."""
    h = DDPGParams.default(lambda_r=4.0, lambda_h=0.5, gamma=0.9)
    table = np.array(
        # reward, q_next, hindsight, expected y (unweighted), expected y (weighted)
        [
            [-1.0, -20.0, 0, -10.0, -22.0],  # -4 - 18: inside [-40, 0], outside [-10, 0]
            [-1.0, -20.0, 1, -10.0, -5.0],  # -0.5 - 18
            [-1.0, -2.0, 0, -5.8, -5.8],
            [-1.0, -2.0, 1, -2.3, -2.3],
            [0.0, -8.0, 1, -7.2, -5.0],
            [0.0, 3.0, 0, 0.0, 0.0],
        ],
        np.float32,
    )
    reward, q_next = jnp.asarray(table[:, 0]), jnp.asarray(table[:, 1])
    hindsight = jnp.asarray(table[:, 2] > 0)
    for clip, col in (("unweighted", 3), ("weighted", 4)):
        y = critic_target(reward, q_next, hindsight, h, clip=clip)
        np.testing.assert_allclose(np.asarray(y), table[:, col], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="clip must be one of"):
        critic_target(reward, q_next, hindsight, h, clip="none")


def test_target_clip_reaches_the_critic_loss():
    """make_ddpg(target_clip=...) is what critic_loss uses: against numpy, both ways, on a
    batch whose weighted targets go below -1/(1-gamma)."""
    h = DDPGParams.default(lambda_r=4.0, lambda_h=0.5, gamma=0.9)
    norm_data = _batch(2)
    batch = _batch(3)
    batch = batch.replace(reward=-jnp.ones_like(batch.reward))
    for clip in ("weighted", "unweighted"):
        d = make_ddpg(OBS, GOAL, ACT, hidden=(8, 8), max_u=MAX_U, clip_obs=CLIP_OBS,
                      norm_eps=NORM_EPS, norm_clip=NORM_CLIP, target_clip=clip)
        state = d.init(jax.random.key(0), h)
        state = d.update_normaliser(state, norm_data.obs, norm_data.goal)
        # A pessimistic target critic: shift its output bias so q_next is about -30.
        tc = jax.tree.map(lambda x: x, state.target_critic_params)
        tc["params"]["mlp"]["out"]["bias"] = tc["params"]["mlp"]["out"]["bias"] - 30.0
        state = state.replace(target_critic_params=tc)
        o2, g2 = (np.asarray(x, np.float64) for x in d.normalise(state, batch.next_obs,
                                                                batch.next_goal))
        a2 = _np_actor(state.target_actor_params, o2, g2, MAX_U)
        q_next = _np_critic(state.target_critic_params, o2, g2, a2, MAX_U)
        lam = np.where(np.asarray(batch.hindsight), 0.5, 4.0)
        bound = lam if clip == "weighted" else np.ones_like(lam)
        y = np.clip(lam * np.asarray(batch.reward) + 0.9 * q_next, -bound / 0.1, 0.0)
        o, g = (np.asarray(x, np.float64) for x in d.normalise(state, batch.obs, batch.goal))
        q = _np_critic(state.critic_params, o, g, np.asarray(batch.action, np.float64), MAX_U)
        c_loss, _ = d.critic_loss(state.critic_params, state, batch, h)
        assert float(c_loss) == pytest.approx(np.mean((q - y) ** 2), rel=1e-4)
        np.testing.assert_allclose(
            np.asarray(d.critic_target(batch.reward, jnp.asarray(q_next, jnp.float32),
                                       batch.hindsight, h)), y, rtol=1e-5, atol=1e-4)
        if clip == "unweighted":
            assert np.any(lam * -1.0 + 0.9 * q_next < -10.0)  # the bound mattered


def test_unknown_target_clip_is_refused():
    with pytest.raises(ValueError, match="target_clip must be one of"):
        make_ddpg(OBS, GOAL, ACT, target_clip="none")


# An ensemble of 3 critics whose targets take the minimum over 2 of them, drawn per step (REDQ).
D_ENS = make_ddpg(
    OBS, GOAL, ACT, hidden=(8, 8), max_u=MAX_U, clip_obs=CLIP_OBS, norm_eps=NORM_EPS,
    norm_clip=NORM_CLIP, n_critics=3, target_critics=2,
)


def _member(params, e: int):
    """Critic e of an ensemble's parameters, in a single critic's layout."""
    return {"params": jax.tree.map(lambda x: x[e], params["params"]["ensemble"])}


def _ens_state(h: DDPGParams, norm_data: Transition, d=D_ENS) -> DDPGState:
    state = jax.jit(d.init)(jax.random.key(0), h)
    other = jax.jit(d.init)(jax.random.key(1), h)
    state = state.replace(target_critic_params=other.critic_params,
                          target_actor_params=other.actor_params)
    return jax.jit(d.update_normaliser)(state, norm_data.obs, norm_data.goal)


def test_ensemble_critics_are_distinct_and_shaped():
    h = DDPGParams.default()
    state = _ens_state(h, _batch(2))
    kernels = state.critic_params["params"]["ensemble"]["mlp"]["hidden_0"]["kernel"]
    assert kernels.shape == (3, OBS + GOAL + ACT, 8)
    assert not np.allclose(kernels[0], kernels[1]) and not np.allclose(kernels[1], kernels[2])
    # The single-critic layout is unchanged (checkpoints and rows of n_critics=1 runs).
    assert "mlp" in init(jax.random.key(0), h).critic_params["params"]


def test_target_subset_draws_distinct_indices():
    seen = set()
    for i in range(40):
        idx = np.asarray(target_subset(jax.random.key(i), 5, 2))
        assert len(set(idx.tolist())) == 2 and idx.min() >= 0 and idx.max() < 5
        seen.add(tuple(sorted(idx.tolist())))
    assert len(seen) >= 8  # of the 10 pairs


def test_ensemble_losses_match_numpy():
    h = DDPGParams.default(lambda_r=1.0, lambda_h=0.5, gamma=0.9, action_l2=0.3)
    norm_data = _batch(2)
    state, batch, key = _ens_state(h, norm_data), _batch(3), jax.random.key(7)
    c_loss, q_mean = jax.jit(D_ENS.critic_loss)(state.critic_params, state, batch, h, key)
    a_loss = jax.jit(D_ENS.actor_loss)(state.actor_params, state, batch, h)

    def norm(x, data):
        return _np_normalise(x, data, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]

    o, g = norm(batch.obs, norm_data.obs), norm(batch.goal, norm_data.goal)
    o2, g2 = norm(batch.next_obs, norm_data.obs), norm(batch.next_goal, norm_data.goal)
    a2 = _np_actor(state.target_actor_params, o2, g2, MAX_U)
    q_next = np.stack([_np_critic(_member(state.target_critic_params, e), o2, g2, a2, MAX_U)
                       for e in range(3)])
    # The subset the learner draws: the second half of the critic loss's key split.
    idx = np.asarray(target_subset(jax.random.split(key)[1], 3, 2))
    lam = np.where(np.asarray(batch.hindsight), 0.5, 1.0)
    y = np.clip(lam * np.asarray(batch.reward) + 0.9 * q_next[idx].min(0), -lam / 0.1, 0.0)
    a = np.asarray(batch.action, np.float64)
    q = np.stack([_np_critic(_member(state.critic_params, e), o, g, a, MAX_U) for e in range(3)])
    assert float(c_loss) == pytest.approx(np.mean((q - y) ** 2), rel=1e-4, abs=1e-6)
    assert float(q_mean) == pytest.approx(np.mean(q), rel=1e-4, abs=1e-6)
    pi = _np_actor(state.actor_params, o, g, MAX_U)
    q_pi = np.mean([_np_critic(_member(state.critic_params, e), o, g, pi, MAX_U)
                    for e in range(3)], axis=0)
    assert float(a_loss) == pytest.approx(-np.mean(q_pi) + 0.3 * np.mean((pi / MAX_U) ** 2),
                                          rel=1e-4, abs=1e-6)
    # Another key, another subset: the target (and the loss) changes with it, and the minimum
    # over all three is never above the minimum over any two.
    losses_by_key = {round(float(jax.jit(D_ENS.critic_loss)(
        state.critic_params, state, batch, h, jax.random.key(k))[0]), 6) for k in range(12)}
    assert len(losses_by_key) >= 2
    with pytest.raises(ValueError, match="PRNG key"):
        D_ENS.critic_loss(state.critic_params, state, batch, h)


def test_twin_critics_take_the_minimum_of_both_targets():
    d = make_ddpg(OBS, GOAL, ACT, hidden=(8, 8), max_u=MAX_U, clip_obs=CLIP_OBS,
                  norm_eps=NORM_EPS, norm_clip=NORM_CLIP, n_critics=2)
    h = DDPGParams.default(gamma=0.9)
    norm_data = _batch(2)
    state, batch = _ens_state(h, norm_data, d), _batch(4)
    o2 = _np_normalise(batch.next_obs, norm_data.obs, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]
    g2 = _np_normalise(batch.next_goal, norm_data.goal, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]
    o = _np_normalise(batch.obs, norm_data.obs, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]
    g = _np_normalise(batch.goal, norm_data.goal, CLIP_OBS, NORM_EPS, NORM_CLIP)[0]
    a2 = _np_actor(state.target_actor_params, o2, g2, MAX_U)
    q_next = np.minimum(*[_np_critic(_member(state.target_critic_params, e), o2, g2, a2, MAX_U)
                          for e in range(2)])
    y = np.clip(np.asarray(batch.reward) + 0.9 * q_next, -10.0, 0.0)
    q = np.stack([_np_critic(_member(state.critic_params, e), o, g,
                             np.asarray(batch.action, np.float64), MAX_U) for e in range(2)])
    # No subset to draw: no key needed, and the loss is deterministic.
    c_loss = float(jax.jit(d.critic_loss)(state.critic_params, state, batch, h)[0])
    assert c_loss == pytest.approx(np.mean((q - y) ** 2), rel=1e-4, abs=1e-6)
    # A gradient step moves every critic, and each only by its own error.
    new, m = jax.jit(d.update)(state, batch, h)
    moved = [not np.allclose(_member(new.critic_params, e)["params"]["mlp"]["out"]["kernel"],
                             _member(state.critic_params, e)["params"]["mlp"]["out"]["kernel"])
             for e in range(2)]
    assert all(moved) and np.isfinite(float(m["critic_loss"]))


def test_ensemble_options_are_checked():
    with pytest.raises(ValueError, match="n_critics"):
        make_ddpg(OBS, GOAL, ACT, n_critics=0)
    with pytest.raises(ValueError, match="target_critics"):
        make_ddpg(OBS, GOAL, ACT, n_critics=2, target_critics=3)
