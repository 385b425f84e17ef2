"""The Fetch scenes: original and MJX-edited variants load, match where they must, and MJX takes
the edited one."""

from __future__ import annotations

import functools

import mujoco
import numpy as np
import pytest
from rdher_jax.envs import scene
from rdher_jax.envs.registry import GYMNASIUM_TASK_NAMES

TASKS = GYMNASIUM_TASK_NAMES
ENV_BODIES = ("object0", "robot0:gripper_link", "robot0:mocap")
ENV_JOINTS = (
    "robot0:l_gripper_finger_joint",
    "robot0:r_gripper_finger_joint",
    "robot0:slide0",
    "robot0:slide1",
    "robot0:slide2",
    "object0:joint",
)
ENV_SITES = ("robot0:grip", "object0", "target0")


@functools.cache
def model(task: str, variant: str) -> mujoco.MjModel:
    return scene.load_model(task, variant)


def _has(m: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> bool:
    return mujoco.mj_name2id(m, obj, name) != -1


@pytest.mark.parametrize("task", TASKS)
def test_mjx_variant_keeps_what_the_env_uses(task: str) -> None:
    orig, edit = model(task, "original"), model(task, "mjx")
    assert (edit.nq, edit.nv, edit.nu, edit.nmocap) == (orig.nq, orig.nv, orig.nu, orig.nmocap)
    assert edit.opt.timestep == orig.opt.timestep == 0.002
    for field in ("solver", "iterations", "ls_iterations", "tolerance", "cone", "integrator"):
        assert getattr(edit.opt, field) == getattr(orig.opt, field), field
    np.testing.assert_array_equal(edit.dof_damping, orig.dof_damping)
    np.testing.assert_array_equal(edit.dof_armature, orig.dof_armature)
    np.testing.assert_array_equal(edit.eq_solref, orig.eq_solref)
    np.testing.assert_array_equal(edit.body_mass, orig.body_mass)
    for obj, names in (
        (mujoco.mjtObj.mjOBJ_BODY, ENV_BODIES),
        (mujoco.mjtObj.mjOBJ_JOINT, ENV_JOINTS),
        (mujoco.mjtObj.mjOBJ_SITE, ENV_SITES),
    ):
        for name in names:
            if "object0" in name and not _has(orig, obj, name):
                continue  # Reach has no object
            assert _has(orig, obj, name) and _has(edit, obj, name), name


@pytest.mark.parametrize("task", TASKS)
def test_put_model_takes_the_mjx_variant_only(task: str) -> None:
    from mujoco import mjx

    mjx.put_model(model(task, "mjx"))
    with pytest.raises(NotImplementedError):
        mjx.put_model(model(task, "original"))


@pytest.mark.parametrize("task", TASKS)
def test_few_collision_pairs_and_no_mesh_margin(task: str) -> None:
    from mujoco.mjx._src import collision_driver

    m = model(task, "mjx")
    pairs = list(collision_driver.geom_pairs(m))
    assert len(pairs) <= 14
    mesh = mujoco.mjtGeom.mjGEOM_MESH
    for g1, g2, ip in pairs:
        if mesh in m.geom_type[[g1, g2]]:
            margin = m.pair_margin[ip] if ip != -1 else m.geom_margin[[g1, g2]].sum()
            assert margin == 0


def test_slide_puck_is_a_prism_with_the_cylinder_inertia() -> None:
    orig, edit = model("FetchSlide", "original"), model("FetchSlide", "mjx")
    bo, be = orig.body("object0").id, edit.body("object0").id
    assert edit.body_mass[be] == orig.body_mass[bo] == 2.0
    np.testing.assert_allclose(edit.body_inertia[be], orig.body_inertia[bo], rtol=1e-12)
    np.testing.assert_allclose(edit.body_ipos[be], orig.body_ipos[bo], atol=1e-12)
    np.testing.assert_allclose(edit.body_iquat[be], orig.body_iquat[bo], atol=1e-12)
    go, ge = orig.geom("object0").id, edit.geom("object0").id
    assert orig.geom_type[go] == mujoco.mjtGeom.mjGEOM_CYLINDER
    assert edit.geom_type[ge] == mujoco.mjtGeom.mjGEOM_MESH
    mesh = edit.geom_dataid[ge]
    assert edit.mesh_vertnum[mesh] == 2 * scene.PUCK_SIDES
    np.testing.assert_array_equal(edit.geom_friction[ge], orig.geom_friction[go])
    assert edit.geom_condim[ge] == orig.geom_condim[go]


def _settle(m: mujoco.MjModel, n: int = 200) -> np.ndarray:
    """Gripper (mocap) pulled down and sideways from the start pose; qpos after n substeps."""
    d = mujoco.MjData(m)
    m.eq_data[0, :7] = [0, 0, 0, 0, 0, 0, 1]  # as gymnasium-robotics' reset_mocap_welds
    mujoco.mj_forward(m, d)
    d.mocap_pos[0] = d.xpos[m.body("robot0:gripper_link").id] + [0.6, 0.2, -0.4]
    d.mocap_quat[0] = [1.0, 0.0, 1.0, 0.0]
    mujoco.mj_step(m, d, nstep=n)
    return d.qpos.copy()


@pytest.mark.parametrize("task", ["FetchReach", "FetchPush"])
def test_pruning_keeps_native_dynamics(task: str) -> None:
    # The base pads must reproduce base_link's floor contact: dropping it moves the arm.
    orig = scene.load_model(task)
    pruned = scene.load_edited(task, ("prune",))
    spec = scene.load_spec(task)
    scene.prune_collisions(spec, task, base_pads=False)
    dropped = spec.compile()
    ref = _settle(orig)
    np.testing.assert_allclose(_settle(pruned), ref, rtol=0, atol=1e-10)
    assert np.abs(_settle(dropped) - ref).max() > 1e-6


def test_unknown_variant_and_edit_raise() -> None:
    with pytest.raises(ValueError, match="variant"):
        scene.load_model("FetchPush", "mjx-fast")
    with pytest.raises(ValueError, match="edits"):
        scene.load_edited("FetchPush", ("prune", "shrink"))
