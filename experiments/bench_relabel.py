"""Relabelling benchmark: the cost of DHER's goal matching against the buffer size, and one
cycle's learner work (40 x sample + DDPG update) for HER, DHER/RDHER and CHER on this CPU.

    python experiments/bench_relabel.py                        # about 3 minutes on 2 cores
    python experiments/bench_relabel.py --quick                # smoke run
    python experiments/bench_relabel.py --sizes 1e4 1e5 --repeats 3 --cycle-size 1e5
    python experiments/bench_relabel.py --limits-script PATH   # also run a machine-limits script

Buffers are synthetic, with the FetchPush dimensions (obs 25, goal 3, action 4, T = 50): desired
goals are static per episode, drawn in a 30 cm box on the table; the object (achieved goal)
either stays where it started, is pushed in a random walk, or (a ``--success`` share of
episodes) is pushed to the goal. DHER's match indices of a full buffer are built by one sort
(checked against the per-cycle merges at the smallest size), then warmed up with cycles that
re-store stored episodes, so its ring of match records is populated as in training.

Every timed function takes the buffer and states as arguments. Variants are interleaved within
each repeat (the order rotates) and reported as medians; ratios are medians of the per-repeat
ratios. Writes ``experiments/results/bench_relabel.md`` and ``.json``.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import harness

HERE = Path(__file__).resolve().parent
OBS, GOAL, ACT, T = 25, 3, 4, 50  # FetchPush
TABLE = (1.34, 0.75, 0.4247)  # centre of the goal box; z: the object resting on the table
BOX = 0.15  # half-width of the goal and object-start box in x and y (a 30 cm box)
THRESHOLD = 0.05
N_BATCHES = 40
TARGETS = {"dher": 1.3, "rdher": 1.3, "cher": 2.0}
MERGE_EVERY = 4  # the suggested DHER change that merges several cycles' episodes at once
# CHER's picks are timed as the selection minus its similarity matrices, two separate timings.
PICKS_IN_NOISE = "below the noise (the selection timed no slower than its similarity alone)"


def merge_before(keys, idx, drop, new_keys, new_idx):
    """``dher.merge`` as it was before its single parallel prefix sum (not library code): two
    ``jnp.cumsum`` over the whole index and a binary search per stored key into the new keys.
    Timed beside the library's merge, which gives the same arrays."""
    import jax
    import jax.numpy as jnp

    P, n = keys.shape[0], new_keys.shape[0]
    new_keys, new_idx = jax.lax.sort((new_keys, new_idx), num_keys=1)
    kept_rank = jnp.cumsum(~drop, dtype=jnp.int32) - 1
    n_new_le = jnp.searchsorted(new_keys, keys, side="left", method="scan_unrolled")
    pos_old = jnp.where(drop, P, kept_rank + n_new_le.astype(jnp.int32))
    lo = jnp.searchsorted(keys, new_keys, side="right", method="scan").astype(jnp.int32)
    dropped_before = jnp.concatenate([jnp.zeros(1, jnp.int32),
                                      jnp.cumsum(drop, dtype=jnp.int32)])[lo]
    pos_new = lo - dropped_before + jnp.arange(n, dtype=jnp.int32)
    out_k = keys.at[pos_old].set(keys, mode="drop").at[pos_new].set(new_keys)
    out_i = idx.at[pos_old].set(idx, mode="drop").at[pos_new].set(new_idx)
    return out_k, out_i


def compute_reward(ag, g):
    import jax.numpy as jnp

    return -(jnp.linalg.norm(ag - g, axis=-1) > THRESHOLD).astype(jnp.float32)


def synth_episodes(key, n: int, success: float, still: float):
    """``n`` FetchPush-like episodes (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    from rdher_jax import buffer as rb

    k = jax.random.split(key, 9)
    centre = jnp.asarray(TABLE, jnp.float32)
    span = jnp.asarray([BOX, BOX, 0.0], jnp.float32)
    goal = centre + jax.random.uniform(k[0], (n, 3), minval=-1, maxval=1) * span
    start = centre + jax.random.uniform(k[1], (n, 3), minval=-1, maxval=1) * span
    u = jax.random.uniform(k[2], (n, 1, 1))
    kind_success = u < success
    kind_still = (u >= success) & (u < success + (1 - success) * still)
    t = (jnp.arange(T + 1, dtype=jnp.float32) / T)[None, :, None]
    contact = jax.random.uniform(k[3], (n, 1, 1), minval=0.1, maxval=0.6)
    # Success: pushed from start to the goal between contact and 90% of the episode.
    prog = jnp.clip((t - contact) / (0.9 - contact), 0.0, 1.0)
    jitter = 0.001 * jax.random.normal(k[4], (n, T + 1, 3)) * span / BOX
    to_goal = start[:, None] + (goal - start)[:, None] * prog + jitter * (prog > 0)
    # Failed push: a 1 cm-per-step random walk in x, y after contact.
    steps = 0.01 * jax.random.normal(k[5], (n, T + 1, 3)) * span / BOX * (t > contact)
    walk = start[:, None] + jnp.cumsum(steps, axis=1)
    still_path = jnp.broadcast_to(start[:, None], (n, T + 1, 3))
    ag = jnp.where(kind_success, to_goal, jnp.where(kind_still, still_path, walk))
    g = jnp.broadcast_to(goal[:, None], (n, T + 1, 3))
    rest = 0.3 * jax.random.normal(k[6], (n, T + 1, OBS - 6))
    grip = ag + 0.02 * jax.random.normal(k[7], (n, T + 1, 3))
    obs = jnp.concatenate([grip, ag, rest], axis=-1)
    action = jax.random.uniform(k[8], (n, T, ACT), minval=-1, maxval=1)
    return rb.Episode(obs=obs, ag=ag, g=g, action=action)


def make_cfg(algo: str, size: int, **overrides):
    from rdher_jax.config import Config, resolve

    return resolve(Config(env="FetchPush", algo=algo, buffer_size=size, run_dir="unused",
                          **overrides))


def full_buffer(key, size: int, success: float, still: float):
    """A full ring buffer of ``size`` transitions; the next slot to write is 0."""
    import jax

    from rdher_jax import buffer as rb

    buf = rb.init(size, T, OBS, GOAL, ACT)
    ep = jax.jit(synth_episodes, static_argnums=(1,))(key, buf.capacity_episodes, success, still)
    return rb.add(buf, ep)


def bulk_index(state, buf, tol):
    """DHER's indices of a full buffer by one sort (``dher.index_buffer``: what the per-cycle
    merges maintain)."""
    from rdher_jax.relabel import dher

    return dher.index_buffer(state, buf, tol, compute_reward)


def replay_cycles(update, state, buf, params, first: int, cycles: int, num_new: int):
    """``cycles`` updates as if the stored episodes at slots ``first, first + num_new, ...`` were
    stored again (same content): fills the ring of records as training would."""
    import jax
    import jax.numpy as jnp

    cap = buf.capacity_episodes

    def body(c, s):
        pos = ((first + (c + 1) * num_new) % cap).astype(jnp.int32)
        return update(s, buf.replace(insert_pos=pos), params)

    return jax.lax.fori_loop(0, cycles, body, state)


def check_bulk(relabeller, buf, params, num_new: int) -> dict:
    """At a small size: the bulk-built indices hold the same (key, point) pairs as the ones the
    per-cycle merges build from empty, and the merged keys are sorted."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    cap = buf.capacity_episodes
    s0 = relabeller.init()
    bulk = jax.jit(bulk_index)(s0, buf, params.dher_tol)

    @jax.jit
    def incremental(s, buf):
        def body(c, s):
            n = (c + 1) * num_new
            b = buf.replace(insert_pos=(n % cap).astype(jnp.int32),
                            num_episodes=jnp.minimum(n, cap).astype(jnp.int32))
            return relabeller.update(s, b, params)

        return jax.lax.fori_loop(0, cap // num_new, body, s)

    inc = incremental(s0, buf)
    ok = True
    for kf, if_ in (("g_keys", "g_idx"), ("ag_keys", "ag_idx")):
        a_k, a_i = np.asarray(getattr(bulk, kf)), np.asarray(getattr(bulk, if_))
        b_k, b_i = np.asarray(getattr(inc, kf)), np.asarray(getattr(inc, if_))
        ok &= bool(np.all(np.diff(b_k.astype(np.int64)) >= 0))
        oa, ob = np.lexsort((a_i, a_k)), np.lexsort((b_i, b_k))
        ok &= bool(np.array_equal(a_k[oa], b_k[ob]) and np.array_equal(a_i[oa], b_i[ob]))
    if not ok:
        raise AssertionError("bulk-built DHER index differs from the per-cycle merges")
    return {"capacity_episodes": cap, "same_pairs_and_sorted": ok}


def update_in_loop(update, k: int):
    """``k`` DHER updates in a jitted loop, as in the trainer's scan over cycles: the state is
    updated in place (a lone jitted call also copies it)."""
    import jax

    @jax.jit
    def f(s, b, p):
        return jax.lax.fori_loop(0, k, lambda _, s: update(s, b, p), s)

    return f


def sample_scan(rl):
    """A jitted scan of ``N_BATCHES`` samples of relabeller ``rl``; returns the batches."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def f(s, b, p, key):
        def body(_, x):
            kk, j = x
            return None, rl.sample(kk, s, b, p, j)

        xs = (jax.random.split(key, N_BATCHES), jnp.arange(N_BATCHES, dtype=jnp.int32))
        return jax.lax.scan(body, None, xs)[1]

    return f


def tree_bytes(tree) -> int:
    from rdher_jax.executor import tree_bytes as sweep_tree_bytes  # one definition

    return sweep_tree_bytes(tree)


def matching_cost(sizes: list[int], repeats: int, min_time: float, args) -> tuple[dict, dict]:
    """Part 1: DHER update and sample against the buffer size, and DHERState's memory."""
    import jax
    import jax.numpy as jnp

    from rdher_jax import buffer as rb
    from rdher_jax.program import hparams_from_config
    from rdher_jax.relabel import DHER, make_relabeller

    bench = harness.Bench(min_time)
    setups, info = {}, {}
    for i, size in enumerate(sizes):
        cfg = make_cfg("dher", size)
        params = hparams_from_config(cfg).relabel
        buf = full_buffer(jax.random.PRNGKey(10 + i), size, args.success, args.still)
        cap = buf.capacity_episodes
        relabeller = make_relabeller(cfg, compute_reward, cap, T, GOAL)
        her = make_relabeller(make_cfg("her", size), compute_reward, cap, T, GOAL)
        if i == 0:
            info["bulk_check"] = check_bulk(relabeller, buf, params, cfg.num_envs)
            print(f"  bulk index check at {size}: {info['bulk_check']}", flush=True)
        t0 = time.perf_counter()
        state = jax.jit(bulk_index)(relabeller.init(), buf, params.dher_tol)
        warm = min(args.warmup_cycles, cap // cfg.num_envs - 1)
        state = jax.jit(replay_cycles, static_argnums=(0, 4, 5, 6))(
            relabeller.update, state, buf, params, 0, warm, cfg.num_envs)
        # The timed update follows adding num_envs fresh episodes at the next slots.
        new = synth_episodes(jax.random.PRNGKey(1000 + i), cfg.num_envs, args.success,
                             args.still)
        buf = rb.add(buf.replace(insert_pos=jnp.int32((warm * cfg.num_envs) % cap)), new)
        jax.block_until_ready(state)
        build_s = time.perf_counter() - t0

        k = args.update_loop
        update_loop = update_in_loop(relabeller.update, k)
        update_once = jax.jit(relabeller.update)

        key = jax.random.PRNGKey(7)
        batches = sample_scan(relabeller)(state, buf, params, key)
        failed = float(jnp.mean(compute_reward(buf.ag[:, T], buf.g[:, T]) < 0))
        info[size] = {
            "capacity_episodes": cap,
            "failed_fraction": failed,
            "warmup_cycles": warm,
            "records_after_warmup": int(state.rec_count),
            "success_rate_last_100": float(state.success_rate),
            "dher_rows_fraction": float(jnp.mean(batches.source == DHER)),
            "state_bytes": tree_bytes(state),
            "state_bytes_per_transition": tree_bytes(state) / size,
            "index_bytes_per_transition": sum(getattr(state, f).nbytes for f in
                                              ("g_keys", "g_idx", "ag_keys", "ag_idx")) / size,
            "buffer_bytes_per_transition": rb.bytes_per_transition(T, OBS, GOAL, ACT),
            "build_s": build_s,
        }
        print(f"  size {size}: {info[size]}", flush=True)
        bench.add(f"update/{size}", update_loop, state, buf, params, per=k)
        bench.add(f"update_call/{size}", update_once, state, buf, params)
        bench.add(f"dher_sample/{size}", sample_scan(relabeller), state, buf, params, key,
                  per=N_BATCHES)
        bench.add(f"her_sample/{size}", sample_scan(her), her.init(), buf, params, key,
                  per=N_BATCHES)
        setups[size] = (cfg, relabeller, state, buf)
    bench.run(repeats)
    rows = {}
    for size in sizes:
        rows[size] = {
            "update_s": bench.med(f"update/{size}"),
            "update_best_s": bench.best(f"update/{size}"),
            "update_call_s": bench.med(f"update_call/{size}"),
            "update_ns_per_transition": bench.med(f"update/{size}") / size * 1e9,
            "dher_sample_s": bench.med(f"dher_sample/{size}"),
            "her_sample_s": bench.med(f"her_sample/{size}"),
            "dher_over_her_sample": bench.ratio(f"dher_sample/{size}", f"her_sample/{size}"),
            **info[size],
        }
    for a, b in zip(sizes, sizes[1:], strict=False):
        rows[b]["exponent_from_previous"] = (math.log(rows[b]["update_s"] / rows[a]["update_s"])
                                             / math.log(b / a))
    return {"rows": rows, "bulk_check": info.get("bulk_check"), "times_s": bench.times,
            "compile_s": bench.compile_s}, setups


def cycle_cost(size: int, repeats: int, min_time: float, args, setups: dict) -> dict:
    """Parts 2 and 3: one cycle's learner work per algorithm, and where its time goes."""
    import jax
    import jax.numpy as jnp

    from rdher_jax import buffer as rb
    from rdher_jax.ddpg import make_ddpg
    from rdher_jax.program import hparams_from_config
    from rdher_jax.relabel import cher as cher_mod
    from rdher_jax.relabel import dher as dher_mod
    from rdher_jax.relabel import her as her_mod
    from rdher_jax.relabel import make_relabeller

    if size in setups:
        _, _, dstate, buf = setups[size]
    else:
        cfg = make_cfg("dher", size)
        buf = full_buffer(jax.random.PRNGKey(99), size, args.success, args.still)
        dstate = None
    cap = buf.capacity_episodes
    algos = ["her", "dher", "rdher", "cher"]
    cfgs = {a: make_cfg(a, size) for a in algos}
    hps = {a: hparams_from_config(cfgs[a]) for a in algos}
    rls = {a: make_relabeller(cfgs[a], compute_reward, cap, T, GOAL) for a in algos}
    cfg = cfgs["her"]
    agent = make_ddpg(OBS, GOAL, ACT, hidden=(cfg.hidden,) * cfg.layers)
    ds = agent.init(jax.random.PRNGKey(0), hps["her"].ddpg)
    norm = rb.Episode(obs=buf.obs[:200], ag=buf.ag[:200], g=buf.g[:200], action=buf.action[:200])
    ds = agent.update_normaliser(ds, norm.obs.reshape(-1, OBS), norm.g.reshape(-1, GOAL))
    if dstate is None:
        p = hps["dher"].relabel
        dstate = jax.jit(bulk_index)(rls["dher"].init(), buf, p.dher_tol)
        warm = min(args.warmup_cycles, cap // cfg.num_envs - 1)
        dstate = jax.jit(replay_cycles, static_argnums=(0, 4, 5, 6))(
            rls["dher"].update, dstate, buf, p, 0, warm, cfg.num_envs)
    states = {"her": (), "cher": (), "dher": dstate, "rdher": dstate}

    def make_learn(rl, agent):
        """As in ``trainer.cycle``: the scan carries the learner; the relabelling state, which
        sampling only reads, stays out of the carry."""

        @jax.jit
        def learn(ds, rs, buf, hp, key, step0):
            def body(ds, x):
                k, i = x
                batch = rl.sample(k, rs, buf, hp.relabel, step0 + i)
                ds, m = agent.update(ds, batch, hp.ddpg)
                return ds, m["critic_loss"]

            xs = (jax.random.split(key, N_BATCHES), jnp.arange(N_BATCHES, dtype=jnp.int32))
            ds, m = jax.lax.scan(body, ds, xs)
            return ds, m

        return learn

    def make_sample(rl):
        @jax.jit
        def sample(rs, buf, hp, key, step0):
            def body(_, x):
                k, i = x
                return None, rl.sample(k, rs, buf, hp.relabel, step0 + i)

            xs = (jax.random.split(key, N_BATCHES), jnp.arange(N_BATCHES, dtype=jnp.int32))
            return jax.lax.scan(body, None, xs)[1]

        return sample

    @jax.jit
    def updates_only(ds, batch, hp):
        def body(ds, _):
            ds, m = agent.update(ds, batch, hp.ddpg)
            return ds, m["critic_loss"]

        return jax.lax.scan(body, ds, None, length=N_BATCHES)

    cand_n = cfgs["cher"].cher_candidates or 2 * cfgs["cher"].batch_size
    cf = cher_mod.build_cher(compute_reward, cfg.batch_size, cand_n, cfgs["cher"].cher_sample)

    @jax.jit
    def cher_gather(buf, hp, key):
        def body(_, k):
            draws, noise = cf.draw(k, buf, hp.relabel.relabel_prob)
            cand = her_mod.gather_her(buf, *draws, compute_reward)
            prox = jnp.linalg.norm(cand.goal - buf.ag[cand.ep, cand.t], axis=-1)
            return None, (cand, prox, noise)

        return jax.lax.scan(body, None, jax.random.split(key, N_BATCHES))[1]

    def select_before(goals, proximity, lam, noise, sample):
        # ``cher.select`` as it was before (not library code): each pick scores the ``sample``
        # not-yet-chosen candidates with the largest of one uniform per candidate (``noise``:
        # (K, C), a top-k per pick) and reads their columns of the similarity (a strided gather).
        sim = cher_mod.similarity(goals)
        C = goals.shape[0]

        def pick(carry, u):
            cover, chosen = carry
            score = jnp.where(chosen, -1.0, u)
            _, cand = jax.lax.top_k(score, sample)
            gain = jnp.sum(jnp.maximum(sim[:, cand] - cover[:, None], 0.0), axis=0)
            gain = gain - lam * proximity[cand]
            best = cand[jnp.argmax(gain)]
            return (jnp.maximum(cover, sim[:, best]), chosen.at[best].set(True)), best

        init = (jnp.zeros((C,), sim.dtype), jnp.zeros((C,), bool))
        return jax.lax.scan(pick, init, noise)[1].astype(jnp.int32)

    def make_cher_select(select, width):
        # Each batch's own candidates (``goals``, ``prox``: one row per batch), so that no
        # similarity matrix is loop-invariant (XLA would hoist it out of the scan).
        @jax.jit
        def run(goals, prox, hp, key, step0):
            def body(_, x):
                k, i, g, p = x
                noise = jax.random.uniform(k, (cfg.batch_size, width))
                lam = hp.relabel.cher_growth ** (step0 + i).astype(jnp.float32)
                return None, select(g, p, lam, noise, cfgs["cher"].cher_sample)

            xs = (jax.random.split(key, N_BATCHES), jnp.arange(N_BATCHES, dtype=jnp.int32),
                  goals, prox)
            return jax.lax.scan(body, None, xs)[1]

        return run

    cher_select = make_cher_select(cf.select, cfgs["cher"].cher_sample)
    cher_select_before = make_cher_select(select_before, cand_n)

    @jax.jit
    def cher_similarity(goals):
        return jax.lax.map(lambda g: cher_mod.similarity(g), goals)

    @jax.jit
    def cher_similarity_dc(goals):
        # The same matrix with the goal dimension leading: the (C, C, d) broadcast of the
        # library reduces over a minor axis of 3, which XLA:CPU vectorises poorly.
        def sim(g):
            gt = g.T  # (d, C)
            d2 = sum(jnp.square(gt[k][:, None] - gt[k][None, :]) for k in range(gt.shape[0]))
            c = g.shape[0]
            mean_d = jnp.sum(jnp.sqrt(d2)) / max(c * (c - 1), 1)
            return jnp.exp(-d2 / jnp.maximum(jnp.square(mean_d), 1e-12))

        return jax.lax.map(sim, goals)

    k_upd = args.update_loop
    dher_update = update_in_loop(rls["dher"].update, k_upd)
    # *alt*: merge every MERGE_EVERY cycles, i.e. one update over MERGE_EVERY cycles' episodes.
    n_batched = MERGE_EVERY * cfgs["dher"].num_envs
    rl_batched = make_relabeller(make_cfg("dher", size, num_envs=n_batched), compute_reward,
                                 cap, T, GOAL)
    dher_update_batched = update_in_loop(rl_batched.update, k_upd)

    # DHER's update, taken apart: the two index merges (dher.merge, with the inputs update
    # builds), and the merge's rank step (every stored key's count of smaller new keys), as
    # the library takes it and two other ways.
    W, n_new = T + 1, cfgs["dher"].num_envs

    # Point ids as the library encodes them: (slot, step) -> id, slot = id // stride.
    point_ids = rls["dher"].init().g_idx.reshape(cap, W)
    stride = int(point_ids[1, 0]) if cap > 1 else W

    def merge_inputs(b, tol):
        first = (b.insert_pos - n_new) % cap
        slots = (first + jnp.arange(n_new, dtype=jnp.int32)) % cap
        ag, g = b.ag[slots], b.g[slots]
        failed = compute_reward(ag[:, T], g[:, T]) < 0
        pts = point_ids[slots].reshape(-1)
        ka = jnp.where(failed[:, None], dher_mod.cell_keys(ag, tol), dher_mod.SENTINEL)
        kg = jnp.where(failed[:, None], dher_mod.cell_keys(g, tol), dher_mod.SENTINEL)
        return first, pts, ka.reshape(-1), kg.reshape(-1)

    def make_merges(merge):
        @jax.jit
        def merges(s, b, p):
            first, pts, ka, kg = merge_inputs(b, p.dher_tol)

            def drop(idx):
                return (idx // stride - first) % cap < n_new

            def body(_, s):
                gk, gi = merge(s.g_keys, s.g_idx, drop(s.g_idx), kg, pts)
                ak, ai = merge(s.ag_keys, s.ag_idx, drop(s.ag_idx), ka, pts)
                return s.replace(g_keys=gk, g_idx=gi, ag_keys=ak, ag_idx=ai)

            return jax.lax.fori_loop(0, k_upd, body, s)

        return merges

    dher_merges = make_merges(dher_mod.merge)
    dher_merges_before = make_merges(merge_before)

    def histogram(keys, new):  # each stored key's count of smaller new keys, as increments
        lo = jnp.searchsorted(keys, jnp.sort(new), side="right", method="scan")
        return jnp.zeros(keys.shape[0] + 1, jnp.int32).at[lo].add(1)

    @jax.jit
    def rank_scan(keys, new):  # as in dher.merge: a search per new key, one parallel scan
        return dher_mod.cumsum(histogram(keys, new))[:-1]

    @jax.jit
    def rank_search(keys, new):  # the merge before: one binary search per stored key
        return jnp.searchsorted(jnp.sort(new), keys, side="left",
                                method="scan_unrolled").astype(jnp.int32)

    @jax.jit
    def rank_cumsum(keys, new):  # the histogram summed by jnp.cumsum
        return jnp.cumsum(histogram(keys, new), dtype=jnp.int32)[:-1]

    key, step0 = jax.random.PRNGKey(3), jnp.int32(123)
    bench = harness.Bench(min_time)
    # Group "main": what the per-algorithm ratios and the suggested DHER changes compare.
    for a in algos:
        bench.add(f"learn/{a}", make_learn(rls[a], agent), ds, states[a], buf, hps[a], key, step0)
    bench.add("dher_update", dher_update, dstate, buf, hps["dher"].relabel, per=k_upd)
    bench.add("dher_update_batched", dher_update_batched, dstate, buf, hps["dher"].relabel,
              per=k_upd * MERGE_EVERY)
    # Group "parts": where the time goes, with HER's learn again as the yardstick.
    g = "parts"
    bench.add("parts/learn_her", make_learn(rls["her"], agent), ds, (), buf, hps["her"], key,
              step0, group=g)
    fixed = rls["her"].sample(key, (), buf, hps["her"].relabel, step0)
    bench.add("update_only", updates_only, ds, fixed, hps["her"], group=g)
    for a in ("her", "dher", "cher"):
        bench.add(f"sample/{a}", make_sample(rls[a]), states[a], buf, hps[a], key, step0,
                  group=g)
    cand, prox, _ = cher_gather(buf, hps["cher"], key)
    bench.add("cher_gather", cher_gather, buf, hps["cher"], key, group=g)
    sel_args = (cand.goal, prox, hps["cher"], key, step0)
    bench.add("cher_select", cher_select, *sel_args, group=g)
    bench.add("cher_select_before", cher_select_before, *sel_args, group=g)
    bench.add("cher_similarity", cher_similarity, cand.goal, group=g)
    bench.add("cher_similarity_dc", cher_similarity_dc, cand.goal, group=g)
    bench.add("dher_update_parts", dher_update, dstate, buf, hps["dher"].relabel, per=k_upd,
              group=g)
    bench.add("dher_merges", dher_merges, dstate, buf, hps["dher"].relabel, per=k_upd, group=g)
    got, want = (f(dstate, buf, hps["dher"].relabel) for f in (dher_merges, dher_merges_before))
    assert all(bool(jnp.array_equal(a, b)) for a, b in zip(jax.tree.leaves(got),
                                                           jax.tree.leaves(want), strict=True))
    bench.add("dher_merges_before", dher_merges_before, dstate, buf, hps["dher"].relabel,
              per=k_upd, group=g)
    kg_new = merge_inputs(buf, hps["dher"].relabel.dher_tol)[3]
    want_rank = rank_scan(dstate.g_keys, kg_new)
    for f in (rank_search, rank_cumsum):
        assert bool(jnp.array_equal(f(dstate.g_keys, kg_new), want_rank)), f.__name__
    bench.add("merge_rank_scan", rank_scan, dstate.g_keys, kg_new, group=g)
    bench.add("merge_rank_search", rank_search, dstate.g_keys, kg_new, group=g)
    bench.add("merge_rank_cumsum", rank_cumsum, dstate.g_keys, kg_new, group=g)
    ref = jax.lax.map(cher_mod.similarity, cand.goal)
    out_check = float(jnp.max(jnp.abs(cher_similarity_dc(cand.goal) - ref)))
    assert out_check < 1e-4, out_check
    bench.run(repeats)

    med = {n: bench.med(n) for n in bench.times}
    # The DHER update runs once per cycle: a cycle's DHER learner work is learn + update.
    cyc = {
        "her": ("learn/her",), "dher": ("learn/dher", "dher_update"),
        "rdher": ("learn/rdher", "dher_update"), "cher": ("learn/cher",),
    }
    out = {"size": size, "capacity_episodes": cap, "cher_candidates": cand_n,
           "cher_sample": cfgs["cher"].cher_sample,
           "merge_every": MERGE_EVERY, "dher_state_bytes": tree_bytes(dstate), "median_s": med,
           "best_s": {n: bench.best(n) for n in bench.times}, "times_s": bench.times,
           "inner_calls": bench.inner, "compile_s": bench.compile_s, "per_algo": {}}
    for a in algos:
        parts = list(cyc[a])
        r = out["per_algo"][a] = {
            "learn_s": med[f"learn/{a}"],
            "cycle_s": sum(med[p] for p in parts),
            "learn_ratio_to_her": bench.ratio(f"learn/{a}", "learn/her"),
            "cycle_ratio_to_her": bench.ratio(parts, "learn/her"),
            "cycle_ratio_to_her_quartiles": bench.ratio_quartiles(parts, "learn/her"),
            "target": TARGETS.get(a),
        }
        if a in TARGETS:
            r["target_met"] = r["cycle_ratio_to_her"] <= TARGETS[a]
            r["repeats_within_target"] = sum(x <= TARGETS[a]
                                             for x in bench.ratios(parts, "learn/her"))
    # Projections for DHER with the suggested changes, from the same repeats (paired).
    alts = {f"merge every {MERGE_EVERY} cycles": ["learn/dher", "dher_update_batched"]}
    out["dher_alternatives"] = {
        name: {"cycle_s": sum(med[n] for n in num),
               "cycle_ratio_to_her": bench.ratio(num, "learn/her"),
               "cycle_ratio_to_her_quartiles": bench.ratio_quartiles(num, "learn/her")}
        for name, num in alts.items()}
    out["repeats"] = repeats
    out["shares"] = {n: bench.ratio(n, "parts/learn_her") for n in bench.groups["parts"]}
    return out


def library_version() -> str:
    """The commit of the repository and any uncommitted change in the modules imported."""
    import rdher_jax

    root = HERE.parent
    pkg = Path(rdher_jax.__file__).resolve().parent
    used = {Path(m.__file__).resolve() for name, m in list(sys.modules.items())
            if name.startswith("rdher_jax") and getattr(m, "__file__", None)}

    def git(*a):
        return subprocess.run(["git", "-C", str(root), *a], capture_output=True).stdout

    head = git("rev-parse", "--short", "HEAD").decode().strip() or "unknown"
    changed = []
    for f in sorted(used):
        rel = f.relative_to(pkg.parent).as_posix()
        if git("show", f"HEAD:{rel}") != f.read_bytes():
            changed.append(rel)
    return f"commit {head}" + (f", with uncommitted changes to {', '.join(changed)}"
                               if changed else ", unmodified")


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.3g}" if s * 1e3 < 100 else f"{s * 1e3:.0f}"


def yes_no(ok: bool) -> str:
    return "yes" if ok else "NO"


def quart(q) -> str:
    return f"{q[0]:.2f}-{q[1]:.2f}"


def report(args, cmd: str, info: dict) -> str:
    p1, p2 = info["matching"], info["cycle"]
    rows = p1["rows"]
    L = [f"`{cmd}` on {info['machine']} (JAX {info['jax']}, {info['jax_backend']}; rdher_jax at "
         f"{info['library']}). Total run "
         f"time {info['total_s']:.0f} s. Other processes shared the 2 cores (load average "
         f"{info['loadavg_start'][0]:.1f} at the start, {info['loadavg_end'][0]:.1f} at the "
         "end), so absolute times jump by up to 2x between repeats: read the ratios. Each "
         f"time is the median of {args.repeats} repeats; each ratio is the median of the "
         "per-repeat ratios of variants timed within seconds of each other (interleaved, order "
         "rotated every repeat), with the first and third quartiles of those ratios beside it; "
         "`best`: a variant's fastest repeat, the least disturbed one.", "",
         f"Synthetic full buffers with the FetchPush sizes (obs {OBS}, goal {GOAL}, action {ACT}, "
         f"T = {T}): static goals in a 30 cm box on the table; {args.success:.0%} of episodes "
         f"pushed to the goal, the others left still ({args.still:.0%}) or pushed in a 1 cm/step "
         f"random walk. DHER defaults: 1 cm cells, {N_BATCHES} batches of 256 per cycle, 2 new "
         "episodes per cycle, 65536 records, 8 partners. The DHER index of a full buffer is "
         "built by one sort (checked against the per-cycle merges from empty at the smallest "
         f"size: {p1['bulk_check']}), then {args.warmup_cycles} cycles re-store stored episodes "
         "to fill the ring of match records.", "",
         "## 1. DHER matching cost against the buffer size", "",
         "`update`: one per-cycle index merge + record lookups on a full buffer after adding 2 "
         f"episodes, timed inside a jitted loop of {args.update_loop} (the state updated in "
         "place, as in the trainer's scan over cycles); `one call`: a lone jitted call, which "
         "also copies the state. `sample`: one batch of 256 (from a jitted scan of 40).", "",
         "| transitions | episodes | update (ms), median (best) | ns / transition, median "
         "(best) | growth exponent vs previous size | one call (ms) | DHER "
         "sample (ms) | HER sample (ms) | DHER / HER sample | DHERState (MB) | DHERState "
         "bytes / transition (indices only) | failed eps | records | DHER rows in a batch |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for size, r in rows.items():
        e = r.get("exponent_from_previous")
        L.append(
            f"| {size:.0e} | {r['capacity_episodes']} | {fmt_ms(r['update_s'])} "
            f"({fmt_ms(r['update_best_s'])}) | {r['update_s'] / size * 1e9:.1f} "
            f"({r['update_best_s'] / size * 1e9:.1f}) | "
            + ("-" if e is None else f"{e:.2f}")
            + f" | {fmt_ms(r['update_call_s'])} | {fmt_ms(r['dher_sample_s'])} | "
            f"{fmt_ms(r['her_sample_s'])} | {r['dher_over_her_sample']:.2f} | "
            f"{r['state_bytes'] / 2**20:.2f} | {r['state_bytes_per_transition']:.1f} "
            f"({r['index_bytes_per_transition']:.1f}) | {r['failed_fraction']:.2f} | "
            f"{r['records_after_warmup']} | {r['dher_rows_fraction']:.2f} |")
    r0 = next(iter(rows.values()))
    bpt = r0["buffer_bytes_per_transition"]
    fixed = (r0["state_bytes"] - r0["index_bytes_per_transition"] * next(iter(rows))) / 2**20
    L += ["", f"The replay buffer itself stores {bpt:.1f} bytes per transition (float32). "
          "DHERState is four int32 index arrays over (T+1)/T points per transition plus the "
          f"ring of records and slot generations ({fixed:.1f} MB at {next(iter(rows)):.0e}; "
          "the ring is fixed), which dominates at small sizes. `records`: matches "
          "recorded after the warm-up; `DHER rows`: share of a batch that are combined "
          "transitions.", ""]

    med, pa = p2["median_s"], p2["per_algo"]
    L += [f"## 2. One cycle's learner work at {p2['size']:.0e} transitions, batch 256, 3x256", "",
          f"`learn`: one jitted scan of {N_BATCHES} x (relabeller.sample + agent.update), the "
          "relabelling state read by the scan, not carried, as in `trainer.cycle`. `cycle`: learn "
          "plus, for DHER/RDHER, the once-per-cycle matching `update`.", "",
          "| algo | learn (ms) | + matching update (ms) | cycle (ms) | per gradient step (ms) | "
          "learn / HER | cycle / HER (quartiles) | target | met | repeats within target |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for a, r in pa.items():
        upd = med["dher_update"] if a in ("dher", "rdher") else None
        tgt = r.get("target")
        L.append(f"| {a} | {fmt_ms(r['learn_s'])} | {'-' if upd is None else fmt_ms(upd)} | "
                 f"{fmt_ms(r['cycle_s'])} | {r['cycle_s'] / N_BATCHES * 1e3:.2f} | "
                 f"{r['learn_ratio_to_her']:.2f} | {r['cycle_ratio_to_her']:.2f} "
                 f"({quart(r['cycle_ratio_to_her_quartiles'])}) | "
                 + ("- | - | - |" if tgt is None else
                    f"<= {tgt} | {yes_no(r['target_met'])} | "
                    f"{r['repeats_within_target']} of {p2['repeats']} |"))
    L += ["", "DHER with the change suggested below (*alt*: timed in the same group as the rows "
          "above, not library code):", "",
          "| DHER cycle | cycle (ms) | cycle / HER (quartiles) |", "|---|---|---|",
          f"| as in the library | {fmt_ms(pa['dher']['cycle_s'])} | "
          f"{pa['dher']['cycle_ratio_to_her']:.2f} "
          f"({quart(pa['dher']['cycle_ratio_to_her_quartiles'])}) |"]
    for name, r in p2["dher_alternatives"].items():
        L.append(f"| *alt*: {name} | {fmt_ms(r['cycle_s'])} | {r['cycle_ratio_to_her']:.2f} "
                 f"({quart(r['cycle_ratio_to_her_quartiles'])}) |")

    sh = p2["shares"]
    L += ["", "## 3. Where the time goes (same run)", "",
          "Each part is its own jitted function, timed in a second interleaved group with HER's "
          "learn as the yardstick (`share`: median per-repeat ratio to it), so parts need not add "
          "up exactly to the fused scans. *alt* rows are not library code: they time what a "
          "change would cost.", "",
          "| part (per cycle: 40 batches, one matching update) | ms | share of HER learn |",
          "|---|---|---|"]
    c = p2["cher_candidates"]
    her_learn = med["parts/learn_her"]
    parts = [
        ("HER learn (the yardstick)", "parts/learn_her"),
        ("DDPG update alone (40 actor+critic steps, fixed batch)", "update_only"),
        ("HER sample alone (40 x 256)", "sample/her"),
        ("DHER sample alone (40 x 256: HER rows + combined rows + mix)", "sample/dher"),
        (f"DHER matching update, once per cycle at {p2['size']:.0e}", "dher_update_parts"),
        ("- of which the two index merges (`dher.merge` x 2)", "dher_merges"),
        ("- *alt*: the two merges as they were before (two `jnp.cumsum` and a binary search "
         "per stored key each; the same arrays)", "dher_merges_before"),
        ("- - one merge's rank step: a histogram of the new keys' positions + a parallel "
         "prefix sum (x 2 per update)", "merge_rank_scan"),
        ("- - *alt*: the same ranks by a binary search per stored key (the merge before)",
         "merge_rank_search"),
        ("- - *alt*: the histogram summed by `jnp.cumsum`", "merge_rank_cumsum"),
        ("- the rest: lookups of the new points, records, success rate (update - merges)",
         None),
        (f"CHER sample alone (40 x {c} candidates -> 256)", "sample/cher"),
        (f"- candidate draw + gather + proximity (40 x {c})", "cher_gather"),
        ("- greedy selection incl. similarity (40 x 256 sequential picks)", "cher_select"),
        (f"- - of which the similarity matrices (40 x {c}^2)", "cher_similarity"),
        ("- - *alt*: the similarity computed in a (d, C) layout", "cher_similarity_dc"),
        ("- - the greedy picks (selection - similarity)", "greedy"),
        ("- *alt*: the greedy selection as it was before: one uniform per candidate and pick "
         "(a top-k per pick) and each candidate's column of the similarity read (a strided "
         "gather), not its row", "cher_select_before"),
    ]
    for label, name in parts:
        if name is None:
            v = med["dher_update_parts"] - med["dher_merges"]
            L.append(f"| {label} | {fmt_ms(v)} | {v / her_learn:.2f} |")
        elif name == "greedy":
            v = med["cher_select"] - med["cher_similarity"]
            L.append(f"| {label} | {fmt_ms(v)} | {v / her_learn:.2f} |" if v > 0 else
                     f"| {label} | {PICKS_IN_NOISE} | - |")
        else:
            L.append(f"| {label} | {fmt_ms(med[name])} | {sh[name]:.2f} |")
    L += ["", "## Reading", ""]
    L += reading(info)
    if info.get("limits"):
        lim = info["limits"]
        L += ["", f"## Machine limits (`{lim['script']}`, run just before the measurements)", "",
              "```", lim["table"], "```"]
    return "\n".join(L) + "\n"


def growth_words(exponent: float) -> str:
    """How a cost growing as ``size ** exponent`` reads in words."""
    if exponent < 0.8:
        return "less than linearly"
    if exponent <= 1.2:
        return "close to linearly"
    return "faster than linearly (a noisy repeat, or caches outgrown)"


def reading(info: dict) -> list[str]:
    p1, p2 = info["matching"], info["cycle"]
    rows = list(p1["rows"].items())
    med, pa, sh = p2["median_s"], p2["per_algo"], p2["shares"]
    alt = p2["dher_alternatives"]
    out = []
    if len(rows) >= 2:
        (s0, _), (s1, r1) = rows[-2], rows[-1]
        sa, ra = rows[0]
        out.append(
            f"- Matching grows {growth_words(r1['exponent_from_previous'])}: from {s0:.0e} to "
            f"{s1:.0e} transitions the "
            f"DHER update grows with exponent {r1['exponent_from_previous']:.2f}; at {s1:.0e} it "
            "takes "
            f"{fmt_ms(r1['update_s'])} ms per cycle ({r1['update_s'] / s1 * 1e9:.0f} ns per "
            f"stored transition). DHERState holds {r1['index_bytes_per_transition']:.1f} bytes "
            f"per transition in its indices ({r1['state_bytes'] / 2**20:.1f} MB at {s1:.0e}, "
            f"beside the buffer's {r1['buffer_bytes_per_transition']:.0f}). A DHER batch costs "
            f"{fmt_ms(ra['dher_sample_s'])} -> {fmt_ms(r1['dher_sample_s'])} ms from {sa:.0e} "
            f"to {s1:.0e} (HER: {fmt_ms(ra['her_sample_s'])} -> {fmt_ms(r1['her_sample_s'])} "
            "ms): its random accesses go to records, index and buffer arrays that outgrow the "
            "caches.")
    out.append(f"- HER's cycle is the network arithmetic: the DDPG update alone is "
               f"{sh['update_only']:.0%} of HER's learn.")
    for a in ("dher", "rdher", "cher"):
        r = pa[a]
        out.append(
            f"- {a}: cycle = {r['cycle_ratio_to_her']:.2f}x HER (quartiles "
            f"{quart(r['cycle_ratio_to_her_quartiles'])}), target <= {r['target']}: "
            + ("met" if r["target_met"] else "missed")
            + f" ({r['repeats_within_target']} of {p2['repeats']} repeats within it).")
    d, rd = pa["dher"], pa["rdher"]
    upd_share = sh["dher_update_parts"]
    out.append(
        f"- DHER/RDHER: the learn scan is {d['learn_ratio_to_her']:.2f}x / "
        f"{rd['learn_ratio_to_her']:.2f}x HER's and the matching update adds "
        f"{upd_share:.2f}x HER's learn per cycle. Of the update "
        f"({fmt_ms(med['dher_update_parts'])} ms), the two merges take "
        f"{fmt_ms(med['dher_merges'])} ms: linear passes over the whole index (a parallel "
        f"prefix sum over the stored keys, {fmt_ms(med['merge_rank_scan'])} ms each, and a "
        "scatter of keys and points), whatever the number of new episodes; the same merges as "
        f"they were before that prefix sum take {fmt_ms(med['dher_merges_before'])} ms "
        f"({med['dher_merges_before'] / med['dher_merges']:.1f}x). The "
        f"sample alone costs {fmt_ms(med['sample/dher'])} ms per cycle against HER's "
        f"{fmt_ms(med['sample/her'])} (combined rows are gathered for every row, then mixed "
        "in).")
    p1_upd = p1["rows"].get(p2["size"], {}).get("update_s")
    if p1_upd is not None and abs(med["dher_update"] / p1_upd - 1) > 0.15:
        alt_ratio = d["learn_ratio_to_her"] + p1_upd / med["learn/her"]
        out.append(
            f"- The matching update timed here among the learn scans ({fmt_ms(med['dher_update'])}"
            f" ms) is slower than in part 1 ({fmt_ms(p1_upd)} ms, same function and inputs): "
            "being bound by memory traffic, it suffers more from the other processes. With part "
            f"1's figure the DHER cycle would be {alt_ratio:.2f}x "
            "HER; the table keeps the figure measured next to HER's learn.")
    k = p2["merge_every"]
    if not (d["target_met"] and rd["target_met"]):
        m = alt[f"merge every {k} cycles"]
        out.append(
            f"- To bring DHER/RDHER under {TARGETS['dher']}x (a suggestion, not implemented): "
            f"merge the index every {k} cycles, over the last {k} cycles' episodes at once "
            f"(measured: {m['cycle_ratio_to_her']:.2f}x HER, quartiles "
            f"{quart(m['cycle_ratio_to_her_quartiles'])}), at the price of matches with the "
            f"newest episodes appearing up to {k - 1} cycles late.")
    else:
        m = alt[f"merge every {k} cycles"]
        out.append(
            f"- DHER/RDHER meet the target with a margin of "
            f"{TARGETS['dher'] - max(d['cycle_ratio_to_her'], rd['cycle_ratio_to_her']):.2f}; "
            f"the matching update is the part to cut if it must grow: merging the index every "
            f"{k} cycles, over {k} cycles' episodes at once, measured "
            f"{m['cycle_ratio_to_her']:.2f}x HER (quartiles "
            f"{quart(m['cycle_ratio_to_her_quartiles'])}),"
            f" at the price of matches with the newest episodes appearing up to {k - 1} cycles "
            "late.")
    no_gain = []
    for name, what in (("merge_rank_search", "a binary search per stored key"),
                       ("merge_rank_cumsum", "the histogram summed by jnp.cumsum")):
        if med[name] >= med["merge_rank_scan"]:
            no_gain.append(f"the merge's ranks by {what} ({fmt_ms(med[name])} vs "
                           f"{fmt_ms(med['merge_rank_scan'])} ms)")
    if no_gain:
        out.append("- Slower than the library's way here: " + "; ".join(no_gain) + ".")
    sel, gat, sim = med["cher_select"], med["cher_gather"], med["cher_similarity"]
    parts = {"the similarity matrices": sim, "the 256 sequential greedy picks": sel - sim,
             "the candidate draw and gather": gat}
    top = max(parts, key=parts.get)
    fixes, out_note = [], ""
    if med["cher_similarity_dc"] < 0.8 * sim:
        fixes.append(
            "compute the distances with the goal dimension leading (a (C, C, 3) broadcast "
            "reduced over its minor axis of 3 vectorises poorly on XLA:CPU): the similarity "
            f"drops from {fmt_ms(sim)} to {fmt_ms(med['cher_similarity_dc'])} ms")
    else:
        out_note = (f" (the library's similarity and the (d, C)-layout one cost the same here, "
                    f"{fmt_ms(sim)} and {fmt_ms(med['cher_similarity_dc'])} ms)")
    before = med["cher_select_before"]
    out.append(
        f"- CHER's greedy selection draws each pick's candidates by a partial Fisher-Yates "
        f"shuffle ({p2['cher_sample']} uniforms per pick) and reads their rows of the symmetric "
        f"similarity: {fmt_ms(sel)} ms per cycle, including its uniforms, against "
        f"{fmt_ms(before)} ms as it was before ({before / sel:.2f}x: one uniform per candidate "
        f"and pick, a top-k, and strided columns).")
    if top == "the 256 sequential greedy picks":
        fixes.append(
            "let the greedy pick several candidates per step from disjoint candidate subsets "
            "(e.g. 8 steps of 32 picks instead of 256 of one), which shortens a sequential loop "
            "that runs on per-step overhead on a CPU")
    if top == "the similarity matrices":
        fixes.append(
            "score fewer candidates (`cher_candidates`): the similarity grows with their "
            "square")
    out.append(
        f"- CHER's sample costs {fmt_ms(med['sample/cher'])} ms per cycle "
        f"({sh['sample/cher']:.0%} of HER's whole learn): similarity matrices {fmt_ms(sim)} ms, "
        + (f"greedy picks {fmt_ms(sel - sim)} ms" if sel > sim else
           f"greedy picks {PICKS_IN_NOISE}")
        + f", candidate draw and gather {fmt_ms(gat)} ms; the "
        f"largest part is {top}"
        + out_note + ". "
        + (("It misses its target; fixes: " if not pa["cher"]["target_met"] else
            "It meets its target; if it has to get cheaper: ") + "; ".join(fixes) + "."
           if fixes else ("It misses its target." if not pa["cher"]["target_met"] else
                          "It meets its target.")))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_relabel.py", __doc__.splitlines()[0], repeats=9,
                        quick="smoke run: small sizes, 2 repeats", limits=True)
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e4, 1e5, 1e6],
                    help="buffer sizes (transitions) for the matching cost")
    ap.add_argument("--cycle-size", type=float, default=1e6,
                    help="buffer size (transitions) for the per-algorithm cycle cost")
    ap.add_argument("--min-time", type=float, default=0.3,
                    help="seconds per measurement (calls are repeated to reach it)")
    ap.add_argument("--update-loop", type=int, default=8,
                    help="DHER updates per timed jitted loop")
    ap.add_argument("--warmup-cycles", type=int, default=80,
                    help="cycles that populate DHER's match records before timing")
    ap.add_argument("--success", type=float, default=0.3, help="share of successful episodes")
    ap.add_argument("--still", type=float, default=0.5,
                    help="share of failed episodes whose object never moves")
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.cycle_size, args.repeats, args.min_time = [1e4, 5e4], 5e4, 2, 0.05

    t_start = time.perf_counter()
    cmd = harness.command("bench_relabel.py", argv)
    limits = harness.machine_limits(args.limits_script)
    if limits:
        print(limits["table"], flush=True)
    from rdher_jax import startup

    startup.setup(startup.Startup())
    import rdher_jax.program  # noqa: F401

    # Import everything measured now, and record what was imported before measuring it.

    library = library_version()
    h = harness.host()
    load0 = os.getloadavg()
    sizes = [int(s) for s in args.sizes]
    print("part 1: matching cost", flush=True)
    p1, setups = matching_cost(sizes, args.repeats, args.min_time, args)
    print("part 2: cycle cost", flush=True)
    p2 = cycle_cost(int(args.cycle_size), args.repeats, args.min_time, args, setups)
    info = {
        "machine": f"{h['processor'] or h['machine']}, {h['cpu_count']} CPUs",
        "jax_backend": h["jax_backend"],
        "jax": h["versions"]["jax"],
        "library": library,
        "loadavg_start": load0,
        "loadavg_end": os.getloadavg(),
        "matching": p1,
        "cycle": p2,
        "limits": limits,
        "total_s": time.perf_counter() - t_start,
    }
    text = report(args, cmd, info).rstrip("\n")
    harness.write_results(args.out, "Relabelling benchmark", [text], info, command=cmd, host=h)


if __name__ == "__main__":
    main()
