"""JAX's persistent compilation cache, in a per-user directory keyed by this host.

A later process loads a compiled program from disk instead of compiling it again. JAX keys each
entry by the program (its HLO), the compile options, the XLA flags and the backend; on a CPU the
cached executables are native code for the CPU that compiled them, which JAX's key does not
name, so a cache directory shared between machines (a networked home) could hand one CPU
another's instructions. The directory here is therefore one per host kind:
``<root>/xla-<key>``, the key a hash of the CPU's model and instruction-set flags, the machine,
and the jax/jaxlib versions. A different CPU, JAX or config is a cache miss, never a crash.

Programs holding a host callback are never written (JAX refuses them: the callback is a pointer
into the process that compiled it). With ``backend=mujoco`` the native physics is such a
callback, so what is cached there is what runs without it: the trainer's ``init``, and with
``overlap=true`` the learner's program (``learn``), which is most of the compile time. On the
``mjx`` backend every program is cached.

``compile_cache=false`` turns it off; ``RDHER_JAX_CACHE_DIR`` moves the root (default
``$XDG_CACHE_HOME/rdher_jax``, else ``~/.cache/rdher_jax``).
"""

from __future__ import annotations

from pathlib import Path

# The root and the host key are the env package's: its FFI library is kept under them too.
from .envs.cache import ENV_VAR as ENV_VAR
from .envs.cache import default_root, host_key

# Programs that compile faster than this are not written: reading one back costs about as much.
MIN_COMPILE_SECS = 0.5
# The directory's size bound; JAX evicts the least recently used entries beyond it (an entry
# is 0.1-1 MB on a CPU).
MAX_BYTES = 1 << 30


def cache_dir(root: str | Path | None = None) -> Path:
    return Path(root if root is not None else default_root()) / f"xla-{host_key()}"


def repair(path: Path) -> int:
    """Give every entry of ``path`` that lacks its access-time file one (its mtime); returns how
    many. JAX writes an entry's ``-cache`` file, then its ``-atime`` file, and its eviction reads
    the ``-atime`` of every entry: one process killed between the two writes (or a cache filled
    with eviction off) would make every later write to the directory fail."""
    import filelock

    fixed = 0
    try:
        with filelock.FileLock(path / ".lockfile", timeout=10):  # JAX's own lock on the dir
            for entry in path.glob("*-cache"):
                atime = entry.with_name(entry.name.removesuffix("-cache") + "-atime")
                if not atime.exists():
                    atime.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))
                    fixed += 1
    except (OSError, filelock.Timeout):  # a busy or read-only cache: JAX copes or warns
        pass
    return fixed


def configure(enabled: bool, root: str | Path | None = None,
              min_compile_secs: float = MIN_COMPILE_SECS) -> Path | None:
    """Point JAX's persistent cache at this host's directory (or turn it off); returns the
    directory. Takes effect for every later compilation of this process, also after earlier
    ones (the cache's once-per-process check is reset)."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    path = None
    if enabled:
        path = cache_dir(root)
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:  # an unwritable home: run without the cache rather than fail
            path = None
        else:
            repair(path)
    jax.config.update("jax_enable_compilation_cache", path is not None)
    jax.config.update("jax_compilation_cache_dir", None if path is None else str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_secs))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES if path is not None else -1)
    cc.reset_cache()
    return path
