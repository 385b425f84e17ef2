"""The device check for a GPU's first minutes: the Fetch physics on MJX's Warp implementation
(``backend=warp``), in stages of known length that fit 8 minutes in all.

    python experiments/bench_gpu_warp.py                 # on the GPU: about 8 minutes at most
    python experiments/bench_gpu_warp.py --tiny --out /tmp/t.md   # on a CPU: tiny sizes

Stages, in order; each is a child process with a hard deadline (``STAGES``: seconds), and the
results (``--out``: markdown, with a JSON file beside it) are rewritten after every figure, so
that a run cut short keeps everything measured up to then:

1. ``env``: FetchPush on the warp backend at 1,024, 4,096 and 16,384 envs (``--tiny``: 4, 8,
   16): for each, XLA compile time of reset + a 50-step ``lax.scan`` of ``vmap(env.step)`` with
   random actions (``bench_envs.make_rollout``), the first call (Warp builds or loads its
   kernels then) and env steps/s (median of 3 calls).
2. ``push``: FetchPush with HER at 4,096 envs (``--tiny``: 4) and the GPU settings of
   docs/performance.md (batch 8,192, 200 batches a cycle, a 10M-transition buffer), one cycle
   an epoch: the program's XLA compile time, then as many epochs as fit (``--tiny``: one),
   each epoch's seconds, env steps and test success (64 test episodes).

The previous device check, ``bench_gpu.py``, ran the mjx backend (results/bench_gpu.md).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import harness  # noqa: E402

DEFAULT_OUT = HERE / "results" / "bench_gpu_warp.md"
# Seconds each stage may take, child start-up included: 8 minutes in all.
STAGES = {"env": 180.0, "push": 300.0}
SIZES = {"full": (1024, 4096, 16384), "tiny": (4, 8, 16)}
PUSH = {"full": dict(num_envs=4096, batch_size=8192, n_batches=200, buffer_size=10_000_000,
                     n_test_rollouts=64),
        "tiny": dict(num_envs=4, batch_size=32, n_batches=2, buffer_size=2000,
                     n_test_rollouts=2, hidden=16)}
ROLLOUT_STEPS = {"full": 50, "tiny": 5}


def env_stage(tiny: bool) -> None:
    """Stage 1, in its own process: one JSON line per figure."""
    from rdher_jax import startup

    startup.setup(startup.Startup(ffi=False, compile_cache=False))
    import jax
    from bench_envs import batch_keys, compile_timed, make_rollout
    from rdher_jax.envs import make_env

    size = "tiny" if tiny else "full"
    steps = ROLLOUT_STEPS[size]
    emit(devices=[str(d) for d in jax.devices()])
    for n in SIZES[size]:
        t0 = time.perf_counter()
        env = make_env("FetchPush", backend="warp", auto_reset=False, worlds=n)
        emit(batch=n, build_s=time.perf_counter() - t0)
        keys = batch_keys(0, n)
        fn, lower_s, compile_s = compile_timed(make_rollout(env, steps=steps), keys)
        emit(batch=n, compile_s=lower_s + compile_s)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(keys))
        emit(batch=n, first_call_s=time.perf_counter() - t0)
        times = []
        for i in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(batch_keys(i + 1, n)))
            times.append(time.perf_counter() - t0)
        emit(batch=n, steps_per_s=n * steps / sorted(times)[1])


def push_stage(tiny: bool) -> None:
    """Stage 2, in its own process: the compile time, then one JSON line per epoch until the
    parent's deadline ends the process."""
    t_start = time.perf_counter()
    from rdher_jax import startup

    startup.setup(startup.Startup(ffi=False, compile_cache=False))
    import tempfile

    import jax

    from rdher_jax.config import Config, resolve
    from rdher_jax.executor import build

    keys = PUSH["tiny" if tiny else "full"]
    cfg = resolve(Config(env="FetchPush", algo="her", backend="warp", n_cycles=1,
                         progress=False, run_dir=tempfile.mkdtemp(), **keys))
    _, program = build(cfg)
    hp = program.hparams
    ts = jax.block_until_ready(jax.jit(program.init)(jax.random.PRNGKey(0), hp))
    t0 = time.perf_counter()
    epoch = jax.jit(program.epoch, donate_argnums=0).lower(ts, hp).compile()
    emit(compile_s=time.perf_counter() - t0, settings=keys,
         ready_s=time.perf_counter() - t_start)
    for i in range(1, 2 if tiny else 10_000):
        t0 = time.perf_counter()
        ts, m = epoch(ts, hp)
        m = jax.device_get(m)
        emit(epoch=i, epoch_s=time.perf_counter() - t0, env_steps=int(m.env_steps),
             test_success=float(m.test_success), since_start_s=time.perf_counter() - t_start)


def emit(**kw) -> None:
    print(json.dumps(kw), flush=True)


def run_stage(name: str, tiny: bool, timeout: float, on_line) -> str:
    """Run stage ``name`` in a child with ``timeout`` seconds; ``on_line(dict)`` for each
    JSON line as it comes. Returns how the stage ended."""
    argv = [sys.executable, str(Path(__file__).resolve()), "--stage", name,
            *(["--tiny"] if tiny else [])]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout
    import selectors

    sel = selectors.DefaultSelector()
    sel.register(p.stdout, selectors.EVENT_READ)
    ended = None
    while ended is None:
        left = deadline - time.monotonic()
        if left <= 0:
            p.kill()
            ended = f"stopped at its {timeout:.0f} s deadline"
            break
        if sel.select(timeout=min(left, 1.0)):
            line = p.stdout.readline()
            if line.startswith("{"):
                on_line(json.loads(line))
            elif not line and p.poll() is not None:
                ended = "ok" if p.returncode == 0 else f"exit {p.returncode}"
        elif p.poll() is not None:
            ended = "ok" if p.returncode == 0 else f"exit {p.returncode}"
    p.wait()
    err = p.stderr.read().strip().splitlines()
    if ended.startswith("exit") and err:
        ended += ": " + err[-1][:300]
    return ended


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser("bench_gpu_warp.py", __doc__.split("\n\n")[0], out=DEFAULT_OUT)
    ap.formatter_class = argparse.RawDescriptionHelpFormatter
    ap.add_argument("--tiny", action="store_true",
                    help="tiny sizes (4-16 envs) and short stages: checks the script on a CPU")
    ap.add_argument("--stages", default=",".join(STAGES), help=f"of {','.join(STAGES)}")
    ap.add_argument("--stage", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.stage == "env":
        env_stage(a.tiny)
        return 0
    if a.stage == "push":
        push_stage(a.tiny)
        return 0
    stages = [s for s in a.stages.split(",") if s]
    bad = [s for s in stages if s not in STAGES]
    if bad:
        print(f"error: unknown stage {bad[0]!r} (of {', '.join(STAGES)})", file=sys.stderr)
        return 2
    from bench_gpu import gpu_info

    result: dict = {"hardware": gpu_info(), "tiny": a.tiny, "stage_s": STAGES,
                    "command": harness.command("bench_gpu_warp.py", argv), "stages": {}}
    t_start = time.perf_counter()

    def write() -> None:
        result["elapsed_s"] = time.perf_counter() - t_start
        harness.write_results(a.out, "The warp backend on a device "
                              "(`experiments/bench_gpu_warp.py`)", render(result), result,
                              echo=False)

    for s in stages:
        st: dict = {"rows": {}, "epochs": [], "end": "running"}
        result["stages"][s] = st

        def on_line(d: dict, st=st) -> None:
            if "batch" in d:
                st["rows"].setdefault(str(d["batch"]), {"batch": d["batch"]}).update(d)
            elif "epoch" in d:
                st["epochs"].append(d)
            else:
                st.update(d)
            write()

        write()
        st["end"] = run_stage(s, a.tiny, STAGES[s], on_line)
        write()
    print(a.out.with_suffix(".md").read_text())
    return 0


def fmt(d: dict, key: str, digits: int = 1) -> str:
    return f"{d[key]:,.{digits}f}" if key in d else "-"


def render(res: dict) -> list:
    hw = res["hardware"]
    blocks: list = [
        f"Device: {hw.get('gpu') or 'no GPU (CPU run)'}; {hw.get('cpu_count')} CPU cores; "
        + ", ".join(f"{k} {v}" for k, v in hw["versions"].items())
        + f". `{res['command']}`{' (tiny sizes)' if res['tiny'] else ''}; "
        f"{res.get('elapsed_s', 0):.0f} s so far. Figures: `{DEFAULT_OUT.stem}.json`."]
    st = res["stages"]
    if "env" in st:
        e = st["env"]
        blocks.append(f"## Warp env steps (FetchPush), stage ended: {e['end']}")
        blocks.append(harness.table(
            ["envs", "build (s)", "XLA compile (s)", "first call (s)", "env steps/s"],
            [[r["batch"], fmt(r, "build_s"), fmt(r, "compile_s"), fmt(r, "first_call_s"),
              fmt(r, "steps_per_s", 0)] for r in e["rows"].values()]))
    if "push" in st:
        p = st["push"]
        blocks.append(f"## FetchPush HER on warp, one cycle an epoch, stage ended: {p['end']}")
        blocks.append(f"Settings {p.get('settings')}; XLA compile of the epoch "
                      f"{fmt(p, 'compile_s')} s, ready {fmt(p, 'ready_s')} s after the "
                      f"stage's process started.")
        blocks.append(harness.table(
            ["epoch", "seconds", "env steps", "test success", "since stage start (s)"],
            [[r["epoch"], fmt(r, "epoch_s"), f"{r['env_steps']:,}",
              fmt(r, "test_success", 3), fmt(r, "since_start_s")] for r in p["epochs"]]))
    return blocks


if __name__ == "__main__":
    sys.exit(main())
