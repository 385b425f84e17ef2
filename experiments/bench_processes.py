"""A sweep in one process against the same sweep over two processes on this machine.

    python experiments/bench_processes.py            # FetchReach, 4 runs, 3 epochs
    python experiments/bench_processes.py --runs 8 --epochs 5

Three ways to run one sweep of N runs (λ pairs x seeds, FetchReach at the paper's learner, 10
cycles per epoch), each from process start to exit, side by side in one call:

- ``1 process, 1 core``: ``taskset -c 0``, one JAX device;
- ``2 processes, 1 core each``: ``rdher_jax.sweep ... coordinator= num_processes=2``, process i
  pinned to core i (``taskset -c i``), one device each: what two machines would do, shrunk;
- ``1 process, 2 cores, 2 devices``: ``--xla_force_host_platform_device_count=2``.

Writes ``experiments/results/bench_processes.md`` and ``.json`` (with ``machine_limits``'s
figures when ``../shared/bench/machine_limits.py`` exists). Needs an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"


def sweep_args(runs: int, epochs: int) -> list[str]:
    pairs = [[1, 1], [2, 1], [1, 2], [4, 1]]
    seeds = max(1, runs // len(pairs))
    n_pairs = max(1, runs // seeds)
    lam = "[" + ",".join(f"[{a},{b}]" for a, b in pairs[:n_pairs]) + "]"
    return ["env=FetchReach", "algo=rdher", f"lambdas={lam}", f"seeds={seeds}",
            f"epochs={epochs}", "n_cycles=10", "progress=false"]


def env(devices: int = 1) -> dict:
    e = {**os.environ, "JAX_PLATFORMS": "cpu"}
    e.pop("XLA_FLAGS", None)
    if devices > 1:
        e["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    return e


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def timed(cmds: list[list[str]], envs: list[dict]) -> float:
    t0 = time.perf_counter()
    procs = [subprocess.Popen(c, env=e, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True) for c, e in zip(cmds, envs, strict=True)]
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            sys.exit(f"error: {' '.join(p.args)} failed:\n{err[-2000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    py = [sys.executable, "-m", "rdher_jax.sweep", *sweep_args(args.runs, args.epochs)]
    tmp = Path(tempfile.mkdtemp(prefix="bench_processes-"))
    res: dict[str, list[float]] = {"1 process, 1 core": [], "2 processes, 1 core each": [],
                                   "1 process, 2 cores, 2 devices": []}
    try:
        for r in range(args.repeats):
            d = tmp / f"one{r}"
            res["1 process, 1 core"].append(
                timed([["taskset", "-c", "0", *py, f"sweep_dir={d}"]], [env()]))
            d = tmp / f"two{r}"
            port = free_port()
            cmds = [["taskset", "-c", str(i), *py, f"sweep_dir={d}",
                     f"coordinator=127.0.0.1:{port}", "num_processes=2", f"process_id={i}"]
                    for i in range(2)]
            res["2 processes, 1 core each"].append(timed(cmds, [env(), env()]))
            d = tmp / f"dev{r}"
            res["1 process, 2 cores, 2 devices"].append(
                timed([[*py, f"sweep_dir={d}"]], [env(2)]))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = statistics.median(res["1 process, 1 core"])
    lines = [
        "# One sweep in one process against two processes on this machine", "",
        f"`python experiments/bench_processes.py --runs {args.runs} --epochs {args.epochs} "
        f"--repeats {args.repeats}` on {platform.machine()} ({os.cpu_count()} CPU cores): "
        f"FetchReach RDHER, {args.runs} runs, {args.epochs} epochs of 10 cycles at the paper's "
        "learner. Wall clock from process start to exit (imports, env build and compilation "
        "included), median of the repeats.", "",
        "| layout | wall clock (s) | against 1 process, 1 core |", "|---|---|---|"]
    for k, v in res.items():
        m = statistics.median(v)
        lines.append(f"| {k} | {m:.1f} | {base / m:.2f}x |")
    lines += ["", "On k hosts each process steps N/k of the runs, so the epochs take about 1/k "
              "of the time; start-up, compilation (every process compiles the same program) and "
              "the exchange between epochs (each epoch's metrics, and the learner states when "
              "a run reaches a new best) do not shrink."]
    text = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_processes.md").write_text(text)
    (args.out / "bench_processes.json").write_text(json.dumps(
        {"runs": args.runs, "epochs": args.epochs, "seconds": res}, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
