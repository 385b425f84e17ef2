"""DHER: goal matching and trajectory combination across failed episodes (RDHER section 4.1).

Algorithm 1 of the paper: among failed episodes, find ``E_i, E_j`` (``i != j``) with
``ag[i, p] == g[j, q]``; with ``m = min(p, q)``, clone E_j's desired-goal trajectory
``g^h_t = g[j, q - m + t]`` and relabel E_i's transitions ``p - m ... p - 1`` with it; the
reward is recomputed with ``compute_reward``.

Matching on device, over the whole buffer
-----------------------------------------
"Equal" means equal cells of a grid of ``dher_tol`` metres (the authors key positions as
``"%.2f"`` strings, a 1 cm grid). Every stored point (slot, step) of a *failed* episode has an
int32 cell key; two sorted indices, one of desired-goal keys and one of achieved-goal keys,
cover the whole buffer (points of successful or unwritten episodes carry a sentinel key that
sorts last). A cycle does not re-sort them: the points of the slots just overwritten are
dropped and the new episodes' points merged in, in one pass linear in the buffer (``merge``).

New matches can only involve the new episodes, so each cycle looks up (binary search)

- every achieved point of a new failed episode among all desired points, and
- every desired cell of a new failed episode among all older achieved points,

takes up to ``partners`` matches of each, spread evenly over the matching range, and appends
the pairs ``(i, p, j, q)`` to a ring of ``records``, as the authors record matches when episodes
are stored. Sampling draws a record, checks that both episodes are still stored (slot
generations) and builds the combined transition; a dead record falls back to a plain sample.
Nothing is ever a host hash table, nothing is quadratic in the buffer, and a sample does no
search at all.

Mixing
------
As in the authors' code, ``dher_fraction * (1 - s)`` of a batch are combined transitions, with
``s`` the success rate of the last 100 stored episodes. Unlike their code, the rest are sampled
with 'future' relabelling at ``relabel_prob`` (set ``replay_k=0`` for their plain samples): on
the static-goal Fetch tasks exact matches are rare, and without 'future' goals DHER would train
almost only on real rewards there (see docs/algorithms.md, "Mixing").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from rdher_jax.buffer import BufferState
from rdher_jax.relabel import her
from rdher_jax.relabel.base import DHER, Relabeller, RewardFn, Transition

SENTINEL = jnp.iinfo(jnp.int32).max
RECENT = 100  # episodes behind the success rate that sets the combined fraction


@struct.dataclass
class DHERState:
    """Match indices over the whole buffer, and the recorded matches.

    Attributes:
        g_keys, g_idx: ``(P,)`` sorted cell keys of desired goals and their points
            (``slot << SHIFT | step``), ``P = capacity_episodes * (T+1)``.
        ag_keys, ag_idx: the same for achieved goals.
        slot_gen: ``(capacity_episodes,)`` int32, how often each slot was written.
        rec_i, rec_p, rec_j, rec_q: ``(records,)`` int32 ring of matches
            ``ag[i, p] == g[j, q]`` (``i != j`` failed, ``p, q >= 1``).
        rec_gi, rec_gj: generations of slots ``i`` and ``j`` when the match was recorded; a
            record is live while both slots still hold those episodes.
        rec_pos: int32 next record to write. rec_count: int32 records stored.
        success_rate: float32 success of the last 100 stored episodes.
    """

    g_keys: jax.Array
    g_idx: jax.Array
    ag_keys: jax.Array
    ag_idx: jax.Array
    slot_gen: jax.Array
    rec_i: jax.Array
    rec_p: jax.Array
    rec_j: jax.Array
    rec_q: jax.Array
    rec_gi: jax.Array
    rec_gj: jax.Array
    rec_pos: jax.Array
    rec_count: jax.Array
    success_rate: jax.Array


def cells(x: jax.Array, tol: jax.Array) -> jax.Array:
    """Grid cell of each point: ``round(x / tol)`` as int32, ``(..., d)``."""
    return jnp.round(x / tol).astype(jnp.int32)


def cell_keys(x: jax.Array, tol: jax.Array) -> jax.Array:
    """One int32 key per point, packing ``30 // d`` low bits of each cell coordinate.

    Keys of different cells can collide only when the cells are ``2**(30 // d)`` cells apart
    (10 m at 1 cm for 3-D goals); matches are re-checked on the cells themselves.
    """
    c = cells(x, tol)
    d = c.shape[-1]
    bits = 30 // d
    mask = (1 << bits) - 1
    key = jnp.zeros(c.shape[:-1], jnp.int32)
    for k in range(d):
        key = (key << bits) | (c[..., k] & mask)
    return key


def cumsum(x: jax.Array) -> jax.Array:
    """Inclusive prefix sum of an int32 vector as a parallel scan. On XLA:CPU ``jnp.cumsum``
    of the index's million entries takes 2-4x as long (``experiments/results/bench_relabel.md``)."""
    return jax.lax.associative_scan(jnp.add, x)


def merge(keys: jax.Array, idx: jax.Array, drop: jax.Array, new_keys: jax.Array,
          new_idx: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Sorted ``(keys, idx)`` without the ``drop``-ped entries and with the new ones merged in.

    ``drop`` must mark exactly ``len(new_keys)`` entries, so the size stays fixed. A kept entry
    goes before new entries with an equal key. Linear in the size: one prefix sum and one
    scatter, plus a binary search per new key into the old ones.
    """
    P, n = keys.shape[0], new_keys.shape[0]
    new_keys, new_idx = jax.lax.sort((new_keys, new_idx), num_keys=1)
    # New key j goes after the old keys <= it: lo[j] is the first old entry above it, so an old
    # entry i moves up by the new keys with lo <= i, and down by the dropped entries before it.
    lo = jnp.searchsorted(keys, new_keys, side="right", method="scan").astype(jnp.int32)
    c = cumsum((~drop).astype(jnp.int32) + jnp.zeros(P, jnp.int32).at[lo].add(1, mode="drop"))
    pos_old = jnp.where(drop, P, c - 1)
    # The kept entries before lo[j]: c counts them and the new keys with lo < lo[j] (lo is
    # sorted, as the new keys are: a search, not an n x n compare; n is 51 per env).
    earlier = jnp.searchsorted(lo, lo, side="left", method="scan").astype(jnp.int32)
    kept_before = jnp.where(lo > 0, c[jnp.maximum(lo - 1, 0)] - earlier, 0)
    pos_new = kept_before + jnp.arange(n, dtype=jnp.int32)
    # Every kept entry and every new one lands on a distinct position of [0, P); dropped ones
    # all go to P and are discarded.
    out_k = keys.at[pos_old].set(keys, mode="drop").at[pos_new].set(new_keys)
    out_i = idx.at[pos_old].set(idx, mode="drop").at[pos_new].set(new_idx)
    return out_k, out_i


class DHERFns(NamedTuple):
    """DHER's functions: the ``Relabeller`` three, and the draws / gather split of combined
    rows so a reference can be fed the same draws."""

    init: Callable
    update: Callable
    sample: Callable
    draw_combined: Callable
    gather_combined: Callable


def point_ids(capacity_episodes: int, W: int) -> jax.Array:
    """Every point's id, slot-major: ``slot << shift | step`` (a point is found without a
    division)."""
    shift = max(1, (W - 1).bit_length())
    return ((jnp.arange(capacity_episodes, dtype=jnp.int32)[:, None] << shift)
            | jnp.arange(W, dtype=jnp.int32)[None, :]).reshape(-1)


def index_buffer(state: DHERState, buffer: BufferState, tol: jax.Array,
                 compute_reward: RewardFn) -> DHERState:
    """``state`` with both indices rebuilt from every stored episode by one sort: what the
    per-cycle merges of ``update`` maintain (the same (key, point) pairs), for a buffer filled
    at once, e.g. a benchmark's or a test's."""
    cap, W = buffer.ag.shape[:2]
    failed = compute_reward(buffer.ag[:, W - 1], buffer.g[:, W - 1]) < 0
    points = point_ids(cap, W)

    def index(x):
        keys = jnp.where(failed[:, None], cell_keys(x, tol), SENTINEL).reshape(-1)
        return jax.lax.sort((keys, points), num_keys=1, is_stable=True)

    (g_keys, g_idx), (ag_keys, ag_idx) = index(buffer.g), index(buffer.ag)
    return state.replace(g_keys=g_keys, g_idx=g_idx, ag_keys=ag_keys, ag_idx=ag_idx)


def make_dher(*args, **kwargs) -> Relabeller:
    """DHER as a ``Relabeller`` (arguments as :func:`build_dher`)."""
    f = build_dher(*args, **kwargs)
    return Relabeller("dher", init=f.init, update=f.update, sample=f.sample)


def build_dher(compute_reward: RewardFn, batch_size: int, capacity_episodes: int, T: int,
               goal_dim: int, num_new: int, records: int = 65536, partners: int = 8) -> DHERFns:
    """DHER relabelling for a buffer of ``capacity_episodes`` slots of horizon ``T``.

    Args:
        compute_reward: the env's ``(achieved, desired) -> reward``.
        batch_size: rows per sample.
        capacity_episodes: buffer slots.
        T: horizon.
        goal_dim: goal size.
        num_new: episodes added per cycle (``num_envs``).
        records: size of the ring of recorded matches.
        partners: achieved points recorded per new desired point.

    Returns:
        :class:`DHERFns`.
    """
    del goal_dim  # shapes come from the buffer; kept for a uniform factory signature
    cap, W = capacity_episodes, T + 1
    P = cap * W
    shift = max(1, (W - 1).bit_length())  # a point is slot << shift | step: no division
    step_mask = (1 << shift) - 1
    n_rec_new = 2 * num_new * W * partners
    if records < n_rec_new:
        raise ValueError(f"dher_records ({records}) must be >= {n_rec_new}, the records one "
                         "cycle can add")
    ks = jnp.arange(partners, dtype=jnp.int32)

    def init() -> DHERState:
        z = jnp.zeros((records,), jnp.int32)
        full = jnp.full((P,), SENTINEL, jnp.int32)
        points = point_ids(cap, W)
        return DHERState(
            g_keys=full, g_idx=points, ag_keys=full, ag_idx=points,
            slot_gen=jnp.zeros((cap,), jnp.int32),
            rec_i=z, rec_p=z, rec_j=z, rec_q=z, rec_gi=z, rec_gj=z,
            rec_pos=jnp.zeros((), jnp.int32), rec_count=jnp.zeros((), jnp.int32),
            success_rate=jnp.zeros((), jnp.float32),
        )

    def failed_of(ag_last: jax.Array, g_last: jax.Array) -> jax.Array:
        return compute_reward(ag_last, g_last) < 0

    def partners_in(keys, idx, query):
        """Up to ``partners`` entries with each query's key, spread evenly over its range:
        their points ``(Q, partners)`` and which are real."""
        lo = jnp.searchsorted(keys, query, side="left", method="scan").astype(jnp.int32)
        hi = jnp.searchsorted(keys, query, side="right", method="scan").astype(jnp.int32)
        cnt = (hi - lo)[:, None]
        off = jnp.where(cnt <= partners, ks[None, :], (ks[None, :] * cnt) // partners)
        pt = idx[jnp.minimum(lo[:, None] + off, P - 1)]
        return pt, (ks[None, :] < cnt) & (query != SENTINEL)[:, None]

    def update(state: DHERState, buffer: BufferState, params) -> DHERState:
        tol = params.dher_tol
        first = (buffer.insert_pos - num_new) % cap
        slots = (first + jnp.arange(num_new, dtype=jnp.int32)) % cap
        gen = state.slot_gen.at[slots].add(1)
        ag, g = buffer.ag[slots], buffer.g[slots]  # (n, W, d)
        failed = failed_of(ag[:, T], g[:, T])  # (n,)
        steps = jnp.arange(W, dtype=jnp.int32)
        pts = ((slots[:, None] << shift) | steps[None, :]).reshape(-1)
        ka = jnp.where(failed[:, None], cell_keys(ag, tol), SENTINEL)  # (n, W)
        kg = jnp.where(failed[:, None], cell_keys(g, tol), SENTINEL)

        def drop(idx):
            return ((idx >> shift) - first) % cap < num_new

        g_keys, g_idx = merge(state.g_keys, state.g_idx, drop(state.g_idx), kg.reshape(-1), pts)
        ag_keys, ag_idx = merge(state.ag_keys, state.ag_idx, drop(state.ag_idx),
                                ka.reshape(-1), pts)

        # (a) each new achieved point against all desired points (new episodes included).
        pt_a, ok_a = partners_in(g_keys, g_idx, ka.reshape(-1))
        i_a = jnp.broadcast_to(jnp.repeat(slots, W)[:, None], pt_a.shape)
        p_a = jnp.broadcast_to(jnp.tile(steps, num_new)[:, None], pt_a.shape)
        j_a, q_a = pt_a >> shift, pt_a & step_mask
        # (b) each new desired cell against all older achieved points. Of a run of steps with
        # the same cell only the last is looked up: it allows the longest combination.
        last = jnp.concatenate([kg[:, 1:] != kg[:, :-1], jnp.ones((num_new, 1), bool)], 1)
        pt_b, ok_b = partners_in(ag_keys, ag_idx, jnp.where(last, kg, SENTINEL).reshape(-1))
        i_b, p_b = pt_b >> shift, pt_b & step_mask
        j_b = jnp.broadcast_to(jnp.repeat(slots, W)[:, None], pt_b.shape)
        q_b = jnp.broadcast_to(jnp.tile(steps, num_new)[:, None], pt_b.shape)
        ok_b = ok_b & ((i_b - first) % cap >= num_new)  # new-with-new matches are (a)'s

        i, p, j, q = (jnp.concatenate([x.reshape(-1), y.reshape(-1)])
                      for x, y in ((i_a, i_b), (p_a, p_b), (j_a, j_b), (q_a, q_b)))
        # Equal keys of different cells (10 m apart) are rejected on the cells themselves.
        same = jnp.all(cells(buffer.ag[i, p], tol) == cells(buffer.g[j, q], tol), axis=-1)
        ok = (jnp.concatenate([ok_a.reshape(-1), ok_b.reshape(-1)]) & same & (i != j)
              & (p >= 1) & (q >= 1))
        rank = jnp.cumsum(ok, dtype=jnp.int32) - 1
        n_ok = jnp.sum(ok, dtype=jnp.int32)
        where = jnp.where(ok, (state.rec_pos + rank) % records, records)

        def put(ring, x):
            return ring.at[where].set(x, mode="drop")

        # Success rate of the last RECENT stored episodes (the newest slots).
        n_ep = buffer.num_episodes
        recent = (buffer.insert_pos - 1 - jnp.arange(RECENT, dtype=jnp.int32)) % cap
        live = jnp.arange(RECENT) < n_ep
        succ = ~failed_of(buffer.ag[recent, T], buffer.g[recent, T])
        rate = jnp.sum(succ & live) / jnp.maximum(jnp.minimum(n_ep, RECENT), 1)

        return DHERState(
            g_keys=g_keys, g_idx=g_idx, ag_keys=ag_keys, ag_idx=ag_idx, slot_gen=gen,
            rec_i=put(state.rec_i, i), rec_p=put(state.rec_p, p),
            rec_j=put(state.rec_j, j), rec_q=put(state.rec_q, q),
            rec_gi=put(state.rec_gi, gen[i]), rec_gj=put(state.rec_gj, gen[j]),
            rec_pos=(state.rec_pos + n_ok) % records,
            rec_count=jnp.minimum(state.rec_count + n_ok, records),
            success_rate=rate.astype(jnp.float32),
        )

    def draw_combined(key: jax.Array, n: int) -> jax.Array:
        """Every random draw of ``n`` combined rows: ``(2, n)`` uint32 bits."""
        return jax.random.bits(key, (2, n), jnp.uint32)

    def gather_combined(bits, state: DHERState, buffer: BufferState, params
                        ) -> tuple[Transition, jax.Array]:
        """Combined transitions for given draws, and which rows are valid (live records)."""
        del params
        n_rec = jnp.maximum(state.rec_count, 1).astype(jnp.uint32)
        r = (bits[0] % n_rec).astype(jnp.int32)
        i, p, j, q = state.rec_i[r], state.rec_p[r], state.rec_j[r], state.rec_q[r]
        ok = ((state.rec_count > 0) & (state.rec_gi[r] == state.slot_gen[i])
              & (state.rec_gj[r] == state.slot_gen[j]))
        m = jnp.maximum(jnp.minimum(p, q), 1)
        # Offset t in [0, m): E_i's step p - m + t with E_j's goals at q - m + t and one later.
        t = (bits[1] % m.astype(jnp.uint32)).astype(jnp.int32)
        s, gq = p - m + t, q - m + t
        next_goal = buffer.g[j, gq + 1]
        tr = Transition(
            obs=buffer.obs[i, s],
            goal=buffer.g[j, gq],
            action=buffer.action[i, s],
            reward=compute_reward(buffer.ag[i, s + 1], next_goal).astype(jnp.float32),
            next_obs=buffer.obs[i, s + 1],
            next_goal=next_goal,
            source=jnp.full_like(i, DHER),
            ep=i, t=s, goal_ep=j, goal_shift=q - p,
        )
        return tr, ok

    def sample(key, state: DHERState, buffer: BufferState, params, step) -> Transition:
        del step
        k_plain, k_comb, k_mix = jax.random.split(key, 3)
        plain = her.sample_her(k_plain, buffer, batch_size, params.relabel_prob, compute_reward)
        comb, ok = gather_combined(draw_combined(k_comb, batch_size), state, buffer, params)
        frac = params.dher_fraction * (1.0 - state.success_rate)
        use = ok & (jax.random.uniform(k_mix, (batch_size,)) < frac)

        def mix(a, b):
            return jnp.where(use.reshape(use.shape + (1,) * (a.ndim - 1)), a, b)

        return jax.tree.map(mix, comb, plain)

    return DHERFns(init, update, sample, draw_combined, gather_combined)
