"""What both physics backends share: the gymnasium-robotics ``_env_setup`` run natively once,
the reset template, the ids the task logic needs, and the layout of the raw physics readout.

A task's constants are the registry's (``registry.TASKS``); a moving-goal task runs on the
scene and setup of the task it is modelled on (``TaskSpec.scene_name``).

A backend turns (physics state, mocap delta, finger command) into (physics state, raw readout).
The raw readout is a flat float32 vector with the quantities the observation is built from; the
observation itself is assembled once, in JAX, by ``fetch``.
"""

from __future__ import annotations

import mujoco
import numpy as np

from .registry import TaskSpec, task_spec
from .scene import load_model

N_SUBSTEPS = 20
GRIPPER_BODY = "robot0:gripper_link"
GRIP_SITE = "robot0:grip"
OBJECT_SITE = "object0"
OBJECT_JOINT = "object0:joint"
FINGER_JOINTS = ("robot0:r_gripper_finger_joint", "robot0:l_gripper_finger_joint")
MOCAP_QUAT_DELTA = np.array([1.0, 0.0, 1.0, 0.0])

# Raw readout layout: name -> (offset, size).
RAW_FIELDS = (
    ("grip_pos", 3),
    ("grip_velp", 3),  # Jacobian(grip site) @ qvel, not yet scaled by dt
    ("obj_pos", 3),
    ("obj_xmat", 9),
    ("obj_velp", 3),
    ("obj_velr", 3),
    ("finger_qpos", 2),  # (right, left): gymnasium's robot_get_obs order
    ("finger_qvel", 2),
)
RAW_SLICES = {}
_o = 0
for _name, _n in RAW_FIELDS:
    RAW_SLICES[_name] = slice(_o, _o + _n)
    _o += _n
RAW_SIZE = _o


def _set_joint_qpos(m: mujoco.MjModel, d: mujoco.MjData, name: str, value) -> None:
    j = m.joint(name)
    n = {0: 7, 1: 4}.get(int(j.type[0]), 1)
    d.qpos[j.qposadr[0] : j.qposadr[0] + n] = value


def _dof_chain(m: mujoco.MjModel, body: int) -> np.ndarray:
    """Dofs whose motion moves ``body``, walked as ``mj_jac`` walks them."""
    while body > 0 and m.body_dofnum[body] == 0:
        body = m.body_parentid[body]
    if body == 0:
        return np.zeros(0, np.int64)
    chain = []
    da = m.body_dofadr[body] + m.body_dofnum[body] - 1
    while da >= 0:
        chain.append(da)
        da = m.dof_parentid[da]
    return np.array(chain, np.int64)


def state_offsets(m: mujoco.MjModel) -> dict[str, int]:
    """Offsets of the components inside an mjSTATE_INTEGRATION vector, in MuJoCo's order."""
    order = ["TIME", "QPOS", "QVEL", "ACT", "WARMSTART", "CTRL", "QFRC_APPLIED", "XFRC_APPLIED",
             "EQ_ACTIVE", "MOCAP_POS", "MOCAP_QUAT", "USERDATA", "PLUGIN"]
    off, out = 0, {}
    for c in order:
        out[c] = off
        off += mujoco.mj_stateSize(m, getattr(mujoco.mjtState, "mjSTATE_" + c))
    assert off == mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION)
    return out


class Setup:
    """The task's model after gymnasium-robotics' ``_env_setup``, run once in native MuJoCo.

    ``task`` is a task name or a ``TaskSpec`` (``make_env`` passes one to override its goal
    speed); the model is that of ``spec.scene_name``.

    Attributes used by the backends and the task logic:
      model: the MjModel with the mocap weld reset (``reset_mocap_welds``), as gymnasium's.
      init_qpos, init_qvel: float64 state after the 10 settling steps.
      reset_data: an MjData after ``mj_resetData`` + the settled qpos/qvel, as ``_reset_sim``
        leaves it before the object is placed (warm start, ctrl, mocap back to defaults).
      initial_gripper_xpos, height_offset: for goal sampling.
    """

    def __init__(self, task: str | TaskSpec, variant: str = "original"):
        self.spec = task if isinstance(task, TaskSpec) else task_spec(task)
        self.variant = variant
        m = load_model(self.spec.scene_name, variant)
        d = mujoco.MjData(m)
        # _env_setup
        for name, value in self.spec.initial_qpos.items():
            _set_joint_qpos(m, d, name, value)
        for i in range(m.neq):
            if m.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                m.eq_data[i, :7] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        mujoco.mj_forward(m, d)
        grip_site = m.site(GRIP_SITE).id
        target = np.array([-0.498, 0.005, -0.431 + self.spec.gripper_extra_height])
        d.mocap_pos[0] = target + d.site_xpos[grip_site]
        d.mocap_quat[0] = [1.0, 0.0, 1.0, 0.0]
        for _ in range(10):
            mujoco.mj_step(m, d, nstep=N_SUBSTEPS)
        self.initial_gripper_xpos = d.site_xpos[grip_site].copy()
        self.height_offset = (
            float(d.site_xpos[m.site(OBJECT_SITE).id][2]) if self.spec.has_object else 0.0
        )
        self.init_qpos = d.qpos.copy()
        self.init_qvel = d.qvel.copy()
        # _reset_sim before the object is placed
        rd = mujoco.MjData(m)
        mujoco.mj_resetData(m, rd)
        rd.qpos[:] = self.init_qpos
        rd.qvel[:] = self.init_qvel
        self.reset_data = rd

        self.model = m
        self.dt = N_SUBSTEPS * float(m.opt.timestep)
        self.grip_site = grip_site
        self.gripper_body = m.body(GRIPPER_BODY).id
        self.finger_qposadr = np.array([m.joint(n).qposadr[0] for n in FINGER_JOINTS])
        self.finger_dofadr = np.array([m.joint(n).dofadr[0] for n in FINGER_JOINTS])
        # Position actuators: ctrl = qpos of the actuated joint + command (ctrl_set_action).
        self.act_qposadr = np.array(
            [m.jnt_qposadr[m.actuator_trnid[i, 0]] for i in range(m.nu)], np.int64
        )
        assert all(m.actuator_biastype[i] != 0 for i in range(m.nu))
        if self.spec.has_object:
            self.object_site = m.site(OBJECT_SITE).id
            self.object_qposadr = int(m.joint(OBJECT_JOINT).qposadr[0])
        else:
            self.object_site = -1
            self.object_qposadr = -1
        self.grip_chain = _dof_chain(m, int(m.site_bodyid[grip_site]))
        self.object_chain = (
            _dof_chain(m, int(m.site_bodyid[self.object_site])) if self.spec.has_object else None
        )
