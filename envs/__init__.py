"""The gymnasium-robotics Fetch tasks on device (installed as ``rdher_jax.envs``).

``make_env(name, backend=None)`` builds one; see ``fetch.FetchEnv`` for the API.
"""

from __future__ import annotations

from .fetch import EPISODE_LENGTH, FetchEnv, State
from .physics import TASKS, Setup, check_task

BACKENDS = ("mujoco", "mjx")
TASK_NAMES = tuple(TASKS)

# XLA:CPU flags under which MJX is usable on a CPU (see README, "MJX on CPU").
CPU_XLA_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
)


def default_backend() -> str:
    """``mjx`` when JAX sees a GPU, ``mujoco`` (native, batched on host threads) otherwise."""
    import jax

    return "mjx" if jax.default_backend() == "gpu" else "mujoco"


def make_env(name: str, backend: str | None = None, scene: str | None = None,
             auto_reset: bool = True, num_threads: int | None = None) -> FetchEnv:
    """Build a Fetch task.

    Args:
      name: FetchReach, FetchPush, FetchSlide or FetchPickAndPlace (a ``-v4`` suffix is accepted).
      backend: ``"mujoco"`` (native MuJoCo via mjbatch), ``"mjx"``, or None for the default.
      scene: ``"original"`` (the unedited gymnasium-robotics scene; native only) or ``"mjx"``
        (the MJX-edited scene). None: original for ``mujoco``, mjx for ``mjx``.
      auto_reset: replace a state whose episode ended by a fresh episode inside ``step``.
      num_threads: host threads for the native backend (default: all usable cores).
    Returns:
      A ``FetchEnv`` with pure ``reset(key)`` and ``step(state, action)``.
    """
    name = name.removesuffix("-v4")
    check_task(name)
    backend = backend or default_backend()
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    scene = scene or ("original" if backend == "mujoco" else "mjx")
    if backend == "mjx" and scene != "mjx":
        raise ValueError("the mjx backend needs scene='mjx': mjx.put_model rejects the original")
    setup = Setup(name, scene)
    if backend == "mujoco":
        from .native import NativeBackend

        physics = NativeBackend(setup, num_threads=num_threads)
    else:
        from .mjx_backend import MjxBackend

        physics = MjxBackend(setup)
    return FetchEnv(setup, physics, auto_reset=auto_reset)


__all__ = ["BACKENDS", "CPU_XLA_FLAGS", "EPISODE_LENGTH", "FetchEnv", "State", "TASK_NAMES",
           "default_backend", "make_env"]
