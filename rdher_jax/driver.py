"""The run driver: N >= 1 runs as one compiled program, and everything around its epochs.

``python -m rdher_jax.train`` (one run) and ``python -m rdher_jax.sweep`` (many) are thin
command lines over :func:`drive`, which takes a :class:`Plan` (the runs' resolved configs and
where they write) and does the rest: build the program, init or resume, the epoch loop,
metrics rows, plots, best-policy and latest checkpoints, NaN handling and, for a sweep, the
summary.

The program is ``program.epoch`` (``rdher_jax.program``) over a leading run axis:
``jax.jit(jax.vmap(epoch))`` for a sweep, and for a single run the unvmapped epoch with the run
axis added and dropped around it (so a run gives exactly the numbers it gave before sweeps
existed). With several JAX devices a
sweep's run axis is split over a 1-D mesh ``"runs"`` (``NamedSharding(mesh, P("runs"))``) and
the vmapped epoch runs under ``shard_map``, so each device steps only its own runs: no
collective is needed, and the native backend's ``pure_callback`` is made once per device per
env step for that device's runs. (Plain ``jit`` with sharded inputs also works, but XLA's
partitioner then pins the callback to device 0 and gathers every run's env batch there and back
at each step.) When the number of runs does not divide the number of devices, the run axis is
padded with copies of the first run, computed and discarded.

Two layouts of outputs (:attr:`Plan.sweep`):

- a run (``train``): ``run_dir/`` holds config.yaml, run_info.json, metrics.csv, success.png,
  ``checkpoints/latest`` (the run's TrainState) and ``checkpoints/best`` (its best policy);
- a sweep: ``sweep_dir/<run>/`` holds what a run holds except the latest state, which is the
  sweep's: ``sweep_dir/checkpoints/latest`` (every run's TrainState, stacked), beside
  ``sweep.yaml`` (what varies), ``base_config.yaml``, ``run_info.json`` and the summary
  (``rdher_jax.summary``).

A run whose losses become NaN or inf stops being logged (its files keep its last good epoch);
the others go on. The program stops only when every run has diverged.
"""

from __future__ import annotations

import atexit
import dataclasses
import math
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import summary
from .checkpoint import Checkpointer
from .config import (
    RESUMABLE_KEYS,
    SUCCESS_TOLERANCE,
    TRACED_KEYS,
    Config,
    ConfigError,
    preset_sets_overlap,
    to_yaml,
)
from .runlog import (
    MetricsCSV,
    TBWriter,
    check_fresh_dir,
    check_resume_dir,
    make_dir,
    metric_fields,
    plot_success,
    write_json_atomic,
    write_text_atomic,
)

SPEC_FILE = "sweep.yaml"
BASE_CONFIG_FILE = "base_config.yaml"


class TrainingDiverged(RuntimeError):
    """Every run's losses became NaN or inf; the last good checkpoint is kept."""


# ------------------------------------------------------------------ building

def resolve_backend(cfg: Config) -> tuple[str, str]:
    """The physics backend and scene a config asks for, with ``auto`` decided here."""
    from .envs import default_backend

    backend = default_backend() if cfg.backend == "auto" else cfg.backend
    scene = cfg.scene if cfg.scene != "auto" else ("original" if backend == "mujoco" else "mjx")
    if backend == "mjx" and scene != "mjx":
        raise ConfigError("backend=mjx needs scene=mjx (mjx.put_model rejects the original)")
    return backend, scene


def build(cfg: Config):
    """Env and training program (``program.make_program``) of a resolved config."""
    from .envs import make_env
    from .program import make_program

    backend, scene = resolve_backend(cfg)
    extra = {}
    if backend == "mujoco":
        # With overlap the physics has a host device, and so a core, of its own: a second
        # physics thread would take the learner's.
        extra["num_threads"] = cfg.physics_threads or (1 if cfg.overlap else None)
    env = make_env(cfg.env, backend=backend, scene=scene, auto_reset=False,
                   goal_speed=cfg.goal_speed, episode_length=cfg.episode_length,
                   physics_call=cfg.physics_call, **extra)
    return env, make_program(cfg, env)


def _cpu_model() -> str:
    """The CPU's model name on Linux (platform.processor() is often empty there)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def run_info(cfg: Config, argv: Sequence[str], prog: str) -> dict:
    """Command line, backend, hardware and package versions, for ``run_info.json``."""
    import importlib.metadata as md

    versions = {}
    for pkg in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "mjbatch", "gymnasium-robotics", "flax",
                "optax", "brax", "orbax-checkpoint"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            versions[pkg] = None
    backend, scene = resolve_backend(cfg)
    return {
        "command": " ".join([prog, *argv]),
        "backend": backend,
        "scene": scene,
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "processor": platform.processor() or _cpu_model(),
        "python": platform.python_version(),
        "versions": versions,
    }


def stack(trees: Sequence[Any]) -> Any:
    """Stack pytrees of equal structure along a new leading (run) axis."""
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def tree_bytes(tree: Any) -> int:
    """Bytes held by the array leaves of ``tree`` (their global size when sharded)."""
    return int(sum(np.dtype(x.dtype).itemsize * math.prod(x.shape)
                   for x in jax.tree.leaves(tree)))


def request_host_devices(n: int = 2) -> None:
    """Ask JAX for ``n`` CPU devices (``overlap=true`` collects on the second). Only possible
    before JAX starts its backends; :func:`overlap_devices` says later whether it worked."""
    try:
        jax.config.update("jax_num_cpu_devices", max(n, jax.config.jax_num_cpu_devices))
    except (RuntimeError, ValueError, AttributeError):
        pass  # the backend is up already: overlap_devices() gives the error


def _preset_overlap_hint(cfg: Config) -> str:
    if preset_sets_overlap(cfg.preset):
        return f" (preset={cfg.preset} sets overlap=true for a CPU: add overlap=false)"
    return ""


def overlap_devices(devices: Sequence[Any] | None) -> tuple[list[Any], Any]:
    """(the learner's device, the collecting device) of an ``overlap=true`` program."""
    devices = list(devices or jax.devices())
    if any(d.platform != "cpu" for d in devices):
        raise ConfigError("overlap=true runs on CPU devices only (backend=mujoco)")
    if len(devices) < 2:
        raise ConfigError(
            "overlap=true collects on a second host device, and JAX has started with "
            f"{len(devices)} CPU device(s); start it with JAX_NUM_CPU_DEVICES=2 (the CLIs do "
            "this themselves)")
    return [devices[0]], devices[1]


class OverlapEpoch:
    """``program.epoch`` in pieces over two host devices (``overlap=true``).

    Per cycle: the learner (``program.learn``: store the pending episodes, then update; no host
    callback, so JAX dispatches it and returns at once) is started on the learner's device, and
    then, in this thread, the next episodes are collected with the same actor on the second
    device (``program.collect``: the native physics through ``pure_callback``, which runs in
    the calling thread). The two run at the same time; XLA:CPU runs the independent halves of
    one program one after the other (experiments/results/bench_overlap.md), and so do two
    programs on one device. ``vmapped``: the state has a run axis of any length (a sweep), or
    of length 1 (one run, :class:`RunBatch` with ``vmapped=False``).
    """

    def __init__(self, program: Any, vmapped: bool, device: Any, collect_device: Any,
                 n_cycles: int) -> None:
        self.device, self.collect_device, self.n_cycles = device, collect_device, n_cycles
        self.vmapped = vmapped
        # One run: the run axis is taken off for the whole epoch (a reshape, free with
        # donation), not per cycle, where lifting each call would copy the replay buffer.
        lift = jax.vmap if vmapped else (lambda f: f)
        self.learn = jax.jit(lift(program.learn), donate_argnums=0)
        self.collect = jax.jit(lift(program.collect))
        self.init_state = jax.jit((jax.vmap if vmapped else _one_run)(program.init_state))
        self.finish = jax.jit(lift(program.finish), donate_argnums=0)
        self.set_pending = jax.jit(lambda ts, p: ts.replace(pending=p), donate_argnums=0)
        self.drop_axis = jax.jit(lambda t: jax.tree.map(lambda x: x.reshape(x.shape[1:]), t),
                                 donate_argnums=0)
        self.add_axis = jax.jit(lambda t: jax.tree.map(lambda x: x.reshape((1, *x.shape)), t),
                                donate_argnums=0)

    def init(self, keys: Any, hp: Any) -> Any:
        """``program.init`` (``init_overlap``) as two programs: the state, whose program has no
        host callback and so is cached for later processes (rdher_jax.compile_cache), then
        the first cycle's episodes by the ``collect`` program every cycle uses."""
        ts = self.init_state(keys, hp)
        if not self.vmapped:
            ts, hp = self.drop_axis(ts), jax.tree.map(lambda x: x[0], hp)
        pending = self.collect(self._view(ts), jax.device_put(hp, self.collect_device),
                               self._first(ts, True))
        ts = self.set_pending(ts, jax.device_put(pending, self.device))
        return ts if self.vmapped else self.add_axis(ts)

    def _view(self, ts: Any) -> Any:
        """What collect reads (actor, normaliser, key), on the collecting device."""
        return jax.device_put(ts.replace(buffer=None, relabel=None, pending=None),
                              self.collect_device)

    def _first(self, ts: Any, value: bool) -> jax.Array:
        """collect's ``first`` flag, one per run when vmapped (always an array: one program)."""
        shape = ts.epoch.shape if self.vmapped else ()
        return jax.device_put(np.full(shape, value), self.collect_device)

    def __call__(self, ts: Any, hp: Any) -> tuple[Any, Any]:
        if not self.vmapped:
            ts, hp = self.drop_axis(ts), jax.tree.map(lambda x: x[0], hp)
        hp_c = jax.device_put(hp, self.collect_device)
        later = self._first(ts, False)
        ms = []
        for _ in range(self.n_cycles):
            view = self._view(ts)  # copied before learn takes ts over
            ts, m = self.learn(ts, hp)
            pending = self.collect(view, hp_c, later)
            ts = self.set_pending(ts, jax.device_put(pending, self.device))
            ms.append(m)
        axis = 1 if self.vmapped else 0  # (runs, cycles, ...) or (cycles, ...)
        m = jax.tree.map(lambda *xs: jnp.stack(xs, axis=axis), *ms)
        ts, metrics = self.finish(ts, m, hp)
        if not self.vmapped:
            ts, metrics = self.add_axis((ts, metrics))
        return ts, metrics


class CompiledAhead:
    """A jitted function that can be compiled on a background thread, from its inputs' shapes,
    while the caller does other work (``start``); calls then run that executable. On a CPU,
    compiling is single-threaded: the trainer's epoch program (most of a short run's compile
    time) compiles on the second core while the first compiles and runs ``init``. Calls whose
    inputs the executable does not take (another placement, a restored state of another kind)
    go to the jitted function, which compiles as it would have."""

    def __init__(self, jitted: Any) -> None:
        self.jitted = jitted
        self._thread: threading.Thread | None = None
        self._compiled: Any = None

    def start(self, *abstract_args: Any) -> None:
        def run() -> None:
            try:
                self._compiled = self.jitted.lower(*abstract_args).compile()
            except Exception:  # noqa: BLE001 - the jitted function compiles (and reports)
                self._compiled = None

        self._thread = threading.Thread(target=run, name="rdher-compile-ahead", daemon=True)
        self._thread.start()
        # A process that ends while XLA compiles on another thread aborts in its teardown
        # (an error exit right after start): it waits for the compile instead.
        atexit.register(self._thread.join)

    def __call__(self, *args: Any) -> Any:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._compiled is not None:
            try:
                return self._compiled(*args)
            except (TypeError, ValueError):  # checked before anything runs or is donated
                self._compiled = None
        return self.jitted(*args)


class RunBatch:
    """A program's ``init`` and ``epoch`` over a leading run axis, each one compiled program.

    ``vmapped=False`` (one run only): the plain functions, the run axis taken off and put back
    inside the jitted program. One device: ``jax.jit(jax.vmap(f))``. Several: the vmapped
    function under ``shard_map`` over the 1-D mesh ``"runs"``; ``n_padded`` (the run count
    rounded up to a multiple of the device count) is the length of the run axis it sees.
    """

    def __init__(self, program: Any, n_runs: int, devices: Sequence[Any] | None = None,
                 vmapped: bool = True, overlap: Any = None) -> None:
        """``overlap``: (n_cycles, the collecting device) for an ``overlap=true`` program on
        one device (:class:`OverlapEpoch`)."""
        self.devices = list(devices or jax.devices())[: n_runs if not vmapped else None]
        if not vmapped and n_runs != 1:
            raise ValueError("an unvmapped program runs exactly one run")
        d = len(self.devices)
        self.n_runs = n_runs
        self.n_padded = -(-n_runs // d) * d
        self.mesh = None
        # This process's block of the (padded) run axis: all of it, unless the devices span
        # several processes (rdher_jax.distributed), each of which owns a contiguous block.
        self.lo, self.hi = 0, self.n_padded
        if d == 1:
            # Committed to the device, as restored checkpoints are: jit's cache tells committed
            # from uncommitted inputs, and a resume in the same process should not recompile.
            self.sharding = jax.sharding.SingleDeviceSharding(self.devices[0])
            lift = jax.vmap if vmapped else _one_run
            if overlap is None:
                self.init = jax.jit(lift(program.init))
                self.epoch = CompiledAhead(jax.jit(lift(program.epoch), donate_argnums=0))
            else:
                self.epoch = OverlapEpoch(program, vmapped, self.devices[0], overlap[1],
                                          overlap[0])
                self.init = self.epoch.init
            return
        if overlap is not None:
            raise ValueError("an overlap=true program runs on one learner device")
        from jax.sharding import Mesh, NamedSharding
        from jax.sharding import PartitionSpec as P

        self.mesh = Mesh(np.array(self.devices), ("runs",))
        self.sharding = NamedSharding(self.mesh, P("runs"))
        blocks = sorted((sl[0].start or 0, sl[0].stop if sl[0].stop is not None
                         else self.n_padded)
                        for sl in self.sharding.addressable_devices_indices_map(
                            (self.n_padded,)).values())
        self.lo, self.hi = blocks[0][0], blocks[-1][1]
        if any(a[1] != b[0] for a, b in zip(blocks, blocks[1:], strict=False)):
            raise ValueError(f"this process's devices hold runs {blocks}, not one block")

        def split(f):
            # check_vma=False: pure_callback results (the native physics) carry no
            # varying-manual-axes type, so scans carrying env states through them fail the check.
            # Every output is split over "runs" (nothing is claimed replicated), so the check
            # has nothing to protect here.
            return jax.shard_map(jax.vmap(f), mesh=self.mesh, in_specs=P("runs"),
                                 out_specs=P("runs"), check_vma=False)

        self.init = jax.jit(split(program.init))
        self.epoch = jax.jit(split(program.epoch), donate_argnums=0)

    def compile_ahead(self, keys: Any, hps: Any) -> None:
        """Start compiling ``epoch`` for the state ``init(keys, hps)`` will return, on a
        background thread (one device, sequential cycles; elsewhere nothing)."""
        if not isinstance(self.epoch, CompiledAhead) or self.epoch._compiled is not None:
            return
        shapes = jax.eval_shape(self.init, keys, hps)
        abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(
            a.shape, a.dtype, sharding=self.sharding, weak_type=a.weak_type), shapes)
        self.epoch.start(abstract, hps)

    def pad(self, tree: Any) -> Any:
        """Extend the run axis to ``n_padded`` with copies of the first run."""
        k = self.n_padded - self.n_runs
        if k == 0:
            return tree
        return jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], k, axis=0)]), tree)

    def unpad(self, tree: Any) -> Any:
        """The real runs of a padded tree, as host arrays.

        On the host on purpose: slicing a run-sharded array on device compiles a program with
        a cross-device collective, and XLA:CPU runs host devices on one thread pool, so with
        more host devices than pool threads two devices can block in the collective's
        rendezvous while the third never gets a thread (seen as a 40 s rendezvous abort).
        Nothing the driver runs between epochs may need a collective.
        """
        return jax.tree.map(lambda x: np.asarray(x)[: self.n_runs], jax.device_get(tree))

    @property
    def multi_process(self) -> bool:
        """Whether the run axis spans the devices of several processes."""
        return self.mesh is not None and not self.sharding.is_fully_addressable

    def host(self, tree: Any) -> Any:
        """Every run of a run-sharded tree (padding included) as host arrays.

        One process: a plain fetch (see :meth:`unpad`: no collective). Several: each process's
        block gathered to every process (``process_allgather``), a collective that every
        process must make at the same point of the loop.
        """
        if not self.multi_process:
            return jax.tree.map(np.asarray, jax.device_get(tree))
        from jax.experimental import multihost_utils

        return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))

    def put(self, tree: Any) -> Any:
        """Pad and place ``tree`` (every run's values, the same on every process) as the
        program's inputs are placed."""
        if not self.multi_process:
            return jax.device_put(self.pad(tree), self.sharding)
        full = jax.tree.map(np.asarray, self.pad(tree))
        return jax.tree.map(lambda x: jax.make_array_from_callback(
            x.shape, self.sharding, lambda idx: x[idx]), full)

    def abstract(self, tree: Any) -> Any:
        """The shapes, dtypes and shardings of a run-sharded tree (a restore template)."""
        return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype,
                                                           sharding=x.sharding), tree)

    def describe(self) -> str:
        if self.mesh is None:
            return f"one device ({self.devices[0]})"
        pad = (f", padded from {self.n_runs} with copies of the first run"
               if self.n_padded != self.n_runs else "")
        procs = len({d.process_index for d in self.devices})
        over = f" in {procs} processes" if procs > 1 else ""
        return (f"shard_map over mesh ('runs',) of {len(self.devices)} devices{over}, "
                f"{self.n_padded // len(self.devices)} runs per device{pad}")


def _one_run(f: Callable) -> Callable:
    """``f`` of one run as a function of a run axis of length 1 (the axis is dropped on the way
    in and restored on the way out, inside the one jitted program)."""

    def g(*args):
        out = f(*jax.tree.map(lambda x: x[0], args))
        return jax.tree.map(lambda x: x[None], out)

    return g


# Fields that change neither the compiled program nor what it computes per epoch.
_LOOP_ONLY = tuple(k for k in RESUMABLE_KEYS if k != "backend" and k != "n_test_rollouts")
_LAST_PROGRAM: dict[str, Any] = {}


def batch_for(runs: Sequence[Config], devices: Sequence[Any] | None = None,
                vmapped: bool = True):
    """Env, program and :class:`RunBatch` of runs that differ only in traced keys and seeds.

    Shapes and the algorithm come from the first run's config; everything that differs between
    runs is in each run's hyperparameters and key. The last program is kept for the life of the
    process, so a sweep resumed in the same process (a notebook, a test) reuses its compilation.
    """
    overlap = None
    if runs[0].overlap:
        try:
            devices, collect_device = overlap_devices(devices)
        except ConfigError as e:
            raise ConfigError(f"{e}{_preset_overlap_hint(runs[0])}") from None
        overlap = (runs[0].n_cycles, collect_device)
    devices = list(devices or jax.devices())
    default = Config()
    shared = dataclasses.replace(
        runs[0], seed=0, **{k: getattr(default, k) for k in (*_LOOP_ONLY, *TRACED_KEYS)})
    for c in runs[1:]:
        other = dataclasses.replace(
            c, seed=0, **{k: getattr(default, k) for k in (*_LOOP_ONLY, *TRACED_KEYS)})
        if other != shared:
            diff = [f.name for f in dataclasses.fields(Config)
                    if getattr(other, f.name) != getattr(shared, f.name)]
            raise ConfigError(f"the runs of one program may differ only in traced keys and "
                              f"seeds, not in {', '.join(diff)}")
    key = (to_yaml(shared), len(runs), tuple(str(d) for d in devices), vmapped)
    if _LAST_PROGRAM.get("key") != key:
        _LAST_PROGRAM.clear()  # one at a time: a program holds its env and compiled code
        env, program = build(runs[0])
        if overlap is not None and env.backend.name != "mujoco":
            raise ConfigError(f"overlap=true needs backend=mujoco (the native physics), not "
                              f"{env.backend.name}{_preset_overlap_hint(runs[0])}")
        _LAST_PROGRAM.update(key=key, value=(env, program, RunBatch(
            program, len(runs), devices, vmapped, overlap)))
    return _LAST_PROGRAM["value"]


# ------------------------------------------------------------------ metrics rows

def epoch_metric_names() -> tuple[str, ...]:
    """The fields of the program's ``EpochMetrics``, in declaration order."""
    from .program import EpochMetrics

    return tuple(f.name for f in dataclasses.fields(EpochMetrics))


def csv_fields() -> tuple[str, ...]:
    """The columns of metrics.csv: the loop's epoch and wall_time plus every EpochMetrics field."""
    return metric_fields(epoch_metric_names())


def loss_fields(fields: Iterable[str]) -> tuple[str, ...]:
    """The columns a NaN or inf stops a run on: the losses and the critic's mean Q. Other
    diagnostics may be NaN by design (e.g. a mean over no samples)."""
    return tuple(f for f in fields if f.endswith("_loss") or f == "q_mean")


def epoch_row(epoch: int, metrics: Any, wall_time: float) -> dict[str, int | float]:
    """The metrics.csv row of one run after ``epoch``: every field of ``metrics`` (an
    ``EpochMetrics`` of host scalars) plus epoch and wall time, in :func:`csv_fields` order."""
    values = {f.name: np.asarray(getattr(metrics, f.name)) for f in dataclasses.fields(metrics)}
    row: dict[str, int | float] = {"epoch": epoch, "wall_time": round(wall_time, 3)}
    for k, v in values.items():
        if v.shape != ():
            raise ValueError(f"EpochMetrics.{k} has shape {v.shape}; one run's are scalars")
        row[k] = int(v) if v.dtype.kind in "iub" else float(v)
    return {k: row[k] for k in metric_fields(values)}


def nonfinite_losses(row: Mapping[str, Any]) -> list[str]:
    """The loss columns of ``row`` that are NaN or inf."""
    return [k for k in loss_fields(row) if not math.isfinite(row[k])]


def last_good_checkpoint(ckpt: Checkpointer) -> str:
    """The sentence a diverged run ends with: where its last good checkpoint is."""
    last = ckpt.latest_epoch()
    if last is None:
        return "No checkpoint was written yet."
    return f"The last good checkpoint (epoch {last}) is kept in {ckpt.directory}"


def is_checkpoint_epoch(cfg: Config, epoch: int) -> bool:
    """Whether the latest state is saved after ``epoch`` (1-based): every ``checkpoint_every``
    epochs and after the last one."""
    return epoch % cfg.checkpoint_every == 0 or epoch == cfg.epochs


def reached_stop(cfg: Config, recent: Sequence[Sequence[float]], live: Iterable[int]) -> bool:
    """Whether ``stop_success`` is met: every live run's last ``stop_window`` test successes
    (``recent[i]``, oldest first) are all there and average at least ``stop_success`` (to
    within ``config.SUCCESS_TOLERANCE``)."""
    if cfg.stop_success is None:
        return False
    live = list(live)
    return bool(live) and all(
        len(recent[i]) >= cfg.stop_window
        and float(np.mean(recent[i][-cfg.stop_window:])) >= cfg.stop_success - SUCCESS_TOLERANCE
        for i in live)


def plot_title(cfg: Config) -> str:
    lam = "" if (cfg.lambda_r, cfg.lambda_h) == (1.0, 1.0) else (
        f" lambda_r={cfg.lambda_r:g} lambda_h={cfg.lambda_h:g}")
    return f"{cfg.env} {cfg.algo} seed {cfg.seed}{lam}"


# success.png is redrawn at most this often while a run trains, and always when it ends: a
# plot costs about 0.2 s (and matplotlib's import 0.4 s the first time), a fifth of a FetchReach
# epoch, and a sweep draws one per run.
PLOT_EVERY_S = 30.0


class RunOutputs:
    """The files of one run in ``run_dir`` and what every epoch adds to them.

    config.yaml and run_info.json (:meth:`start`), metrics.csv (a row per epoch), success.png
    (redrawn every ``PLOT_EVERY_S`` seconds of training and by :meth:`flush`), the best-policy
    checkpoint (ties go to the later epoch, as in baselines) and TensorBoard scalars.
    ``latest=True`` (a run's own layout): ``ckpt`` also keeps the run's latest state.
    """

    def __init__(self, cfg: Config, run_dir: str | Path, latest: bool = True) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.ckpt = Checkpointer(self.run_dir, latest=latest)
        try:
            self.csv = MetricsCSV(self.run_dir / "metrics.csv", csv_fields(), extend=True)
        except ValueError as e:
            raise ConfigError(f"cannot continue {self.run_dir}: {e}") from None
        self.tb = TBWriter(self.run_dir) if cfg.tensorboard else None
        self.best = -1.0
        self._plot_due = time.monotonic() + PLOT_EVERY_S
        self._unplotted = False

    def start(self, info: Mapping[str, Any]) -> None:
        """Begin the run from epoch 0: write config.yaml and run_info.json, and drop any rows
        and best policy a run killed before its first checkpoint left."""
        self.rewind(0, -1.0)
        write_text_atomic(self.run_dir / "config.yaml", to_yaml(self.cfg))
        write_json_atomic(self.run_dir / "run_info.json", info)

    def rewind(self, epoch: int, best: float) -> None:
        """Continue after ``epoch`` (a resume): later rows and best policies are abandoned."""
        self.ckpt.discard_after(epoch)
        self.csv.truncate_after(epoch)
        self.best = best

    def record(self, row: Mapping[str, Any], policy: Callable[[], Any]) -> bool:
        """Append ``row``; save ``policy()`` when its test success is the best so far.
        Returns whether it was a new best. The plot is :meth:`plot_if_due`'s and
        :meth:`flush`'s."""
        self.csv.append(row)
        if self.tb is not None:
            self.tb.scalars(row, step=int(row["env_steps"]))
        new_best = row["test_success"] >= self.best  # baselines saves on >= (ties keep the latest)
        if new_best:
            self.best = float(row["test_success"])
            self.ckpt.save_best(int(row["epoch"]), policy(),
                                {"test_success": self.best, "epoch": int(row["epoch"])})
        self._unplotted = True
        return new_best

    def plot_if_due(self) -> None:
        """Redraw success.png if ``PLOT_EVERY_S`` passed since it was last drawn."""
        if time.monotonic() >= self._plot_due:
            self.flush()

    def flush(self) -> None:
        """Redraw success.png if rows came since it was last drawn."""
        if self._unplotted:
            plot_success(self.run_dir / "metrics.csv", self.run_dir / "success.png",
                         plot_title(self.cfg))
            self._unplotted = False
        self._plot_due = time.monotonic() + PLOT_EVERY_S

    def close(self) -> None:
        self.flush()
        self.ckpt.close()
        if self.tb is not None:
            self.tb.close()


def restore_or_refuse(ckpt: Checkpointer, template: Any, directory: Path) -> tuple[int, Any, dict]:
    """``ckpt.restore_latest(template)``; any failure to read it is a one-line ConfigError (a
    resume of a directory whose checkpoint is damaged or from another configuration)."""
    try:
        return ckpt.restore_latest(template)
    except Exception as e:  # orbax, tensorstore and our own template checks raise many kinds
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"cannot resume {directory}: its latest checkpoint is unusable: "
                          f"{msg[:300]}") from None


# ------------------------------------------------------------------ the plan

@dataclass(frozen=True)
class Plan:
    """What :func:`drive` runs and where it writes.

    Attributes:
      runs: one resolved Config per run, each with its own ``run_dir`` and seed; they may
        differ only in traced keys (``config.TRACED_KEYS``) and seeds.
      out_dir: the run directory (one run) or the sweep directory.
      sweep: the sweep layout (a spec, a summary and one stacked latest checkpoint) rather than
        a run's own; a sweep is vmapped even over one run.
      resume: continue ``out_dir`` from its latest checkpoint.
      varies: the sweep's varying keys as written to ``sweep.yaml``: ``lambdas`` (pairs),
        ``seeds`` and ``grid`` (``{field: values}``).
      names: each run's directory name under a sweep directory.
      base: the config the runs are made from (a sweep's ``base_config.yaml``, its run_dir the
        sweep directory); a single run's own.
    """

    runs: tuple[Config, ...]
    out_dir: Path
    base: Config
    sweep: bool = False
    resume: bool = False
    varies: Mapping[str, Any] = field(default_factory=dict)
    names: tuple[str, ...] = ()

    @classmethod
    def single(cls, cfg: Config) -> Plan:
        """One run in its own directory (``cfg`` resolved; ``resume`` set to continue it)."""
        out = Path(cfg.resume if cfg.resume is not None else cfg.run_dir)
        return cls((cfg,), out, cfg, sweep=False, resume=cfg.resume is not None, names=("",))


def check_out_dir(plan: Plan) -> None:
    """The output directory is usable for the plan (before anything is built or written)."""
    marker = SPEC_FILE if plan.sweep else "config.yaml"
    what = "sweep_dir" if plan.sweep else "run_dir"
    if plan.resume:
        check_resume_dir(plan.out_dir, marker=marker)
    else:
        check_fresh_dir(plan.out_dir, what)


def latest_slot(processes: int) -> str:
    """The name of a sweep's latest-state checkpoint slot: ``latest`` with one process,
    ``latest-<N>-processes`` when N processes save it together."""
    return "latest" if processes == 1 else f"latest-{processes}-processes"


def check_process_count(out_dir: Path, processes: int) -> None:
    """A sweep checkpointed by N processes resumes only with N: a one-line ConfigError naming
    the number it needs otherwise."""
    ck = Path(out_dir) / "checkpoints"
    if not ck.is_dir():
        return
    found = set()
    for p in ck.iterdir():
        if p.name == "latest" and any(q.name.isdigit() for q in p.iterdir()):
            found.add(1)
        elif p.name.startswith("latest-") and p.name.endswith("-processes"):
            try:
                found.add(int(p.name.split("-")[1]))
            except ValueError:
                continue
    if found and processes not in found:
        need = max(found)
        how = "in one process" if need == 1 else f"with num_processes={need}"
        raise ConfigError(f"{out_dir} was checkpointed by {need} process"
                          f"{'es' if need > 1 else ''}; resume it {how}, not with {processes}")


def _owner(batch: RunBatch, i: int) -> int:
    """The process whose devices step run ``i``."""
    per = batch.n_padded // len(batch.devices)
    return int(batch.devices[i // per].process_index)


# ------------------------------------------------------------------ the loop

def _row_of(metrics: Any, i: int) -> Any:
    return jax.tree.map(lambda x: x[i], metrics)


def drive(plan: Plan, argv: Sequence[str] = (), prog: str = "", log=print,
          devices: Sequence[Any] | None = None) -> dict:
    """Run (or continue) every run of ``plan`` as one program.

    Returns ``{"out_dir", "names", "rows" (each run's last metrics row, or {}), "best" (each
    run's best test success), "diverged" ({name: epoch}), "program", "summary" (sweep: the
    summary's runs and settings)}``.
    """
    from . import compile_cache, distributed
    from .program import hparams_from_config

    argv = list(argv)
    runs, cfg, n = plan.runs, plan.runs[0], len(plan.runs)
    names = list(plan.names)
    main = distributed.is_main()
    procs = distributed.count()
    if procs > 1 and not plan.sweep:
        raise ConfigError("a run of its own is one process; start a multi-process sweep with "
                          "python -m rdher_jax.sweep")
    if procs > 1 and cfg.overlap:
        raise ConfigError("overlap=true runs in one process (two host devices of one machine)")
    if main:
        check_out_dir(plan)
    if plan.sweep and plan.resume:
        check_process_count(plan.out_dir, procs)
    compile_cache.configure(cfg.compile_cache)
    env, _, batch = batch_for(runs, devices, vmapped=plan.sweep)
    hps = batch.put(stack([hparams_from_config(c) for c in runs]))
    keys = batch.put(stack([jax.random.PRNGKey(c.seed) for c in runs]))
    batch.compile_ahead(keys, hps)
    ts = batch.init(keys, hps)
    # The runs this process steps: all of them with one process. With several, each steps
    # its own block of the run axis, and process 0 writes every run's files (metrics, plots,
    # best policies: orbax writes host data from process 0 only), from the metrics and
    # policies the processes gather to each other between epochs.
    mine = [i for i in range(n) if batch.lo <= i < batch.hi]

    if not plan.resume and main:
        make_dir(plan.out_dir, "sweep_dir" if plan.sweep else "run_dir")
    distributed.barrier("rdher_jax.drive.out_dir")
    outs = ({i: RunOutputs(c, Path(c.run_dir), latest=not plan.sweep)
             for i, c in enumerate(runs)} if main else {})
    # The sweep's latest state: with several processes a global array that they save
    # together (each its own runs' shards) under a slot named by their number.
    ckpt = (Checkpointer(plan.out_dir, best=False, latest_name=latest_slot(procs),
                         collective=procs > 1)
            if plan.sweep else outs[0].ckpt)
    best = [-1.0] * n  # every run's best test success so far, on every process
    info = run_info(cfg, argv, prog)
    if plan.sweep:
        per_run = tree_bytes(ts) // batch.n_padded
        info.update(runs=names, n_runs=n, n_padded=batch.n_padded,
                    program=batch.describe(), state_bytes_per_run=per_run,
                    state_bytes=per_run * batch.n_padded)
    if procs > 1:
        info.update(processes=procs, hosts=distributed.hosts(),
                    process_of_run={names[i]: _owner(batch, i) for i in range(n)})

    def saved(ts):  # the latest checkpoint: a sweep's stacked state, a run's own
        if batch.multi_process:  # the global array, padding included
            return ts
        host = batch.unpad(ts)
        return host if plan.sweep else jax.tree.map(lambda x: x[0], host)

    start, wall0, diverged = 0, 0.0, {}
    recent: list[list[float]] = [[] for _ in runs]  # each run's last test successes (stop_*)
    if plan.resume and ckpt.latest_epoch() is not None:
        template = batch.abstract(ts) if batch.multi_process else saved(ts)
        start, state, meta = restore_or_refuse(ckpt, template, plan.out_dir)
        if plan.sweep and meta.get("runs") != names:
            raise ConfigError(f"cannot resume {plan.out_dir}: its checkpoint holds runs "
                              f"{meta.get('runs')}, not {names}")
        if batch.multi_process:
            ts = state
        else:
            ts = batch.put(state if plan.sweep else stack([state]))
        del state
        try:
            wall0 = float(meta["wall_time"])
            bests = meta["best_success"]
            best = [float(b) for b in (bests if plan.sweep else [bests])]
            diverged = {k: int(v) for k, v in meta.get("diverged", {}).items()
                        if int(v) <= start}
            saved_recent = meta.get("recent_success")  # absent before stop_success existed
            if saved_recent is not None:
                recent = [[float(x) for x in r] for r in
                          (saved_recent if plan.sweep else [saved_recent])]
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
            raise ConfigError(f"cannot resume {plan.out_dir}: its checkpoint's metadata is "
                              f"damaged ({type(e).__name__}: {e})") from None
        for i, o in outs.items():
            o.rewind(start, best[i])
        log(f"resuming {plan.out_dir} after epoch {start}")
    else:
        if plan.resume and main:  # killed before its first checkpoint: start over
            log(f"{plan.out_dir} has no checkpoint yet; starting it over")
        if plan.sweep:
            if main:
                # The spec file goes last of the two: it is what marks a directory as a sweep's.
                write_text_atomic(plan.out_dir / BASE_CONFIG_FILE, to_yaml(plan.base))
                write_text_atomic(plan.out_dir / SPEC_FILE,
                                  summary.spec_yaml(plan.varies, names))
                write_json_atomic(plan.out_dir / "run_info.json", info)
            for i, o in outs.items():
                o.start({**info, "sweep_dir": str(plan.out_dir), "run": names[i]})
        else:
            outs[0].start(info)
    distributed.barrier("rdher_jax.drive.started")
    if plan.sweep and main:
        summary.write(plan, diverged)

    steps_per_epoch = cfg.n_cycles * cfg.num_envs * env.episode_length * n
    bar = None
    if cfg.progress and main:
        from tqdm.auto import tqdm

        desc = f"{cfg.env} {cfg.algo}" + (f" x{n} runs" if plan.sweep else "")
        bar = tqdm(total=cfg.epochs, initial=start, desc=desc, unit="epoch",
                   dynamic_ncols=True, file=sys.stderr)
    t_start = time.perf_counter() - wall0
    last_rows: list[dict] = [{} for _ in runs]

    def live() -> list[int]:
        return [i for i, name in enumerate(names) if name not in diverged]

    stopped = None  # the epoch after which stop_success was met
    # Each epoch's files are written in this order: metrics rows and best policies, then the
    # latest state (so that a run killed in between resumes consistent); then the next epoch is
    # dispatched (it donates the state), and the plot, sweep summary and progress bar are
    # written while it runs.
    pending = None
    if start < cfg.epochs:
        if reached_stop(cfg, recent, live()):  # a resumed run that had already met it
            stopped = start
        else:
            pending = batch.epoch(ts, hps)
    t_prev = time.perf_counter()
    try:
        for epoch in range(start, cfg.epochs):
            if pending is None:
                break
            ts, m = pending
            pending = None
            m = batch.host(m)  # every run's, on every process
            now = time.perf_counter()
            dt, t_prev = now - t_prev, now
            wall = now - t_start
            rows: dict[int, dict] = {}
            for i, name in enumerate(names):
                if name in diverged:
                    continue
                row = epoch_row(epoch + 1, _row_of(m, i), wall)
                bad = nonfinite_losses(row)
                if bad:
                    diverged[name] = epoch + 1
                    if not plan.sweep:
                        raise TrainingDiverged(
                            f"{', '.join(bad)} became non-finite in epoch {epoch + 1}; "
                            f"stopped. {last_good_checkpoint(ckpt)}")
                    if main:
                        log(f"{name}: {', '.join(bad)} became non-finite in epoch {epoch + 1}; "
                            f"its outputs stop at epoch {epoch}, the other runs go on")
                    continue
                rows[i] = row
            if len(diverged) == n:
                raise TrainingDiverged(
                    f"the losses of every run became non-finite (the last in epoch "
                    f"{epoch + 1}); stopped. {last_good_checkpoint(ckpt)}")
            new_best = [i for i, r in rows.items() if r["test_success"] >= best[i]]
            tests = []
            for i, row in rows.items():
                best[i] = max(best[i], float(row["test_success"]))
                recent[i] = (recent[i] + [float(row["test_success"])])[-cfg.stop_window:]
                last_rows[i] = row
                tests.append(row["test_success"])
            stop = reached_stop(cfg, recent, live())
            go_on = not stop and epoch + 1 < cfg.epochs
            meta = None
            if stop or is_checkpoint_epoch(cfg, epoch + 1):
                bests = list(best)
                meta = ({"best_success": bests, "wall_time": round(wall, 3),
                         "diverged": diverged, "runs": names, "recent_success": recent}
                        if plan.sweep else
                        {"best_success": bests[0], "wall_time": round(wall, 3),
                         "recent_success": recent[0]})
            # Learner states are fetched once, and only when some run has a new best (ties go
            # to the later epoch, as in RunOutputs.record); sliced per run on the host.
            pol = batch.host(ts.ddpg) if new_best else None
            for i, row in rows.items():
                if i in outs:
                    outs[i].record(row, lambda i=i, pol=pol: _row_of(pol, i))
            del pol
            if meta is not None:
                ckpt.save_latest(epoch + 1, saved(ts), meta)
            if go_on:
                pending = batch.epoch(ts, hps)
            for o in outs.values():
                o.plot_if_due()
            if plan.sweep and main:
                summary.write(plan, diverged)
            if bar is not None:
                if tests:  # this process's runs that have not diverged
                    post = {"env_steps": int(np.max(m.env_steps)),
                            "sps": f"{steps_per_epoch / dt:.0f}",
                            "test": f"{np.mean(tests):.2f}"}
                    if plan.sweep:
                        post["best"] = f"{max(tests):.2f}"
                    bar.set_postfix(post)
                bar.update(1)
            if stop:
                stopped = epoch + 1
                break
    finally:
        for o in outs.values():
            o.flush()
    if bar is not None:
        bar.close()
    if stopped is not None and main:
        log(f"stopped after epoch {stopped}: the mean test success of the last "
            f"{cfg.stop_window} epochs reached stop_success={cfg.stop_success:g}"
            + (" on every run" if plan.sweep else "")
            + ("; resume with stop_success=null to train on" if stopped == start else ""))
    for i, o in outs.items():
        if not last_rows[i]:
            done = o.csv.rows()
            last_rows[i] = done[-1] if done else {}
        o.close()
    if plan.sweep:
        ckpt.close()
    distributed.barrier("rdher_jax.drive.done")
    result = {"out_dir": str(plan.out_dir), "names": names, "rows": last_rows,
              "best": best,
              "diverged": diverged, "program": batch.describe(), "local": mine}
    if plan.sweep:
        result["summary"] = summary.collect(plan, diverged) if main else ([], [])
    return result

