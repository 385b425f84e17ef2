"""The ``mjx`` backend on CPU, at small batch: the same task logic as the native backend, with
MJX physics on the MJX-edited scene.

Tolerance, measured (``experiments/results/scene_edits.md``, section MJX vs native): over 50
random actions the gripper of MJX and of native MuJoCo on the same edited scene drift apart by
up to 1.3 cm. The cause is known: native MuJoCo 3.11 subtracts the weld's Jdot*qvel term from
the mocap weld's reference acceleration and MJX 3.11 does not; with that term removed from the
native step the two agree to 1e-15 (float64). Random actions rarely touch the object, so its
deviation stays near float32 round-off. We assert 2.5 cm for the gripper and the object, and
exact agreement of the reset (same state, before any dynamics).

Each task compiles MJX's reset and step (one to three minutes each on 2 cores), so all are
marked slow (``python -m pytest -m slow``); the default suite checks the MJX scene itself
(tests/test_scene.py: ``mjx.put_model`` takes the edited scene and only it).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rdher_jax import make_env

GRIP_TOL = 0.025
OBJ_TOL = 0.025


@pytest.mark.slow
@pytest.mark.parametrize("task", ["FetchPush", "FetchReach", "FetchSlide", "FetchPickAndPlace"])
def test_mjx_matches_native_on_the_edited_scene(task):
    n, T = 2, 50
    mjx_env = make_env(task, "mjx", auto_reset=False)
    nat_env = make_env(task, "mujoco", scene="mjx", auto_reset=False)
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    a = jax.random.uniform(jax.random.PRNGKey(1), (T, n, 4), minval=-1.0, maxval=1.0)

    def rollout(env):
        def step(s, act):
            s = jax.vmap(env.step)(s, act)
            return s, (s.obs["observation"], s.reward, s.info["is_success"])

        s0 = jax.vmap(env.reset)(keys)
        _, out = jax.lax.scan(step, s0, a)
        return s0.obs, out

    (m0, (mo, mr, ms)), (n0, (no, nr, ns)) = jax.jit(lambda: rollout(mjx_env))(), jax.jit(
        lambda: rollout(nat_env))()
    for k in m0:
        np.testing.assert_allclose(m0[k], n0[k], atol=1e-5)
    mo, no = np.asarray(mo), np.asarray(no)
    assert np.all(np.isfinite(mo))
    assert mo.shape == (T, n, mjx_env.obs_size)
    grip = np.abs(mo[..., :3] - no[..., :3]).max()
    assert grip < GRIP_TOL, grip
    if mjx_env.spec.has_object:
        obj = np.abs(mo[..., 3:6] - no[..., 3:6]).max()
        assert obj < OBJ_TOL, obj
    assert set(np.unique(np.asarray(mr))) <= {-1.0, 0.0}
    # Reward and success are the same function of the observation on both backends.
    np.testing.assert_array_equal(np.asarray(mr) + 1.0, np.asarray(ms))
    np.testing.assert_array_equal(np.asarray(nr) + 1.0, np.asarray(ns))


@pytest.mark.slow
def test_trainer_runs_unchanged_on_mjx(tmp_path):
    """The trainer's epoch, unchanged, on the mjx backend (the GPU path), at a tiny size: one
    cycle of 16 envs (a GPU run's batched path, small enough for a CPU)."""
    from rdher_jax import train as train_mod
    from rdher_jax.config import Config, resolve

    cfg = resolve(Config(env="FetchReach", backend="mjx", epochs=1, n_cycles=1, num_envs=16,
                         n_batches=2, batch_size=16, buffer_size=2000, n_test_rollouts=2,
                         hidden=16, run_dir=str(tmp_path / "run"), progress=False))
    out = train_mod.train(cfg)
    assert np.isfinite(float(out.rows[0]["critic_loss"]))
    assert 0.0 <= float(out.rows[0]["test_success"]) <= 1.0
    assert jnp.isfinite(out.rows[0]["actor_loss"])
    assert int(float(out.rows[0]["env_steps"])) == 16 * 50
