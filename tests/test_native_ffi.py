"""The native physics as XLA FFI calls (envs/native_ffi.cc): bit for bit the callback's, and
cacheable across processes."""

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from rdher_jax.envs import TASK_NAMES, native_ffi

from rdher_jax import make_env

# Where no C++ compiler is found the backend keeps the callback (the last test checks that);
# what needs the handlers is skipped there, saying so.
needs_ffi = pytest.mark.skipif(native_ffi.library() is None,
                               reason="the FFI handlers could not be built here")


def rollout(env, key, steps=25, batch=3):
    """A jitted, vmapped rollout with random actions and auto-reset: every state's physics
    bits and every observation, reward and info along the way."""
    keys = jax.random.split(key, batch)

    def run(key):
        state = jax.vmap(env.reset)(keys)

        def body(state, k):
            a = jax.random.uniform(k, (batch, 4), minval=-1.2, maxval=1.2)
            state = jax.vmap(env.step)(state, a)
            return state, state

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    return jax.jit(run)(key)


@needs_ffi
@pytest.mark.parametrize("task", TASK_NAMES)
def test_ffi_is_the_callback_bit_for_bit(task):
    """Every task, through resets (auto-reset mid-rollout: 25 steps of episodes of 10) and
    steps: the FFI handlers give the callback's states and readouts exactly."""
    ffi = make_env(task, "mujoco", episode_length=10)
    cb = make_env(task, "mujoco", episode_length=10, physics_call="callback")
    assert ffi.backend.ffi_task is not None and cb.backend.ffi_task is None
    a, b = rollout(ffi, jax.random.PRNGKey(3)), rollout(cb, jax.random.PRNGKey(3))
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_unknown_physics_call_is_refused():
    with pytest.raises(ValueError, match="physics_call"):
        make_env("FetchReach", "mujoco", physics_call="socket")


@needs_ffi
def test_an_unregistered_task_is_an_error_not_a_crash():
    from rdher_jax.envs import native_ffi

    env = make_env("FetchReach", "mujoco")
    state = env.reset(jax.random.PRNGKey(0))
    shapes = env.backend._shapes(())
    with pytest.raises(Exception, match="not registered"):
        jax.block_until_ready(native_ffi.step_call(
            12345, shapes, state.data.bits, np.zeros(3, np.float32), np.zeros((), np.float32)))


def child(code: str, env: dict) -> str:
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)],
                       env={**os.environ, "JAX_PLATFORMS": "cpu", **env},
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-4000:]
    return p.stdout


ROLLOUT_IN_A_PROCESS = """
    import jax, numpy as np
    from jax._src import monitoring
    from rdher_jax import compile_cache, make_env
    compile_cache.configure(True, min_compile_secs=0.0)
    hits = []
    monitoring.register_event_listener(
        lambda event, **_: hits.append(event) if event.endswith("cache_hits") else None)
    env = make_env("FetchPush", "mujoco", physics_call={call!r})
    keys = jax.random.split(jax.random.PRNGKey(1), 2)

    def run(keys):
        state = jax.vmap(env.reset)(keys)
        def body(state, _):
            state = jax.vmap(env.step)(state, jax.numpy.full((2, 4), 0.5))
            return state, state.obs["observation"]
        return jax.lax.scan(body, state, None, length=5)[1]

    out = np.asarray(jax.jit(run)(keys))
    print(len(hits), out.tobytes().hex())
"""


@needs_ffi
def test_a_program_holding_the_physics_is_loaded_by_another_process(tmp_path):
    """The point of the FFI path: a second process loads the first one's compiled rollout from
    the persistent cache (the task named by id, registered anew there) and gets the same
    result. (That the callback's program is never written: tests/test_compile_cache.py.)"""
    env = {"RDHER_JAX_CACHE_DIR": str(tmp_path)}
    first = child(ROLLOUT_IN_A_PROCESS.format(call="ffi"), env).split()
    second = child(ROLLOUT_IN_A_PROCESS.format(call="ffi"), env).split()
    assert int(second[0]) > int(first[0])  # the rollout came from the cache
    assert second[1] == first[1]


def test_without_a_compiler_the_callback_runs_with_one_warning(tmp_path):
    """No library on this machine and no compiler: a warning naming why, then the callback."""
    out = child("""
        import warnings
        import jax, numpy as np
        from rdher_jax import make_env
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            env = make_env("FetchReach", "mujoco")
            other = make_env("FetchPush", "mujoco")
            # resolved when a program that steps the env is first traced
            s = jax.jit(env.step)(env.reset(jax.random.PRNGKey(0)), np.ones(4, np.float32))
            jax.jit(other.reset)(jax.random.PRNGKey(0))
        msgs = [str(x.message) for x in w if "pure_callback" in str(x.message)]
        assert len(msgs) == 1, msgs
        assert env.backend.ffi_task is None and other.backend.ffi_task is None
        print(msgs[0])
    """, {"RDHER_JAX_CACHE_DIR": str(tmp_path / "empty"), "CXX": str(tmp_path / "no-cxx")})
    assert "failed" in out or "compiler" in out


@needs_ffi
def test_a_program_outlives_the_envs_that_registered_its_task():
    """Envs of one task share its id; the handlers step a copy of the model that lives as long
    as the process, so dropping every env (and editing one's model) never reaches a program
    still holding the task."""
    import gc

    env = make_env("FetchPush", "mujoco")
    step = jax.jit(env.step)
    state = env.reset(jax.random.PRNGKey(0))
    first = np.asarray(step(state, np.ones(4, np.float32)).data.bits)
    other = make_env("FetchPush", "mujoco")
    assert other.backend.ffi_task == env.backend.ffi_task
    env.backend.setup.model.opt.timestep = 0.5  # an edit after registration: not seen
    del env, other
    gc.collect()
    again = np.asarray(step(state, np.ones(4, np.float32)).data.bits)
    np.testing.assert_array_equal(again, first)


def test_the_handlers_are_resolved_when_a_program_is_traced_not_when_the_env_is_built(
        monkeypatch):
    """Building an env does not wait for the handlers' library (on a new machine its C++ build
    then overlaps the programs that do not step the env); the first trace of a step resolves
    it, once per env."""
    calls = []
    monkeypatch.setattr(native_ffi, "register", lambda backend: calls.append(backend) or None)
    env = make_env("FetchReach", "mujoco")
    assert calls == []
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    jax.jit(env.step)(state, np.zeros(4, np.float32))
    assert calls == [env.backend]
    assert env.backend.ffi_task is None  # (the stub's answer: the callback ran)
