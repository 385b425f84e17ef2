"""brax's normaliser imported without MJX, which the native path never runs.

The learner uses one module of brax, its running-statistics normaliser, which needs only jax and
flax; but ``import brax`` runs ``brax/__init__.py``, which imports ``brax.base`` and so MJX,
trimesh and scipy: about 0.5 s of every command's start-up on an idle 2-core CPU, for a physics
backend the native path never runs (``docs/performance.md``, 'Start-up'). :func:`defer_brax_init`,
a step of start-up (``rdher_jax.startup``; importing a module never does it), registers ``brax``
with its ``__init__`` deferred until something reads an attribute of the package itself
(``brax.State``, ``brax.base``, ...): then it runs in full, as a plain ``import brax`` would
have. Without that step, ``import brax...`` is the plain one.
"""

from __future__ import annotations

import importlib.util
import sys
import types

from .envs.notices import quiet_mjx  # brax's __init__ imports MJX: quietly, as the envs do


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


def defer_brax_init() -> None:
    """Register the ``brax`` package with its ``__init__`` deferred (nothing if brax is
    imported already), so that importing its normaliser imports no MJX."""
    if "brax" not in sys.modules:
        spec = importlib.util.find_spec("brax")
        if spec is not None and spec.submodule_search_locations is not None:
            pkg = _DeferredPackage("brax")
            pkg.__spec__, pkg.__loader__, pkg.__file__ = spec, spec.loader, spec.origin
            pkg.__path__ = list(spec.submodule_search_locations)
            pkg.__package__ = "brax"
            sys.modules["brax"] = pkg


def brax_deferred() -> bool:
    """Whether ``brax`` is registered with its ``__init__`` still deferred."""
    return isinstance(sys.modules.get("brax"), _DeferredPackage)
