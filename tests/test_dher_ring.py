"""DHER's ring of recorded matches and its per-point partner cap, against a numpy replay of
Algorithm 1's matching cycle by cycle (``rdher_jax.relabel.dher`` documents the rule).

The rule, as the replay below implements it with plain loops: after each cycle's new episodes
are stored, for every new failed episode

(a) each achieved point ``(i, p)`` is looked up among the desired points of all stored failed
    episodes in its cell, and
(b) each desired cell ``(j, q)`` (only the last step of a run of equal cells) among the achieved
    points of the older stored failed episodes;

a lookup's matching range is ordered oldest episode first, then by step, and of ``cnt`` entries
it takes ``min(cnt, partners)``: all of them, or the ``floor(k * cnt / partners)``-th for
``k < partners`` (spread evenly). A pick is recorded when ``i != j``, ``p >= 1`` and ``q >= 1``
(so the cap counts the picks that are then dropped). Records go into a ring of ``records`` in
the order (a) then (b), query by query; a record is live while both its episodes are stored.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rdher_jax import buffer as rb
from rdher_jax import relabel
from rdher_jax.config import Config
from rdher_jax.relabel import dher as dher_mod

OBS, ACT, D = 2, 2, 3
CAP, T, NEW = 5, 4, 2  # 5 slots of episodes of 4 steps, 2 new episodes per cycle
W = T + 1
PARAMS = relabel.RelabelParams.default(relabel_prob=0.0, dher_fraction=1.0, dher_tol=1.0)


def reward_fn(achieved, desired):
    return -(jnp.linalg.norm(achieved - desired, axis=-1) > 0.5).astype(jnp.float32)


@functools.cache
def dher(partners: int, records: int):
    cfg = Config(algo="dher", batch_size=64, num_envs=NEW, dher_records=records,
                 dher_partners=partners)
    r = relabel.make_relabeller(cfg, reward_fn, CAP, T, D)
    return r, jax.jit(r.update), jax.jit(rb.add)


def episodes(rng, n, span=2):
    """Goals on a grid of span**3 one-metre cells (tolerance 1 m): matches everywhere."""
    return rb.Episode(
        obs=rng.standard_normal((n, W, OBS)).astype(np.float32),
        ag=rng.integers(0, span, (n, W, D)).astype(np.float32),
        g=rng.integers(0, span, (n, W, D)).astype(np.float32),
        action=rng.standard_normal((n, T, ACT)).astype(np.float32),
    )


class Replay:
    """Algorithm 1's matching with the partner cap, replayed over episode ids (the n-th episode
    ever stored has id n and lives in slot n % CAP until id n + CAP overwrites it)."""

    def __init__(self, partners: int):
        self.partners = partners
        self.stored: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # id -> (ag, g), failed only
        self.written = 0
        self.records: list[tuple[int, int, int, int]] = []  # (id_i, p, id_j, q)
        self.capped = 0  # lookups whose range held more than `partners` entries

    def picks(self, field: int, cell: np.ndarray) -> list[tuple[int, int]]:
        rng = [(e, s) for e in sorted(self.stored) for s in range(W)
               if np.array_equal(self.stored[e][field][s], cell)]
        cnt, P = len(rng), self.partners
        self.capped += cnt > P
        return [rng[k if cnt <= P else k * cnt // P] for k in range(min(cnt, P))]

    def cycle(self, ep: rb.Episode) -> None:
        new = list(range(self.written, self.written + NEW))
        self.written += NEW
        for e in new:
            self.stored.pop(e - CAP, None)
        for k, e in enumerate(new):
            if not np.array_equal(ep.ag[k, T], ep.g[k, T]):  # failed (grid goals: exact)
                self.stored[e] = (ep.ag[k], ep.g[k])
        failed = [e for e in new if e in self.stored]
        for i in failed:  # (a)
            for p in range(W):
                for j, q in self.picks(1, self.stored[i][0][p]):
                    if i != j and p >= 1 and q >= 1:
                        self.records.append((i, p, j, q))
        for j in failed:  # (b)
            g = self.stored[j][1]
            for q in range(W):
                if q < T and np.array_equal(g[q], g[q + 1]):
                    continue
                for i, p in self.picks(0, g[q]):
                    if i < new[0] and p >= 1 and q >= 1:
                        self.records.append((i, p, j, q))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("partners, records, wraps, capped", [
    (2, 40, True, True),  # the smallest ring one cycle may need (2 * NEW * W * partners)
    (2, 4096, False, True),
    (16, 320, True, False),
])
def test_ring_holds_the_newest_records_of_the_capped_matching(seed, partners, records, wraps,
                                                               capped):
    r, update, add = dher(partners, records)
    rng = np.random.default_rng(seed)
    buf, state = rb.init(CAP * T, T, OBS, D, ACT), r.init()
    replay = Replay(partners)
    for _ in range(30):  # 60 episodes through 5 slots
        ep = episodes(rng, NEW)
        buf = add(buf, ep)
        state = update(state, buf, PARAMS)
        replay.cycle(ep)
    n = len(replay.records)
    assert (n > records) == wraps and (replay.capped > 0) == capped
    assert int(state.rec_count) == min(n, records) and int(state.rec_pos) == n % records
    # The ring, oldest first, against the newest min(n, records) records of the replay.
    kept = replay.records[n - min(n, records):]
    pos = [(n - len(kept) + k) % records for k in range(len(kept))]
    ring = [tuple(int(np.asarray(getattr(state, f))[x]) for f in ("rec_i", "rec_p", "rec_j",
                                                                   "rec_q")) for x in pos]
    assert ring == [(i % CAP, p, j % CAP, q) for i, p, j, q in kept]
    # A slot's generation counts its writes: episode id e is the (e // CAP + 1)-th in its slot.
    gi, gj = np.asarray(state.rec_gi)[pos], np.asarray(state.rec_gj)[pos]
    np.testing.assert_array_equal(gi, [i // CAP + 1 for i, _, _, _ in kept])
    np.testing.assert_array_equal(gj, [j // CAP + 1 for _, _, j, _ in kept])
    # Live records (both episodes still stored) are exactly the replay's whose ids are stored.
    gen = np.asarray(state.slot_gen)
    live = [rec for rec, a, b in zip(ring, gi, gj, strict=True)
            if a == gen[rec[0]] and b == gen[rec[2]]]
    oldest = replay.written - CAP
    want = [(i % CAP, p, j % CAP, q) for i, p, j, q in kept if i >= oldest and j >= oldest]
    assert live == want
    assert 0 < len(live) < len(ring)  # some recorded episodes were overwritten since


def test_per_cycle_merges_keep_the_index_one_sort_gives():
    """After cycles that fill and wrap the buffer, the incrementally merged indices hold the
    same (key, point) pairs as one sort of the whole buffer (dher.index_buffer), in key order."""
    r, update, add = dher(2, 4096)
    rng = np.random.default_rng(3)
    buf, state = rb.init(CAP * T, T, OBS, D, ACT), r.init()
    for _ in range(7):  # 14 episodes through 5 slots
        buf = add(buf, episodes(rng, NEW, span=3))
        state = update(state, buf, PARAMS)
    bulk = jax.jit(dher_mod.index_buffer, static_argnums=3)(r.init(), buf, PARAMS.dher_tol,
                                                              reward_fn)
    for keys, idx in (("g_keys", "g_idx"), ("ag_keys", "ag_idx")):
        a_k, a_i = np.asarray(getattr(bulk, keys)), np.asarray(getattr(bulk, idx))
        b_k, b_i = np.asarray(getattr(state, keys)), np.asarray(getattr(state, idx))
        assert np.all(np.diff(b_k.astype(np.int64)) >= 0), keys
        assert (a_k != dher_mod.SENTINEL).sum() > 0, keys  # some failed episodes indexed
        oa, ob = np.lexsort((a_i, a_k)), np.lexsort((b_i, b_k))
        np.testing.assert_array_equal(a_k[oa], b_k[ob], err_msg=keys)
        np.testing.assert_array_equal(a_i[oa], b_i[ob], err_msg=idx)
