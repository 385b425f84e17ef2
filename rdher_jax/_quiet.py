"""Third-party imports: their notices kept off the user's terminal, and MJX kept off the native
path.

Two notices reach every command otherwise: MJX's optional Warp backend prints "Failed to import
warp" and "Failed to import mujoco_warp" to stdout when Warp is absent (it is not used here), and
gymnasium-robotics prints a notice about its Adroit hand tasks' rewards to stderr on import
(through ``farama_notifications``). Each is removed at its source, before the first import of
its package; any other output of those imports still shows.

The learner uses one module of brax, its running-statistics normaliser, which needs only jax and
flax; but ``import brax`` runs ``brax/__init__.py``, which imports ``brax.base`` and so MJX,
trimesh and scipy: about 0.5 s of every command's start-up on an idle 2-core CPU, for a physics
backend the native path never runs (``docs/performance.md``, 'Start-up'). ``running_statistics()``
imports the normaliser with ``brax/__init__.py`` deferred until something reads an attribute of
the package itself (``brax.State``, ``brax.base``, ...): then it runs in full, as a plain
``import brax`` would have.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import sys
import types

_WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")


def quiet_mjx() -> None:
    """Import ``mujoco.mjx`` with Warp's absence notices dropped. Call it before any import of
    MJX (or of something that imports it); a no-op once MJX is loaded."""
    if "mujoco.mjx" not in sys.modules:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            import mujoco.mjx  # noqa: F401
        rest = [ln for ln in buf.getvalue().splitlines(keepends=True)
                if not ln.startswith(_WARP_NOTICES)]
        sys.stdout.write("".join(rest))


def quiet_imports() -> None:
    """Drop gymnasium-robotics' Adroit notice before it is imported. Idempotent; a no-op once
    ``gymnasium_robotics`` is loaded."""
    if "gymnasium_robotics" not in sys.modules:
        with contextlib.suppress(ImportError):
            from farama_notifications import notifications

            adroit = notifications.get("gymnasium_robotics", {})
            for version in [v for v, text in adroit.items() if text.startswith("Adroit")]:
                del adroit[version]


class _DeferredPackage(types.ModuleType):
    """The ``brax`` package before its ``__init__`` has run: submodules import through its
    ``__path__``; the first read of any other attribute runs ``__init__`` in it."""

    def __getattr__(self, name: str):
        if name.startswith("__") and name not in ("__all__", "__version__"):
            raise AttributeError(name)  # probes (inspect, pickle, ...), not the package's API
        spec = self.__spec__
        # Run once, and only this way: a plain module from here on.
        self.__class__ = types.ModuleType
        quiet_mjx()
        spec.loader.exec_module(self)
        return getattr(self, name)


def running_statistics():
    """``brax.training.acme.running_statistics``, imported without ``brax/__init__.py``."""
    if "brax" not in sys.modules:
        spec = importlib.util.find_spec("brax")
        if spec is not None and spec.submodule_search_locations is not None:
            pkg = _DeferredPackage("brax")
            pkg.__spec__, pkg.__loader__, pkg.__file__ = spec, spec.loader, spec.origin
            pkg.__path__ = list(spec.submodule_search_locations)
            pkg.__package__ = "brax"
            sys.modules["brax"] = pkg
    from brax.training.acme import running_statistics as rs

    return rs
