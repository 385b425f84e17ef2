import atexit
import os
import shutil
import subprocess
import tempfile

import pytest
from rdher_jax.envs import CPU_XLA_FLAGS

# MJX on CPU needs these XLA flags (see docs/performance.md, "MJX on a CPU"). XLA reads them when
# JAX first initialises a backend, which importing the package above does not do.
_missing = [f for f in CPU_XLA_FLAGS if f not in os.environ.get("XLA_FLAGS", "")]
if _missing:
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_missing]).strip()

# Compiled programs persist between processes (rdher_jax.compile_cache): the tests share a
# cache of their own, never the user's.
if "RDHER_JAX_CACHE_DIR" not in os.environ:
    os.environ["RDHER_JAX_CACHE_DIR"] = tempfile.mkdtemp(prefix="rdher-jax-test-cache-")
    atexit.register(shutil.rmtree, os.environ["RDHER_JAX_CACHE_DIR"], True)


def _one_line_error(p: subprocess.Popen) -> str:
    """The stderr of a CLI that must fail cleanly: exit 2, one ``error:`` line, no traceback."""
    out, err = p.communicate(timeout=300)
    assert p.returncode == 2, (p.args, out, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


@pytest.fixture
def one_line_error():
    """``one_line_error(popen) -> the error line``, asserting the one-line error contract."""
    return _one_line_error

