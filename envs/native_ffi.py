"""The native backend's step and reset as XLA FFI calls, so the programs that hold them can be
kept in JAX's persistent compilation cache.

A ``jax.pure_callback`` is a pointer into the process that traced it: JAX never writes a program
holding one to its persistent cache, so with the callback every process compiles the trainer's
epoch program again (about 8 s for FetchReach). An FFI call names its handler
(``rdher_physics_step``, registered with XLA in every process that builds a native env) and
its task by an integer id, a hash of the model and of everything the handler reads from it;
a program compiled in one process then runs in another.

The handlers (``native_ffi.cc``) are ``NativeBackend.host_step`` and ``host_reset`` written out
in C++, operation for operation, on the libmujoco that mjbatch steps with: the results are the
callback's, bit for bit (``tests/test_native_ffi.py``), so which path runs never changes a
result. The library is compiled once per machine with the system C++ compiler, against the
installed jaxlib's FFI headers and mujoco's (``ffi_build``); where that fails (no
compiler, say) the backend keeps the callback and says why, once.
``physics_call=callback`` (``make_env``, and the trainer's config) keeps the callback.
"""

from __future__ import annotations

import copy
import ctypes
import hashlib
import threading
import warnings

import jax
import mujoco
import numpy as np

STEP_TARGET = "rdher_physics_step"
RESET_TARGET = "rdher_physics_reset"
# The layout of rdher_register's int64 field array: the enum Field of native_ffi.cc, in order.
FIELDS = (
    "nstate", "off_qpos", "off_qvel", "off_ctrl", "off_mocap_pos", "off_mocap_quat", "nq", "nv",
    "block_gripper", "has_object", "grip_site", "object_site", "gripper_body", "grip_root",
    "object_root", "finger_qpos0", "finger_qpos1", "finger_dof0", "finger_dof1", "num_threads",
    "raw_size", "raw_grip_pos", "raw_grip_velp", "raw_obj_pos", "raw_obj_xmat", "raw_obj_velp",
    "raw_obj_velr", "raw_finger_qpos", "raw_finger_qvel", "n_act", "n_grip_chain",
    "n_object_chain",
)

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failed: str | None = None
# Every registered task's model, a private copy kept for the life of the process: the handlers
# hold a pointer to it, and a compiled program may outlive the env that registered its task.
# An id registers once; a later env with the same id (the same model and layout) reuses it.
_models: dict[int, mujoco.MjModel] = {}


def library() -> ctypes.CDLL | None:
    """The handlers' library, built on first use on this machine and registered with XLA once
    per process; None (with one warning) where it cannot be built."""
    global _lib, _failed
    with _lock:
        if _lib is not None or _failed is not None:
            return _lib
        from . import ffi_build

        try:
            ffi_build.wait()  # a build the trainer started in the background
            lib = ctypes.CDLL(str(ffi_build.build()))
            lib.rdher_register.restype = ctypes.c_int
            lib.rdher_register.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p,
                                           ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p]
            lib.rdher_num_fields.restype = ctypes.c_int64
            if lib.rdher_num_fields() != len(FIELDS):
                raise RuntimeError("the library's field layout differs from native_ffi.py's")
            jax.ffi.register_ffi_target(STEP_TARGET, jax.ffi.pycapsule(lib.RdherPhysicsStep),
                                        platform="cpu")
            jax.ffi.register_ffi_target(RESET_TARGET, jax.ffi.pycapsule(lib.RdherPhysicsReset),
                                        platform="cpu")
        except Exception as e:  # noqa: BLE001 - any failure means: keep the callback
            _failed = f"{type(e).__name__}: {e}"
            warnings.warn(f"native physics stays a pure_callback, whose programs JAX does not "
                          f"cache ({_failed})", RuntimeWarning, stacklevel=3)
            return None
        _lib = lib
        return lib


def register(backend) -> int | None:
    """Register ``backend``'s task with the handlers; returns its id, or None (callback)."""
    lib = library()
    if lib is None:
        return None
    from .physics import RAW_SIZE, RAW_SLICES

    s, m, off = backend.setup, backend.setup.model, backend.off

    def root(site):
        return int(m.body_rootid[m.site_bodyid[site]])

    vals = dict(
        nstate=backend.nstate, off_qpos=off["QPOS"], off_qvel=off["QVEL"], off_ctrl=off["CTRL"],
        off_mocap_pos=off["MOCAP_POS"], off_mocap_quat=off["MOCAP_QUAT"], nq=m.nq, nv=m.nv,
        block_gripper=int(s.spec.block_gripper), has_object=int(s.spec.has_object),
        grip_site=s.grip_site, object_site=s.object_site, gripper_body=s.gripper_body,
        grip_root=root(s.grip_site),
        object_root=root(s.object_site) if s.spec.has_object else -1,
        finger_qpos0=s.finger_qposadr[0], finger_qpos1=s.finger_qposadr[1],
        finger_dof0=s.finger_dofadr[0], finger_dof1=s.finger_dofadr[1],
        num_threads=backend.num_threads, raw_size=RAW_SIZE,
        **{f"raw_{k}": RAW_SLICES[k].start for k in
           ("grip_pos", "grip_velp", "obj_pos", "obj_xmat", "obj_velp", "obj_velr",
            "finger_qpos", "finger_qvel")},
        n_act=len(s.act_qposadr), n_grip_chain=len(s.grip_chain),
        n_object_chain=0 if s.object_chain is None else len(s.object_chain),
    )
    fields = np.array([int(vals[k]) for k in FIELDS], np.int64)
    lists = np.concatenate([np.asarray(s.act_qposadr, np.int64),
                            np.asarray(s.grip_chain, np.int64),
                            np.asarray(s.object_chain if s.object_chain is not None else [],
                                       np.int64)])
    tmpl = np.ascontiguousarray(backend.template, np.float64)
    # The id names everything the handler reads: the compiled model, the layout (which also
    # holds the thread count) and the reset template. A cached program that names it finds
    # the same task in any process that registered an identical one.
    h = hashlib.sha256()
    buf = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    h.update(buf.tobytes())
    for a in (fields, lists, tmpl):
        h.update(a.tobytes())
    task_id = int.from_bytes(h.digest()[:8], "little") & ((1 << 63) - 1)
    lists = np.ascontiguousarray(lists) if len(lists) else np.zeros(1, np.int64)
    with _lock:
        if task_id not in _models:
            own = copy.copy(m)  # a deep copy: later edits to the env's model change nothing
            rc = lib.rdher_register(task_id, ctypes.c_void_p(own._address), fields.ctypes.data,
                                    len(fields), lists.ctypes.data, tmpl.ctypes.data)
            if rc != 0:
                raise RuntimeError("rdher_register rejected the task layout")
            _models[task_id] = own
    return task_id


def step_call(task_id: int, shapes, bits, delta, grip):
    return jax.ffi.ffi_call(STEP_TARGET, shapes, vmap_method="broadcast_all")(
        bits, delta, grip, task_id=np.int64(task_id))


def reset_call(task_id: int, shapes, qpos, qvel):
    return jax.ffi.ffi_call(RESET_TARGET, shapes, vmap_method="broadcast_all")(
        qpos, qvel, task_id=np.int64(task_id))
