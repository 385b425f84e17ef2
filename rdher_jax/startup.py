"""Process start-up: one function, one fixed order, for every command line and script.

Some settings take effect only before something else happens: JAX fixes its CPU device count
when its backends start, joins a multi-process runtime only before any device is touched, and
MuJoCo binds its OpenGL backend when it is first imported. So a command line parses its
arguments first (without importing JAX), then calls :func:`setup` once with what they ask
for, then builds and runs. Importing this module imports nothing heavy, and importing any
module of the package changes no other package's state: what start-up changes, it changes here.

The order, and why:

0. brax is registered with its ``__init__`` deferred (``rdher_jax._quiet``): the learner's
   one module of brax, its normaliser, then imports without MJX (about 0.5 s);
1. the native physics' FFI handlers start compiling on a background thread (a C++ build on a
   machine that never ran the project; it needs nothing from JAX, so it overlaps JAX's import);
2. host devices: ``jax_num_cpu_devices`` (``overlap=true`` collects on a second CPU device);
   the one way the package asks for host devices (a child process gets the same through the
   ``JAX_NUM_CPU_DEVICES`` variable that this option reads);
3. the multi-process join (``jax.distributed.initialize``), before any device is touched;
4. JAX's persistent compilation cache (``rdher_jax.compile_cache``);
5. MuJoCo's offscreen GL backend, for videos, before anything imports ``mujoco``.
"""

from __future__ import annotations

from dataclasses import dataclass

from .config import Config
from .distributed import ProcessSpec


@dataclass(frozen=True)
class Startup:
    """What a process needs set up before it builds anything.

    Attributes:
      host_devices: CPU devices JAX should start with (at least; 2 for ``overlap=true``).
      processes: how to join a multi-process sweep (None: one process).
      compile_cache: use JAX's persistent compilation cache.
      ffi: start building the native physics' FFI handlers in the background (a process that
        may step ``backend=mujoco``).
      gl: choose MuJoCo's offscreen GL backend (a process that renders video).
    """

    host_devices: int = 1
    processes: ProcessSpec | None = None
    compile_cache: bool = True
    ffi: bool = True
    gl: bool = False


@dataclass(frozen=True)
class Started:
    """What :func:`setup` did: whether this process joined a multi-process runtime, the
    compilation cache's directory (None: off) and the GL backend chosen (None: not asked)."""

    multi_process: bool = False
    cache_dir: str | None = None
    gl: str | None = None


def for_config(cfg: Config, processes: ProcessSpec | None = None) -> Startup:
    """What a training run (or every run of a sweep, ``cfg`` its base) needs: a second host
    device for ``overlap=true``, the compilation cache as configured."""
    return Startup(host_devices=2 if cfg.overlap else 1, processes=processes,
                   compile_cache=cfg.compile_cache)


def setup(s: Startup) -> Started:
    """Set the process up as ``s`` says, in the module's order. Safe to call again: steps that
    can no longer take effect (host devices once JAX's backend is up) are left as they are, and
    what needs them reports it (``executor.overlap_devices``)."""
    from ._quiet import defer_brax_init

    defer_brax_init()
    if s.ffi:
        from .envs.ffi_build import start

        start()
    import jax

    if s.host_devices > 1:
        try:
            jax.config.update("jax_num_cpu_devices",
                              max(s.host_devices, jax.config.jax_num_cpu_devices))
        except (RuntimeError, ValueError, AttributeError):
            pass  # the backend is up already: overlap_devices() gives the error
    multi = False
    if s.processes is not None:
        from .distributed import initialize

        multi = initialize(s.processes)
    from . import compile_cache

    cache = compile_cache.configure(s.compile_cache)
    gl = None
    if s.gl:
        from .render import select_gl

        gl = select_gl()
    return Started(multi, None if cache is None else str(cache), gl)
