"""The gymnasium-robotics Fetch tasks on device (installed as ``rdher_jax.envs``), and DHER's
moving-goal variants of two of them.

``make_env(name, backend=None)`` builds one; see ``fetch.FetchEnv`` for the API and the
``fetch`` module docstring for the moving tasks. ``registry`` holds every task's physical facts.

Importing the package imports neither JAX nor MuJoCo (the registry is read before they load):
``make_env``, ``FetchEnv`` and ``State`` import them on first use.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from .registry import GYMNASIUM_TASK_NAMES, MOVING_TASK_NAMES, TASK_NAMES, task_spec

if TYPE_CHECKING:
    from .fetch import FetchEnv, State

BACKENDS = ("mujoco", "mjx", "warp")
# What installs the warp backend (NVIDIA Warp, ``warp-lang``).
WARP_INSTALL = "pip install -e '.[warp]'"

# XLA:CPU flags under which MJX is usable on a CPU (see docs/performance.md, "MJX on a CPU").
CPU_XLA_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
)


def __getattr__(name: str):
    if name in ("FetchEnv", "State"):
        from . import fetch

        return getattr(fetch, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def default_backend() -> str:
    """``warp`` on an NVIDIA GPU when Warp is installed, else ``mjx`` when JAX sees a GPU, and
    ``mujoco`` (native, batched on host threads) otherwise."""
    import jax

    if jax.default_backend() != "gpu":
        return "mujoco"
    return "warp" if warp_available() is None else "mjx"


def quiet_warp(wp=None) -> None:
    """Warp prints its version, devices, each module it builds and, on a machine without
    CUDA, a warning that GPU execution is unavailable: off (errors still print)."""
    if wp is None:
        import warp as wp
    wp.config.log_level = wp.LOG_ERROR


def warp_available() -> str | None:
    """None when MJX's Warp implementation (``backend=warp``) can run on JAX's default device;
    otherwise why not, in one line that names the install command."""
    import jax

    try:
        import warp as wp
    except ImportError:
        return f"backend=warp needs NVIDIA Warp (warp-lang), which is not installed: {WARP_INSTALL}"
    try:
        quiet_warp(wp)
        wp.init()
        cuda = wp.is_cuda_available()
    except Exception as e:  # a broken install or driver
        return f"backend=warp: Warp could not start ({e}); reinstall it: {WARP_INSTALL}"
    platform = jax.default_backend()
    if platform == "gpu" and not cuda:
        return (f"backend=warp: JAX runs on a GPU that Warp cannot use (no CUDA device); run "
                f"on an NVIDIA GPU or on the CPU ({WARP_INSTALL})")
    if platform not in ("gpu", "cpu"):
        return (f"backend=warp runs on an NVIDIA GPU or the CPU, not on JAX's {platform!r} "
                f"device ({WARP_INSTALL})")
    return None


def make_env(name: str, backend: str | None = None, scene: str | None = None,
             auto_reset: bool = True, num_threads: int | None = None,
             goal_speed: float | None = None,
             episode_length: int | None = None, physics_call: str = "ffi",
             worlds: int | None = None) -> FetchEnv:
    """Build a Fetch task.

    Args:
      name: a task of ``TASK_NAMES`` (a gymnasium-robotics task's ``-v4`` suffix is accepted):
        FetchReach, FetchPush, FetchSlide, FetchPickAndPlace, or a moving-goal task,
        FetchReachMoving or FetchPushMoving.
      backend: ``"mujoco"`` (native MuJoCo via mjbatch), ``"mjx"`` (MJX's JAX
        implementation), ``"warp"`` (MJX's Warp implementation), or None for the default.
      scene: ``"original"`` (the unedited gymnasium-robotics scene; native only), ``"mjx"``
        (the MJX-edited scene) or ``"warp"`` (the mjx scene with Warp's edits; native and
        warp). None: original for ``mujoco``, mjx for ``mjx``, warp for ``warp``.
      auto_reset: replace a state whose episode ended by a fresh episode inside ``step``.
      num_threads: host threads for the native backend (default: all usable cores).
      goal_speed: moving tasks only: metres per step the goal moves (None: the task's,
        ``registry.TASKS[name].goal_speed``; 0 keeps the goal still).
      episode_length: env steps per episode (None: the task's).
      physics_call: native backend only: ``"ffi"`` (XLA FFI handlers, so compiled programs
        can be cached; built once per machine, falling back to the callback with a warning)
        or ``"callback"`` (``jax.pure_callback``). Bit-identical results.
      worlds: warp backend only: the most envs one batched call steps (a sweep's runs times
        its envs); Warp's shared contact buffer is sized for it (default 1024). ``rollout``
        refuses a larger batch; a hand-written ``vmap`` over more envs could overflow the
        buffer, which crashes Warp on a CPU.
    Returns:
      A ``FetchEnv`` with pure ``reset(key)`` and ``step(state, action)``.
    """
    spec = task_spec(name)
    if goal_speed is not None:
        if not spec.moving:
            raise ValueError(f"goal_speed applies to the moving tasks "
                             f"({', '.join(MOVING_TASK_NAMES)}), not {spec.name}")
        spec = dataclasses.replace(spec, goal_speed=float(goal_speed))
    backend = backend or default_backend()
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    scene = scene or {"mujoco": "original", "mjx": "mjx", "warp": "warp"}[backend]
    if backend == "mjx" and scene != "mjx":
        raise ValueError("the mjx backend needs scene='mjx': mjx.put_model rejects the original")
    if backend == "warp" and scene != "warp":
        raise ValueError("the warp backend needs scene='warp': mjx.put_model(impl='warp') "
                         "rejects the others")
    from .fetch import FetchEnv
    from .physics import Setup

    setup = Setup(spec, scene)
    if backend == "mujoco":
        from .native import NativeBackend

        physics = NativeBackend(setup, num_threads=num_threads, physics_call=physics_call)
    elif backend == "mjx":
        from .mjx_backend import MjxBackend

        physics = MjxBackend(setup)
    else:
        why = warp_available()
        if why:
            raise RuntimeError(why)
        from .mjx_backend import WarpBackend

        physics = WarpBackend(setup, worlds=worlds or 1024)
    if episode_length is not None and episode_length < 1:
        raise ValueError(f"episode_length must be a positive integer, got {episode_length}")
    return FetchEnv(setup, physics, auto_reset=auto_reset, episode_length=episode_length)


__all__ = ["BACKENDS", "CPU_XLA_FLAGS", "FetchEnv", "GYMNASIUM_TASK_NAMES", "MOVING_TASK_NAMES",
           "State", "TASK_NAMES", "WARP_INSTALL", "default_backend", "make_env", "quiet_warp",
           "warp_available"]
