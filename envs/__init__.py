"""Fetch tasks on device (installed as ``rdher_jax.envs``)."""
