"""The ``mujoco`` backend: native MuJoCo C, a batch of simulations stepped on host threads by
``mjbatch``, called from jitted code through one ``jax.pure_callback`` per batched env step.

The backend is pure: the whole float64 mjSTATE_INTEGRATION vector of each simulation (plus the
gripper body pose that the next action is applied to) travels in the JAX state as its raw bits
(a uint32 array), and every call loads it into mjbatch, steps, and hands the new bits back. So a
state can be copied, checkpointed, vmapped or replayed like any other array, with no float32
rounding of the physics: from the same state and actions the trajectory is gymnasium-robotics'
(observations agree to float32 round-off; tests/test_envs.py).

A reset from float64 host arrays (``reset_exact``, which ``FetchEnv.reset_to`` uses for numpy
input) runs on the host without a callback and keeps them exactly; ``reset`` takes float32.

Under ``jax.vmap`` the callback is made once for the whole batch (``vmap_method="broadcast_all"``),
so one env step of N envs costs one host round trip, whatever N.
"""

from __future__ import annotations

import os
import threading

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from .physics import MOCAP_QUAT_DELTA, N_SUBSTEPS, RAW_SIZE, RAW_SLICES, Setup, state_offsets

_REF = 7  # gripper body xpos (3) + xquat (4) that mocap_set_action reads


@struct.dataclass
class NativeState:
    """Float64 physics state of one env, carried as raw bits: (2 * (nstate + 7),) uint32."""

    bits: jax.Array


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross for (..., 3) arrays, written out: bit-identical and 2-3x faster on small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _cpu_threads() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


class NativeBackend:
    """Batched native stepping behind the physics interface ``reset`` / ``step``."""

    name = "mujoco"

    def __init__(self, setup: Setup, num_threads: int | None = None, physics_call: str = "ffi"):
        import mjbatch  # noqa: F401  (fail early with a clear ImportError)

        self.setup = setup
        m = setup.model
        self.nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION)
        self.width = self.nstate + _REF
        self.off = state_offsets(m)
        self.num_threads = num_threads or _cpu_threads()
        row = np.empty(self.nstate)
        mujoco.mj_getState(m, setup.reset_data, row, mujoco.mjtState.mjSTATE_INTEGRATION)
        self.template = row
        self._batches: dict[int, tuple] = {}
        self._lock = threading.Lock()
        qp, qv = self.off["QPOS"], self.off["QVEL"]
        self._qpos = slice(qp, qp + m.nq)
        self._qvel = slice(qv, qv + m.nv)
        if physics_call not in ("ffi", "callback"):
            raise ValueError(f"physics_call must be 'ffi' or 'callback', got {physics_call!r}")
        # (The handlers are registered for XLA:CPU; where JAX's default device is an
        # accelerator the callback, which runs anywhere, stays.)
        self._use_ffi = physics_call == "ffi" and jax.default_backend() == "cpu"
        self._ffi_task: int | None = None
        self._ffi_resolved = False
        self._ffi_lock = threading.Lock()

    @property
    def ffi_task(self) -> int | None:
        """The task's id with the FFI handlers (cacheable programs, bit-identical results), or
        None: the pure_callback (asked for, or the handlers could not be built). Resolved on
        first use, when a program that steps the env is first traced, not when the env is
        built: on a machine that never ran the project the handlers' C++ build (about 2.5 s,
        started in the background by the CLIs) then overlaps building and tracing the
        programs that do not step it."""
        if not self._ffi_resolved:
            with self._ffi_lock:
                if not self._ffi_resolved:
                    from . import native_ffi

                    self._ffi_task = native_ffi.register(self) if self._use_ffi else None
                    self._ffi_resolved = True
        return self._ffi_task

    # ------------------------------------------------------------------ host side
    def _batch(self, n: int):
        if n not in self._batches:
            import mjbatch

            # Block-gripper tasks observe current kinematics (gymnasium-robotics runs mj_forward
            # after the step), so their batch ends every step with a forward on the worker.
            b = mjbatch.Batch(self.setup.model, n, num_threads=min(self.num_threads, n),
                              forward=self.setup.spec.block_gripper)
            views = {f: b.bind(f) for f in
                     ("state", "site_xpos", "site_xmat", "xpos", "xquat", "cdof", "subtree_com")}
            self._batches[n] = (b, views)
        return self._batches[n]

    def _site_vel(self, v, states, site, chain):
        """Site linear and angular velocity, Jacobian @ qvel, computed as ``mj_jacSite`` does."""
        m = self.setup.model
        root = m.body_rootid[m.site_bodyid[site]]
        offset = v["site_xpos"][:, site] - v["subtree_com"][:, root]
        cd = v["cdof"][:, chain]  # (B, k, 6): rotational [:3], translational [3:]
        qvel = states[:, self._qvel][:, chain]
        jp = cd[..., 3:] + _cross(cd[..., :3], offset[:, None, :])
        velp = np.einsum("bkx,bk->bx", jp, qvel)
        velr = np.einsum("bkx,bk->bx", cd[..., :3], qvel)
        return velp, velr

    def _readout(self, v, states):
        s = self.setup
        n = states.shape[0]
        raw = np.zeros((n, RAW_SIZE))
        raw[:, RAW_SLICES["grip_pos"]] = v["site_xpos"][:, s.grip_site]
        raw[:, RAW_SLICES["grip_velp"]] = self._site_vel(v, states, s.grip_site, s.grip_chain)[0]
        if s.spec.has_object:
            raw[:, RAW_SLICES["obj_pos"]] = v["site_xpos"][:, s.object_site]
            raw[:, RAW_SLICES["obj_xmat"]] = v["site_xmat"][:, s.object_site]
            velp, velr = self._site_vel(v, states, s.object_site, s.object_chain)
            raw[:, RAW_SLICES["obj_velp"]] = velp
            raw[:, RAW_SLICES["obj_velr"]] = velr
        raw[:, RAW_SLICES["finger_qpos"]] = states[:, self._qpos][:, s.finger_qposadr]
        raw[:, RAW_SLICES["finger_qvel"]] = states[:, self._qvel][:, s.finger_dofadr]
        ref = np.concatenate(
            [v["xpos"][:, s.gripper_body], v["xquat"][:, s.gripper_body]], axis=-1
        )
        return raw, ref

    def _pack(self, states, ref, lead):
        full = np.ascontiguousarray(np.concatenate([states, ref], axis=-1))
        bits = full.view(np.uint32).reshape(*lead, 2 * self.width)
        return bits

    def _forward_and_pack(self, b, v, states, lead):
        v["state"][:] = states
        b.forward()
        raw, ref = self._readout(v, states)
        return self._pack(states, ref, lead), raw.astype(np.float32).reshape(*lead, RAW_SIZE)

    def host_reset(self, qpos, qvel):
        """Reset a batch from float32 qpos/qvel (what the JAX side carries)."""
        lead = qpos.shape[:-1]
        qpos = np.asarray(qpos, np.float64).reshape(-1, qpos.shape[-1])
        qvel = np.asarray(qvel, np.float64).reshape(-1, qvel.shape[-1])
        states = np.repeat(self.template[None], qpos.shape[0], axis=0)
        # Entries the caller left at the settled state (equal to it in float32) keep its float64
        # value, so a reset is gymnasium-robotics' settled state exactly, but for what the caller
        # changed (the sampled object position).
        for sl, new in ((self._qpos, qpos), (self._qvel, qvel)):
            old = states[:, sl]
            states[:, sl] = np.where(new == old.astype(np.float32), old, new)
        return self._load(states, lead)

    def host_reset_exact(self, qpos: np.ndarray, qvel: np.ndarray):
        """Reset a batch from float64 qpos/qvel, taken bit for bit."""
        lead = qpos.shape[:-1]
        states = np.repeat(self.template[None], int(np.prod(lead, dtype=np.int64)), axis=0)
        states[:, self._qpos] = np.asarray(qpos, np.float64).reshape(-1, qpos.shape[-1])
        states[:, self._qvel] = np.asarray(qvel, np.float64).reshape(-1, qvel.shape[-1])
        return self._load(states, lead)

    def _load(self, states, lead):
        with self._lock:
            b, v = self._batch(states.shape[0])
            return self._forward_and_pack(b, v, states, lead)

    def host_step(self, bits, delta, grip, clock=None):
        """One env step of a batch. ``clock(part)``, if given, is called as each part ends
        ("unpack", "step", "readout", "pack"): the env benchmark times the parts with it."""
        mark = clock or (lambda part: None)
        s, off = self.setup, self.off
        lead = delta.shape[:-1]
        full = np.ascontiguousarray(bits).reshape(-1, 2 * self.width).view(np.float64)
        states = full[:, : self.nstate].copy()
        ref = full[:, self.nstate :]
        n = states.shape[0]
        delta = np.asarray(delta).reshape(n, 3).astype(np.float64)
        # mocap_set_action: the mocap goes to the welded body's pose, then moves by the delta.
        states[:, off["MOCAP_POS"] : off["MOCAP_POS"] + 3] = ref[:, :3] + delta
        states[:, off["MOCAP_QUAT"] : off["MOCAP_QUAT"] + 4] = ref[:, 3:7] + MOCAP_QUAT_DELTA
        if len(s.act_qposadr):
            # ctrl_set_action for position actuators: ctrl = qpos of the joint + command.
            g = np.asarray(grip).reshape(n, 1).astype(np.float64)
            ctrl = states[:, self._qpos][:, s.act_qposadr] + g
            states[:, off["CTRL"] : off["CTRL"] + len(s.act_qposadr)] = ctrl
        mark("unpack")
        with self._lock:
            b, v = self._batch(n)
            v["state"][:] = states
            b.step(nstep=N_SUBSTEPS)
            states = v["state"].copy()
            mark("step")
            if s.spec.block_gripper:
                # _step_callback: fingers held closed, then mj_forward. The batch already ran the
                # forward (forward=True); zeroing the finger joints afterwards moves only the
                # finger bodies, which no observed site or gripper-body pose depends on, so a
                # second forward would change the readout by round-off only (the conformance
                # tests hold it to gymnasium-robotics at 1e-6).
                states[:, self._qpos.start + s.finger_qposadr] = 0.0
            # PickAndPlace: no forward; kinematics stay one substep behind qpos, as in gymnasium.
            raw, ref = self._readout(v, states)
            mark("readout")
            out = self._pack(states, ref, lead), raw.astype(np.float32).reshape(*lead, RAW_SIZE)
            mark("pack")
            return out

    # ------------------------------------------------------------------ JAX side
    def _shapes(self, lead):
        return (
            jax.ShapeDtypeStruct((*lead, 2 * self.width), jnp.uint32),
            jax.ShapeDtypeStruct((*lead, RAW_SIZE), jnp.float32),
        )

    def reset(self, qpos: jax.Array, qvel: jax.Array) -> tuple[NativeState, jax.Array]:
        if self.ffi_task is not None:
            from . import native_ffi

            bits, raw = native_ffi.reset_call(
                self.ffi_task, self._shapes(qpos.shape[:-1]),
                jnp.asarray(qpos, jnp.float32), jnp.asarray(qvel, jnp.float32))
            return NativeState(bits), raw
        bits, raw = jax.pure_callback(
            self.host_reset, self._shapes(qpos.shape[:-1]), qpos, qvel,
            vmap_method="broadcast_all",
        )
        return NativeState(bits), raw

    def reset_exact(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[NativeState, jax.Array]:
        """``reset`` from float64 host arrays, kept exactly (JAX itself runs without x64, so a
        float64 value cannot pass through ``reset``). Runs on the host, outside any trace."""
        bits, raw = self.host_reset_exact(np.asarray(qpos, np.float64),
                                          np.asarray(qvel, np.float64))
        return NativeState(jnp.asarray(bits)), jnp.asarray(raw)

    def step(self, state: NativeState, delta: jax.Array, grip: jax.Array):
        if self.ffi_task is not None:
            from . import native_ffi

            bits, raw = native_ffi.step_call(
                self.ffi_task, self._shapes(delta.shape[:-1]), state.bits,
                jnp.asarray(delta, jnp.float32), jnp.asarray(grip, jnp.float32))
            return NativeState(bits), raw
        bits, raw = jax.pure_callback(
            self.host_step, self._shapes(delta.shape[:-1]), state.bits, delta, grip,
            vmap_method="broadcast_all",
        )
        return NativeState(bits), raw

    def qpos_qvel(self, state: NativeState) -> tuple[np.ndarray, np.ndarray]:
        """Host-side float64 qpos and qvel of (a batch of) states, for tests and tools."""
        full = np.asarray(state.bits).reshape(-1, 2 * self.width).view(np.float64)
        lead = np.shape(state.bits)[:-1]
        return (full[:, self._qpos].reshape(*lead, -1), full[:, self._qvel].reshape(*lead, -1))
