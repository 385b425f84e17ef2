"""Sweep benchmark: wall time per epoch of N runs vmapped as one program, against one run.

    python experiments/bench_sweep.py                   # N = 1, 2, 4, 7, 35; ~5 min on 2 cores
    python experiments/bench_sweep.py --runs 1 2 4 7    # without the 35-run sweep
    python experiments/bench_sweep.py --quick           # smoke run

One epoch here is deliberately small: FetchReach with ``n_cycles=2`` (2 cycles x 2 envs x 50
steps, 2 x 40 updates of batch 256, then 10 test episodes), all other settings the defaults
(3x256 networks, 1e6-transition buffer). The single run is ``jax.jit(trainer.epoch)`` as in
``python -m rdher_jax.train``; the N-run sweeps are ``rdher_jax.executor.Executor`` on one
device (``jax.jit(jax.vmap(trainer.epoch))``), their runs the task's 7 lambda pairs x 5 seeds
in order. All programs are compiled first, then timed in interleaved rounds (1 run, N=1, N=2,
...), so that the ratios are measured side by side under the same machine load.

Memory is the bytes of the stacked TrainState's leaves (replay buffer, networks, optimiser
states, normaliser, keys), per run and per sweep; also for FetchPush at the default settings
(``jax.eval_shape``, nothing allocated), the size of the paper's 7 x 5 sweep.

Writes ``experiments/results/bench_sweep.md`` and ``.json``.
"""

from __future__ import annotations

import dataclasses

import harness
import jax

from rdher_jax import startup
from rdher_jax.config import Config, resolve
from rdher_jax.executor import Executor, build, stack, tree_bytes
from rdher_jax.program import hparams_from_config

LAMBDAS = [(1, 1), (1, 2), (2, 1), (1, 4), (4, 1), (0.5, 4), (4, 0.5)]
SEEDS = range(5)


def run_configs(base: Config, n: int) -> list[Config]:
    """The first ``n`` runs of the 7 lambda pairs x 5 seeds sweep, lambda major."""
    out = [dataclasses.replace(base, lambda_r=float(lr), lambda_h=float(lh), seed=s)
           for lr, lh in LAMBDAS for s in SEEDS]
    return out[:n]


def state_bytes_paper_sweep() -> dict:
    """Stacked TrainState bytes of FetchPush at the defaults, by shape only."""
    cfg = resolve(Config(env="FetchPush", algo="her", run_dir="unused", progress=False))
    _, trainer = build(cfg)
    runs = run_configs(cfg, 35)
    hps = stack([hparams_from_config(c) for c in runs])
    keys = stack([jax.random.PRNGKey(c.seed) for c in runs])
    shape = jax.eval_shape(jax.vmap(trainer.init), keys, hps)
    total = tree_bytes(shape)
    return {"env": "FetchPush", "runs": 35, "bytes": total, "bytes_per_run": total // 35}


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_sweep.py", __doc__.splitlines()[0], quick="N = 1, 2; one round")
    ap.add_argument("--runs", type=int, nargs="+", default=[1, 2, 4, 7, 35])
    ap.add_argument("--rounds", type=int, default=3, help="timed epochs per program (median)")
    ap.add_argument("--n-cycles", type=int, default=2)
    a = ap.parse_args(argv)
    if a.quick:
        a.runs, a.rounds = [1, 2], 1
    startup.setup(startup.Startup())

    base = resolve(Config(env="FetchReach", algo="her", n_cycles=a.n_cycles, run_dir="unused",
                          progress=False))
    _, trainer = build(base)
    dev = jax.devices()[0]

    # ---- build and compile every program (the first epoch includes compilation)
    bench = harness.Bench()
    hp1 = hparams_from_config(base)
    single = jax.jit(trainer.epoch, donate_argnums=0)
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(base.seed), hp1)
    bench.add("1 run", harness.donated(single, ts, hp1))
    runs_of, state_bytes = {"1 run": 1}, {"1 run": tree_bytes(ts)}
    for n in a.runs:
        runs = run_configs(base, n)
        prog = Executor(trainer, n, devices=[dev])
        hps = prog.put(stack([hparams_from_config(c) for c in runs]))
        keys = prog.put(stack([jax.random.PRNGKey(c.seed) for c in runs]))
        vts = prog.init(keys, hps)
        state_bytes[f"{n} vmapped"] = tree_bytes(vts)  # before the epoch donates it
        bench.add(f"{n} vmapped", harness.donated(prog.epoch, vts, hps))
        runs_of[f"{n} vmapped"] = n

    # ---- interleaved timed rounds
    bench.run(a.rounds)

    t1 = bench.med("1 run")
    rows = []
    for name, n in runs_of.items():
        t = bench.med(name)
        rows.append({
            "program": name, "runs": n, "epoch_s": t, "epoch_s_all": bench.times[name],
            "vs_one_run": t / t1, "speedup_vs_separate": n * t1 / t,
            "first_epoch_s": bench.compile_s[name], "state_bytes": state_bytes[name],
            "state_bytes_per_run": state_bytes[name] // n,
        })
    paper = state_bytes_paper_sweep()
    cmd = harness.command("bench_sweep.py", argv)
    h = harness.host()
    info = {
        "epoch": {"env": base.env, "n_cycles": base.n_cycles, "num_envs": base.num_envs,
                  "n_batches": base.n_batches, "batch_size": base.batch_size,
                  "hidden": base.hidden, "layers": base.layers,
                  "n_test_rollouts": base.n_test_rollouts, "buffer_size": base.buffer_size},
        "rounds": a.rounds,
    }
    cells = [(r["program"], r["runs"], f"{r['epoch_s']:.2f}", f"{r['vs_one_run']:.2f}x",
              f"{r['speedup_vs_separate']:.2f}x", f"{r['first_epoch_s']:.1f}",
              f"{r['state_bytes'] / 1e6:.1f}", f"{r['state_bytes_per_run'] / 1e6:.1f}")
             for r in rows]
    vm = [r for r in rows if r["program"] != "1 run"]
    best = max(vm, key=lambda r: r["speedup_vs_separate"])
    last = vm[-1]
    harness.write_results(a.out, "Sweep benchmark: N runs vmapped as one program vs one run", [
        f"`{cmd}` on {harness.machine(h)} (one device). One epoch = FetchReach, "
        f"{base.n_cycles} cycles x {base.num_envs} envs x 50 steps, "
        f"{base.n_cycles * base.n_batches} updates of batch {base.batch_size}, "
        f"{base.n_test_rollouts} test episodes; defaults otherwise ({base.layers}x{base.hidden} "
        f"networks, buffer {base.buffer_size:,}). Median of {a.rounds} epochs per program, the "
        "programs timed in interleaved rounds (order rotated every round).",
        harness.table(["program", "runs", "s / epoch", "vs 1 run", "speedup vs N separate runs",
                       "first epoch incl. compile (s)", "TrainState MB (sweep)", "MB per run"],
                      cells),
        f"Reading: N runs in one vmapped program take {last['vs_one_run']:.2f}x the time of one "
        f"run at N = {last['runs']} ({last['speedup_vs_separate']:.2f}x the throughput of "
        f"running them one after the other; best {best['speedup_vs_separate']:.2f}x at N = "
        f"{best['runs']}). On this CPU the epoch is bound by the learner's matmuls, which already "
        "keep both cores busy for one run, so batching runs adds little arithmetic efficiency: "
        "what a sweep gains here is one compilation and one process for all runs, not speed. "
        "An accelerator, which one run leaves mostly idle, is where the vmapped sweep should pay.",
        f"Paper-sized sweep: {paper['env']} at the default settings, {paper['runs']} runs "
        f"(7 lambda pairs x 5 seeds): stacked TrainState {paper['bytes'] / 1e9:.2f} GB, "
        f"{paper['bytes_per_run'] / 1e6:.1f} MB per run (by shape, `jax.eval_shape`).",
    ], {"info": info, "rows": rows, "paper_sweep": paper}, command=cmd, host=h)


if __name__ == "__main__":
    main()
