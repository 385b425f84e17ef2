"""Where per-machine build products go: the per-user cache root and a key naming this host.

The native physics' FFI library (``ffi_build``) and the trainer's compiled programs are native
code for the CPU that built them; a cache directory shared between machines (a networked home)
could hand one CPU another's instructions, so each is kept under a key of the CPU's model and
instruction-set flags, the machine, and the jax/jaxlib versions. Imports nothing heavy: the key
is read before JAX loads.

``RDHER_JAX_CACHE_DIR`` moves the root (default ``$XDG_CACHE_HOME/rdher_jax``, else
``~/.cache/rdher_jax``).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import platform
from pathlib import Path

ENV_VAR = "RDHER_JAX_CACHE_DIR"


def default_root() -> Path:
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "rdher_jax"


def _cpuinfo() -> tuple[str, str]:
    """(model name, sorted instruction-set flags) of this host's first CPU; empty strings where
    /proc/cpuinfo is not there (then platform.processor() stands for both)."""
    model = flags = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip().lower()
                if key == "model name" and not model:
                    model = value.strip()
                elif key in ("flags", "features") and not flags:
                    flags = " ".join(sorted(value.split()))
                if model and flags:
                    break
    except OSError:
        pass
    return model or platform.processor(), flags


def host_key(cpuinfo: tuple[str, str] | None = None) -> str:
    """16 hex digits naming what a cached CPU executable depends on beyond JAX's own key."""
    # The installed versions, read without importing JAX.
    version = importlib.metadata.version
    model, flags = cpuinfo if cpuinfo is not None else _cpuinfo()
    parts = [platform.machine(), model, flags, version("jax"), version("jaxlib")]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]
