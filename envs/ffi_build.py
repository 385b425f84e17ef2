"""Builds the native physics' XLA FFI handlers (``native_ffi.cc``) once per machine.

Importing this module does not import JAX, so the trainer can start the build on a background
thread (``start``) while JAX loads: on a machine that never ran the project the compile (a few
seconds of the C++ compiler) then overlaps the imports instead of adding to them. The library
goes in the per-user cache root (``cache.default_root()``), in a directory named by a hash of
the source, this host (``cache.host_key``), and the installed jaxlib and mujoco versions;
several processes building at once take turns under a file lock, and a build that is killed
leaves no library behind.
"""

from __future__ import annotations

import atexit
import hashlib
import importlib.metadata
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from .cache import default_root, host_key

LIB_NAME = "librdher_physics.so"

_thread: threading.Thread | None = None
_thread_lock = threading.Lock()


def _package_dir(name: str) -> Path:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"package {name} is not installed")
    return Path(next(iter(spec.submodule_search_locations)))


def source() -> Path:
    return Path(__file__).with_name("native_ffi.cc")


def library_path() -> Path:
    version = importlib.metadata.version
    parts = [source().read_bytes().hex(), host_key(), version("jaxlib"), version("mujoco"),
             sys.platform]
    key = hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]
    return default_root() / f"ffi-{key}" / LIB_NAME


def _compile(out: Path) -> None:
    """Compile the handlers into ``out``, atomically."""
    cxx = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not cxx or not shutil.which(cxx):
        raise RuntimeError(f"no C++ compiler ({cxx or 'c++ or g++'} not found; $CXX names one)")
    mj_dir = _package_dir("mujoco")
    libs = sorted(mj_dir.glob("libmujoco.so*")) or sorted(mj_dir.glob("libmujoco*.dylib"))
    if not libs:
        raise RuntimeError(f"no libmujoco shared library in {mj_dir}")
    # jax.ffi.include_dir(), found without importing JAX
    ffi_include = _package_dir("jaxlib") / "include"
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        part = Path(tmp) / out.name
        # No -march and no contraction into fused multiply-adds: the results must be numpy's.
        cmd = [cxx, "-O2", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off", "-w",
               "-I", str(ffi_include), "-I", str(mj_dir / "include"), str(source()),
               "-o", str(part), str(libs[0]), f"-Wl,-rpath,{mj_dir}", "-pthread"]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            lines = (res.stderr or res.stdout).strip().splitlines()
            first_error = next((ln for ln in lines if "error" in ln), lines[-1] if lines else "")
            raise RuntimeError(f"{Path(cxx).name} failed: {first_error.strip()}")
        os.replace(part, out)


def build() -> Path:
    """The library's path, compiled first if this machine has none; raises RuntimeError (or
    OSError) where it cannot be built."""
    out = library_path()
    if out.exists():
        return out
    import filelock

    out.parent.mkdir(parents=True, exist_ok=True)
    with filelock.FileLock(str(out) + ".lock", timeout=600):
        if not out.exists():
            _compile(out)
    return out


def start() -> None:
    """Start building on a background thread if no library is there yet (errors are left for
    the foreground ``build``, which reports them)."""
    global _thread
    with _thread_lock:
        if _thread is not None:
            return
        try:
            if library_path().exists():
                return
        except Exception:  # noqa: BLE001 - the foreground build says what is wrong
            return

        def run():
            try:
                build()
            except Exception:  # noqa: BLE001
                pass

        _thread = threading.Thread(target=run, name="rdher-ffi-build", daemon=True)
        _thread.start()
        atexit.register(_thread.join)  # an early exit leaves no half-built library behind


def wait() -> None:
    """Wait for a build that ``start`` began (if any)."""
    t = _thread
    if t is not None:
        t.join()
