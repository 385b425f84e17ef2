"""Env-step throughput of the Fetch tasks: gymnasium-robotics, the ``mujoco`` backend, MJX on CPU.

Absolute figures move 2x between machines of the same kind (and with the load of a shared
machine), so every figure is measured in this one run next to gymnasium-robotics'
``FetchPush-v4`` ``env.step`` and also given as a ratio to it. Each figure is the median of
repeats; the ``mujoco`` backend's jitted and Python-loop figures are taken in alternation.

What it measures:

1. gymnasium-robotics ``Fetch*-v4`` ``env.step``, random actions, a reset every 50 steps. The
   FetchPush reference is re-measured between the task blocks; its median over the run is the
   denominator of every ratio (its spread says how much the machine's load moved). Next to it,
   bare mjbatch on all cores over one thread: the parallel CPU this process really got.
2. The ``mujoco`` backend, original and MJX-edited scene: ``jit`` of a 50-step ``lax.scan`` over
   ``vmap(env.step)`` with random actions and ``auto_reset=False``, the episode's reset
   included; compile time apart. Both ways of calling the physics, in alternation: one
   ``jax.pure_callback`` (mjbatch) per batched env step (``physics_call=callback``, what parts 3
   dissects) and the XLA FFI handlers (``physics_call=ffi``, the default).
3. The same ``host_reset`` / ``host_step`` calls made from a plain Python loop with numpy arrays
   (no JAX), the ratio jitted / loop, and where the difference goes (FetchPush, original scene):
   ``host_step`` timed inside the callback and in the loop, the time between two callbacks, a
   trivial ``pure_callback`` round trip in a scan, the jitted rollout with ``host_step`` replaced
   by constants and by a busy-wait of the same length, ``host_step``'s parts timed one by one,
   bare mjbatch stepping on one and on all threads, and the cost of ``auto_reset=True``.
4. The ``mjx`` backend on CPU (FetchPush, MJX-edited scene), one subprocess per XLA flag setting
   (``XLA_FLAGS`` must be set before JAX starts), with a persistent compilation cache: compile
   time cold and warm, env-steps/s with and without ``--xla_cpu_use_fusion_emitters=false``, and
   sharded over two host devices.

    python experiments/bench_envs.py              # ~10-12 min on 2 cores
    python experiments/bench_envs.py --quick      # smoke run: ~1 min with --no-mjx, ~2 min without

It writes ``experiments/results/bench_envs.md`` and a JSON file beside it (``--out``), the
MJX children with their XLA flags in their environment and their host devices through start-up.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from statistics import median
from typing import Any

import harness
import numpy as np
from rdher_jax.envs.notices import quiet_gymnasium_robotics
from rdher_jax.envs.registry import task_spec

from rdher_jax.tasks import PAPER_TASKS

HERE = os.path.dirname(os.path.abspath(__file__))
TASKS = PAPER_TASKS
SCENES = ("original", "mjx")
REF_TASK = "FetchPush"
EPISODE = 50
TARGET = 2.5  # the mujoco backend, original scene, vs gymnasium's FetchPush env.step
FUSION_OFF = "--xla_cpu_use_fusion_emitters=false"
WORKER_MARK = "BENCH_ENVS_MJX_RESULT "


# ----------------------------------------------------------------------------- gymnasium
def gym_env(task: str):
    import gymnasium as gym

    quiet_gymnasium_robotics()
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make(task_spec(task).gymnasium_id)
    env.reset(seed=0)
    env.action_space.seed(0)
    return env


def gym_rate(env, n: int) -> float:
    """env-steps/s of ``env.step`` with random actions, a reset every 50 steps (timed too)."""
    env.reset()
    t0 = time.perf_counter()
    for i in range(1, n + 1):
        env.step(env.action_space.sample())
        if i % EPISODE == 0:
            env.reset()
    return n / (time.perf_counter() - t0)


# ----------------------------------------------------------------------------- JAX rollouts
def make_rollout(env, steps: int = EPISODE, sharding=None):
    """jit of: reset a batch of envs (one key each), then ``steps`` x vmap(env.step) in a scan.

    Observations and rewards are the scan's outputs, as a collector keeps them (so XLA cannot
    drop the observation arithmetic).
    """
    import jax
    from rdher_jax.envs.rollout import rollout as env_rollout

    def policy(k, _):
        return jax.vmap(lambda kk: jax.random.uniform(kk, (env.action_size,), minval=-1.0,
                                                      maxval=1.0))(k)

    def rollout(keys: jax.Array):
        k_reset, k_act = jax.vmap(jax.random.split, out_axes=1)(keys)
        step_keys = jax.vmap(lambda k: jax.random.split(k, steps), out_axes=1)(k_act)
        return env_rollout(env, policy, k_reset, step_keys,
                           lambda s, a, nxt: (nxt.obs["observation"], nxt.reward))[2]

    if sharding is None:
        return jax.jit(rollout)
    return jax.jit(rollout, in_shardings=sharding)


def batch_keys(seed: int, batch: int):
    import jax

    return jax.random.split(jax.random.PRNGKey(seed), batch)


def compile_timed(fn, *args) -> tuple[Any, float, float]:
    """Compiled ``fn`` for ``args``, seconds to trace + lower, seconds for XLA to compile."""
    t0 = time.perf_counter()
    lowered = fn.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    return compiled, t1 - t0, time.perf_counter() - t1


# ----------------------------------------------------------------------------- Python loop
def sample_object_xy(rng: np.random.Generator, grip: np.ndarray, r: float, n: int) -> np.ndarray:
    """Object xy within r of the gripper and >= 0.1 m from it, as ``FetchEnv.reset`` samples."""
    xy = np.repeat(grip[None, :2], n, axis=0)
    bad = np.ones(n, bool)
    while bad.any():
        xy[bad] = grip[:2] + rng.uniform(-r, r, (int(bad.sum()), 2))
        bad = np.linalg.norm(xy - grip[:2], axis=1) < 0.1
    return xy


class LoopRollout:
    """The backend's ``host_reset`` and 50 ``host_step`` calls made from Python, no JAX."""

    def __init__(self, env, batch: int, host_step: Callable, seed: int = 0):
        self.env, self.batch, self.host_step = env, batch, host_step
        self.rng = np.random.default_rng(seed)
        s = env.setup
        self.qpos0 = np.asarray(s.init_qpos, np.float32)
        self.qvel0 = np.asarray(s.init_qvel, np.float32)
        self.grip0 = np.asarray(s.initial_gripper_xpos)

    def __call__(self) -> np.ndarray:
        env, n, rng = self.env, self.batch, self.rng
        qpos = np.repeat(self.qpos0[None], n, axis=0)
        qvel = np.repeat(self.qvel0[None], n, axis=0)
        if env.spec.has_object:
            a = env.setup.object_qposadr
            qpos[:, a : a + 2] = sample_object_xy(rng, self.grip0, env.spec.obj_range, n)
        bits, raw = env.backend.host_reset(qpos, qvel)
        for _ in range(EPISODE):
            act = rng.uniform(-1.0, 1.0, (n, 4)).astype(np.float32)
            delta = act[:, :3] * np.float32(0.05)
            grip = np.zeros(n, np.float32) if env.spec.block_gripper else act[:, 3]
            bits, raw = self.host_step(bits, delta, grip)
        return raw


# ----------------------------------------------------------------------------- mujoco backend
def repeats_for(batch: int, repeats: int) -> int:
    if batch <= 16:
        return repeats
    if batch <= 64:
        return max(2, repeats - 2)
    return 2


def bench_native_row(env, timed: harness.Stamps, batch: int, repeats: int, min_steps: int,
                     ffi_env=None) -> dict:
    """Jitted 50-step rollout (``env``: the ``pure_callback`` path) vs the same host calls from
    Python, and the same rollout through the FFI handlers (``ffi_env``), in alternation."""
    import jax

    fn = make_rollout(env)
    compiled, t_lower, t_xla = compile_timed(fn, batch_keys(0, batch))
    ffi = compile_timed(make_rollout(ffi_env), batch_keys(0, batch)) if ffi_env else None
    n_roll = max(1, math.ceil(min_steps / (EPISODE * batch)))
    reps = repeats_for(batch, repeats)
    keys = [batch_keys(1 + i, batch) for i in range(reps * n_roll + 1)]
    loop = LoopRollout(env, batch, timed)
    # Warm-up: the first call builds the mjbatch Batch of this size.
    if batch * EPISODE <= 1000:
        jax.block_until_ready(compiled(keys[-1]))
    else:
        loop.env.backend.host_reset(np.repeat(loop.qpos0[None], batch, 0),
                                    np.repeat(loop.qvel0[None], batch, 0))
    steps = n_roll * EPISODE * batch
    t = {k: [] for k in ("jit", "loop", "ffi", "host_jit", "host_loop", "host_ffi", "gap_jit",
                         "gap_loop", "gap_ffi")}
    if ffi:
        jax.block_until_ready(ffi[0](keys[-1]))
    for r in range(reps):
        ks = keys[r * n_roll : (r + 1) * n_roll]

        def run_jit(ks=ks):
            for k in ks:
                jax.block_until_ready(compiled(k))

        def run_loop():
            for _ in range(n_roll):
                loop()

        def run_ffi(ks=ks):
            for k in ks:
                jax.block_until_ready(ffi[0](k))

        order = (("jit", run_jit), ("loop", run_loop)) + ((("ffi", run_ffi),) if ffi else ())
        for name, run in order if r % 2 == 0 else order[::-1]:
            timed.clear()
            t[name].append(harness.seconds(run))
            t[f"host_{name}"].append(timed.mean_call() * 1e6)
            t[f"gap_{name}"].append(timed.mean_gap(EPISODE) * 1e6)
    jit_s, loop_s = t["jit"], t["loop"]
    pair = [lt / jt for jt, lt in zip(jit_s, loop_s, strict=True)]
    ffi_row = {} if not ffi else {
        "ffi_compile_s": ffi[1] + ffi[2],
        "ffi_rate": steps / median(t["ffi"]),
        "ffi_over_jit": median([jt / ft for jt, ft in zip(jit_s, t["ffi"], strict=True)]),
    }
    return {
        **ffi_row,
        "batch": batch,
        "compile_s": t_lower + t_xla,
        "lower_s": t_lower,
        "repeats": reps,
        "env_steps_per_repeat": steps,
        "jit_rate": steps / median(jit_s),
        "loop_rate": steps / median(loop_s),
        "jit_over_loop": median(pair),
        "jit_rates": [steps / x for x in jit_s],
        "loop_rates": [steps / x for x in loop_s],
        "step_us_jit": median(jit_s) / (n_roll * EPISODE) * 1e6,
        "step_us_loop": median(loop_s) / (n_roll * EPISODE) * 1e6,
        "host_step_us_jit": median(t["host_jit"]),
        "host_step_us_loop": median(t["host_loop"]),
        "gap_us_jit": median(t["gap_jit"]),
        "gap_us_loop": median(t["gap_loop"]),
    }


def callback_round_trip_us(be, batch: int, length: int = 200, repeats: int = 5) -> float:
    """One trivial ``pure_callback`` per scan step, with the env step's shapes and dtypes."""
    import jax
    import jax.numpy as jnp
    from rdher_jax.envs.physics import RAW_SIZE

    raw = np.zeros((batch, RAW_SIZE), np.float32)
    shapes = (jax.ShapeDtypeStruct((batch, 2 * be.width), jnp.uint32),
              jax.ShapeDtypeStruct((batch, RAW_SIZE), jnp.float32))

    def host(bits, delta, grip):
        return np.asarray(bits), raw

    def body(c, _):
        bits, acc = c
        bits, r = jax.pure_callback(host, shapes, bits, jnp.zeros((batch, 3)), jnp.zeros(batch))
        return (bits, acc + r), None

    f = jax.jit(lambda c: jax.lax.scan(body, c, None, length=length)[0])
    c = (jnp.zeros(shapes[0].shape, jnp.uint32), jnp.zeros(shapes[1].shape, jnp.float32))
    jax.block_until_ready(f(c))
    ts = [harness.seconds(f, c) for _ in range(repeats)]
    return median(ts) / length * 1e6


PARTS = ("unpack", "step", "readout", "pack")


def host_step_parts(be, bits, delta, grip, acc: dict[str, float]):
    """``NativeBackend.host_step`` itself, with a clock at the end of each of its parts."""
    last = [time.perf_counter()]

    def clock(part: str) -> None:
        now = time.perf_counter()
        acc[part] += now - last[0]
        last[0] = now

    return be.host_step(bits, delta, grip, clock=clock)


class PartsRollout:
    """Random-action episodes through ``host_step`` with its parts timed."""

    def __init__(self, env, batch: int, seed: int = 0):
        self.env, self.batch = env, batch
        self.rng = np.random.default_rng(seed)
        loop = LoopRollout(env, batch, env.backend.host_step)
        self.qpos = np.repeat(loop.qpos0[None], batch, 0)
        self.qvel = np.repeat(loop.qvel0[None], batch, 0)

    def _action(self) -> tuple[np.ndarray, np.ndarray]:
        act = self.rng.uniform(-1.0, 1.0, (self.batch, 4)).astype(np.float32)
        grip = np.zeros(self.batch, np.float32) if self.env.spec.block_gripper else act[:, 3]
        return act[:, :3] * np.float32(0.05), grip

    def __call__(self, n_steps: int) -> dict[str, float]:
        """Microseconds per call of each part of ``host_step``."""
        be = self.env.backend
        acc = dict.fromkeys(PARTS, 0.0)
        for i in range(n_steps):
            if i % EPISODE == 0:
                bits, _ = be.host_reset(self.qpos, self.qvel)
            bits, _ = host_step_parts(be, bits, *self._action(), acc)
        return {k: x / n_steps * 1e6 for k, x in acc.items()}


def bare_mjbatch(setup, batch: int, threads: int) -> Callable[[int], float]:
    """mjbatch alone: the mocap target set as ``host_step`` sets it, 20 substeps; no state load,
    no forward, no readout. Returns a function of n_steps giving microseconds per batched step."""
    import mjbatch
    import mujoco
    from rdher_jax.envs.physics import MOCAP_QUAT_DELTA, N_SUBSTEPS

    s = setup
    m, gb = s.model, s.gripper_body
    b = mjbatch.Batch(m, batch, num_threads=threads)
    state, mpos, mquat, xpos, xquat = (b.bind(f) for f in
                                       ("state", "mocap_pos", "mocap_quat", "xpos", "xquat"))
    s0 = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(m, s.reset_data, s0, mujoco.mjtState.mjSTATE_INTEGRATION)
    rng = np.random.default_rng(0)

    def run(n_steps: int) -> float:
        t0 = time.perf_counter()
        for i in range(n_steps):
            if i % EPISODE == 0:
                state[:] = s0
                b.forward()
            mpos[:, 0] = xpos[:, gb] + 0.05 * rng.uniform(-1.0, 1.0, (batch, 3))
            mquat[:, 0] = xquat[:, gb] + MOCAP_QUAT_DELTA
            b.step(nstep=N_SUBSTEPS)
        return (time.perf_counter() - t0) / n_steps * 1e6

    return run


class ParallelProbe:
    """How much parallel CPU this process gets right now: bare mjbatch (FetchPush, original
    scene, batch 16) env-steps/s on all usable cores over the same on one thread. 2.0 on two
    free cores; 1.0 when other processes leave the equivalent of one."""

    def __init__(self, batch: int = 16, n_steps: int = 20):
        from rdher_jax.envs.physics import Setup

        setup = Setup(REF_TASK, "original")
        threads = len(os.sched_getaffinity(0))
        self.runs = {1: bare_mjbatch(setup, batch, 1), threads: bare_mjbatch(setup, batch, threads)}
        self.threads, self.n_steps = threads, n_steps
        self.speedups: list[float] = []

    def __call__(self) -> float:
        one = self.runs[1](self.n_steps)
        many = self.runs[self.threads](self.n_steps)
        one = median([one, self.runs[1](self.n_steps)])
        self.speedups.append(one / many)
        return self.speedups[-1]


class JitRunner:
    """The jitted 50-step rollout of ``env`` at one batch size, compiled once, ``host_step``
    optionally replaced while tracing. A call runs it and returns the microseconds per batched
    step and the mean microseconds between two ``host_step`` calls."""

    def __init__(self, env, batch: int, min_steps: int, host_step: Callable | None = None):
        import jax

        be = env.backend
        saved = be.__dict__.get("host_step")
        self.timed = harness.Stamps(host_step or be.host_step)
        be.host_step = self.timed
        try:
            self.compiled, _, _ = compile_timed(make_rollout(env), batch_keys(0, batch))
        finally:
            if saved is None:
                del be.host_step
            else:
                be.host_step = saved
        self.n_roll = max(1, math.ceil(min_steps / (EPISODE * batch)))
        self.keys = batch_keys(1, batch)
        jax.block_until_ready(self.compiled(self.keys))

    def __call__(self) -> tuple[float, float]:
        import jax

        self.timed.clear()
        t0 = time.perf_counter()
        for _ in range(self.n_roll):
            jax.block_until_ready(self.compiled(self.keys))
        dt = time.perf_counter() - t0
        return dt / (self.n_roll * EPISODE) * 1e6, self.timed.mean_gap(EPISODE) * 1e6


def constant_host_step(batch: int) -> Callable:
    """A ``host_step`` that returns its input state and a constant readout: no physics."""
    from rdher_jax.envs.physics import RAW_SIZE

    raw = np.zeros((batch, RAW_SIZE), np.float32)
    return lambda bits, delta, grip: (np.asarray(bits), raw)


def busy_host_step(batch: int, us: float) -> Callable:
    """A ``host_step`` that busy-waits ``us`` microseconds (holding the GIL), then returns
    constants: the callback's duration without mjbatch, its threads or its memory traffic."""
    const = constant_host_step(batch)

    def host(bits, delta, grip):
        end = time.perf_counter() + us * 1e-6
        while time.perf_counter() < end:
            pass
        return const(bits, delta, grip)

    return host


def breakdown(env, rows: dict[int, dict], batches: Sequence[int], repeats: int,
              min_steps: int) -> dict[int, dict]:
    """Where the jitted rollout's time goes, per batched env step, for each batch size."""
    from rdher_jax import make_env

    auto = make_env(env.name, backend="mujoco", scene=env.setup.variant, auto_reset=True)
    out = {}
    for batch in batches:
        row = rows[batch]
        n_steps = max(EPISODE, min_steps // batch)
        threads = min(env.backend.num_threads, batch)
        parts_run = PartsRollout(env, batch)
        bare_runs = {t: bare_mjbatch(env.setup, batch, t) for t in sorted({1, threads})}
        parts, bare = [], {t: [] for t in bare_runs}
        for _ in range(repeats):
            parts.append(parts_run(n_steps))
            for t, run in bare_runs.items():
                bare[t].append(run(n_steps))
        runners = {
            "plain": JitRunner(env, batch, min_steps),
            "auto": JitRunner(auto, batch, min_steps),
            "null": JitRunner(env, batch, min_steps, constant_host_step(batch)),
            "busy": JitRunner(env, batch, min_steps,
                              busy_host_step(batch, row["host_step_us_jit"])),
        }
        jr = {k: [] for k in runners}
        for _ in range(repeats):
            for k, run in runners.items():
                jr[k].append(run())
        out[batch] = {
            **{k: row[k] for k in ("step_us_jit", "step_us_loop", "host_step_us_jit",
                                   "host_step_us_loop", "gap_us_jit", "gap_us_loop")},
            "null_step_us": median([x[0] for x in jr["null"]]),
            "null_gap_us": median([x[1] for x in jr["null"]]),
            "busy_step_us": median([x[0] for x in jr["busy"]]),
            "busy_gap_us": median([x[1] for x in jr["busy"]]),
            "plain_step_us": median([x[0] for x in jr["plain"]]),
            "auto_reset_step_us": median([x[0] for x in jr["auto"]]),
            "auto_over_plain": median([a[0] / p[0] for a, p in
                                       zip(jr["auto"], jr["plain"], strict=True)]),
            "callback_us": callback_round_trip_us(env.backend, batch),
            "parts_us": {k: median([p[k] for p in parts]) for k in PARTS},
            "bare_mjbatch_us": median(bare[threads]),
            "bare_mjbatch_1thread_us": median(bare[1]),
            "threads": threads,
        }
        print(f"  breakdown B={batch}: " + ", ".join(
            f"{k} {v:.0f}" for k, v in out[batch].items() if isinstance(v, float)), flush=True)
    return out


# ----------------------------------------------------------------------------- MJX (subprocess)
def count_files(path: str) -> int:
    return sum(len(files) for _, _, files in os.walk(path))


def mjx_worker(cfg: dict) -> dict:
    """Run in a fresh process (``run_mjx`` puts the flags in its ``XLA_FLAGS``: read once, when
    JAX starts); its host devices through start-up."""
    from rdher_jax import startup

    startup.setup(startup.Startup(host_devices=cfg["devices"], ffi=False, compile_cache=False))
    import jax

    # This run's own cache, every compilation kept: cold and warm compiles are what is measured.
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", cfg["cache_dir"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    from rdher_jax import make_env

    t0 = time.perf_counter()
    env = make_env("FetchPush", backend="mjx", auto_reset=False)
    setup_s = time.perf_counter() - t0
    batch, steps, devices = cfg["batch"], cfg["steps"], cfg["devices"]
    sharding = None
    if devices > 1:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        # A plain (auto-sharded) mesh: the batch axis is split, XLA propagates it.
        mesh = Mesh(np.array(jax.devices()[:devices]), ("b",))
        sharding = NamedSharding(mesh, PartitionSpec("b"))
    keys = [batch_keys(i, batch) for i in range(cfg["repeats"] + 1)]
    if sharding is not None:
        keys = [jax.device_put(k, sharding) for k in keys]
    before = count_files(cfg["cache_dir"])
    compiled, lower_s, compile_s = compile_timed(make_rollout(env, steps, sharding), keys[0])
    written = count_files(cfg["cache_dir"]) - before
    out = jax.block_until_ready(compiled(keys[0]))
    used = len(out[0].sharding.device_set)
    ts = [harness.seconds(compiled, k) for k in keys[1:]]
    return {
        **{k: cfg[k] for k in ("name", "flags", "batch", "steps", "devices", "repeats")},
        "jax_devices": len(jax.devices()),
        "devices_used": used,
        "setup_s": setup_s,
        "lower_s": lower_s,
        "compile_s": compile_s,
        "cache": "cold" if written > 0 else "warm",
        "rate": batch * steps / median(ts),
        "rates": [batch * steps / t for t in ts],
    }


def mjx_configs(batches: Sequence[int], quick: bool) -> list[dict]:
    if quick:
        return [{"name": "fusion emitters off", "flags": FUSION_OFF, "batch": 1, "steps": 2,
                 "devices": 1, "repeats": 1}]

    def steps(b: int) -> int:
        return max(2, 8 // b)

    cfgs = []
    if 1 in batches:
        cfgs.append({"name": "as shipped (no XLA flags)", "flags": "", "batch": 1,
                     "steps": 2, "devices": 1, "repeats": 2})
    for b in batches:
        cfgs.append({"name": "fusion emitters off", "flags": FUSION_OFF, "batch": b,
                     "steps": steps(b), "devices": 1, "repeats": 3})
        if b == min(batches):
            cfgs.append({**cfgs[-1], "name": "fusion emitters off, second process"})
    for b in batches:
        if b >= 2 and b % 2 == 0:
            cfgs.append({"name": "fusion emitters off, 2 host devices, batch sharded",
                         "flags": FUSION_OFF, "batch": b, "steps": steps(b),
                         "devices": 2, "repeats": 3})
    return cfgs


def run_mjx(cfgs: list[dict], cache_dir: str, timeout: float) -> list[dict]:
    results = []
    for cfg in cfgs:
        cfg = {**cfg, "cache_dir": cache_dir}
        print(f"  mjx: {cfg['name']}, B={cfg['batch']} ...", flush=True)
        cmd = [sys.executable, os.path.abspath(__file__), "--mjx-worker", json.dumps(cfg)]
        t0 = time.perf_counter()
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                               env={**os.environ, "XLA_FLAGS": cfg["flags"]})
        except subprocess.TimeoutExpired:
            results.append({**cfg, "error": f"timed out after {timeout:.0f} s"})
            print(f"    timed out after {timeout:.0f} s", flush=True)
            continue
        lines = [ln for ln in p.stdout.splitlines() if ln.startswith(WORKER_MARK)]
        if p.returncode != 0 or not lines:
            tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
            results.append({**cfg, "error": " / ".join(tail) or f"exit {p.returncode}"})
            print(f"    failed: {results[-1]['error']}", flush=True)
            continue
        res = json.loads(lines[-1][len(WORKER_MARK) :])
        res["process_s"] = time.perf_counter() - t0
        results.append(res)
        print(f"    lower {res['lower_s']:.1f} s, compile {res['compile_s']:.1f} s "
              f"({res['cache']}), "
              f"{res['rate']:.1f} env-steps/s", flush=True)
    return results


# ----------------------------------------------------------------------------- report
def fmt_rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.1f}"


def report(res: dict, command: str, host: dict) -> str:
    """The results page below its title: ``res`` is the JSON's figures, ``host``
    :func:`harness.host`'s."""
    hw, ref, sp = res["hardware"], res["gym_ref_rate"], res["parallel_speedups"]
    v = hw["versions"]
    lines = [
        f"Produced by `{command}` on {res['date']} ({res['wall_s'] / 60:.1f} min).",
        "",
        f"- Hardware: {harness.machine(host)}, {hw['platform']}; load average at start "
        f"{', '.join(f'{x:.1f}' for x in hw['loadavg_start'])}, at end "
        f"{', '.join(f'{x:.1f}' for x in res['loadavg_end'])}.",
        "- Versions: " + ", ".join(f"{k} {x or 'not installed'}" for k, x in v.items()) + ".",
        f"- XLA_FLAGS of the main process: `{hw['xla_flags'] or '(none)'}`; the `mujoco` backend "
        f"steps on {res.get('native_threads', '?')} mjbatch threads at most "
        "(`min(threads, batch)`).",
        f"- Reference: gymnasium-robotics FetchPush-v4 `env.step`, median "
        f"**{fmt_rate(ref)} env-steps/s** over {len(res['gym_ref_rates'])} blocks spread over the "
        f"run (min {fmt_rate(min(res['gym_ref_rates']))}, max "
        f"{fmt_rate(max(res['gym_ref_rates']))}). Every `x` column divides by it.",
        f"- Parallel CPU actually available (other processes share the machine): bare mjbatch, "
        f"FetchPush, batch 16, {res['parallel_threads']} threads over 1 thread = median "
        f"**{median(sp):.2f}x** over {len(sp)} probes spread over the run (min {min(sp):.2f}, "
        f"max {max(sp):.2f}); {res['parallel_threads']:.1f}x would be {res['parallel_threads']} "
        "free cores. gymnasium steps on one thread, so the `mujoco` backend's ratio to it "
        "scales with this figure.",
        "",
        "## gymnasium-robotics `env.step` (random actions, reset every 50 steps)",
        "",
        "| task | env-steps/s | x gym Push |",
        "|---|---:|---:|",
    ]
    for task, r in res["gym"].items():
        lines.append(f"| {task} | {fmt_rate(r['rate'])} | {r['rate'] / ref:.2f}x |")
    lines += [
        "",
        "## `mujoco` backend: jitted 50-step rollout vs the same host calls from Python",
        "",
        "jit: `jit(lax.scan(50 x vmap(env.step)))` from `vmap(env.reset)`, random actions, "
        "`auto_reset=False`, reset included; compile measured apart. loop: the backend's "
        "`host_reset` + 50 `host_step` calls from Python with numpy arrays. jit/loop: median of "
        "the ratios of alternating repeats. jit is the `pure_callback` path "
        "(`physics_call=callback`); ffi the same rollout through the XLA FFI handlers (the "
        "default), timed in the same alternation; ffi/jit: median of the ratios.",
        "",
        "| task | scene | batch | compile s | jit env-steps/s | x gym Push | loop env-steps/s "
        "| x gym Push | jit/loop | ffi env-steps/s | x gym Push | ffi/jit |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in res["native"]:
        ffi = (f"| {fmt_rate(row['ffi_rate'])} | {row['ffi_rate'] / ref:.2f}x "
               f"| {row['ffi_over_jit']:.2f} |" if "ffi_rate" in row else "| | | |")
        lines.append(
            f"| {row['task']} | {row['scene']} | {row['batch']} | {row['compile_s']:.1f} "
            f"| {fmt_rate(row['jit_rate'])} | {row['jit_rate'] / ref:.2f}x "
            f"| {fmt_rate(row['loop_rate'])} | {row['loop_rate'] / ref:.2f}x "
            f"| {row['jit_over_loop']:.2f} " + ffi
        )
    push = [r for r in res["native"] if r["task"] == REF_TASK and r["scene"] == "original"]
    if push:
        best = max(push, key=lambda r: r["jit_rate"])
        met = [str(r["batch"]) for r in push if r["jit_rate"] / ref >= TARGET]
        lines += [
            "",
            f"Target (`mujoco` backend, original scene, FetchPush >= {TARGET}x gymnasium's "
            f"FetchPush `env.step`): best {best['jit_rate'] / ref:.2f}x at batch {best['batch']}; "
            + (f"met at batch {', '.join(met)}." if met else "not met at any batch measured."),
        ]
        ratios = [r["jit_over_loop"] for r in res["native"]]
        lines.append(f"jit/loop over all rows: median {median(ratios):.2f}, range "
                     f"{min(ratios):.2f}-{max(ratios):.2f}.")
    if res["breakdown"]:
        bd = res["breakdown"]
        bs = list(bd)
        head = "| us per batched env step | " + " | ".join(f"B={b}" for b in bs) + " |"
        lines += [
            "",
            f"## Where the time goes ({REF_TASK}, original scene)",
            "",
            "Microseconds per batched env step (one `host_step` call). `host_step` in jit is "
            "timed inside the callback during the jitted rollouts above; its parts are timed "
            "with `time.perf_counter` through `host_step`'s own `clock` hook.",
            "",
            head,
            "|---|" + "---:|" * len(bs),
        ]

        def add(label: str, get: Callable[[dict], float]) -> None:
            lines.append(f"| {label} | " + " | ".join(f"{get(bd[b]):,.0f}" for b in bs) + " |")

        add("**jitted rollout**, per step", lambda d: d["step_us_jit"])
        add("- `host_step`, timed inside the callback", lambda d: d["host_step_us_jit"])
        add("- between two `host_step` calls (callback exit, XLA work, callback entry)",
            lambda d: d["gap_us_jit"])
        add("- rest (the episode's reset, dispatch), per step",
            lambda d: d["step_us_jit"] - d["host_step_us_jit"] - d["gap_us_jit"])
        add("**Python loop**, per step", lambda d: d["step_us_loop"])
        add("- `host_step`", lambda d: d["host_step_us_loop"])
        add("- between two `host_step` calls (numpy random action)", lambda d: d["gap_us_loop"])
        add("- rest (the episode's reset), per step",
            lambda d: d["step_us_loop"] - d["host_step_us_loop"] - d["gap_us_loop"])
        add("jitted rollout, `host_step` returning constants: per step",
            lambda d: d["null_step_us"])
        add("- between two calls", lambda d: d["null_gap_us"])
        add("jitted rollout, `host_step` a busy-wait as long as the real one: per step",
            lambda d: d["busy_step_us"])
        add("- between two calls", lambda d: d["busy_gap_us"])
        add("trivial `pure_callback` round trip in a jitted scan, same shapes",
            lambda d: d["callback_us"])
        labels = {
            "unpack": "`host_step` part: unpack bits, apply the action",
            "step": "part: load state + mjbatch `step(nstep=20)` (+ forward for block-gripper "
                    "tasks) + copy out",
            "readout": "part: `_readout` (site velocities, raw vector)",
            "pack": "part: pack the float64 state as bits, float32 cast",
        }
        for k, label in labels.items():
            add(label, lambda d, k=k: d["parts_us"][k])
        add("bare mjbatch (set mocap, `step(nstep=20)`), the backend's threads",
            lambda d: d["bare_mjbatch_us"])
        add("bare mjbatch, 1 thread", lambda d: d["bare_mjbatch_1thread_us"])
        add("jitted rollout, `auto_reset=False`, measured beside the next row",
            lambda d: d["plain_step_us"])
        add("jitted rollout, `auto_reset=True` (a `host_reset` callback every step)",
            lambda d: d["auto_reset_step_us"])
        lines.append("| `auto_reset=True` / `False`, median of paired repeats | " + " | ".join(
            f"{bd[b]['auto_over_plain']:.2f}x" for b in bs) + " |")
        lines.append("")
        lines.append("Threads of the backend per batch: " + ", ".join(
            f"B={b}: {bd[b]['threads']}" for b in bs) + ". Bare mjbatch 1 thread / backend's "
            "threads = the parallel speed-up the second core gave during this run: " + ", ".join(
            f"B={b}: {bd[b]['bare_mjbatch_1thread_us'] / bd[b]['bare_mjbatch_us']:.2f}x"
            for b in bs if bd[b]["threads"] > 1) + ".")
    if res["mjx"]:
        lines += [
            "",
            "## `mjx` backend on CPU (FetchPush, MJX-edited scene)",
            "",
            "One subprocess per row (XLA_FLAGS is read when JAX starts), persistent compilation "
            "cache shared by the rows: `cold` = the compile wrote cache entries, `warm` = it "
            "read them. Rollout = `vmap(env.reset)` + `steps` x `vmap(env.step)` in a jitted "
            "scan, reset included.",
            "",
            "| setting | XLA_FLAGS | batch | steps | devices | trace+lower s | XLA compile s "
            "| cache | env-steps/s | x gym Push |",
            "|---|---|---:|---:|---:|---:|---:|---|---:|---:|",
        ]
        for r in res["mjx"]:
            flags = f"`{r['flags']}`" if r["flags"] else "(none)"
            if "error" in r:
                lines.append(f"| {r['name']} | {flags} | {r['batch']} | {r['steps']} | "
                             f"{r['devices']} | | | | {r['error']} | |")
                continue
            lines.append(
                f"| {r['name']} | {flags} | {r['batch']} | {r['steps']} | {r['devices_used']} "
                f"| {r['lower_s']:.1f} | {r['compile_s']:.1f} | {r['cache']} "
                f"| {fmt_rate(r['rate'])} | {r['rate'] / ref:.3f}x |"
            )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main
def parse_ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def main(argv: Sequence[str] | None = None) -> None:
    p = harness.parser("bench_envs.py", __doc__.splitlines()[0],
                       quick="FetchPush only, batches 1 and 16, fewer repeats, one MJX "
                       "configuration")
    p.add_argument("--tasks", default=None, help="comma-separated tasks (default: all four)")
    p.add_argument("--batches", default=None,
                   help="batch sizes for every task (default: 1,16; see --push-batches)")
    p.add_argument("--push-batches", default=None,
                   help="batch sizes for FetchPush (default: --batches if given, else "
                        "1,2,16,64,256 on the original scene and 1,2,16,64 on the MJX one)")
    p.add_argument("--scenes", default=",".join(SCENES), help="original,mjx")
    p.add_argument("--repeats", type=int, default=None, help="repeats per figure (default 5)")
    p.add_argument("--gym-steps", type=int, default=None, help="env steps per gymnasium repeat")
    p.add_argument("--breakdown-batches", default=None, help="default 1,16")
    p.add_argument("--no-mjx", action="store_true", help="skip the MJX-on-CPU part")
    p.add_argument("--mjx-batches", default="1,16", help="MJX batch sizes (default 1,16)")
    p.add_argument("--mjx-timeout", type=float, default=600.0, help="seconds per MJX subprocess")
    p.add_argument("--cache-dir", default=None,
                   help="persistent JAX compilation cache for the MJX part (default: a fresh "
                        "temporary directory, so the first compile of each setting is cold)")
    p.add_argument("--mjx-worker", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.mjx_worker is not None:
        print(WORKER_MARK + json.dumps(mjx_worker(json.loads(args.mjx_worker))), flush=True)
        return

    from rdher_jax import startup

    startup.setup(startup.Startup())  # the mujoco backend's FFI handlers, built in the background
    t_start = time.perf_counter()
    quick = args.quick
    tasks = args.tasks.split(",") if args.tasks else ([REF_TASK] if quick else list(TASKS))
    for t in tasks:
        if t not in TASKS:
            p.error(f"unknown task {t!r}; valid: {', '.join(TASKS)}")
    scenes = args.scenes.split(",")
    batches = parse_ints(args.batches) if args.batches else [1, 16]
    if args.push_batches:
        push_batches = dict.fromkeys(SCENES, parse_ints(args.push_batches))
    elif args.batches or quick:
        push_batches = dict.fromkeys(SCENES, batches)
    else:  # batch 256 takes ~10 s a rollout: on the scene of the target only
        push_batches = {"original": [1, 2, 16, 64, 256], "mjx": [1, 2, 16, 64]}
    repeats = args.repeats or (2 if quick else 5)
    gym_steps = args.gym_steps or (200 if quick else 500)
    min_steps = 100 if quick else 400
    bd_default = [16] if quick else [1, 16]
    bd_batches = parse_ints(args.breakdown_batches) if args.breakdown_batches else bd_default

    cmd, h = harness.command("bench_envs.py", argv), harness.host()
    res: dict[str, Any] = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        # The host's figures the page reads (all of them under "host"), the main process's
        # XLA flags and the versions of the packages measured.
        "hardware": {
            "cpu": h["processor"] or "unknown",
            "logical_cpus": h["cpu_count"],
            "usable_cpus": h["affinity"],
            "platform": platform.platform(),
            "loadavg_start": h["loadavg"],
            "versions": {"python": h["python"],
                         **{k: h["versions"][k] for k in harness.PACKAGES}},
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
        },
    }
    harness.say(f"{harness.machine(h)}, load {h['loadavg'][0]:.1f}")

    # 1. gymnasium-robotics
    gym_envs = {t: gym_env(t) for t in dict.fromkeys([REF_TASK, *tasks])}
    probe = ParallelProbe()
    print(f"parallel speed-up of mjbatch now: {probe():.2f}x", flush=True)
    res["gym"], ref_rates = {}, []
    for task, env in gym_envs.items():
        gym_rate(env, EPISODE)  # warm-up
        rates = [gym_rate(env, gym_steps) for _ in range(repeats if task == REF_TASK else 3)]
        if task == REF_TASK:
            ref_rates += rates
        res["gym"][task] = {"rate": median(rates), "rates": rates}
        print(f"gymnasium {task}: {median(rates):.0f} env-steps/s", flush=True)

    # 2-3. the mujoco backend
    import jax

    from rdher_jax import make_env

    res["native"], res["breakdown"] = [], {}
    for task in tasks:
        for scene in scenes:
            env = make_env(task, backend="mujoco", scene=scene, auto_reset=False,
                           physics_call="callback")
            ffi_env = make_env(task, backend="mujoco", scene=scene, auto_reset=False,
                               physics_call="ffi")
            res["native_threads"] = env.backend.num_threads
            timed = harness.Stamps(env.backend.host_step)
            env.backend.host_step = timed
            rows = {}
            for batch in push_batches[scene] if task == REF_TASK else batches:
                row = bench_native_row(env, timed, batch, repeats, min_steps, ffi_env)
                rows[batch] = row
                res["native"].append({"task": task, "scene": scene, **row})
                print(f"{task} {scene} B={batch}: compile {row['compile_s']:.1f} s, jit "
                      f"{row['jit_rate']:.0f}, loop {row['loop_rate']:.0f} env-steps/s, "
                      f"jit/loop {row['jit_over_loop']:.2f}, ffi {row['ffi_rate']:.0f} "
                      f"({row['ffi_over_jit']:.2f}x jit)", flush=True)
            if task == REF_TASK and scene == "original":
                for b in bd_batches:
                    if b not in rows:
                        rows[b] = bench_native_row(env, timed, b, repeats, min_steps)
                res["breakdown"] = breakdown(env, rows, bd_batches, repeats, min_steps)
            jax.clear_caches()
        ref_rates.append(gym_rate(gym_envs[REF_TASK], gym_steps))
        probe()

    # 4. MJX on CPU
    res["mjx"] = []
    if not args.no_mjx:
        cache_dir = args.cache_dir or tempfile.mkdtemp(prefix="bench_envs_jax_cache_")
        try:
            cfgs = mjx_configs(parse_ints(args.mjx_batches), quick)
            res["mjx"] = run_mjx(cfgs, cache_dir, args.mjx_timeout)
        finally:
            if args.cache_dir is None:
                shutil.rmtree(cache_dir, ignore_errors=True)
        ref_rates.append(gym_rate(gym_envs[REF_TASK], gym_steps))
        probe()

    res["gym_ref_rates"] = ref_rates
    res["parallel_speedups"] = probe.speedups
    res["parallel_threads"] = probe.threads
    res["gym_ref_rate"] = median(ref_rates)
    res["loadavg_end"] = list(os.getloadavg())
    res["wall_s"] = time.perf_counter() - t_start
    print()
    harness.write_results(args.out, "Env-step throughput: gymnasium-robotics, the `mujoco` "
                          "backend, MJX on CPU", [report(res, cmd, h)], res, command=cmd,
                          host=h)


if __name__ == "__main__":
    main()
