"""The FFI build's old place: ``rdher_jax.envs.ffi_build`` under its former name, until
``train`` imports it from there."""

from .envs.ffi_build import build, library_path, source, start, wait

__all__ = ["build", "library_path", "source", "start", "wait"]
