"""Executing N >= 1 runs as one compiled program: :class:`Executor` and how it is built.

The program is ``program.epoch`` (``rdher_jax.program``) over a leading run axis:
``jax.jit(jax.vmap(epoch))`` for a sweep, and for a run of its own the unvmapped epoch with the
run axis added and dropped around it (so a run gives exactly the numbers it gave before sweeps
existed). With several JAX devices the run axis is split over a 1-D mesh ``"runs"``
(``NamedSharding(mesh, P("runs"))``) and the vmapped epoch runs under ``shard_map``, so each
device steps only its own runs: no collective is needed, and the native backend's
``pure_callback`` is made once per device per env step for that device's runs. (Plain ``jit``
with sharded inputs also works, but XLA's partitioner then pins the callback to device 0 and
gathers every run's env batch there and back at each step.) When the number of runs does not
divide the number of devices, the run axis is padded with copies of the first run, computed and
discarded. The devices may span several processes (``rdher_jax.distributed``): each process
steps its own block of the run axis.

With ``overlap=true`` (one CPU learner device) the epoch is :class:`OverlapEpoch`: each cycle's
learner and the next cycle's rollouts run at once on two host devices. With one device and
sequential cycles the epoch program is compiled on a background thread (:class:`CompiledAhead`)
while ``init`` compiles and runs.

The driver sees one interface whatever the case: ``init``, ``epoch``, ``put``, ``host``,
``latest_state`` / ``place_restored`` (the latest checkpoint's state) and ``describe``.
"""

from __future__ import annotations

import atexit
import dataclasses
import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .config import RESUMABLE_KEYS, TRACED_KEYS, Config, ConfigError, preset_sets_overlap, to_yaml
from .envs import default_backend, make_env, warp_available
from .program import make_program


def resolve_backend(cfg: Config) -> tuple[str, str]:
    """The physics backend and scene a config asks for, with ``auto`` decided here."""
    backend = default_backend() if cfg.backend == "auto" else cfg.backend
    scene = cfg.scene if cfg.scene != "auto" else {"mujoco": "original"}.get(backend, backend)
    if backend == "mjx" and scene != "mjx":
        raise ConfigError("backend=mjx needs scene=mjx (mjx.put_model rejects the original)")
    if backend == "warp":
        why = warp_available()
        if why:
            raise ConfigError(why)
        if scene != "warp":
            raise ConfigError("backend=warp needs scene=warp (mjx.put_model(impl='warp') "
                              "rejects the others)")
    return backend, scene


def build(cfg: Config, runs: int = 1):
    """Env and training program (``program.make_program``) of a resolved config; ``runs``:
    how many such runs one program steps at once (the warp backend sizes its buffers for
    them)."""
    backend, scene = resolve_backend(cfg)
    extra = {}
    if backend == "warp":
        extra["worlds"] = runs * max(cfg.num_envs, cfg.n_test_rollouts)
    if backend == "mujoco":
        # With overlap the physics has a host device, and so a core, of its own: a second
        # physics thread would take the learner's.
        extra["num_threads"] = cfg.physics_threads or (1 if cfg.overlap else None)
    env = make_env(cfg.env, backend=backend, scene=scene, auto_reset=False,
                   goal_speed=cfg.goal_speed, episode_length=cfg.episode_length,
                   physics_call=cfg.physics_call, **extra)
    return env, make_program(cfg, env)


def stack(trees: Sequence[Any]) -> Any:
    """Stack pytrees of equal structure along a new leading (run) axis."""
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def tree_bytes(tree: Any) -> int:
    """Bytes held by the array leaves of ``tree`` (their global size when sharded)."""
    return int(sum(np.dtype(x.dtype).itemsize * math.prod(x.shape)
                   for x in jax.tree.leaves(tree)))


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
    of length 1 (one run, :class:`Executor` with ``vmapped=False``).
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


class Executor:
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

    def local_runs(self) -> list[int]:
        """The runs this process steps: all of them with one process; with several, its own
        block of the run axis."""
        return [i for i in range(self.n_runs) if self.lo <= i < self.hi]

    def owner(self, i: int) -> int:
        """The process whose devices step run ``i``."""
        per = self.n_padded // len(self.devices)
        return int(self.devices[i // per].process_index)

    def latest_state(self, ts: Any, stacked: bool) -> Any:
        """What the latest checkpoint saves of ``ts``: the global array with several processes
        (each saves its shards, padding included); else the real runs on the host, stacked
        (a sweep's layout) or the one run's state without the run axis (a run's own)."""
        if self.multi_process:
            return ts
        host = self.unpad(ts)
        return host if stacked else jax.tree.map(lambda x: x[0], host)

    def restore_template(self, ts: Any, stacked: bool) -> Any:
        """The template a latest checkpoint is restored into (see :meth:`latest_state`)."""
        return self.abstract(ts) if self.multi_process else self.latest_state(ts, stacked)

    def place_restored(self, state: Any, stacked: bool) -> Any:
        """A restored latest state as the program's input (the inverse of
        :meth:`latest_state`)."""
        if self.multi_process:
            return state
        return self.put(state if stacked else stack([state]))

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


def executor_for(runs: Sequence[Config], devices: Sequence[Any] | None = None,
                 vmapped: bool = True) -> tuple[Any, Any, Executor]:
    """Env, program and :class:`Executor` of runs that differ only in traced keys and seeds.

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
        # Padded runs (see the module docstring) are stepped too.
        env, program = build(runs[0], runs=-(-len(runs) // len(devices)) * len(devices))
        if overlap is not None and env.backend.name != "mujoco":
            raise ConfigError(f"overlap=true needs backend=mujoco (the native physics), not "
                              f"{env.backend.name}{_preset_overlap_hint(runs[0])}")
        _LAST_PROGRAM.update(key=key, value=(env, program, Executor(
            program, len(runs), devices, vmapped, overlap)))
    return _LAST_PROGRAM["value"]
