"""One sweep over several processes, through JAX's multi-controller runtime.

The same ``python -m rdher_jax.sweep ...`` command is started once per process: by ``srun`` or
``mpirun`` (``jax.distributed.initialize`` detects SLURM and Open MPI by itself), or by hand
with ``coordinator=HOST:PORT num_processes=N process_id=I``. After :func:`initialize` every
process sees every process's devices in ``jax.devices()``; the driver lays the sweep's run axis
over all of them (``executor.Executor``), and each process steps, logs and checkpoints only the
runs on its own devices. Nothing inside an epoch is a collective; between epochs the processes
exchange one small array (which runs have diverged), which is also what keeps them in step.

On CPU the cross-process collectives use gloo (``jax_cpu_collectives_implementation``).

The runtime ends a process that cannot join (a ``process_id`` given twice, fewer processes than
``num_processes``) or whose peer died with an abort (``LOG(FATAL)``, exit 134) and a native stack
trace. So a command-line process that joins a multi-process sweep runs its work in a child
(:func:`supervise`) and turns such an end into one ``error:`` line: exit 2 when it never joined,
exit 1 when the sweep it had joined stopped.
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .config import ConfigError

# key -> help text; the sweep command line takes these (see sweep.SWEEP_KEYS).
PROCESS_KEYS: dict[str, str] = {
    "coordinator": "multi-process sweep: HOST:PORT of process 0's coordination service (every "
                   "process passes the same); with num_processes and process_id. Not needed "
                   "under SLURM or Open MPI, which the runtime detects",
    "num_processes": "multi-process sweep: number of processes N, each started with the same "
                     "command",
    "process_id": "multi-process sweep: this process's index, 0 <= process_id < num_processes",
    "init_timeout": "multi-process sweep: seconds to wait for every process to join (default "
                    "300, the runtime's)",
    "heartbeat_timeout": "multi-process sweep: seconds without a heartbeat after which a process "
                         "counts as dead and the sweep stops (default 100, the runtime's)",
}


# Set in a supervised child: the pipe's write end, on which it reports having joined.
JOINED_FD_ENV = "RDHER_JAX_JOINED_FD"


@dataclass(frozen=True)
class ProcessSpec:
    """How this process joins a multi-process sweep (all None: as the cluster says, or alone)."""

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    init_timeout: int = 300
    heartbeat_timeout: int = 100

    @property
    def explicit(self) -> bool:
        return self.num_processes is not None


def _int(key: str, raw: str, lo: int) -> int:
    try:
        v = int(str(raw).strip())
    except ValueError:
        raise ConfigError(f"{key} must be an integer, got {raw!r}") from None
    if v < lo:
        raise ConfigError(f"{key} must be >= {lo}, got {v}")
    return v


def parse(other: Mapping[str, str]) -> ProcessSpec:
    """The process keys of a command line (``{key: value text}``); one-line ConfigErrors."""
    given = [k for k in ("coordinator", "num_processes", "process_id") if k in other]
    if given and len(given) < 3:
        missing = [k for k in ("coordinator", "num_processes", "process_id") if k not in other]
        raise ConfigError(f"a multi-process sweep started by hand needs coordinator=HOST:PORT, "
                          f"num_processes=N and process_id=I; missing {', '.join(missing)}")
    spec: dict[str, Any] = {}
    for key in ("init_timeout", "heartbeat_timeout"):
        if key in other:
            spec[key] = _int(key, other[key], 1)
    if not given:
        return ProcessSpec(**spec)
    coord = other["coordinator"].strip()
    if not re.fullmatch(r"\[?[A-Za-z0-9_.:-]+\]?:\d{1,5}", coord) or \
            not 0 < int(coord.rsplit(":", 1)[1]) < 65536:
        raise ConfigError(f"coordinator must be HOST:PORT (port 1-65535), got {coord!r}")
    n = _int("num_processes", other["num_processes"], 1)
    i = _int("process_id", other["process_id"], 0)
    if i >= n:
        raise ConfigError(f"process_id must be < num_processes ({n}), got {i}")
    return ProcessSpec(coord, n, i, **spec)


def cluster_detected() -> bool:
    """Whether this process was started as one of several by ``srun`` or ``mpirun``: a job
    step of several tasks (``SLURM_STEP_NUM_TASKS``; a batch script's own python, outside
    ``srun``, is one process whatever the allocation) or an Open MPI world of several."""
    env = os.environ
    if int(env.get("OMPI_COMM_WORLD_SIZE", "1") or 1) > 1:
        return True
    return "SLURM_JOB_ID" in env and int(env.get("SLURM_STEP_NUM_TASKS", "1") or 1) > 1


def initialize(spec: ProcessSpec) -> bool:
    """Join the multi-process runtime when asked to (explicit keys, or SLURM/Open MPI); returns
    whether this is a multi-process run. Must run before anything touches a JAX device.

    A coordinator that cannot be reached, or processes that never all join, end in a one-line
    ConfigError after ``init_timeout`` seconds.
    """
    import jax

    if not spec.explicit and not cluster_detected():
        return False
    if spec.explicit and spec.num_processes == 1:
        return False
    if jax.distributed.is_initialized():
        return jax.process_count() > 1
    if spec.explicit:
        _check_coordinator(spec)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(
            coordinator_address=spec.coordinator, num_processes=spec.num_processes,
            process_id=spec.process_id, initialization_timeout=spec.init_timeout,
            heartbeat_timeout_seconds=spec.heartbeat_timeout)
    except Exception as e:  # the runtime raises XlaRuntimeError, ValueError, RuntimeError
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ConfigError(f"could not join the multi-process sweep{_where(spec)}: "
                          f"{first[:300]}") from None
    _report_joined()
    if spec.explicit:
        # The runtime takes process 0's count and lets a process that says otherwise join.
        counts = [int(c) for c in gather(np.int64(spec.num_processes))]
        if len(set(counts)) > 1:
            raise ConfigError(
                "the processes disagree on num_processes: " + ", ".join(
                    f"process {i} says {c}" for i, c in enumerate(counts)) +
                "; start every process with the same num_processes")
    return jax.process_count() > 1


def _where(spec: ProcessSpec) -> str:
    return (f" (coordinator {spec.coordinator}, process {spec.process_id} of "
            f"{spec.num_processes})" if spec.explicit else "")


def _report_joined() -> None:
    """Tell the supervising parent (if any) that this process joined the runtime."""
    fd = os.environ.pop(JOINED_FD_ENV, None)
    if fd is not None:
        try:
            os.write(int(fd), b"1")
            os.close(int(fd))
        except (OSError, ValueError):
            pass


def wanted(spec: ProcessSpec) -> bool:
    """Whether :func:`initialize` would join a multi-process runtime."""
    return (spec.num_processes or 1) > 1 or (not spec.explicit and cluster_detected())


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: a killed parent leaves its child to the runtime's heartbeat


def supervise(spec: ProcessSpec, command: list[str] | None = None) -> int | None:
    """Run this process's part of a multi-process sweep in a child and return its exit status;
    None (do the work here) when no multi-process runtime is wanted or this is the child.

    The child is the same command line (``sys.orig_argv`` unless ``command`` is given). When the
    runtime aborts it, this prints one line and returns 2 (it never joined: a ``process_id``
    given twice, fewer processes than ``num_processes`` within ``init_timeout``) or 1 (the sweep
    it had joined stopped, e.g. another process died). SIGINT, SIGTERM and SIGHUP are passed on
    to the child, and the child dies with this process.
    """
    if JOINED_FD_ENV in os.environ or not wanted(spec):
        return None
    command = list(command or [sys.executable, *sys.orig_argv[1:]])
    r, w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    child = subprocess.Popen(command, env={**os.environ, JOINED_FD_ENV: str(w)}, pass_fds=(w,),
                             preexec_fn=_die_with_parent, process_group=0)
    os.close(w)
    forward = {sig: signal.signal(sig, lambda s, _f: child.send_signal(s))
               for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        rc = child.wait()
    finally:
        for sig, old in forward.items():
            signal.signal(sig, old)
    with os.fdopen(r, "rb") as f:
        joined = f.read(1) == b"1"
    if rc not in (134, -signal.SIGABRT):
        return rc if rc >= 0 else 128 - rc
    sys.stdout.flush()
    if not joined:
        print(f"error: could not join the multi-process sweep{_where(spec)}: the runtime "
              f"stopped this process (a process_id given twice, or fewer processes than "
              f"num_processes joined within init_timeout={spec.init_timeout} s)",
              file=sys.stderr)
        return 2
    print(f"error: the multi-process sweep stopped{_where(spec)}: another process failed or "
          f"stopped answering (heartbeat_timeout={spec.heartbeat_timeout} s); start every "
          "process again with resume=<sweep_dir> to continue from the last checkpoint",
          file=sys.stderr)
    return 1


def _check_coordinator(spec: ProcessSpec) -> None:
    """What the runtime would end with an abort and a stack trace, as a one-line ConfigError:
    process 0 cannot listen on the coordinator's port, or another process cannot reach it
    within ``init_timeout`` seconds."""
    host, port = spec.coordinator.rsplit(":", 1)
    host = host.strip("[]")
    if spec.process_id == 0:
        try:
            with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind(("", int(port)))
        except OSError as e:
            raise ConfigError(f"process 0 cannot serve the coordinator on port {port}: "
                              f"{e.strerror or e}") from None
        return
    deadline = time.monotonic() + spec.init_timeout
    while True:
        try:
            with socket.create_connection((host, int(port)), timeout=2):
                return
        except OSError as e:
            if time.monotonic() >= deadline:
                raise ConfigError(
                    f"could not reach the coordinator {spec.coordinator} within "
                    f"{spec.init_timeout} s (init_timeout): {e.strerror or e}; start process 0 "
                    "there, or check coordinator=") from None
            time.sleep(0.5)


def index() -> int:
    import jax

    return jax.process_index()


def count() -> int:
    import jax

    return jax.process_count()


def is_main() -> bool:
    """Process 0 (the only process of a one-process run) writes the sweep's shared files."""
    return index() == 0


def gather(x: Any) -> Any:
    """Every process's ``x`` (an array of the same shape and dtype everywhere), stacked along a
    new leading process axis, on every process. One process: ``x[None]``. A collective: every
    process must call it at the same point."""
    if count() == 1:
        return np.asarray(x)[None]
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(np.asarray(x), tiled=False))


def barrier(name: str) -> None:
    """Wait until every process reaches the barrier ``name`` (nothing with one process)."""
    if count() == 1:
        return
    from jax.experimental import multihost_utils

    multihost_utils.sync_global_devices(name)


def hosts() -> list[str]:
    """Each process's host name, in process order."""
    name = socket.gethostname().encode()[:64].ljust(64, b"\0")
    rows = gather(np.frombuffer(name, dtype=np.uint8))
    return [bytes(r).rstrip(b"\0").decode(errors="replace") for r in rows]
