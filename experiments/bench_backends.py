"""The three physics backends on this CPU: compile time, first epoch and env steps/s of the
FetchPush training program, at 16, 256 and 1,024 envs.

    python experiments/bench_backends.py --limits-script ../shared/bench/machine_limits.py

For each backend (``mujoco``, ``mjx``, ``warp``) and each ``num_envs``, one child process, with
a deadline (``--timeout``), no persistent XLA compilation cache (the compile times are among
the figures) and Warp's kernel cache as it is (warm after the first warp child; the first
child's Warp build is recorded in its row; ``mjx`` children run with ``envs.CPU_XLA_FLAGS``, as
MJX on a CPU should):

1. env steps/s: ``jit`` of reset + a ``--steps``-step ``lax.scan`` of ``vmap(env.step)`` with
   random actions (``bench_envs.make_rollout``): XLA compile time, then the median of
   ``--calls`` timed calls after one warm call;
2. the training program: FetchPush, HER, ``num_envs`` envs, one cycle per epoch
   (``n_cycles=1``; every other key the default: 40 batches of 256, 10 test episodes): XLA
   compile time of ``program.epoch`` (trace + lower + compile) and the first epoch's time.

A child that misses its deadline leaves the figures it printed; the rest of its row reads
"did not finish in N s". Then, for ``warp`` at 1,024 envs, the time from process start to the
start of the first epoch (start-up, build, init and the epoch's compile, as ``rdher_jax.train``
does first), with Warp's kernel cache warm and no XLA cache; and the machine's ceilings
(``--limits-script``), measured first.
Writes ``experiments/results/bench_backends.{md,json}``. Pin it to one core (``taskset -c 0``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import harness  # noqa: E402

TITLE = "Physics backends on this CPU (`experiments/bench_backends.py`)"
BACKENDS = ("mujoco", "mjx", "warp")
SIZES = (16, 256, 1024)
# The training program: FetchPush with HER, one cycle an epoch, the rest the defaults.
TRAIN_KEYS = dict(env="FetchPush", algo="her", n_cycles=1, progress=False)


def child(backend: str, num_envs: int, steps: int, calls: int) -> None:
    """One (backend, num_envs) row, printed as JSON lines as the figures come."""
    t_start = time.perf_counter()
    from rdher_jax import startup

    startup.setup(startup.Startup(ffi=backend == "mujoco", compile_cache=False))
    import jax
    from bench_envs import batch_keys, compile_timed, make_rollout

    from rdher_jax.config import Config, resolve
    from rdher_jax.executor import build

    def emit(**kw):
        print(json.dumps(kw), flush=True)

    cfg = resolve(Config(**TRAIN_KEYS, backend=backend, num_envs=num_envs,
                         run_dir=tempfile.mkdtemp()))
    t0 = time.perf_counter()
    env, program = build(cfg)
    emit(build_s=time.perf_counter() - t0, scene=env.setup.variant)

    # 1. env steps/s
    rollout = make_rollout(env, steps=steps)
    keys = batch_keys(0, num_envs)
    fn, lower_s, compile_s = compile_timed(rollout, keys)
    emit(env_compile_s=lower_s + compile_s)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(keys))
    emit(env_first_call_s=time.perf_counter() - t0)
    times = []
    for i in range(calls):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(batch_keys(i + 1, num_envs)))
        times.append(time.perf_counter() - t0)
    t = sorted(times)[len(times) // 2]
    emit(env_steps_per_s=num_envs * steps / t)

    # 2. the training program
    hp = program.hparams
    ts = jax.block_until_ready(jax.jit(program.init)(jax.random.PRNGKey(0), hp))
    t0 = time.perf_counter()
    compiled = jax.jit(program.epoch).lower(ts, hp).compile()
    emit(epoch_compile_s=time.perf_counter() - t0)
    t0 = time.perf_counter()
    ts, m = jax.block_until_ready(compiled(ts, hp))
    emit(first_epoch_s=time.perf_counter() - t0, epoch_env_steps=int(m.env_steps),
         process_s=time.perf_counter() - t_start)


def run_child(args: list[str], timeout: float, env: dict | None = None) -> tuple[dict, str]:
    """Run this script as a child; its JSON lines merged, and how it ended. A child that steps
    ``mjx`` gets ``envs.CPU_XLA_FLAGS`` (the flags MJX needs on a CPU, docs/performance.md)."""
    if "mjx" in args:
        from rdher_jax.envs import CPU_XLA_FLAGS

        env = {**(env or os.environ),
               "XLA_FLAGS": " ".join([os.environ.get("XLA_FLAGS", ""), *CPU_XLA_FLAGS]).strip()}
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args],
                           capture_output=True, text=True, timeout=timeout, env=env)
        out, end = p.stdout, ("ok" if p.returncode == 0 else f"exit {p.returncode}: "
                              + (p.stderr.strip().splitlines() or [""])[-1][:200])
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        end = f"did not finish in {timeout:.0f} s"
    row: dict = {}
    for ln in out.splitlines():
        if ln.startswith("{"):
            row.update(json.loads(ln))
    row["end"], row["wall_s"] = end, time.perf_counter() - t0
    return row, end


def ready_child(backend: str, num_envs: int, t_launch: float) -> None:
    """From process start to the first epoch's start: start-up, the env and program built,
    the learner initialised and the epoch compiled, as ``rdher_jax.train`` does before its
    first epoch. ``t_launch``: the parent's ``time.time()`` just before it started this
    process (so interpreter start-up and imports count)."""
    from rdher_jax import startup

    startup.setup(startup.Startup(ffi=backend == "mujoco", compile_cache=False))
    import jax

    from rdher_jax.config import Config, resolve
    from rdher_jax.executor import build

    cfg = resolve(Config(**TRAIN_KEYS, backend=backend, num_envs=num_envs,
                         run_dir=tempfile.mkdtemp()))
    _, program = build(cfg)
    hp = program.hparams
    ts = jax.block_until_ready(jax.jit(program.init)(jax.random.PRNGKey(0), hp))
    jax.jit(program.epoch).lower(ts, hp).compile()
    print(json.dumps({"ready_s": time.time() - t_launch}), flush=True)


def fmt(row: dict, key: str, digits: int = 1) -> str:
    if key in row:
        return f"{row[key]:,.{digits}f}"
    return row["end"] if row["end"] != "ok" else "-"


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser("bench_backends.py", __doc__.split("\n\n")[0], limits=True)
    ap.add_argument("--backends", default=",".join(BACKENDS))
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--timeout", type=float, default=420.0, help="seconds per child")
    ap.add_argument("--steps", type=int, default=10, help="env steps per timed rollout")
    ap.add_argument("--calls", type=int, default=3, help="timed rollout calls (median)")
    ap.add_argument("--mjx-timeout", type=float, default=300.0,
                    help="seconds per mjx child (MJX's JAX implementation is slow on a CPU)")
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows (and machine ceilings) of the backends not measured "
                         "now from the existing results file")
    ap.add_argument("--render", action="store_true",
                    help="only rewrite the markdown from the results file's JSON")
    ap.add_argument("--note", default=None,
                    help="with --render: a sentence to record under the table")
    ap.add_argument("--child", nargs=2, default=None, help=argparse_suppress())
    ap.add_argument("--ready", nargs=3, default=None, help=argparse_suppress())
    a = ap.parse_args(argv)
    if a.ready:
        ready_child(a.ready[0], int(a.ready[1]), float(a.ready[2]))
        return 0
    if a.render:
        doc = json.loads(a.out.with_suffix(".json").read_text())
        command, host = doc.pop("command"), doc.pop("host")
        if a.note:
            doc["note"] = a.note
        harness.write_results(a.out, TITLE, render(doc, host), doc, command=command, host=host)
        return 0
    if a.child:
        child(a.child[0], int(a.child[1]), a.steps, a.calls)
        return 0
    limits = harness.machine_limits(a.limits_script)
    kept: list = []
    if a.merge and a.out.with_suffix(".json").is_file():
        old = json.loads(a.out.with_suffix(".json").read_text())
        kept = [r for r in old["rows"] if r["backend"] not in a.backends.split(",")]
        limits = limits or old.get("limits")
    from rdher_jax import startup

    startup.setup(startup.Startup(ffi=False, compile_cache=False))
    host = harness.host()
    rows = list(kept)
    data = {"train_keys": TRAIN_KEYS, "steps": a.steps, "calls": a.calls,
            "timeout_s": a.timeout, "limits": limits, "rows": rows}

    def write():
        harness.write_results(a.out, TITLE, render(data, host),
                              data, command=harness.command("bench_backends.py", argv),
                              host=host, echo=False)

    for backend in a.backends.split(","):
        for n in map(int, a.sizes.split(",")):
            harness.say(f"{backend} at {n} envs ...")
            row, end = run_child(["--child", backend, str(n), "--steps", str(a.steps),
                                  "--calls", str(a.calls)],
                                 a.mjx_timeout if backend == "mjx" else a.timeout)
            rows.append({"backend": backend, "num_envs": n, **row})
            harness.say(f"  {end}: {row}")
            write()
    if "warp" in a.backends.split(","):
        n = max(map(int, a.sizes.split(",")))
        harness.say(f"warp: from process start to the first epoch at {n} envs ...")
        row, _ = run_child(["--ready", "warp", str(n), repr(time.time())], a.timeout)
        data["from_start"] = {"num_envs": n, **row}
        harness.say(f"  {data['from_start']}")
    write()
    print((a.out.with_suffix(".md")).read_text())
    return 0


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


def render(data: dict, host: dict) -> list:
    rows = data["rows"]
    blocks: list = [
        f"{harness.machine(host)}; load average {host['loadavg'][0]:.2f}. One child process "
        f"per row (deadline {data['timeout_s']:.0f} s), no persistent XLA cache. Env steps/s: "
        f"median of {data['calls']} calls of reset + {data['steps']} steps of FetchPush with "
        f"random actions. Epoch: FetchPush HER with n_cycles=1 (one cycle of num_envs x 50 "
        f"env steps, 40 batches of 256, 10 test episodes). Figures: `bench_backends.json`.",
        harness.table(
            ["backend", "envs", "env compile (s)", "env first call (s)", "env steps/s",
             "epoch compile (s)", "first epoch (s)", "child process (s)"],
            [[r["backend"], r["num_envs"], fmt(r, "env_compile_s"),
              fmt(r, "env_first_call_s"), fmt(r, "env_steps_per_s", 0),
              fmt(r, "epoch_compile_s"), fmt(r, "first_epoch_s"), fmt(r, "process_s")]
             for r in rows]),
    ]
    if data.get("note"):
        blocks.append(data["note"])
    fs = data.get("from_start")
    if fs:
        ready = (f"{fs['ready_s']:.1f} s" if "ready_s" in fs else fs["end"])
        blocks.append(
            f"From process start to the first epoch's start, warp, {fs['num_envs']} envs, "
            f"Warp's kernel cache warm and no XLA cache (start-up, env and program built, "
            f"learner initialised, epoch compiled, as `rdher_jax.train` does first): {ready}.")
    lim = data.get("limits")
    if lim:
        blocks.append(f"Machine ceilings, same run (`{lim['script']}`):")
        blocks.append(["```", lim["table"], "```"])
    return blocks


if __name__ == "__main__":
    sys.exit(main())
