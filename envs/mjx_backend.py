"""The ``mjx`` and ``warp`` backends: MuJoCo MJX, jittable end to end (the GPU paths).

``mjx`` steps MJX's JAX implementation on the MJX-edited scene (``scene.load_model(task,
"mjx")``); ``warp`` steps MJX's Warp implementation (``mjx.put_model(m, impl="warp")``, MuJoCo
Warp's kernels called from JAX through XLA FFI) on the Warp-edited scene (``"warp"``). Both are
``MjxBackend``: the mocap and finger commands, the substeps and the raw readout are written once
here; the task logic, the settling and the reset template are the native backend's
(``physics.Setup``).

On CPU, XLA's fusion emitters fuse MJX's kinematic tree into fusions whose recomputation grows
with the batch; ``rdher_jax.envs.CPU_XLA_FLAGS`` lists the flags that avoid it (set them in
``XLA_FLAGS`` before JAX starts). MJX's JAX implementation on CPU is for correctness checks, not
for training; Warp has CPU kernels and trains on a CPU too (docs/performance.md).

Warp's contacts and constraint rows live in buffers of fixed capacity: ``naconmax`` contacts
shared by all the envs (worlds) of one batched call and ``njmax`` constraint rows per env.
``WarpBackend`` sizes both from the scene (``contact_capacity``) and the number of envs it is
built for. The contact bound is a true upper bound (each pair's most contacts, summed), so the
contact buffer cannot overflow; it must not: on a CPU, Warp 1.14's convex narrowphase crashes
the process (segmentation fault) when it does. The row bound assumes every contact active at
once. A step that needs more rows than ``njmax`` sets a bit of Warp's per-env overflow mask,
which stays set until the env's next reset. ``WarpBackend.overflow(data)`` reads it, and
``envs.rollout`` raises on it at the end of every rollout (``WarpBackend.check``): a dropped
constraint is an error, never silent.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from . import quiet_warp, warp_available
from .notices import quiet_mjx

quiet_mjx()
from mujoco import mjx  # noqa: E402
from mujoco.mjx._src import support  # noqa: E402

from .physics import MOCAP_QUAT_DELTA, N_SUBSTEPS, RAW_SIZE, RAW_SLICES, Setup  # noqa: E402


class MjxBackend:
    """Physics interface ``reset`` / ``step`` over ``mjx.Data`` (MJX's JAX implementation)."""

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


# ---------------------------------------------------------------------------------------------
# Warp
# ---------------------------------------------------------------------------------------------

# Contacts one pair of geoms can make at most, by MuJoCo's collision functions (a sphere: one
# point; a capsule: two; plane-box and the multi-contact convex pairs: up to four; box-box:
# up to eight). Anything not listed is bounded by eight.
_SPHERE, _CAPSULE = mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE
_MAX_PAIR_CONTACTS = 8


def _pair_contacts(t1: int, t2: int) -> int:
    if _SPHERE in (t1, t2):
        return 1
    if t1 == t2 == _CAPSULE:
        return 2
    return _MAX_PAIR_CONTACTS


@dataclasses.dataclass(frozen=True)
class ContactCapacity:
    """Warp's buffer sizes for one env of a scene.

    Attributes:
      pairs: geom pairs that can collide (MJX's enumeration, explicit pairs included).
      contacts: contacts the env can make at most (each pair's most, summed); also bounds the
        broadphase's candidate pairs.
      rows: constraint rows the env can need at most: every contact's rows (pyramidal cones:
        2 * (condim - 1), one for condim 1), the equality constraints' and one per limited
        joint and per dof with friction loss.
    """

    pairs: int
    contacts: int
    rows: int


def contact_capacity(m: mujoco.MjModel) -> ContactCapacity:
    """Upper bounds of one env's contacts and constraint rows on the model ``m``."""
    from mujoco.mjx._src import collision_driver

    pairs = list(collision_driver.geom_pairs(m))
    contacts, rows = 0, 0
    for g1, g2, ip in pairs:
        n = _pair_contacts(int(m.geom_type[g1]), int(m.geom_type[g2]))
        condim = int(m.pair_dim[ip]) if ip != -1 else int(max(m.geom_condim[[g1, g2]]))
        contacts += n
        rows += n * (1 if condim == 1 else 2 * (condim - 1))
    eq_rows = {int(mujoco.mjtEq.mjEQ_WELD): 6, int(mujoco.mjtEq.mjEQ_CONNECT): 3}
    rows += sum(eq_rows.get(int(t), 1) for t in m.eq_type)
    rows += int(m.jnt_limited.sum()) + int((m.dof_frictionloss > 0).sum())
    rows += int(m.tendon_limited.sum()) if m.ntendon else 0
    return ContactCapacity(pairs=len(pairs), contacts=max(contacts, len(pairs)), rows=rows)


class WarpBackend(MjxBackend):
    """``MjxBackend`` stepping MJX's Warp implementation (``impl="warp"``).

    ``worlds`` is the most envs any one batched call will step (all of them: a sweep's runs
    times its envs); the shared contact buffer is sized for it. ``capacity`` replaces the
    scene's ``contact_capacity`` (tests use it to provoke an overflow).
    """

    name = "warp"

    def __init__(self, setup: Setup, worlds: int = 1024, capacity: ContactCapacity | None = None):
        why = warp_available()
        if why:
            raise RuntimeError(why)
        quiet_warp()
        self.setup = setup
        m = setup.model
        self.capacity = capacity or contact_capacity(m)
        self.worlds = int(worlds)
        self.naconmax = self.capacity.contacts * self.worlds
        self.njmax = self.capacity.rows
        self.model = mjx.put_model(m, impl="warp")
        d = mjx.make_data(m, impl="warp", naconmax=self.naconmax, njmax=self.njmax)
        rd = setup.reset_data
        # The reset template's state (what put_data carries for the jax implementation).
        self.data0 = d.replace(
            qpos=jnp.asarray(rd.qpos, d.qpos.dtype), qvel=jnp.asarray(rd.qvel, d.qvel.dtype),
            ctrl=jnp.asarray(rd.ctrl, d.ctrl.dtype),
            mocap_pos=jnp.asarray(rd.mocap_pos, d.mocap_pos.dtype),
            mocap_quat=jnp.asarray(rd.mocap_quat, d.mocap_quat.dtype),
            qacc_warmstart=jnp.asarray(rd.qacc_warmstart, d.qacc_warmstart.dtype),
        )

    @staticmethod
    def overflow(d: mjx.Data) -> jax.Array:
        """Warp's overflow bits of each env since its reset (``OverflowType``); 0: none."""
        return d._impl.overflow

    def check(self, d: mjx.Data) -> None:
        """Raise, at run time and from jitted code, if any env of ``d`` (a batch or one env)
        overflowed Warp's contact or constraint buffers since its reset."""
        bits = jax.lax.reduce(jnp.ravel(self.overflow(d)).astype(jnp.int32), np.int32(0),
                              jax.lax.bitwise_or, (0,))
        jax.debug.callback(_raise_on_overflow, bits)


def _raise_on_overflow(bits) -> None:
    if int(bits):
        from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType

        raise RuntimeError(
            f"backend=warp: the physics ran out of buffer ({OverflowType(int(bits))!r}): "
            f"contacts or constraint rows were dropped; the buffers are sized from the scene "
            f"(envs/mjx_backend.contact_capacity) and the worlds make_env was given")
