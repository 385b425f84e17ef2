"""Tests for the episode-major replay buffer."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import sample_indices
from hypothesis import given, settings
from hypothesis import strategies as st

from rdher_jax import buffer as rb

# Every stored value encodes (episode id, field, step) as id * 1000 + field * 100 + step, which
# float32 holds exactly here; id 0 never occurs, so a 0 marks an unwritten slot.
FIELDS = ("obs", "ag", "g", "action")


def make_episodes(ids, T: int, obs_dim: int = 2, goal_dim: int = 3, act_dim: int = 1):
    """Episodes whose every element encodes its episode id, field and step."""
    ids = np.asarray(ids, np.float32)[:, None, None]
    dims = {"obs": obs_dim, "ag": goal_dim, "g": goal_dim, "action": act_dim}
    out = {}
    for f, name in enumerate(FIELDS):
        steps = T if name == "action" else T + 1
        step = np.arange(steps, dtype=np.float32)[None, :, None]
        val = ids * 1000 + f * 100 + step
        # numpy leaves: jitted add takes them as is, without an eager op per array.
        out[name] = np.ascontiguousarray(np.broadcast_to(val, (ids.shape[0], steps, dims[name])))
    return rb.Episode(**out)


# Shared jitted entry points, so tests with equal shapes reuse one compilation (and init runs
# as one program rather than one eager op per array).
new_buffer = jax.jit(rb.init, static_argnums=(0, 1, 2, 3, 4), static_argnames="dtype")
add_jit = jax.jit(rb.add)
sample_jit = jax.jit(sample_indices, static_argnums=2)
# Shapes shared by the sampling tests: 7 episode slots of T = 5 steps, 1024 samples per draw.
CAP, HORIZON, BATCH = 7, 5, 1024


def decode(x):
    """Split encoded values into (id, field, step)."""
    x = np.asarray(x).astype(np.int64)
    return x // 1000, (x % 1000) // 100, x % 100


def test_init_shapes_and_dtypes():
    s = rb.init(1000, 50, 25, 3, 4)
    assert s.capacity_episodes == 20 and s.horizon == 50
    assert s.obs.shape == (20, 51, 25)
    assert s.ag.shape == (20, 51, 3)
    assert s.g.shape == (20, 51, 3)
    assert s.action.shape == (20, 50, 4)
    for name in FIELDS:
        assert getattr(s, name).dtype == jnp.float32
        assert not np.any(np.asarray(getattr(s, name)))
    for name in ("insert_pos", "num_episodes"):
        x = getattr(s, name)
        assert x.shape == () and x.dtype == jnp.int32 and int(x) == 0

    # The capacity is floored to whole episodes; float sizes from configs are accepted.
    # (eval_shape: shapes only, nothing is allocated.)
    assert jax.eval_shape(lambda: rb.init(1049, 50, 25, 3, 4)).capacity_episodes == 20
    assert jax.eval_shape(lambda: rb.init(1e6, 50, 25, 3, 4)).obs.shape == (20000, 51, 25)

    h = new_buffer(100, 10, 5, 3, 2, dtype=jnp.bfloat16)
    assert all(getattr(h, n).dtype == jnp.bfloat16 for n in FIELDS)
    h = add_jit(h, make_episodes([1], 10, 5, 3, 2))
    assert h.obs.dtype == jnp.bfloat16


@pytest.mark.parametrize(
    "args",
    [
        (49, 50, 25, 3, 4),  # less than one episode
        (0, 50, 25, 3, 4),
        (-100, 50, 25, 3, 4),
        (100, 0, 25, 3, 4),
        (100, 10, 0, 3, 4),
        (100, 10, 5, 0, 4),
        (100, 10, 5, 3, 0),
        (100.5, 10, 5, 3, 4),
    ],
)
def test_init_rejects_bad_sizes(args):
    with pytest.raises(ValueError):
        rb.init(*args)


def test_add_rejects_bad_batches():
    s = rb.init(30, 10, 2, 3, 1)  # 3 episode slots
    with pytest.raises(ValueError):
        rb.add(s, make_episodes([1, 2, 3, 4], 10))
    with pytest.raises(ValueError):
        rb.add(s, make_episodes([1], 9))  # wrong horizon
    with pytest.raises(ValueError):
        rb.add(s, make_episodes([1], 10, obs_dim=3))


@st.composite
def wrap_cases(draw):
    cap = draw(st.integers(1, 5))
    T = draw(st.sampled_from([1, 3]))
    extra = draw(st.integers(0, T - 1))  # capacity need not be a multiple of T
    b = draw(st.integers(1, cap))
    n_adds = draw(st.integers(0, 7))
    return cap, T, cap * T + extra, b, n_adds


@settings(max_examples=20, deadline=None)
@given(wrap_cases())
def test_wraparound_keeps_last_episodes_in_their_slots(case):
    cap, T, capacity, b, n_adds = case
    s = new_buffer(capacity, T, 2, 3, 1)
    assert s.capacity_episodes == cap
    n = 0
    for _ in range(n_adds):
        prev_num = int(s.num_episodes)
        s = add_jit(s, make_episodes(np.arange(n, n + b) + 1, T))
        n += b
        assert int(s.insert_pos) == n % cap
        assert int(s.num_episodes) == min(n, cap)
        assert prev_num <= int(s.num_episodes) <= cap
        assert 0 <= int(s.insert_pos) < cap

    # Episode k (0-based, id k + 1) lives in slot k % cap; the last write to a slot wins.
    expected_id = np.zeros(cap, np.int64)
    for k in range(n):
        expected_id[k % cap] = k + 1
    stored = set(expected_id[expected_id > 0].tolist())
    assert stored == set(range(max(n - cap, 0) + 1, n + 1))
    for f, name in enumerate(FIELDS):
        ids, fields, steps = decode(getattr(s, name))
        for slot in range(cap):
            if expected_id[slot] == 0:
                assert not np.any(np.asarray(getattr(s, name))[slot])
                continue
            assert np.all(ids[slot] == expected_id[slot])
            assert np.all(fields[slot] == f)
            assert np.all(steps[slot] == np.arange(steps.shape[1])[:, None])


def gather_sample(s, ep_idx, t):
    """Decode every field touched by the sampled transitions."""
    e, t = np.asarray(ep_idx), np.asarray(t)
    obs, ag, g, action = (np.asarray(getattr(s, n)) for n in FIELDS)
    parts = {
        "obs": obs[e, t],
        "next_obs": obs[e, t + 1],
        "ag": ag[e, t],
        "next_ag": ag[e, t + 1],
        "g": g[e, t],
        "next_g": g[e, t + 1],
        "action": action[e, t],
    }
    return {k: decode(v) for k, v in parts.items()}


def check_untorn(s, ep_idx, t, allowed_ids):
    e, t = np.asarray(ep_idx), np.asarray(t)
    assert np.all((0 <= e) & (e < int(s.num_episodes)))
    assert np.all((0 <= t) & (t < s.horizon))
    parts = gather_sample(s, e, t)
    ref_id = parts["obs"][0][:, 0]
    assert np.all(np.isin(ref_id, list(allowed_ids)))
    for name, (ids, fields, steps) in parts.items():
        # Every dimension of every field of a sample carries the same episode id.
        assert np.all(ids == ref_id[:, None]), name
        assert np.all(fields == FIELDS.index(name.removeprefix("next_"))), name
        want_step = t + 1 if name.startswith("next_") else t
        assert np.all(steps == want_step[:, None]), name


def test_samples_are_never_torn_or_unwritten():
    cap, T, b = CAP, HORIZON, 3
    s = new_buffer(cap * T, T, 2, 3, 1)
    keys = iter(jax.random.split(jax.random.key(0), 24))

    # Partly full: only slots 0..2 are written and only they may be sampled.
    s = add_jit(s, make_episodes([1, 2, 3], T))
    e, t = sample_jit(next(keys), s, BATCH)
    check_untorn(s, e, t, {1, 2, 3})
    assert set(np.asarray(e).tolist()) == {0, 1, 2}

    n = b
    seen_e, seen_t = set(), set()
    for _ in range(20):  # 63 episodes through 7 slots: wraps many times, mid-batch too
        s = add_jit(s, make_episodes(np.arange(n, n + b) + 1, T))
        n += b
        e, t = sample_jit(next(keys), s, BATCH)
        check_untorn(s, e, t, set(range(n - cap + 1, n + 1)))
        seen_e |= set(np.asarray(e).tolist())
        seen_t |= set(np.asarray(t).tolist())
    # Uniform draws reach every slot and every step.
    assert seen_e == set(range(cap))
    assert seen_t == set(range(T))


def test_sample_from_empty_buffer_is_slot_zero():
    s = new_buffer(CAP * HORIZON, HORIZON, 2, 3, 1)
    e, t = sample_jit(jax.random.key(0), s, BATCH)
    assert e.dtype == jnp.int32 and t.dtype == jnp.int32
    assert np.all(np.asarray(e) == 0)


def test_jit_vmap_over_seed_axis_matches_per_seed_loop():
    n_seeds, cap, T, b, n_adds = 3, CAP, HORIZON, 3, 5
    base = new_buffer(cap * T, T, 2, 3, 1)
    ids = np.arange(n_seeds * n_adds * b).reshape(n_seeds, n_adds, b) + 1
    eps = [[make_episodes(ids[i, j], T) for j in range(n_adds)] for i in range(n_seeds)]
    # Leading axes (seed, add, ...) for the batched run.
    stack = lambda xs: jax.tree.map(lambda *y: np.stack(y), *xs)
    stacked = stack([stack(row) for row in eps])
    keys = jax.random.split(jax.random.key(3), n_seeds)

    def run(key, ep_seq):
        def body(state, ep):
            return rb.add(state, ep), None

        state, _ = jax.lax.scan(body, base, ep_seq)
        return state, sample_indices(key, state, BATCH)

    states, (e_b, t_b) = jax.jit(jax.vmap(run))(keys, stacked)
    assert states.obs.shape == (n_seeds, cap, T + 1, 2)
    assert states.insert_pos.shape == (n_seeds,)
    for i, key in enumerate(keys):
        s = base
        for j in range(n_adds):
            s = add_jit(s, eps[i][j])
        e, t = sample_jit(key, s, BATCH)
        for name in FIELDS + ("insert_pos", "num_episodes"):
            np.testing.assert_array_equal(np.asarray(getattr(states, name))[i], getattr(s, name))
        np.testing.assert_array_equal(np.asarray(e_b)[i], e)
        np.testing.assert_array_equal(np.asarray(t_b)[i], t)
        # 15 episodes through 7 slots: the last 7 of this seed remain.
        check_untorn(s, e, t, set(ids[i].ravel()[-cap:].tolist()))


def test_bytes_per_transition_fetch_push():
    # Per episode: 51 obs * 25 + 2 * 51 goals * 3 + 50 actions * 4 = 1781 floats = 7124 bytes.
    assert rb.bytes_per_transition(50, 25, 3, 4) == pytest.approx(7124 / 50)
    assert rb.bytes_per_transition(50, 25, 3, 4, itemsize=2) == pytest.approx(3562 / 50)
    # It matches what init allocates.
    s = jax.eval_shape(lambda: rb.init(500, 50, 25, 3, 4))
    nbytes = sum(np.prod(getattr(s, n).shape) * getattr(s, n).dtype.itemsize for n in FIELDS)
    assert nbytes / (s.capacity_episodes * 50) == pytest.approx(
        rb.bytes_per_transition(50, 25, 3, 4)
    )
