"""rdher-jax: fully-jitted DDPG + HER / DHER / RDHER for the Fetch tasks."""

__version__ = "0.1.0"
