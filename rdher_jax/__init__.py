"""rdher-jax: fully-jitted DDPG + HER / DHER / RDHER for the gymnasium-robotics Fetch tasks."""

__version__ = "0.1.0"


def make_env(name: str, backend: str | None = None, **kwargs):
    """Build a Fetch task; see ``rdher_jax.envs.make_env``."""
    from .envs import make_env as _make_env

    return _make_env(name, backend, **kwargs)


__all__ = ["make_env", "__version__"]
