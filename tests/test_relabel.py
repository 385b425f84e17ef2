"""Relabelling strategies against plain numpy references: DHER's matcher and combination, CHER's
selection, the observed-return diagnostic, and the per-row reward weights."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import cher_select_np
from hypothesis import given, settings
from hypothesis import strategies as st

from rdher_jax import buffer as rb
from rdher_jax import relabel
from rdher_jax.config import Config, resolve
from rdher_jax.ddpg import DDPGParams, critic_target
from rdher_jax.relabel import cher, dher
from rdher_jax.relabel.base import DHER, HER, REAL

OBS, ACT, D = 2, 2, 3
TOL = 1.0  # goals live on an integer grid: a cell is a point


def reward_fn(achieved, desired):
    return -(jnp.linalg.norm(achieved - desired, axis=-1) > 0.5).astype(jnp.float32)


def reward_np(achieved, desired):
    return -(np.linalg.norm(achieved - desired, axis=-1) > 0.5).astype(np.float32)


PARAMS = relabel.RelabelParams.default(relabel_prob=0.0, dher_fraction=1.0, dher_tol=TOL)


@functools.cache
def dher_fns(cap, T, num_new, partners, batch=64, records=4096):
    f = dher.build_dher(reward_fn, batch, cap, T, D, num_new=num_new, records=records,
                        partners=partners)
    return f, jax.jit(f.update), jax.jit(f.gather_combined), jax.jit(rb.add)


def random_episodes(rng, n, T, span):
    """Episodes with goals on a small integer grid, so that cross-episode matches are common."""
    return rb.Episode(
        obs=rng.standard_normal((n, T + 1, OBS)).astype(np.float32),
        ag=rng.integers(0, span, (n, T + 1, D)).astype(np.float32),
        g=rng.integers(0, span, (n, T + 1, D)).astype(np.float32),
        action=rng.standard_normal((n, T, ACT)).astype(np.float32),
    )


def failed_slots(buf):
    n = int(buf.num_episodes)
    T = buf.horizon
    ag, g = np.asarray(buf.ag), np.asarray(buf.g)
    fail = reward_np(ag[:, T], g[:, T]) < 0
    fail[n:] = False
    return fail


def brute_matches(buf):
    """Every (i, p, j, q) with i != j failed, p >= 1, and equal cells, by plain loops."""
    fail = failed_slots(buf)
    ag, g = np.round(np.asarray(buf.ag) / TOL), np.round(np.asarray(buf.g) / TOL)
    W = buf.horizon + 1
    out = set()
    for i in np.flatnonzero(fail):
        for p in range(1, W):
            for j in np.flatnonzero(fail):
                if j == i:
                    continue
                for q in range(W):
                    if np.array_equal(ag[i, p], g[j, q]):
                        out.add((int(i), p, int(j), q))
    return out


def check_index(keys, idx, buf, field):
    """The sorted index holds exactly the failed episodes' points, each once."""
    keys, idx = np.asarray(keys), np.asarray(idx)
    assert np.all(np.diff(keys.astype(np.int64)) >= 0)
    W = buf.horizon + 1
    shift = max(1, (W - 1).bit_length())  # points are slot << shift | step
    idx = (idx >> shift) * W + (idx & ((1 << shift) - 1))
    np.testing.assert_array_equal(np.sort(idx), np.arange(idx.size))
    fail = failed_slots(buf)
    want_keys = np.asarray(dher.cell_keys(jnp.asarray(getattr(buf, field)), TOL)).reshape(-1)
    live = np.repeat(fail, W)
    expect = np.where(live, want_keys, dher.SENTINEL)
    np.testing.assert_array_equal(keys, expect[idx])


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_adds=st.integers(1, 9), span=st.integers(2, 4))
def test_dher_index_and_records_match_brute_force(seed, n_adds, span):
    """After every cycle (ring wraparound included, since cap=5 slots receive up to 18
    episodes), the index covers exactly the failed episodes and every current match of an
    achieved point is recorded."""
    rng = np.random.default_rng(seed)
    cap, T, n_new = 5, 4, 2
    f, update, _, add = dher_fns(cap, T, n_new, partners=64)
    buf = rb.init(cap * T, T, OBS, D, ACT)
    state = f.init()
    for _ in range(n_adds):
        buf = add(buf, random_episodes(rng, n_new, T, span))
        state = update(state, buf, PARAMS)
        check_index(state.g_keys, state.g_idx, buf, "g")
        check_index(state.ag_keys, state.ag_idx, buf, "ag")
    matches = brute_matches(buf)
    usable = {mt for mt in matches if mt[3] >= 1}
    gen = np.asarray(state.slot_gen)
    n = int(state.rec_count)
    rec = [tuple(int(x) for x in r) for r in zip(
        *(np.asarray(getattr(state, f))[:n] for f in ("rec_i", "rec_p", "rec_j", "rec_q",
                                                       "rec_gi", "rec_gj")), strict=True)]
    live = {r[:4] for r in rec if r[4] == gen[r[0]] and r[5] == gen[r[2]]}
    # Sound: every live record is a current match of two failed episodes with p, q >= 1.
    assert live <= usable
    # Complete: every achieved point with a usable match has a live record.
    assert {(i, p) for i, p, _, _ in usable} <= {(i, p) for i, p, _, _ in live}
    # The recent success rate is that of the stored episodes (all of them: fewer than 100).
    fail = failed_slots(buf)[: int(buf.num_episodes)]
    assert float(state.success_rate) == pytest.approx(1.0 - fail.mean())


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_adds=st.integers(2, 8))
def test_dher_combined_rows_are_algorithm_1(seed, n_adds):
    """Each valid combined row is a genuine current match, built exactly as Algorithm 1
    defines it, and the draws reach every match of the buffer."""
    rng = np.random.default_rng(seed)
    cap, T, n_new, batch = 5, 4, 2, 4096
    f, update, _, add = dher_fns(cap, T, n_new, partners=64)
    gather = jax.jit(f.gather_combined)
    buf = rb.init(cap * T, T, OBS, D, ACT)
    state = f.init()
    for _ in range(n_adds):
        buf = add(buf, random_episodes(rng, n_new, T, 2))
        state = update(state, buf, PARAMS)
    bits = f.draw_combined(jax.random.PRNGKey(seed % 1000), batch)
    tr, ok = jax.tree.map(np.asarray, gather(bits, state, buf, PARAMS))  # numpy: indexed per row
    matches = brute_matches(buf)
    obs, ag, g, act = (np.asarray(x) for x in (buf.obs, buf.ag, buf.g, buf.action))
    i, s, j, shift = tr.ep, tr.t, tr.goal_ep, tr.goal_shift
    seen = set()
    for r in np.flatnonzero(ok):
        # Recover (p, q, m, t) from the row and check it against the definition.
        p_q = [(p, q) for (ii, p, jj, q) in matches
               if ii == i[r] and jj == j[r] and q - p == shift[r] and p - min(p, q) <= s[r] < p]
        assert p_q, f"row {r} is not a current match"
        seen.update((i[r], p, j[r], q) for p, q in p_q)
        p, q = p_q[0]  # any of them gives the same row: its goals are g[j, s + q - p]
        m, t = min(p, q), s[r] - (p - min(p, q))
        np.testing.assert_array_equal(tr.obs[r], obs[i[r], p - m + t])
        np.testing.assert_array_equal(tr.action[r], act[i[r], p - m + t])
        np.testing.assert_array_equal(tr.next_obs[r], obs[i[r], p - m + t + 1])
        np.testing.assert_array_equal(tr.goal[r], g[j[r], q - m + t])
        np.testing.assert_array_equal(tr.next_goal[r], g[j[r], q - m + t + 1])
        assert tr.reward[r] == reward_np(ag[i[r], p - m + t + 1], g[j[r], q - m + t + 1])
        assert tr.source[r] == DHER
    # A match at q = 0 has m = 0: nothing to relabel. With 4096 draws over a handful of
    # records, every point with a usable match is drawn.
    usable = {(a, b) for a, b, _, q in matches if q >= 1}
    if usable:
        assert ok.any()
        assert usable == {(int(a), int(b)) for a, b, _, _ in seen}


def hand_made_buffer():
    """Three episodes, T = 6, on a grid. E0 fails and its achieved goal at p = 3 equals E1's
    (moving) desired goal at q = 5; E1 fails; E2 succeeds and also has that goal."""
    T, W = 6, 7
    far = np.array([50.0, 50.0, 50.0])
    ag = np.zeros((3, W, D), np.float32)
    g = np.zeros((3, W, D), np.float32)
    ag[0] = np.arange(W)[:, None] * np.array([1.0, 0.0, 0.0]) + 10.0  # (10..16, 10, 10)
    g[0] = far
    ag[1] = far + 7.0
    g[1] = np.arange(W)[:, None] * np.array([0.0, 1.0, 0.0]) + np.array([13.0, 5.0, 10.0])
    g[1, 5] = ag[0, 3]  # the one cross-episode match (E1's goal moves; a jump at q = 5)
    ag[2] = ag[0, 3]
    g[2] = ag[0, 3]  # E2 succeeds: never a partner
    obs = np.arange(3 * W * OBS, dtype=np.float32).reshape(3, W, OBS)
    act = -np.arange(3 * T * ACT, dtype=np.float32).reshape(3, T, ACT)
    return rb.Episode(obs=obs, ag=ag, g=g, action=act)


def test_dher_hand_made_episodes():
    ep = hand_made_buffer()
    T = 6
    f = dher.build_dher(reward_fn, 64, 4, T, D, num_new=3, records=4096, partners=8)
    buf = rb.add(rb.init(4 * T, T, OBS, D, ACT), ep)
    state = jax.jit(f.update)(f.init(), buf, PARAMS)
    n = int(state.rec_count)
    recs = {tuple(int(x) for x in r) for r in zip(
        *(np.asarray(getattr(state, f))[:n] for f in ("rec_i", "rec_p", "rec_j", "rec_q")),
        strict=True)}
    assert recs == {(0, 3, 1, 5)}
    assert float(state.success_rate) == pytest.approx(1 / 3)
    tr, ok = jax.jit(f.gather_combined)(f.draw_combined(jax.random.PRNGKey(0), 512), state,
                                        buf, PARAMS)
    ok = np.asarray(ok)
    assert ok.all()
    # p = 3, q = 5, m = 3: E0's steps 0, 1, 2 with E1's goals 2..3, 3..4, 4..5.
    assert set(np.asarray(tr.t).tolist()) == {0, 1, 2}
    for r in range(512):
        t = int(tr.t[r])
        np.testing.assert_array_equal(tr.goal[r], ep.g[1, 2 + t])
        np.testing.assert_array_equal(tr.next_goal[r], ep.g[1, 3 + t])
        np.testing.assert_array_equal(tr.obs[r], ep.obs[0, t])
        np.testing.assert_array_equal(tr.next_obs[r], ep.obs[0, t + 1])
        np.testing.assert_array_equal(tr.action[r], ep.action[0, t])
    # Only the last combined step reaches the cloned goal.
    np.testing.assert_array_equal(np.asarray(tr.reward), np.where(np.asarray(tr.t) == 2, 0, -1))


def test_dher_sample_mixes_by_recent_success():
    """With matches everywhere, the combined share is dher_fraction * (1 - success rate)."""
    ep = hand_made_buffer()
    T, n = 6, 20_000
    f = dher.build_dher(reward_fn, n, 4, T, D, num_new=3, records=4096, partners=8)
    buf = rb.add(rb.init(4 * T, T, OBS, D, ACT), ep)
    state = f.update(f.init(), buf, PARAMS)
    for frac in (0.0, 0.5, 0.8):
        params = PARAMS.replace(dher_fraction=jnp.float32(frac), relabel_prob=jnp.float32(0.8))
        tr = jax.jit(f.sample)(jax.random.PRNGKey(1), state, buf, params, jnp.int32(0))
        src = np.asarray(tr.source)
        want = frac * (1 - 1 / 3)
        assert abs((src == DHER).mean() - want) < 5 * np.sqrt(want * (1 - want) / n) + 1e-9
        # The rest are HER-sampled: relabelled with probability 0.8.
        rest = src[src != DHER]
        assert abs((rest == HER).mean() - 0.8) < 0.02


@settings(max_examples=12, deadline=None)  # each new shape compiles the merge anew
@given(seed=st.integers(0, 2**31 - 1), P=st.integers(1, 60), n=st.integers(1, 12))
def test_merge_equals_sort(seed, P, n):
    rng = np.random.default_rng(seed)
    n = min(n, P)
    keys = np.sort(rng.integers(0, 8, P)).astype(np.int32)
    idx = rng.permutation(P).astype(np.int32)
    drop = np.zeros(P, bool)
    drop[rng.choice(P, n, replace=False)] = True
    new_keys = rng.integers(0, 8, n).astype(np.int32)
    new_idx = (1000 + np.arange(n)).astype(np.int32)
    k, i = dher.merge(jnp.asarray(keys), jnp.asarray(idx), jnp.asarray(drop),
                      jnp.asarray(new_keys), jnp.asarray(new_idx))
    # The exact order: by key, an equal key's kept entries first (in their old order), then
    # its new ones in the order the merge's own sort gives them (the runs' matches, and so
    # their rows, depend on it).
    nk, ni = (np.asarray(a) for a in jax.lax.sort((jnp.asarray(new_keys), jnp.asarray(new_idx)),
                                                   num_keys=1))
    entries = [(int(a), 0, r, int(b)) for r, (a, b) in enumerate(zip(keys[~drop], idx[~drop],
                                                                     strict=True))]
    entries += [(int(a), 1, r, int(b)) for r, (a, b) in enumerate(zip(nk, ni, strict=True))]
    want = sorted(entries)
    np.testing.assert_array_equal(np.asarray(k), [e[0] for e in want])
    np.testing.assert_array_equal(np.asarray(i), [e[3] for e in want])


@pytest.mark.parametrize("seed, lam", [(0, 1.0), (1, 30.0), (2, 0.0)])
def test_cher_selection_matches_numpy(seed, lam):
    rng = np.random.default_rng(seed)
    C, K = 24, 10
    goals = rng.normal(0, 0.1, (C, D)).astype(np.float32)
    prox = rng.uniform(0, 0.3, C).astype(np.float32)
    noise = rng.random((K, 3)).astype(np.float32)
    got = np.asarray(jax.jit(cher.select, static_argnums=4)(goals, prox, jnp.float32(lam),
                                                            noise, 3))
    want = cher_select_np(goals.astype(np.float64), prox, lam, noise, 3)
    np.testing.assert_array_equal(got, want)
    assert len(set(got.tolist())) == K  # no candidate twice


@pytest.mark.parametrize("C, K", [(16, 16), (16, 15), (5, 5)])
def test_cher_selection_takes_each_candidate_once_when_few_remain(C, K):
    """With fewer than ``sample`` candidates left, only those are scored: at candidates ==
    batch_size every candidate is chosen exactly once, whatever the gains (here half the goals
    repeat one, so the last picks would gain most from a candidate already chosen)."""
    rng = np.random.default_rng(C + K)
    goals = rng.normal(0, 0.1, (C, D)).astype(np.float32)
    goals[C // 2:] = goals[0]
    prox = rng.uniform(0, 0.3, C).astype(np.float32)
    noise = rng.random((K, 3)).astype(np.float32)
    got = np.asarray(jax.jit(cher.select, static_argnums=4)(goals, prox, jnp.float32(5.0),
                                                            noise, 3))
    assert len(set(got.tolist())) == K
    np.testing.assert_array_equal(got, cher_select_np(goals.astype(np.float64), prox, 5.0,
                                                      noise, 3))


def test_cher_selection_draws_its_candidates_uniformly():
    """Equal goals and proximities give every scored candidate the same gain, so a pick keeps
    its first draw: over many draws the first pick must be uniform over the candidates, and the
    second uniform over the rest (chi-square against uniform, below its upper 0.1% quantile)."""
    C, n = 12, 24_000
    goals, prox = jnp.zeros((C, D)), jnp.zeros(C)
    noise = jax.random.uniform(jax.random.PRNGKey(0), (n, 2, 3))
    idx = np.asarray(jax.jit(jax.vmap(lambda u: cher.select(goals, prox, 0.0, u, 3)))(noise))
    assert (idx[:, 0] != idx[:, 1]).all()
    for counts, cells in ((np.bincount(idx[:, 0], minlength=C), C),
                          (np.bincount(idx[:, 1] - (idx[:, 1] > idx[:, 0]), minlength=C - 1),
                           C - 1)):
        expected = n / cells
        chi2 = float(((counts - expected) ** 2 / expected).sum())
        assert chi2 < 31.3, (chi2, counts)  # the upper 0.1% quantile of chi2 with 11 d.o.f.


def test_cher_sample_fields_come_from_candidates():
    rng = np.random.default_rng(3)
    T, cap = 5, 6
    buf = rb.add(rb.init(cap * T, T, OBS, D, ACT),
                 random_episodes(rng, cap, T, 3))
    f = cher.build_cher(reward_fn, 16, 32, 3)
    params = PARAMS.replace(relabel_prob=jnp.float32(0.8))
    tr = jax.jit(f.sample)(jax.random.PRNGKey(4), (), buf, params, jnp.int32(7))
    draws, noise = f.draw(jax.random.PRNGKey(4), buf, params.relabel_prob)
    cand = relabel.her.gather_her(buf, *draws, reward_fn)
    prox = np.linalg.norm(np.asarray(cand.goal) - np.asarray(buf.ag)[cand.ep, cand.t], axis=-1)
    idx = cher_select_np(np.asarray(cand.goal, np.float64), prox, 1.0001**7, np.asarray(noise), 3)
    for a, b in zip(jax.tree.leaves(tr), jax.tree.leaves(cand), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[idx])


def test_observed_return_matches_loop():
    rng = np.random.default_rng(5)
    T, cap, gamma = 6, 3, 0.9
    ep = random_episodes(rng, cap, T, 2)
    buf = rb.add(rb.init(cap * T, T, OBS, D, ACT), ep)
    B = 9
    src = np.arange(B) % 3
    ep_idx = rng.integers(0, cap, B)
    real = src == REAL  # real rows follow their own stored goals (goal_ep = ep, no shift)
    tr = relabel.Transition(
        obs=jnp.zeros((B, OBS)), goal=jnp.asarray(rng.integers(0, 2, (B, D)), jnp.float32),
        action=jnp.zeros((B, ACT)), reward=jnp.zeros(B), next_obs=jnp.zeros((B, OBS)),
        next_goal=jnp.zeros((B, D)),
        source=jnp.asarray(src, jnp.int32),
        ep=jnp.asarray(ep_idx, jnp.int32),
        t=jnp.asarray(rng.integers(0, T, B), jnp.int32),
        goal_ep=jnp.asarray(np.where(real, ep_idx, rng.integers(0, cap, B)), jnp.int32),
        goal_shift=jnp.asarray(np.where(real, 0, rng.integers(-3, 4, B)), jnp.int32),
    )
    got = np.asarray(relabel.observed_return(buf, tr, reward_fn, jnp.float32(gamma)))
    for r in range(B):
        e, t, src = int(tr.ep[r]), int(tr.t[r]), int(tr.source[r])
        total = 0.0
        for k in range(t, T):
            if src == HER:
                goal = np.asarray(tr.goal[r])
            elif src == REAL:
                goal = ep.g[e, k + 1]
            else:
                goal = ep.g[int(tr.goal_ep[r]), min(max(k + 1 + int(tr.goal_shift[r]), 0), T)]
            total += gamma ** (k - t) * reward_np(ep.ag[e, k + 1], goal)
        assert got[r] == pytest.approx(total, abs=1e-5)


def test_reward_weights_apply_to_exactly_their_rows():
    """lambda_r on real rows; lambda_h on HER-relabelled and DHER-combined rows."""
    source = jnp.asarray([REAL, HER, DHER, REAL, DHER, HER], jnp.int32)
    tr = relabel.Transition(*(jnp.zeros(6) for _ in range(6)), source=source,
                            ep=source, t=source, goal_ep=source, goal_shift=source)
    h = DDPGParams.default(lambda_r=3.0, lambda_h=0.25, gamma=0.5)
    y = np.asarray(critic_target(-jnp.ones(6), -jnp.ones(6), tr.hindsight, h))
    lam = np.where(np.asarray(source) == REAL, 3.0, 0.25)
    np.testing.assert_allclose(y, np.maximum(-lam - 0.5, -lam / 0.5))


@pytest.mark.parametrize("stop", [False, True])
@pytest.mark.parametrize("n", [1, 3, 8])
def test_n_step_matches_loop(n, stop):
    """n-step rows against a plain loop: rewards summed along the row's goal trajectory, the
    bootstrap state m = min(n, T - t) steps on, discount gamma^m; n = 1 keeps one-step rows."""
    rng = np.random.default_rng(6 + n)
    T, cap, gamma, B = 6, 3, 0.9, 12
    ep = random_episodes(rng, cap, T, 2)
    buf = rb.add(rb.init(cap * T, T, OBS, D, ACT), ep)
    src = np.arange(B) % 3
    ep_idx = rng.integers(0, cap, B)
    t = rng.integers(0, T, B)
    t[:3] = T - 1  # rows at the episode's end, one per source
    real = src == REAL
    shift = np.where(real, 0, rng.integers(-3, 4, B))
    goal_ep = np.where(real, ep_idx, rng.integers(0, cap, B))
    goal = np.where((src == HER)[:, None], rng.integers(0, 2, (B, D)),
                    ep.g[goal_ep, np.clip(t + shift, 0, T)]).astype(np.float32)
    tr = relabel.Transition(
        obs=jnp.asarray(ep.obs[ep_idx, t]), goal=jnp.asarray(goal),
        action=jnp.asarray(ep.action[ep_idx, t]), reward=jnp.zeros(B),
        next_obs=jnp.zeros((B, OBS)), next_goal=jnp.zeros((B, D)),
        source=jnp.asarray(src, jnp.int32), ep=jnp.asarray(ep_idx, jnp.int32),
        t=jnp.asarray(t, jnp.int32), goal_ep=jnp.asarray(goal_ep, jnp.int32),
        goal_shift=jnp.asarray(shift, jnp.int32),
    )
    got = jax.jit(relabel.n_step_returns, static_argnums=(2, 4, 5))(
        buf, tr, n, jnp.float32(gamma), reward_fn, stop)
    ended = 0
    for r in range(B):
        e, t0, s = int(ep_idx[r]), int(t[r]), int(src[r])

        def goal_at(k, r=r, s=s):  # the goal in force at step k of episode e
            if s == HER:
                return goal[r]
            return ep.g[int(goal_ep[r]), min(max(k + int(shift[r]), 0), T)]

        want, m, done = 0.0, 0, False
        while m < min(n, T - t0) and not done:
            rew = reward_np(ep.ag[e, t0 + m + 1], goal_at(t0 + m + 1))
            want += gamma**m * rew
            m += 1
            done = stop and rew == 0
        ended += done
        assert float(got.reward[r]) == pytest.approx(want, abs=1e-5)
        np.testing.assert_array_equal(np.asarray(got.next_obs[r]), ep.obs[e, t0 + m])
        np.testing.assert_array_equal(np.asarray(got.next_goal[r]), goal_at(t0 + m))
        assert float(got.discount[r]) == pytest.approx(0.0 if done else gamma**m, rel=1e-6)
    assert ended > 0 or not stop or n == 1  # the stop is exercised
    # Obs, goal, action and indices are untouched.
    for f in ("obs", "goal", "action", "source", "ep", "t", "goal_ep", "goal_shift"):
        np.testing.assert_array_equal(np.asarray(getattr(got, f)), np.asarray(getattr(tr, f)))


def test_n_step_one_equals_sampled_rows():
    """n = 1 reproduces what each relabeller's own gather computed, for real, HER and DHER
    rows drawn from a real DHER sample."""
    rng = np.random.default_rng(11)
    cap, T = 8, 5
    f, update, _, add = dher_fns(cap, T, 4, 4)
    buf, state = rb.init(cap * T, T, OBS, D, ACT), f.init()
    for _ in range(2):
        buf = add(buf, random_episodes(rng, 4, T, 2))
        state = update(state, buf, PARAMS)
    params = relabel.RelabelParams.default(relabel_prob=0.5, dher_fraction=0.5, dher_tol=TOL)
    tr = jax.jit(f.sample)(jax.random.key(0), state, buf, params, jnp.int32(0))
    assert {0, 1, 2} <= set(np.asarray(tr.source).tolist())
    got = relabel.n_step_returns(buf, tr, 1, jnp.float32(0.9), reward_fn)
    for name in ("reward", "next_obs", "next_goal"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)),
                                      np.asarray(getattr(tr, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.discount), 0.9, rtol=1e-6)


def test_terminal_rules_set_discount_zero_on_exactly_their_rows():
    rng = np.random.default_rng(3)
    T, cap, B = 6, 3, 40
    ep = random_episodes(rng, cap, T, 2)
    buf = rb.add(rb.init(cap * T, T, OBS, D, ACT), ep)
    e = rng.integers(0, cap, B)
    t = rng.integers(0, T, B)
    ag1 = ep.ag[e, t + 1]
    # Rows take the very next achieved goal (reward 0, 'exact'), a goal near it (reward 0, not
    # exact) or one far from it (reward -1), in turn.
    near = ag1 + rng.uniform(-0.2, 0.2, (B, D))
    far = ag1 + 2.0
    goal = np.choose((np.arange(B) % 3)[:, None], [ag1, near, far]).astype(np.float32)
    reward = reward_np(ag1, goal)
    tr = relabel.Transition(
        obs=jnp.zeros((B, OBS)), goal=jnp.asarray(goal), action=jnp.zeros((B, ACT)),
        reward=jnp.asarray(reward), next_obs=jnp.zeros((B, OBS)), next_goal=jnp.asarray(goal),
        source=jnp.full(B, HER, jnp.int32), ep=jnp.asarray(e, jnp.int32),
        t=jnp.asarray(t, jnp.int32), goal_ep=jnp.asarray(e, jnp.int32),
        goal_shift=jnp.zeros(B, jnp.int32),
    )
    g = jnp.float32(0.9)
    assert relabel.mark_terminal(buf, tr, "none", g) is tr
    exact = np.all(goal == ag1, axis=-1)
    success = reward == 0
    assert exact.sum() < success.sum()  # the two rules differ on this batch
    for rule, want in (("exact", exact), ("success", success)):
        got = np.asarray(relabel.mark_terminal(buf, tr, rule, g).discount)
        np.testing.assert_allclose(got, np.where(want, 0.0, 0.9), rtol=1e-6)
    # Terminal rows' targets are their rewards: the critic target honours the discount.
    h = DDPGParams.default(gamma=0.9)
    y = critic_target(tr.reward, jnp.full(B, -3.0), tr.hindsight, h,
                      relabel.mark_terminal(buf, tr, "success", g).discount)
    np.testing.assert_allclose(np.asarray(y), np.where(success, 0.0, -1.0 - 2.7), rtol=1e-6)
    with pytest.raises(ValueError, match="unknown terminal rule"):
        relabel.mark_terminal(buf, tr, "sometimes", g)


@pytest.mark.parametrize("algo", ["her", "cher", "dher"])
def test_every_strategy_samples_a_transition_and_keeps_its_state_shape(algo):
    """The interface: ``sample`` returns only the batch (it never changes the state), and
    ``update`` returns a state of the shape ``init`` made, so both fit a ``lax.scan``."""
    cfg = resolve(Config(env="FetchReach", algo=algo, batch_size=16, num_envs=2))
    T, cap = 5, 8
    rl = relabel.make_relabeller(cfg, reward_fn, cap, T, D)
    ep = random_episodes(np.random.default_rng(0), 2, T, 2)
    buf = rb.add(rb.init(cap * T, T, OBS, D, ACT), ep)
    params = relabel.params_from_config(cfg)
    state = rl.init()
    new_state = jax.eval_shape(rl.update, state, buf, params)
    assert jax.tree.structure(new_state) == jax.tree.structure(state)
    assert all(a.shape == b.shape and a.dtype == b.dtype for a, b in
               zip(jax.tree.leaves(new_state), jax.tree.leaves(state), strict=True))
    tr = jax.eval_shape(rl.sample, jax.random.key(0), state, buf, params, jnp.int32(0))
    assert isinstance(tr, relabel.Transition)
    assert tr.obs.shape == (16, OBS) and tr.source.shape == (16,)


def test_merge_is_not_quadratic_in_the_new_keys():
    """A GPU run merges num_envs x 51 new points a cycle (208,896 at 4,096 envs): no
    intermediate of the merge may grow with their square."""
    P, n = 4096, 512
    args = (jax.ShapeDtypeStruct((P,), jnp.int32), jax.ShapeDtypeStruct((P,), jnp.int32),
            jax.ShapeDtypeStruct((P,), jnp.bool_), jax.ShapeDtypeStruct((n,), jnp.int32),
            jax.ShapeDtypeStruct((n,), jnp.int32))

    def sizes(jaxpr):  # every intermediate, those of nested programs (pjit, scan, ...) too
        for e in jaxpr.eqns:
            yield from (int(np.prod(v.aval.shape)) for v in e.outvars)
            for val in e.params.values():
                for x in val if isinstance(val, (tuple, list)) else (val,):
                    inner = getattr(x, "jaxpr", x)
                    if hasattr(inner, "eqns"):
                        yield from sizes(inner)

    assert max(sizes(jax.make_jaxpr(dher.merge)(*args).jaxpr)) < n * n
