"""The Fetch tasks, written once in JAX over a small physics interface.

What makes FetchPush FetchPush (reset sampling, action -> mocap target, observation, reward,
success, 50-step truncation, a moving goal) lives here; the ``mujoco`` and ``mjx`` backends only
say how to reset and step the physics and return the raw readout (``physics.RAW_FIELDS``).

The API has the MuJoCo Playground shape: ``reset(key) -> State``, ``step(state, action) ->
State``, both pure and vmappable.

Moving goals: FetchReachMoving and FetchPushMoving
--------------------------------------------------
DHER's Dy-Reaching and Dy-Pushing (Fang et al., ICLR 2019), matched to the authors' env code in
github.com/mengf1/DHER: ``dygym/dygym/envs/robotics/fetch_env.py`` (``DyFetchEnv``),
``robot_env.py`` (its ``step``), ``reach.py`` / ``push.py`` (constructor defaults) and the
``DyReachEnv-v0`` registration in ``dher/dher/ddpg_dher/experiment/train_dyreach.py``.
Matched:

- Goal motion: ``goal += direction * speed`` once per env step, a fixed direction (no random
  sign, no per-episode sampling), no bounds: nothing flips or clips it, the goal may leave the
  workspace or the table. Both tasks run with ``move_obj=True``, whose ``step`` calls
  ``_step_callback`` *before* the action: if the achieved goal (gripper or object site) already
  satisfies the goal (``d < distance_threshold``) at the start of the step the goal stays put,
  otherwise it moves. Then the action and 20 substeps run, and the observation's
  ``desired_goal``, the reward and ``is_success`` all use the moved goal and the new achieved
  goal. Here: ``move_goal(goal, achieved)`` on the previous state's observation, then the physics
  step, then the observation, reward and success on the moved goal, which ``info["goal"]``
  carries to the next step. The motion does not touch the physics, so backends know nothing of it.
- Dy-Reaching (``FetchReachMoving``): FetchReach's scene and setup; the registration's
  direction (1, 0, 0), speed 0.011 m per step, distance_threshold 0.01, target_range 0.10,
  50 steps. Goal at reset: ``initial_gripper_xpos + U(+-0.10, 3)``, then z set to 0.5 (the
  no-object branch of ``DyFetchEnv._sample_goal``; target_in_the_air plays no part).
- Dy-Pushing (``FetchPushMoving``): FetchPush's scene and setup; ``DyPushEnv``'s defaults
  (also those of the authors' ``test_dypush.py``): direction (0, 1, 0), speed 0.005,
  distance_threshold 0.01, target_range 0.15. The object starts at ``initial_gripper_xpos[:2] +
  (0.1, U(+-0.15))``, without FetchPush's rejection sampling; the goal is FetchPush's
  (``initial_gripper_xpos + U(+-0.15, 3)``, z = the object's height). The object itself is not
  moved by the task.

Not matched, or not found:

- The repository trains only Dy-Reaching (``train_dyreach.py``); no Dy-Pushing registration
  exists, so its speed and episode length are the class defaults and those of the authors'
  test script (which uses 200-step episodes); here every task has 50 steps.
- ``DyFetchEnv`` defaults differ from the registration: direction (0, 0, 1), speed 0.012 for
  ``DyReachEnv``; we follow the registration that the authors' training script uses.
- Goals are float32 here (observations are) and the reached-goal check that holds the goal
  runs on float32 positions; the authors' goal is float64. Over 50 steps the goal differs from
  a float64 sum by < 5e-6 m (tests/test_moving.py).
- The authors' ``block`` option (zero the action and the object's velocity once the goal is
  reached) is off in both tasks and is not implemented.
- The physics is gymnasium-robotics ``Fetch*-v4``'s (mujoco bindings); the authors ran
  mujoco-py on gym 0.10's assets. The extra ``mj_forward`` their ``_step_callback`` runs before
  the action changes no state and is not repeated.

The speed is a task constant (``registry.TaskSpec.goal_speed``) that ``make_env(...,
goal_speed=...)`` overrides; it is a static float, fixed when the env is built.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from .physics import RAW_SLICES, Setup

_EPS4 = np.finfo(np.float64).eps * 4.0


@struct.dataclass
class State:
    """One env's state; every field gets a leading axis under ``jax.vmap``.

    Attributes:
      data: the backend's physics state (``mjx.Data`` or ``native.NativeState``).
      obs: ``observation``, ``achieved_goal``, ``desired_goal``.
      reward: sparse reward of the last step, -(||achieved - desired|| > threshold), with the
        task's threshold (0.05; 0.01 for the moving tasks).
      done: True on the step that ends an episode. Fetch episodes are truncated at T = 50,
        never terminated, so learners must still bootstrap through it.
      metrics: scalars for logging.
      info: ``is_success``, ``t`` (steps taken in this episode), ``goal`` (the desired goal of
        this state; the moving tasks move it in ``step``), ``rng``; with auto-reset also
        ``final_obs``, the observation the episode ended on.
    """

    data: Any
    obs: dict
    reward: jax.Array
    done: jax.Array
    metrics: dict = struct.field(default_factory=dict)
    info: dict = struct.field(default_factory=dict)


def goal_distance(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.linalg.norm(a - b, axis=-1)


def _host_float64(x) -> bool:
    """A float64 value on the host (numpy, or a list of floats), not a JAX array or tracer."""
    return not isinstance(x, jax.Array) and np.asarray(x).dtype == np.float64


def mat2euler(mat: jax.Array) -> jax.Array:
    """gymnasium_robotics.utils.rotations.mat2euler, for (..., 3, 3) matrices."""
    cy = jnp.sqrt(mat[..., 2, 2] * mat[..., 2, 2] + mat[..., 1, 2] * mat[..., 1, 2])
    cond = cy > _EPS4
    z = jnp.where(cond, -jnp.arctan2(mat[..., 0, 1], mat[..., 0, 0]),
                  -jnp.arctan2(-mat[..., 1, 0], mat[..., 1, 1]))
    y = -jnp.arctan2(-mat[..., 0, 2], cy)
    x = jnp.where(cond, -jnp.arctan2(mat[..., 1, 2], mat[..., 2, 2]), 0.0)
    return jnp.stack([x, y, z], axis=-1)


class FetchEnv:
    """A Fetch task over a physics backend. Build it with ``make_env``."""

    def __init__(self, setup: Setup, backend, auto_reset: bool = True,
                 episode_length: int | None = None):
        self.setup = setup
        self.spec = setup.spec
        self.backend = backend
        self.auto_reset = auto_reset
        self.name = self.spec.name
        self.episode_length = int(episode_length or self.spec.episode_length)
        self.dt = setup.dt
        self.distance_threshold = self.spec.distance_threshold
        self.obs_size = 25 if self.spec.has_object else 10
        self.goal_size = 3
        self.action_size = 4
        self._init_qpos = jnp.asarray(setup.init_qpos, jnp.float32)
        self._init_qvel = jnp.asarray(setup.init_qvel, jnp.float32)
        self._grip0 = jnp.asarray(setup.initial_gripper_xpos, jnp.float32)

    def __repr__(self) -> str:
        return f"FetchEnv({self.name}, backend={self.backend.name}, scene={self.setup.variant})"

    # ------------------------------------------------------------------ goals and rewards
    def compute_reward(self, achieved_goal: jax.Array, desired_goal: jax.Array) -> jax.Array:
        """Sparse reward, pure and vmappable: the function relabelling calls."""
        d = goal_distance(achieved_goal, desired_goal)
        return -(d > self.distance_threshold).astype(jnp.float32)

    def is_success(self, achieved_goal: jax.Array, desired_goal: jax.Array) -> jax.Array:
        d = goal_distance(achieved_goal, desired_goal)
        return (d < self.distance_threshold).astype(jnp.float32)

    def sample_goal(self, key: jax.Array) -> jax.Array:
        """A goal as gymnasium-robotics' ``_sample_goal`` (DHER's, for the moving tasks)."""
        s = self.spec
        k1, k2, k3 = jax.random.split(key, 3)
        goal = self._grip0 + jax.random.uniform(k1, (3,), minval=-s.target_range,
                                                maxval=s.target_range)
        if s.has_object:
            goal = goal + jnp.asarray(s.target_offset, jnp.float32)
            goal = goal.at[2].set(self.setup.height_offset)
            if s.target_in_the_air:
                lift = jax.random.uniform(k3, (), minval=0.0, maxval=0.45)
                goal = goal.at[2].add(jnp.where(jax.random.uniform(k2) < 0.5, lift, 0.0))
        if s.goal_z is not None:
            goal = goal.at[2].set(s.goal_z)
        return goal

    def move_goal(self, goal: jax.Array, achieved_goal: jax.Array) -> jax.Array:
        """One step of a moving goal, pure: it advances by ``goal_speed * goal_direction``
        unless ``achieved_goal`` (that of the state the step starts from) already satisfies it,
        as DHER's ``_step_callback``. A static task's goal is returned unchanged."""
        s = self.spec
        if not s.moving:
            return goal
        stay = self.is_success(achieved_goal, goal)[..., None]
        v = jnp.asarray(s.goal_direction, jnp.float32) * jnp.float32(s.goal_speed)
        return goal + (1.0 - stay) * v

    def sample_object_xy(self, key: jax.Array) -> jax.Array:
        """Object xy within obj_range of the gripper and at least 0.1 m from it (rejection);
        with ``object_x_offset`` (FetchPushMoving), at the gripper + (offset, U(+-obj_range))."""
        r = self.spec.obj_range
        grip = self._grip0[:2]
        if self.spec.object_x_offset is not None:
            dy = jax.random.uniform(key, (), minval=-r, maxval=r)
            return grip + jnp.stack([jnp.float32(self.spec.object_x_offset), dy])

        def cond(c):
            return jnp.linalg.norm(c[1] - grip) < 0.1

        def body(c):
            k, _ = c
            k, sub = jax.random.split(k)
            return k, grip + jax.random.uniform(sub, (2,), minval=-r, maxval=r)

        return jax.lax.while_loop(cond, body, (key, grip))[1]

    # ------------------------------------------------------------------ observation
    def _obs(self, raw: jax.Array, goal: jax.Array) -> dict:
        def f(name):
            return raw[..., RAW_SLICES[name]]

        dt = self.dt
        grip_pos = f("grip_pos")
        grip_velp = f("grip_velp") * dt
        finger_qpos, finger_vel = f("finger_qpos"), f("finger_qvel") * dt
        if self.spec.has_object:
            obj_pos = f("obj_pos")
            obj_rot = mat2euler(f("obj_xmat").reshape(raw.shape[:-1] + (3, 3)))
            obj_velp = f("obj_velp") * dt - grip_velp
            obj_velr = f("obj_velr") * dt
            obs = jnp.concatenate([grip_pos, obj_pos, obj_pos - grip_pos, finger_qpos, obj_rot,
                                   obj_velp, obj_velr, grip_velp, finger_vel], axis=-1)
            achieved = obj_pos
        else:
            obs = jnp.concatenate([grip_pos, finger_qpos, grip_velp, finger_vel], axis=-1)
            achieved = grip_pos
        return {"observation": obs, "achieved_goal": achieved, "desired_goal": goal}

    def _state(self, data, raw, goal, t, rng, after_step: bool) -> State:
        obs = self._obs(raw, goal)
        success = self.is_success(obs["achieved_goal"], goal)
        reward = (self.compute_reward(obs["achieved_goal"], goal) if after_step
                  else jnp.zeros((), jnp.float32))
        return State(
            data=data,
            obs=obs,
            reward=reward,
            done=t >= self.episode_length,
            metrics={"success": success},
            info={"is_success": success, "t": t, "goal": goal, "rng": rng},
        )

    # ------------------------------------------------------------------ API
    def reset(self, key: jax.Array) -> State:
        """A fresh episode: new object position (object tasks) and goal."""
        k_obj, k_goal, k_next = jax.random.split(key, 3)
        qpos = self._init_qpos
        if self.spec.has_object:
            a = self.setup.object_qposadr
            qpos = qpos.at[a : a + 2].set(self.sample_object_xy(k_obj))
        return self._reset_physics(qpos, self._init_qvel, self.sample_goal(k_goal), k_next)

    def reset_to(self, qpos, qvel, goal, key: jax.Array | None = None) -> State:
        """Start an episode from a MuJoCo state in the gymnasium-robotics model's layout.

        Precision depends on what is passed. On the native (``mujoco``) backend, qpos and qvel
        given as float64 host arrays (numpy, e.g. gymnasium's ``data.qpos``) are kept exactly:
        they go to the host directly, since JAX runs without x64, and the episode starts from
        that state bit for bit. This path runs eagerly, so call it outside ``jax.jit`` (the
        returned state steps under jit as any other). JAX arrays, and anything inside a trace,
        take the pure, jittable, vmappable path: qpos and qvel as float32, where entries equal
        in float32 to the settled reset state keep its float64 value and the others are
        rounded. The mjx backend is float32 throughout and always takes that path. The goal is
        float32 either way, as the observation and reward use it.

        Args:
          qpos, qvel: (nq,) and (nv,) for one env.
          goal: (3,) desired goal.
          key: PRNG key of the state (the auto-reset draws from it); default PRNGKey(0).
        """
        key = jax.random.PRNGKey(0) if key is None else key
        goal = jnp.asarray(goal, jnp.float32)
        if _host_float64(qpos) and _host_float64(qvel) and hasattr(self.backend, "reset_exact"):
            qpos, qvel = np.asarray(qpos), np.asarray(qvel)
            m = self.setup.model
            if qpos.shape != (m.nq,) or qvel.shape != (m.nv,):
                raise ValueError(f"reset_to takes one env's qpos ({m.nq},) and qvel ({m.nv},), "
                                 f"got {qpos.shape} and {qvel.shape}")
            data, raw = self.backend.reset_exact(qpos, qvel)
            return self._start(data, raw, goal, key)
        return self._reset_physics(jnp.asarray(qpos, jnp.float32),
                                   jnp.asarray(qvel, jnp.float32), goal, key)

    def _reset_physics(self, qpos, qvel, goal, rng) -> State:
        data, raw = self.backend.reset(qpos, qvel)
        return self._start(data, raw, goal, rng)

    def _start(self, data, raw, goal, rng) -> State:
        state = self._state(data, raw, goal, jnp.zeros((), jnp.int32), rng, after_step=False)
        if self.auto_reset:
            state.info["final_obs"] = state.obs
        return state

    def step(self, state: State, action: jax.Array) -> State:
        """Clip the action, move the mocap target by 0.05 * a[:3], command the fingers
        (PickAndPlace) and advance 20 substeps; a moving goal advances first (``move_goal``),
        and the new observation, reward and success use it. With auto-reset, a state whose
        episode just ended is replaced by a fresh episode, and ``info["final_obs"]`` keeps the
        last one."""
        goal = self.move_goal(state.info["goal"], state.obs["achieved_goal"])
        a = jnp.clip(action, -1.0, 1.0)
        delta = a[..., :3] * jnp.float32(0.05)
        grip = a[..., 3] if not self.spec.block_gripper else jnp.zeros_like(a[..., 3])
        data, raw = self.backend.step(state.data, delta, grip)
        new = self._state(data, raw, goal, state.info["t"] + 1, state.info["rng"],
                          after_step=True)
        if not self.auto_reset:
            return new
        new.info["final_obs"] = new.obs
        fresh = self.reset(state.info["rng"])
        fresh = fresh.replace(reward=new.reward, done=new.done,
                              metrics=new.metrics,
                              info={**fresh.info, "is_success": new.info["is_success"],
                                    "final_obs": new.obs})
        return jax.tree.map(lambda x, y: jnp.where(new.done, x, y), fresh, new)
