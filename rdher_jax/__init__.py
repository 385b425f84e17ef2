"""rdher-jax: fully-jitted DDPG + HER / DHER / RDHER for the gymnasium-robotics Fetch tasks."""

__version__ = "0.1.0"


def make_env(name: str, backend: str | None = None, **kwargs):
    """Build a Fetch task; see ``rdher_jax.envs.make_env``."""
    from .envs import make_env as _make_env

    return _make_env(name, backend, **kwargs)


def make_vector_env(name: str, num_envs: int, backend: str | None = None,
                    seed: int | None = None, **kwargs):
    """A Fetch task as a ``gymnasium.vector.VectorEnv``; see ``rdher_jax.vector``."""
    from .vector import make_vector_env as _make_vector_env

    return _make_vector_env(name, num_envs, backend, seed=seed, **kwargs)


__all__ = ["make_env", "make_vector_env", "__version__"]
