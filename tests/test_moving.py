"""The moving-goal tasks against a numpy re-implementation of DHER's ``DyFetchEnv`` goal logic.

The reference below is written from the authors' code (github.com/mengf1/DHER,
``dygym/dygym/envs/robotics/fetch_env.py`` and ``robot_env.py``, with the constants of
``reach.py``, ``push.py`` and the ``DyReachEnv-v0`` registration in ``train_dyreach.py``), not
from ``rdher_jax.envs``: at the start of each step, ``_step_callback`` checks the achieved goal
against the goal and, unless it is reached (``d < distance_threshold``), moves the goal by
``direction * velocity``; the step's observation, reward and success then use the moved goal.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rdher_jax import make_env

# The authors' settings.
DY_REACH = dict(direction=(1.0, 0.0, 0.0), velocity=0.011, distance_threshold=0.01,
                target_range=0.10, goal_z=0.5)
DY_PUSH = dict(direction=(0.0, 1.0, 0.0), velocity=0.005, distance_threshold=0.01,
               target_range=0.15, obj_range=0.15, object_dx=0.1)


def dher_goals(goal0, achieved, direction, velocity, distance_threshold, **_):
    """DyFetchEnv.step with move_obj=True, goal part only, in float64.

    ``achieved[t]`` is the achieved goal of the state step t starts from; returns the goal of
    the state after each step."""
    goal = np.asarray(goal0, np.float64).copy()
    out = []
    for ag in np.asarray(achieved, np.float64):
        success = np.linalg.norm(ag - goal) < distance_threshold  # _step_callback
        if not success:
            goal = goal + np.asarray(direction) * velocity  # _move_goal
        out.append(goal.copy())
    return np.stack(out)


def dher_reward(achieved, goal, distance_threshold, **_):
    d = np.linalg.norm(np.asarray(achieved, np.float64) - goal, axis=-1)
    return -(d > distance_threshold).astype(np.float32), (d < distance_threshold).astype(np.float32)


@pytest.fixture(scope="module")
def reach():
    return make_env("FetchReachMoving", "mujoco", auto_reset=False)


def chase(obs, lead, gain=20.0):
    """Steer the gripper to where the goal will be in ``lead`` steps: it catches the goal now
    and then, so the goal's pause is exercised as well as its motion."""
    target = obs["desired_goal"] + lead * DY_REACH["velocity"] * jnp.asarray(DY_REACH["direction"])
    a = jnp.clip((target - obs["achieved_goal"]) * gain, -1.0, 1.0)
    return jnp.concatenate([a, jnp.zeros_like(a[..., :1])], -1)


def rollout(env, state, policy, steps):
    def body(s, _):
        nxt = jax.vmap(env.step)(s, policy(s.obs))
        return nxt, (s.obs["achieved_goal"], nxt.obs, nxt.reward, nxt.info)

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=steps))(state)


def test_constants_are_the_authors(reach):
    s = reach.spec
    assert (s.goal_direction, s.goal_speed, s.distance_threshold, s.target_range, s.goal_z) == (
        DY_REACH["direction"], DY_REACH["velocity"], DY_REACH["distance_threshold"],
        DY_REACH["target_range"], DY_REACH["goal_z"])
    assert reach.episode_length == 50 and reach.spec.scene_name == "FetchReach"
    p = make_env("FetchPushMoving", "mujoco").spec
    assert (p.goal_direction, p.goal_speed, p.distance_threshold, p.target_range,
            p.obj_range, p.object_x_offset) == tuple(DY_PUSH.values())


def test_reach_goal_trajectory_matches_the_authors_logic(reach):
    n, T = 4, reach.episode_length
    keys = jax.random.split(jax.random.PRNGKey(7), n)
    s0 = jax.jit(jax.vmap(reach.reset))(keys)
    grip0 = reach.setup.initial_gripper_xpos
    goal0 = np.asarray(s0.obs["desired_goal"])
    # Reset: initial_gripper_xpos + U(+-0.10, 3), then z = 0.5.
    np.testing.assert_array_equal(goal0[:, 2], DY_REACH["goal_z"])
    assert np.all(np.abs(goal0[:, :2] - grip0[:2]) <= DY_REACH["target_range"] + 1e-6)
    assert len({tuple(g) for g in goal0}) == n

    _, (ag_before, obs, reward, info) = rollout(reach, s0, lambda o: chase(o, lead=2.0), T)
    ag_before, goals = np.asarray(ag_before), np.asarray(obs["desired_goal"])
    moved = paused = 0
    for i in range(n):
        ref = dher_goals(goal0[i], ag_before[:, i], **DY_REACH)
        np.testing.assert_allclose(goals[:, i], ref, rtol=0, atol=5e-6)
        step_len = np.linalg.norm(np.diff(np.concatenate([goal0[i][None], ref]), axis=0), axis=-1)
        moved += int(np.sum(step_len > 0))
        paused += int(np.sum(step_len == 0))
        # Reward and success: the new achieved goal against the moved goal.
        r, ok = dher_reward(obs["achieved_goal"][:, i], ref, **DY_REACH)
        np.testing.assert_array_equal(reward[:, i], r)
        np.testing.assert_array_equal(info["is_success"][:, i], ok)
    assert moved > 20 and paused > 20, (moved, paused)  # both branches of _step_callback ran
    np.testing.assert_array_equal(info["goal"], obs["desired_goal"])


def test_step_uses_the_moved_goal(reach):
    """A goal 0.011 m behind the gripper (just outside 0.01) moves onto it in the first step, so
    that step succeeds; a goal already within 0.01 does not move."""
    qpos, qvel = reach.setup.init_qpos, reach.setup.init_qvel
    grip0 = reach.setup.initial_gripper_xpos
    step = jax.jit(reach.step)
    behind = reach.reset_to(qpos, qvel, grip0 - np.array([0.011, 0.0, 0.0]))
    assert float(behind.info["is_success"]) == 0.0
    after = step(behind, jnp.zeros(4))
    np.testing.assert_allclose(after.obs["desired_goal"], grip0, atol=1e-6)
    assert float(after.reward) == 0.0 and float(after.info["is_success"]) == 1.0
    np.testing.assert_array_equal(
        after.reward, reach.compute_reward(after.obs["achieved_goal"], after.obs["desired_goal"]))
    # A reached goal stays put while it stays reached.
    near = reach.reset_to(qpos, qvel, grip0 + np.array([0.005, 0.0, 0.0]))
    s = near
    for _ in range(5):
        s = step(s, jnp.zeros(4))
        np.testing.assert_array_equal(s.obs["desired_goal"], near.obs["desired_goal"])
        assert float(s.reward) == 0.0


def test_auto_reset_gives_a_fresh_moving_goal():
    env = make_env("FetchReachMoving", "mujoco", auto_reset=True)
    n, T = 3, env.episode_length
    s0 = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(3), n))
    last, (_, obs, _, info) = rollout(env, s0, lambda o: jnp.zeros(o["achieved_goal"].shape[:-1]
                                                                    + (4,)), T + 2)
    goal0 = np.asarray(s0.obs["desired_goal"])
    v = DY_REACH["velocity"] * np.asarray(DY_REACH["direction"])
    # The gripper rests far from the goal: the goal moves every step until the episode ends.
    final = np.asarray(info["final_obs"]["desired_goal"][T - 1])
    np.testing.assert_allclose(final, goal0 + T * v, atol=5e-6)
    assert np.all(np.asarray(info["t"][T - 1]) == 0)
    fresh = np.asarray(obs["desired_goal"][T - 1])
    assert np.all(np.linalg.norm(fresh - final, axis=-1) > 1e-3)
    assert np.all(np.linalg.norm(fresh - goal0, axis=-1) > 1e-3)
    np.testing.assert_array_equal(fresh[:, 2], DY_REACH["goal_z"])
    assert np.all(np.abs(fresh[:, :2] - env.setup.initial_gripper_xpos[:2]) <= 0.10 + 1e-6)
    # ... and the fresh goal moves from the next step on.
    np.testing.assert_allclose(np.asarray(obs["desired_goal"][T]), fresh + v, atol=1e-6)
    np.testing.assert_allclose(np.asarray(last.obs["desired_goal"]), fresh + 2 * v, atol=1e-6)


def test_vmapped_batch_equals_single_envs(reach):
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    acts = jax.random.uniform(jax.random.PRNGKey(6), (4, 3, 4), minval=-1, maxval=1)
    batch = jax.jit(jax.vmap(reach.reset))(keys)
    singles = [jax.jit(reach.reset)(k) for k in keys]
    vstep, step = jax.jit(jax.vmap(reach.step)), jax.jit(reach.step)
    for t in range(4):
        batch = vstep(batch, acts[t])
        singles = [step(s, acts[t, i]) for i, s in enumerate(singles)]
    for i, s in enumerate(singles):
        for k in s.obs:
            np.testing.assert_array_equal(batch.obs[k][i], s.obs[k])
        np.testing.assert_array_equal(batch.reward[i], s.reward)


def test_goal_speed_parameter():
    zeros = jnp.zeros(4)
    moved = {}
    for speed in (0.0, 0.011, 0.02):
        env = make_env("FetchReachMoving", "mujoco", auto_reset=False, goal_speed=speed)
        assert env.spec.goal_speed == speed
        s0 = jax.jit(env.reset)(jax.random.PRNGKey(0))
        s = s0
        for _ in range(5):
            s = jax.jit(env.step)(s, zeros)
        moved[speed] = np.asarray(s.obs["desired_goal"] - s0.obs["desired_goal"])
    np.testing.assert_array_equal(moved[0.0], 0.0)
    np.testing.assert_allclose(moved[0.011], [0.055, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(moved[0.02], [0.1, 0.0, 0.0], atol=1e-6)
    assert make_env("FetchReachMoving", "mujoco").spec.goal_speed == DY_REACH["velocity"]
    with pytest.raises(ValueError, match="moving tasks"):
        make_env("FetchReach", "mujoco", goal_speed=0.01)


def test_episode_length_and_goal_speed_reach_the_env():
    """``episode_length=`` and ``goal_speed=`` (config keys) set the built env's T and goal
    motion: an episode of T=7 steps is done at its 7th step, not before, and the goal moved
    7 x speed along +y."""
    from rdher_jax.config import parse_args, resolve
    from rdher_jax.executor import build

    cfg = resolve(parse_args(["env=FetchPushMoving", "episode_length=7", "goal_speed=0.003",
                              "hidden=8", "buffer_size=1000", "batch_size=8"]))
    env, _ = build(cfg)
    assert env.episode_length == 7 and env.spec.goal_speed == 0.003
    s0 = jax.jit(env.reset)(jax.random.PRNGKey(3))
    step = jax.jit(env.step)
    s, dones = s0, []
    for _ in range(7):
        s = step(s, jnp.zeros(4))
        dones.append(bool(s.done))
    assert dones == [False] * 6 + [True]
    moved = np.asarray(s.obs["desired_goal"] - s0.obs["desired_goal"])
    # The goal pauses only when the object reaches it; a still arm leaves the object 0.1 m
    # away in x.
    np.testing.assert_allclose(moved, [0.0, 0.021, 0.0], atol=1e-6)


def test_push_moving_reset_and_goal_motion():
    env = make_env("FetchPushMoving", "mujoco", auto_reset=False)
    n = 4
    s0 = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(11), n))
    grip0, h = env.setup.initial_gripper_xpos, env.setup.height_offset
    obj = np.asarray(s0.obs["achieved_goal"])
    # _reset_sim: object at initial_gripper_xpos[:2] + (0.1, U(+-obj_range)), no rejection.
    np.testing.assert_allclose(obj[:, 0], grip0[0] + DY_PUSH["object_dx"], atol=1e-6)
    assert np.all(np.abs(obj[:, 1] - grip0[1]) <= DY_PUSH["obj_range"] + 1e-6)
    assert len(set(obj[:, 1].tolist())) == n
    goal0 = np.asarray(s0.obs["desired_goal"])
    np.testing.assert_allclose(goal0[:, 2], h, atol=1e-6)
    assert np.all(np.abs(goal0[:, :2] - grip0[:2]) <= DY_PUSH["target_range"] + 1e-6)
    acts = jax.random.uniform(jax.random.PRNGKey(12), (n, 4), minval=-1, maxval=1)
    _, (ag_before, obs, reward, info) = rollout(env, s0, lambda o: acts, 10)
    for i in range(n):
        ref = dher_goals(goal0[i], np.asarray(ag_before)[:, i], **DY_PUSH)
        np.testing.assert_allclose(np.asarray(obs["desired_goal"])[:, i], ref, atol=2e-6)
        r, ok = dher_reward(np.asarray(obs["achieved_goal"])[:, i], ref, **DY_PUSH)
        np.testing.assert_array_equal(reward[:, i], r)
        np.testing.assert_array_equal(info["is_success"][:, i], ok)


@pytest.mark.slow
def test_mjx_backend_moves_the_goal_as_native():
    """The goal motion is task logic: on the mjx backend the goal trajectory (auto-reset
    included) is the native backend's. Compiles MJX (about a minute on 2 cores)."""
    keys = jax.random.split(jax.random.PRNGKey(0), 2)

    def goals(env):
        def body(s, _):
            s = jax.vmap(env.step)(s, jnp.zeros((2, 4)))
            return s, s.obs["desired_goal"]

        return jax.lax.scan(body, jax.vmap(env.reset)(keys), None, length=52)[1]

    mjx_env = make_env("FetchReachMoving", "mjx", auto_reset=True)
    nat_env = make_env("FetchReachMoving", "mujoco", scene="mjx", auto_reset=True)
    np.testing.assert_array_equal(jax.jit(lambda: goals(mjx_env))(),
                                  jax.jit(lambda: goals(nat_env))())
