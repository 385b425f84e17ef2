"""Trainer benchmark: cold start to 0.95 test success on FetchReach, learner speed against its
arithmetic bound, and env-steps/s of the whole training loop.

    python experiments/bench_train.py                 # about 3-5 minutes on a 2-core CPU
    python experiments/bench_train.py --quick         # smoke run
    python experiments/bench_train.py --repeats 3     # median of 3 cold starts

Writes ``experiments/results/bench_train.md`` and ``.json``.
"""

from __future__ import annotations

import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import harness


def cold_start_to(target: float, env: str | None, max_epochs: int | None, extra: list[str],
                  cache_dir: str | Path | None = None, to_end: bool = False) -> dict:
    """Launch ``python -m rdher_jax.train`` and time, from process start, until an epoch with
    test success >= target is written (compile, imports and env setup included).

    ``env`` / ``max_epochs`` None: the trainer's defaults. ``cache_dir``: the compilation
    cache the process uses (default: a new empty one, so the start is cold). ``to_end``: let
    the process finish and report its whole wall clock too (else it is stopped at the hit)."""
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "rdher_jax.train",
               *([f"env={env}"] if env else []),
               *([f"epochs={max_epochs}"] if max_epochs else []),
               f"run_dir={run}", "progress=false", *extra]
        env_vars = {**os.environ, "RDHER_JAX_CACHE_DIR": str(cache_dir or Path(tmp) / "cache")}
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             env=env_vars)
        hit = None
        rows: list[dict] = []
        while p.poll() is None:
            time.sleep(0.02)
            f = run / "metrics.csv"
            if f.exists() and hit is None:
                with open(f) as fh:
                    rows = list(csv.DictReader(fh))
                ok = [r for r in rows if float(r["test_success"]) >= target]
                if ok:
                    hit = {"seconds": time.perf_counter() - t0, "epoch": int(ok[0]["epoch"]),
                           "env_steps": int(ok[0]["env_steps"])}
                    if not to_end:
                        p.kill()
                        break
        p.wait()
        process_s = time.perf_counter() - t0
        if p.returncode not in (0, -9) and hit is None:
            raise RuntimeError(f"training failed: {p.stderr.read()[-2000:]}")
        with open(run / "metrics.csv") as fh:
            rows = list(csv.DictReader(fh))
        if hit is None:  # reached in the last epoch, written as the process ended
            ok = [r for r in rows if float(r["test_success"]) >= target]
            if ok:
                hit = {"seconds": process_s, "epoch": int(ok[0]["epoch"]),
                       "env_steps": int(ok[0]["env_steps"])}
        # env-steps/s of the loop, epochs after the first (the first includes compilation)
        loop = None
        if len(rows) >= 2:
            r0, r1 = rows[0], rows[-1]
            steps = int(r1["env_steps"]) - int(r0["env_steps"])
            loop = steps / (float(r1["wall_time"]) - float(r0["wall_time"]))
        return {"hit": hit, "epochs_run": len(rows), "loop_env_steps_per_s": loop,
                "first_epoch_s": float(rows[0]["wall_time"]) if rows else None,
                "process_s": process_s if to_end else None}


def learner_speed(batch: int, n: int, repeats: int) -> dict:
    """Gradient steps/s: update only (a fixed batch) and sample + update (as in training)."""
    import jax
    import jax.numpy as jnp

    from rdher_jax import buffer as rb
    from rdher_jax.ddpg import DDPGParams, make_ddpg
    from rdher_jax.relabel import sample_her

    obs_dim, goal_dim, act_dim, T = 25, 3, 4, 50  # FetchPush sizes
    agent = make_ddpg(obs_dim, goal_dim, act_dim)
    hp = DDPGParams.default()
    relabel_prob = 0.8  # baselines' k = 4
    ds = agent.init(jax.random.PRNGKey(0), hp)
    buf = rb.init(100_000, T, obs_dim, goal_dim, act_dim)
    k = jax.random.PRNGKey(1)
    ep = rb.Episode(
        obs=jax.random.normal(k, (2000, T + 1, obs_dim)),
        ag=jax.random.uniform(k, (2000, T + 1, goal_dim)),
        g=jax.random.uniform(k, (2000, T + 1, goal_dim)),
        action=jax.random.uniform(k, (2000, T, act_dim), minval=-1, maxval=1),
    )
    buf = rb.add(buf, ep)

    def reward(a, g):
        return -(jnp.linalg.norm(a - g, axis=-1) > 0.05).astype(jnp.float32)

    fixed = sample_her(k, buf, batch, relabel_prob, reward)

    @jax.jit
    def updates_only(ds):
        return jax.lax.scan(lambda s, _: (agent.update(s, fixed, hp)[0], None), ds, None,
                            length=n)[0]

    @jax.jit
    def sample_and_update(ds, buf, key):  # the buffer is an argument, as in the trainer
        def body(s, kk):
            return agent.update(s, sample_her(kk, buf, batch, relabel_prob, reward), hp)[0], None

        return jax.lax.scan(body, ds, jax.random.split(key, n))[0]

    one = jax.jit(lambda ds: agent.update(ds, fixed, hp)[0])
    flops = one.lower(ds).compile().cost_analysis()
    flops = flops[0] if isinstance(flops, list) else flops
    flops = float(flops.get("flops", float("nan")))

    # The two learners interleaved (order rotated every repeat), as the machine's speed drifts.
    bench = harness.Bench(log=None)
    bench.add("updates only", updates_only, ds, per=n)
    bench.add("sample and update", sample_and_update, ds, buf, k, per=n)
    bench.run(repeats)
    u, su = 1 / bench.med("updates only"), 1 / bench.med("sample and update")
    # This CPU's dense-matmul throughput in XLA: the arithmetic ceiling the learner runs against.
    a = jnp.ones((1024, 1024), jnp.float32)
    mm = jax.jit(lambda x: jax.lax.fori_loop(0, 20, lambda i, y: jnp.tanh(y @ a), x))
    ceiling = harness.Bench(log=None)
    ceiling.add("matmul", mm, a)
    ceiling.run(max(repeats, 5))
    mm_rate = 20 * 2 * 1024**3 / ceiling.best("matmul")  # a ceiling: the best of the repeats
    return {"batch": batch, "flops_per_update": flops, "updates_per_s": u,
            "sample_updates_per_s": su, "achieved_gflops": u * flops / 1e9,
            "matmul_gflops": mm_rate / 1e9,
            "bound_updates_per_s": mm_rate / flops if flops == flops else None}


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_train.py", __doc__.splitlines()[0],
                        quick="smoke run: 1 repeat, fewer updates")
    ap.add_argument("--repeats", type=int, default=1, help="cold starts to time (median)")
    ap.add_argument("--target", type=float, default=0.95)
    args = ap.parse_args(argv)
    from rdher_jax import startup

    startup.setup(startup.Startup())
    cmd = harness.command("bench_train.py", argv)
    n = 20 if args.quick else 100
    learner = learner_speed(256, n, 3)
    print(f"learner: {learner}", flush=True)
    starts = [cold_start_to(args.target, "FetchReach", 10, []) for _ in range(args.repeats)]
    for s in starts:
        print(f"cold start: {s}", flush=True)
    hits = [s["hit"]["seconds"] for s in starts if s["hit"]]
    loops = [s["loop_env_steps_per_s"] for s in starts if s["loop_env_steps_per_s"]]
    h = harness.host()
    info = {
        "learner": learner,
        "cold_starts": starts,
        "median_seconds_to_target": statistics.median(hits) if hits else None,
        "median_loop_env_steps_per_s": statistics.median(loops) if loops else None,
    }
    cells = [
        (f"cold start to test success >= {args.target} on FetchReach (median of {len(starts)})",
         f"{info['median_seconds_to_target']:.1f} s" if hits else "not reached"),
        *((f"run {i}: epoch / env steps at target",
           f"{s['hit']['epoch']} / {s['hit']['env_steps']}" if s["hit"] else "-")
          for i, s in enumerate(starts)),
        ("first epoch incl. compile (s)",
         ", ".join(f"{s['first_epoch_s']:.1f}" for s in starts if s["first_epoch_s"])),
        ("whole-loop env-steps/s after the first epoch",
         f"{info['median_loop_env_steps_per_s']:.0f}" if loops else "-"),
        ("learner: FLOP per actor+critic update, batch 256 (XLA cost analysis)",
         f"{learner['flops_per_update'] / 1e9:.2f} GFLOP"),
        ("learner: updates/s, fixed batch", f"{learner['updates_per_s']:.0f}"),
        ("learner: updates/s incl. HER sampling", f"{learner['sample_updates_per_s']:.0f}"),
        ("learner: achieved GFLOP/s", f"{learner['achieved_gflops']:.1f}"),
        ("this CPU: XLA 1024x1024 matmul GFLOP/s", f"{learner['matmul_gflops']:.1f}"),
        ("arithmetic bound on updates/s (matmul rate / FLOP per update)",
         f"{learner['bound_updates_per_s']:.0f}"),
    ]
    harness.write_results(args.out, "Trainer benchmark", [
        f"`{cmd}` on {harness.machine(h)}; the learner's two loops timed interleaved "
        "(medians of 3).",
        harness.table(["figure", "value"], cells),
    ], info, command=cmd, host=h)


if __name__ == "__main__":
    main()
