"""Tests for 'future' hindsight relabelling."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from rdher_jax import buffer as rb
from rdher_jax.relabel import her, relabel_prob_from_k


def fetch_reward(achieved, desired):
    """Sparse Fetch reward: 0 within 5 cm of the goal, -1 otherwise."""
    d = jnp.linalg.norm(achieved - desired, axis=-1)
    return -(d > 0.05).astype(jnp.float32)


def grid_reward(achieved, desired):
    """A reward that is exact on integer-valued goals, for bitwise comparisons."""
    return -(jnp.sum((achieved - desired) ** 2, axis=-1) > 2.0).astype(jnp.float32)


def grid_reward_np(achieved, desired):
    return np.float32(-1.0 if np.sum((achieved - desired) ** 2) > 2.0 else 0.0)


# Fixed buffer shapes, so that most tests reuse a handful of compilations.
CAP, OBS_DIM, ACT_DIM, BATCH = 4, 2, 2, 64
# Shapes shared by the statistical tests: T = 10, 20,000 samples.
HORIZON, N = 10, 20_000

init_jit = jax.jit(rb.init, static_argnums=(0, 1, 2, 3, 4))
add_jit = jax.jit(rb.add)
draw_jit = jax.jit(her.draw_her, static_argnums=(2, 3))
gather_jit = jax.jit(her.gather_her, static_argnums=5)
sample_jit = jax.jit(her.sample_her, static_argnums=(2, 4))


def random_buffer(rng, T, n_adds, cap=CAP, scale=1.0, integer=False):
    """A buffer after n_adds single random episodes, with per-step (moving) desired goals."""

    def draw(*shape):
        if integer:
            return rng.integers(-2, 3, (1,) + shape).astype(np.float32)
        return (scale * rng.standard_normal((1,) + shape)).astype(np.float32)

    state = init_jit(cap * T, T, OBS_DIM, 3, ACT_DIM)
    for _ in range(n_adds):
        ep = rb.Episode(
            obs=draw(T + 1, OBS_DIM), ag=draw(T + 1, 3), g=draw(T + 1, 3), action=draw(T, ACT_DIM)
        )
        state = add_jit(state, ep)
    return state


def reference_her(buf, ep_idx, t, future_t, mask, reward_fn):
    """Plain numpy loop over the samples, after baselines' her_sampler.py."""
    obs, ag, g, action = (np.asarray(x) for x in (buf.obs, buf.ag, buf.g, buf.action))
    out = {k: [] for k in ("obs", "goal", "action", "reward", "next_obs", "next_goal")}
    for i in range(len(ep_idx)):
        e, s, f, m = int(ep_idx[i]), int(t[i]), int(future_t[i]), bool(mask[i])
        goal = ag[e, f] if m else g[e, s]
        next_goal = ag[e, f] if m else g[e, s + 1]
        out["obs"].append(obs[e, s])
        out["goal"].append(goal)
        out["action"].append(action[e, s])
        out["reward"].append(reward_fn(ag[e, s + 1], next_goal))
        out["next_obs"].append(obs[e, s + 1])
        out["next_goal"].append(next_goal)
    return {k: np.stack(v) for k, v in out.items()}


@st.composite
def her_cases(draw):
    return dict(
        T=draw(st.sampled_from([1, 4])),
        # Up to twice the capacity, so some buffers have wrapped.
        n_adds=draw(st.integers(1, 2 * CAP)),
        relabel_prob=draw(st.sampled_from([0.0, 0.3, 0.8, 1.0])),
        seed=draw(st.integers(0, 2**31 - 1)),
    )


# No shrink phase: every example compiles new shapes, so shrinking a failure takes minutes;
# the failing example is still reported in full.
@settings(
    max_examples=20,
    deadline=None,
    phases=(Phase.explicit, Phase.reuse, Phase.generate, Phase.target, Phase.explain),
)
@given(her_cases())
def test_sample_her_matches_numpy_reference(case):
    rng = np.random.default_rng(case["seed"])
    buf = random_buffer(rng, case["T"], case["n_adds"], integer=True)
    n_eps = min(case["n_adds"], CAP)
    assert int(buf.num_episodes) == n_eps
    key = jax.random.key(case["seed"])
    p = jnp.float32(case["relabel_prob"])
    ep_idx, t, future_t, mask = draw_jit(key, buf.num_episodes, case["T"], BATCH, p)
    ep_idx, t, future_t, mask = (np.asarray(x) for x in (ep_idx, t, future_t, mask))
    assert np.all((0 <= ep_idx) & (ep_idx < n_eps))
    assert np.all((0 <= t) & (t < case["T"]))
    assert np.all((t < future_t) & (future_t <= case["T"]))

    got = sample_jit(key, buf, BATCH, p, grid_reward)
    # sample_her is exactly draw_her followed by gather_her.
    split = gather_jit(buf, ep_idx, t, future_t, mask, grid_reward)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(split), strict=True):
        np.testing.assert_array_equal(a, b)

    ref = reference_her(buf, ep_idx, t, future_t, mask, grid_reward_np)
    for name, want in ref.items():
        have = np.asarray(getattr(got, name))
        assert have.dtype == want.dtype, name
        np.testing.assert_array_equal(have, want, err_msg=name)
    np.testing.assert_array_equal(np.asarray(got.hindsight), mask)
    assert got.hindsight.dtype == jnp.bool_


def test_future_t_strictly_future_and_covers_range():
    T, n = HORIZON, N
    ep_idx, t, future_t, _ = draw_jit(jax.random.key(0), jnp.int32(3), T, n, jnp.float32(0.8))
    ep_idx, t, future_t = np.asarray(ep_idx), np.asarray(t), np.asarray(future_t)
    assert ep_idx.dtype == t.dtype == future_t.dtype == np.int32
    # Episodes and steps are uniform too.
    for x, k in ((ep_idx, 3), (t, T)):
        counts = np.bincount(x, minlength=k)
        assert len(counts) == k
        assert np.all(np.abs(counts - n / k) <= 5 * np.sqrt(n * (1 / k) * (1 - 1 / k)))
    assert np.all(future_t > t) and np.all(future_t <= T)
    # For each t, future_t is uniform on [t+1, T]: every value appears at about its share.
    for s in range(T):
        f = future_t[t == s]
        values, counts = np.unique(f, return_counts=True)
        assert values.tolist() == list(range(s + 1, T + 1))
        share = 1 / (T - s)
        sigma = np.sqrt(len(f) * share * (1 - share))
        assert np.all(np.abs(counts - len(f) * share) <= 5 * sigma)


def test_future_step_edges():
    T = jnp.arange(1, 2001, dtype=jnp.int32)
    below_one = jnp.full(T.shape, np.nextafter(np.float32(1), np.float32(0)))
    for t in (jnp.zeros_like(T), T // 2, T - 1):
        hi = np.asarray(her.future_step(t, below_one, T))
        lo = np.asarray(her.future_step(t, jnp.zeros(T.shape), T))
        np.testing.assert_array_equal(lo, t + 1)
        # The largest uniform maps to the last step, never past it.
        np.testing.assert_array_equal(hi, T)


def test_relabel_prob_from_k():
    assert relabel_prob_from_k(4) == pytest.approx(0.8)
    assert relabel_prob_from_k(0) == 0.0
    assert relabel_prob_from_k(1) == pytest.approx(0.5)


def test_relabel_fraction_rewards_and_goals():
    rng = np.random.default_rng(0)
    cap, T, n = 8, HORIZON, N
    # Goals within a few cm of each other so both reward values occur.
    buf = random_buffer(rng, T, cap, cap=cap, scale=0.03)
    g, ag = np.asarray(buf.g), np.asarray(buf.ag)
    keys = jax.random.split(jax.random.key(1), 4)
    # relabel_prob is traced: one compilation serves every value.
    for key, p in zip(keys, (0.0, 0.25, 0.8, 1.0), strict=True):
        tr = sample_jit(key, buf, n, jnp.float32(p), fetch_reward)
        ep_idx, t, future_t, mask = (
            np.asarray(x) for x in draw_jit(key, buf.num_episodes, T, n, jnp.float32(p))
        )
        hs = np.asarray(tr.hindsight)
        np.testing.assert_array_equal(hs, mask)
        frac = hs.mean()
        if p in (0.0, 1.0):
            assert frac == p
        else:
            assert abs(frac - p) <= 5 * np.sqrt(p * (1 - p) / n)

        goal, next_goal = np.asarray(tr.goal), np.asarray(tr.next_goal)
        np.testing.assert_array_equal(next_goal[hs], goal[hs])
        np.testing.assert_array_equal(goal[hs], ag[ep_idx, future_t][hs])
        np.testing.assert_array_equal(goal[~hs], g[ep_idx, t][~hs])
        np.testing.assert_array_equal(next_goal[~hs], g[ep_idx, t + 1][~hs])

        reward = np.asarray(tr.reward)
        assert reward.dtype == np.float32 and reward.shape == (n,)
        want = np.asarray(jax.jit(fetch_reward)(ag[ep_idx, t + 1], next_goal))
        np.testing.assert_array_equal(reward, want)
        # A goal relabelled to the very next achieved goal is always reached.
        assert np.all(reward[hs & (future_t == t + 1)] == 0.0)
        if 0.0 < p < 1.0:
            assert set(np.unique(reward).tolist()) == {-1.0, 0.0}


def test_sample_her_vmaps_over_seeds():
    rng = np.random.default_rng(2)
    bufs = [random_buffer(rng, 4, n_adds, integer=True) for n_adds in (1, 6)]
    stacked = jax.tree.map(lambda *x: np.stack(x), *bufs)
    keys = jax.random.split(jax.random.key(5), 2)
    probs = np.array([0.3, 0.9], np.float32)

    vmapped = jax.vmap(her.sample_her, in_axes=(0, 0, None, 0, None))
    batched = jax.jit(vmapped, static_argnums=(2, 4))
    out = batched(keys, stacked, BATCH, probs, grid_reward)
    assert out.obs.shape == (2, BATCH, OBS_DIM) and out.reward.shape == (2, BATCH)
    for i, (key, buf) in enumerate(zip(keys, bufs, strict=True)):
        one = sample_jit(key, buf, BATCH, probs[i], grid_reward)
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(one), strict=True):
            np.testing.assert_array_equal(np.asarray(a)[i], b)
