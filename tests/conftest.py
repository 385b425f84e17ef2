import os

# MJX on CPU needs these XLA flags (see README); they must be set before JAX starts.
_FLAGS = "--xla_cpu_use_fusion_emitters=false"
if _FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _FLAGS).strip()
