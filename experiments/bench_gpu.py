"""The trainer on a GPU, from process start: MJX env-step throughput, FetchReach (the README's
main job, unchanged) to 0.95, FetchPush with HER at the GPU settings docs/performance.md
suggests, and RDHER's matching at that scale, each stage a subprocess with its own deadline so
that one slow compile cannot eat the others' time.

    python experiments/bench_gpu.py --budget 540      # every stage inside 540 s

Stages, in order (each gets what is left of the budget, capped at its own share):

1. ``env``: ``jit`` of reset + a 50-step ``lax.scan`` over ``vmap(env.step)`` with random actions,
   FetchPush on the ``mjx`` backend (its MJX-edited scene), at each ``--batches`` size: compile
   time and env steps/s (median of 3 after one warm call).
2. ``reach``: ``python -m rdher_jax.train env=FetchReach stop_success=0.95`` with every other key
   the default (``backend=auto`` picks ``mjx`` on a GPU): seconds from process start to exit,
   and the env steps and in-run seconds of the first epoch whose 3-epoch mean reached 0.95.
3. ``push``: ``env=FetchPush algo=her`` at ``num_envs=4096 batch_size=8192 n_batches=200
   buffer_size=10000000`` (docs/performance.md, 'What a GPU run should set'), ``n_cycles=5``,
   ``stop_success=0.9``: its success curve until it stops or its share of the budget ends.
4. ``rdher``: ``env=FetchPush algo=rdher`` at the same settings for one epoch of 2 cycles:
   that DHER's matching and RDHER's weights run at 4,096 envs, and their cost per cycle.

It writes ``--out`` (markdown), a JSON file beside it, and each stage's ``metrics.csv`` as
``bench_gpu_<stage>.csv``. Without a GPU the stages run on the CPU (slowly: use ``--batches 16``
and a small budget to check the script itself).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import harness  # noqa: E402
from bench_learning import first_hit  # noqa: E402

DEFAULT_OUT = HERE / "results" / "bench_gpu.md"
GPU_KEYS = ["num_envs=4096", "batch_size=8192", "n_batches=200", "buffer_size=10000000"]
STAGES = ("reach", "push", "rdher", "env")


def env_worker(batches: list[int], deadline: float) -> None:
    """Stage 1, in its own process: one JSON line per batch size."""
    from rdher_jax import startup

    # No persistent compilation cache: the compile times are among the figures.
    startup.setup(startup.Startup(ffi=False, compile_cache=False))
    import jax
    from bench_envs import batch_keys, compile_timed, make_rollout
    from rdher_jax.envs import make_env

    env = make_env("FetchPush", backend="mjx", auto_reset=False)
    rollout = make_rollout(env)
    print(json.dumps({"devices": [str(d) for d in jax.devices()],
                      "scene": env.setup.variant}), flush=True)
    for b in batches:
        if time.time() > deadline:
            break
        keys = batch_keys(0, b)
        fn, lower_s, compile_s = compile_timed(rollout, keys)
        jax.block_until_ready(fn(keys))
        times = []
        for i in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(batch_keys(i + 1, b)))
            times.append(time.perf_counter() - t0)
        t = sorted(times)[1]
        print(json.dumps({"batch": b, "lower_s": lower_s, "compile_s": compile_s,
                          "rollout_s": t, "steps_per_s": b * 50 / t}), flush=True)


def run_stage(name: str, argv: list[str], timeout: float, log, cwd: Path) -> dict:
    """Run ``argv`` in ``cwd`` (not the checkout: ``rdher_jax`` is the installed package, as a
    user has it) with ``timeout`` seconds; its output goes to ``log``."""
    t0 = time.time()
    log.write(f"\n===== {name}: {' '.join(argv)} (timeout {timeout:.0f} s)\n")
    log.flush()
    try:
        p = subprocess.run(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, timeout=max(timeout, 1.0))
        out, rc = p.stdout, p.returncode
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        rc = "timeout"
    log.write(out)
    log.flush()
    return {"command": " ".join(argv[2:] if argv[1] == "-m" else argv), "rc": rc,
            "process_s": round(time.time() - t0, 1), "output": out}


def read_metrics(run_dir: Path) -> list[dict[str, str]]:
    f = run_dir / "metrics.csv"
    if not f.is_file():
        return []
    with open(f, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def gpu_info() -> dict:
    info: dict = {"machine": platform.machine(), "python": platform.python_version(),
                  "cpu_count": os.cpu_count()}
    try:
        q = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
                            "--format=csv,noheader"], capture_output=True, text=True, timeout=20)
        info["gpu"] = q.stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        info["gpu"] = None
    info["versions"] = {"python": platform.python_version(), **harness.versions()}
    return info


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser("bench_gpu.py", __doc__.split("\n\n")[0], out=DEFAULT_OUT)
    ap.formatter_class = argparse.RawDescriptionHelpFormatter
    ap.add_argument("--budget", type=float, default=540.0, help="seconds for all stages")
    ap.add_argument("--batches", default="1024,4096,16384", help="stage env: batch sizes")
    ap.add_argument("--stages", default=",".join(STAGES), help=f"of {','.join(STAGES)}")
    ap.add_argument("--num-envs", type=int, default=4096, help="push and rdher: num_envs")
    ap.add_argument("--env-worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.env_worker is not None:
        env_worker([int(b) for b in a.batches.split(",")], float(a.env_worker))
        return 0
    stages = [s for s in a.stages.split(",") if s]
    bad = [s for s in stages if s not in STAGES]
    if bad or a.budget <= 0:
        print(f"error: unknown stage {bad[0]!r} (of {', '.join(STAGES)})" if bad
              else f"error: --budget must be > 0, got {a.budget}", file=sys.stderr)
        return 2
    start = time.time()
    end = start + a.budget
    out_dir = a.out.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_gpu_{os.getpid()}"
    shutil.rmtree(runs, ignore_errors=True)
    runs.mkdir(parents=True)
    py = sys.executable
    keys = [k.replace("num_envs=4096", f"num_envs={a.num_envs}") for k in GPU_KEYS]
    # Each stage's share of the whole budget (the last one takes what is left).
    share = {"reach": 0.27, "push": 0.5, "rdher": 0.17, "env": 0.2}
    result: dict = {"hardware": gpu_info(), "budget_s": a.budget, "stages": {}}
    log = open(out_dir / "bench_gpu.log", "w", encoding="utf-8")

    def left() -> float:
        return end - time.time()

    for s in stages:
        cap = min(left(), share[s] * a.budget if s != stages[-1] else left())
        if cap < 20:
            result["stages"][s] = {"skipped": f"{left():.0f} s left"}
            continue
        run_dir = runs / s
        # progress bars go to the log: where a stage is stopped at its deadline, they show how far
        # it got and when its first cycle began (the end of compiling)
        common = ["progress=true", f"run_dir={run_dir}"]
        if s == "env":
            r = run_stage(s, [py, str(Path(__file__).resolve()), "--batches", a.batches,
                              "--env-worker", str(time.time() + 0.5 * cap)], cap, log, runs)
            lines = [json.loads(ln) for ln in r.pop("output").splitlines()
                     if ln.startswith("{")]
            r["rows"] = [ln for ln in lines if "batch" in ln]
            r.update(next((ln for ln in lines if "devices" in ln), {}))
        elif s == "reach":
            r = run_stage(s, [py, "-m", "rdher_jax.train", "env=FetchReach",
                              "stop_success=0.95", *common], cap, log, runs)
        elif s == "push":
            r = run_stage(s, [py, "-m", "rdher_jax.train", "env=FetchPush", "algo=her", *keys,
                              "n_cycles=5", "epochs=200", "n_test_rollouts=1",
                              "checkpoint_every=1000", "stop_success=0.9", *common], cap, log, runs)
        else:
            r = run_stage(s, [py, "-m", "rdher_jax.train", "env=FetchPush", "algo=rdher",
                              "lambda_r=4", "lambda_h=0.5", *keys, "n_cycles=2", "epochs=1",
                              "n_test_rollouts=1", *common], cap, log, runs)
        if s != "env":
            out = r.pop("output")
            r["tail"] = out.strip().splitlines()[-3:]
            rows = read_metrics(run_dir)
            if rows:
                shutil.copyfile(run_dir / "metrics.csv", out_dir / f"bench_gpu_{s}.csv")
            r["epochs"] = len(rows)
            r["last"] = rows[-1] if rows else None
            target = {"reach": 0.95, "push": 0.9}.get(s)
            if target is not None:
                r["target"] = target
                # the trainer's stop_success rule: a trailing mean of 3 epochs
                r["reached"] = (first_hit(rows, target, 3) or {}).get("window")
        result["stages"][s] = r
        (a.out.with_suffix(".json")).write_text(json.dumps(result, indent=1) + "\n")
    log.close()
    shutil.rmtree(runs, ignore_errors=True)
    # The host is nvidia-smi's and the versions' (gpu_info): harness.host would start JAX in
    # this process, on the GPU the stages need.
    harness.write_results(a.out, "The trainer on a GPU (`experiments/bench_gpu.py`)",
                          [render(result)], result)
    return 0


def render(res: dict) -> str:
    """The results page below its title."""
    hw = res["hardware"]
    lines = [f"GPU: {hw.get('gpu')}; {hw.get('cpu_count')} CPU cores; Python {hw.get('python')}; "
             + ", ".join(f"{k} {v}" for k, v in hw["versions"].items()) + "; "
             f"budget {res['budget_s']:.0f} s.", ""]
    st = res["stages"]
    if "env" in st and "rows" in st["env"]:
        e = st["env"]
        lines += ["## MJX env steps (FetchPush, scene " + str(e.get("scene")) + ")", "",
                  "| envs | compile (s) | 50-step rollout (s) | env steps/s |", "|---|---|---|---|"]
        lines += [f"| {r['batch']} | {r['lower_s'] + r['compile_s']:.1f} | {r['rollout_s']:.3f} "
                  f"| {r['steps_per_s']:,.0f} |" for r in e["rows"]]
        lines.append("")
    lines += ["## Training runs, from process start", "",
              "| stage | command | exit | process (s) | epochs | reached target at "
              "(epoch, env steps, in-run s) | last epoch: test success, env steps, in-run s |",
              "|---|---|---|---|---|---|---|"]
    for s in ("reach", "push", "rdher"):
        if s not in st:
            continue
        r = st[s]
        if "skipped" in r:
            lines.append(f"| {s} | skipped ({r['skipped']}) | | | | | |")
            continue
        reached = r.get("reached")
        rc = f"{r.get('target')}: " + (f"{reached['epoch']}, {reached['env_steps']:,}, "
                                       f"{reached['wall_s']:.0f}" if reached else "no") \
            if "target" in r else "n/a"
        last = r.get("last")
        ls = (f"{float(last['test_success']):.3f}, {int(float(last['env_steps'])):,}, "
              f"{float(last['wall_time']):.0f}") if last else "none"
        lines.append(f"| {s} | `{r['command']}` | {r['rc']} | {r['process_s']} | "
                     f"{r.get('epochs')} | {rc} | {ls} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
