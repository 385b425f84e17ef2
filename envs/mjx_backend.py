"""The ``mjx`` backend: MuJoCo MJX, jittable end to end (the GPU path).

It steps the MJX-edited scene (``scene.load_model(task, "mjx")``); the task logic, the settling
and the reset template are the same as the native backend's (``physics.Setup``).

On CPU, XLA's fusion emitters fuse MJX's kinematic tree into fusions whose recomputation grows
with the batch; ``rdher_jax.envs.CPU_XLA_FLAGS`` lists the flags that avoid it (set them in
``XLA_FLAGS`` before JAX starts). MJX on CPU is for correctness checks, not for training.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .notices import quiet_mjx

quiet_mjx()
from mujoco import mjx  # noqa: E402
from mujoco.mjx._src import support  # noqa: E402

from .physics import MOCAP_QUAT_DELTA, N_SUBSTEPS, RAW_SIZE, RAW_SLICES, Setup  # noqa: E402


class MjxBackend:
    """Physics interface ``reset`` / ``step`` over ``mjx.Data``."""

    name = "mjx"

    def __init__(self, setup: Setup):
        self.setup = setup
        self.model = mjx.put_model(setup.model)
        self.data0 = mjx.put_data(setup.model, setup.reset_data)

    def _site_vel(self, d: mjx.Data, site: int):
        body = int(self.setup.model.site_bodyid[site])
        jacp, jacr = support.jac(self.model, d, d.site_xpos[site], body)
        return jacp.T @ d.qvel, jacr.T @ d.qvel

    def _readout(self, d: mjx.Data) -> jax.Array:
        s = self.setup
        parts = {
            "grip_pos": d.site_xpos[s.grip_site],
            "grip_velp": self._site_vel(d, s.grip_site)[0],
            "finger_qpos": d.qpos[s.finger_qposadr],
            "finger_qvel": d.qvel[s.finger_dofadr],
        }
        if s.spec.has_object:
            velp, velr = self._site_vel(d, s.object_site)
            parts.update(
                obj_pos=d.site_xpos[s.object_site],
                obj_xmat=d.site_xmat[s.object_site].reshape(9),
                obj_velp=velp,
                obj_velr=velr,
            )
        raw = jnp.zeros(RAW_SIZE, jnp.float32)
        for k, x in parts.items():
            raw = raw.at[RAW_SLICES[k]].set(x.astype(jnp.float32))
        return raw

    def reset(self, qpos: jax.Array, qvel: jax.Array):
        d = self.data0.replace(qpos=qpos.astype(self.data0.qpos.dtype),
                               qvel=qvel.astype(self.data0.qvel.dtype))
        d = mjx.forward(self.model, d)
        return d, self._readout(d)

    def step(self, d: mjx.Data, delta: jax.Array, grip: jax.Array):
        s = self.setup
        gb = s.gripper_body
        d = d.replace(
            mocap_pos=d.mocap_pos.at[0].set(d.xpos[gb] + delta),
            mocap_quat=d.mocap_quat.at[0].set(d.xquat[gb] + jnp.asarray(MOCAP_QUAT_DELTA)),
        )
        if len(s.act_qposadr):
            d = d.replace(ctrl=d.qpos[s.act_qposadr] + grip)

        def substep(d, _):
            return mjx.step(self.model, d), None

        d, _ = jax.lax.scan(substep, d, None, length=N_SUBSTEPS)
        if s.spec.block_gripper:
            d = d.replace(qpos=d.qpos.at[np.asarray(s.finger_qposadr)].set(0.0))
            d = mjx.forward(self.model, d)
        return d, self._readout(d)
