import os

from rdher_jax.envs import CPU_XLA_FLAGS

# MJX on CPU needs these XLA flags (see README, "MJX on a CPU"). XLA reads them when JAX first
# initialises a backend, which importing the package above does not do.
_missing = [f for f in CPU_XLA_FLAGS if f not in os.environ.get("XLA_FLAGS", "")]
if _missing:
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_missing]).strip()
