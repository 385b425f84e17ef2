"""A sweep in one process against the same sweep over two processes on this machine.

    python experiments/bench_processes.py            # FetchReach, 4 runs, 3 epochs
    python experiments/bench_processes.py --runs 8 --epochs 5

Three ways to run one sweep of N runs (λ pairs x seeds, FetchReach at the paper's learner, 10
cycles per epoch), each from process start to exit, side by side in one call:

- ``1 process, 1 core``: ``taskset -c 0``, one JAX device;
- ``2 processes, 1 core each``: ``rdher_jax.sweep ... coordinator= num_processes=2``, process i
  pinned to core i (``taskset -c i``), one device each: what two machines would do, shrunk;
- ``1 process, 2 cores, 2 devices``: two host devices (``JAX_NUM_CPU_DEVICES=2`` in the
  child's environment, the option start-up sets).

The layouts are interleaved (the order rotated every repeat) and medians reported. Writes
``experiments/results/bench_processes.md`` and ``.json`` (with the machine's ceilings from
``--limits-script``). Needs an otherwise idle machine.
"""

from __future__ import annotations

import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import harness

LAYOUTS = ("1 process, 1 core", "2 processes, 1 core each", "1 process, 2 cores, 2 devices")


def sweep_args(runs: int, epochs: int) -> list[str]:
    pairs = [[1, 1], [2, 1], [1, 2], [4, 1]]
    seeds = max(1, runs // len(pairs))
    n_pairs = max(1, runs // seeds)
    lam = "[" + ",".join(f"[{a},{b}]" for a, b in pairs[:n_pairs]) + "]"
    return ["env=FetchReach", "algo=rdher", f"lambdas={lam}", f"seeds={seeds}",
            f"epochs={epochs}", "n_cycles=10", "progress=false"]


def env(devices: int = 1) -> dict:
    """A child's environment: CPU only, its host devices as start-up reads them."""
    e = {**os.environ, "JAX_PLATFORMS": "cpu"}
    e.pop("XLA_FLAGS", None)
    e.pop("JAX_NUM_CPU_DEVICES", None)
    if devices > 1:
        e["JAX_NUM_CPU_DEVICES"] = str(devices)
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


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_processes.py", __doc__.splitlines()[0], repeats=1, limits=True)
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=3)
    args = ap.parse_args(argv)
    from rdher_jax import startup

    # This process only starts the sweeps (and reads the host): nothing to build.
    startup.setup(startup.Startup(ffi=False, compile_cache=False))
    limits = harness.machine_limits(args.limits_script)
    py = [sys.executable, "-m", "rdher_jax.sweep", *sweep_args(args.runs, args.epochs)]
    tmp = Path(tempfile.mkdtemp(prefix="bench_processes-"))
    count = iter(range(1 << 30))  # a fresh sweep directory per measurement

    def measure(layout: str) -> float:
        d = tmp / f"sweep{next(count)}"
        if layout == LAYOUTS[0]:
            return timed([["taskset", "-c", "0", *py, f"sweep_dir={d}"]], [env()])
        if layout == LAYOUTS[1]:
            port = free_port()
            cmds = [["taskset", "-c", str(i), *py, f"sweep_dir={d}",
                     f"coordinator=127.0.0.1:{port}", "num_processes=2", f"process_id={i}"]
                    for i in range(2)]
            return timed(cmds, [env(), env()])
        return timed([[*py, f"sweep_dir={d}"]], [env(2)])

    try:
        res = harness.interleave(LAYOUTS, args.repeats, measure)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = statistics.median(res[LAYOUTS[0]])
    cmd = harness.command("bench_processes.py", argv)
    h = harness.host()
    cells = [(k, f"{statistics.median(v):.1f}", f"{base / statistics.median(v):.2f}x")
             for k, v in res.items()]
    blocks = [
        f"`{cmd}` on {harness.machine(h)}: FetchReach RDHER, {args.runs} runs, {args.epochs} "
        "epochs of 10 cycles at the paper's learner. Wall clock from process start to exit "
        "(imports, env build and compilation included), median of the repeats (layouts "
        "interleaved, order rotated every repeat).",
        harness.table(["layout", "wall clock (s)", "against 1 process, 1 core"], cells),
        "On k hosts each process steps N/k of the runs, so the epochs take about 1/k "
        "of the time; start-up, compilation (every process compiles the same program) and "
        "the exchange between epochs (each epoch's metrics, and the learner states when "
        "a run reaches a new best) do not shrink.",
    ]
    if limits:
        blocks += [f"The machine's ceilings, measured just before the runs (`python "
                   f"{limits['script']}`):", ["```", limits["table"], "```"]]
    harness.write_results(args.out, "One sweep in one process against two processes on this "
                          "machine", blocks, {"runs": args.runs, "epochs": args.epochs,
                                              "seconds": res, "machine_limits": limits},
                          command=cmd, host=h)


if __name__ == "__main__":
    main()
