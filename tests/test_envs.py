"""The Fetch envs against gymnasium-robotics' own ``Fetch*-v4``, and the API's invariants."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import scripted_action
from rdher_jax.envs import GYMNASIUM_TASK_NAMES
from rdher_jax.envs.registry import task_spec

from rdher_jax import make_env

warnings.filterwarnings("ignore", category=UserWarning)
gym = pytest.importorskip("gymnasium")
gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
gym.register_envs(gymnasium_robotics)

OBS_KEYS = ("observation", "achieved_goal", "desired_goal")


def _gym(task, seed):
    """gymnasium-robotics' env, reset with ``seed``: its own float64 state is the start."""
    genv = gym.make(task_spec(task).gymnasium_id).unwrapped
    genv.reset(seed=seed)
    return genv


@pytest.fixture(scope="module", params=GYMNASIUM_TASK_NAMES)
def native(request):
    return request.param, make_env(request.param, "mujoco", auto_reset=False)


def run_side_by_side(task, env, genv, policy, steps=50, seed=0):
    """Step gymnasium-robotics and our env with the same actions; return the worst deviation.
    ``reset_to`` runs eagerly on gymnasium's float64 state, which it then keeps exactly."""
    step = jax.jit(env.step)
    st = env.reset_to(genv.data.qpos.copy(), genv.data.qvel.copy(), genv.goal.copy())
    o = genv._get_obs()
    rng = np.random.default_rng(seed)
    worst = {k: float(np.abs(np.asarray(st.obs[k]) - o[k]).max()) for k in OBS_KEYS}
    for _ in range(steps):
        if policy == "random":
            a = rng.uniform(-1, 1, 4).astype(np.float32)
        else:
            a = np.asarray(
                scripted_action(task, {k: jnp.asarray(v, jnp.float32) for k, v in o.items()}),
                np.float32,
            )
        o, r, term, trunc, info = genv.step(a)
        st = step(st, jnp.asarray(a))
        for k in OBS_KEYS:
            worst[k] = max(worst[k], float(np.abs(np.asarray(st.obs[k]) - o[k]).max()))
        assert float(st.reward) == r
        assert float(st.info["is_success"]) == info["is_success"]
        assert not term and not trunc  # gymnasium-robotics never ends an episode itself
    return worst


@pytest.mark.parametrize("policy, seeds", [("random", (1234, 1235, 1236)), ("scripted", (0, 1))])
def test_native_matches_gymnasium_robotics(native, policy, seeds):
    """From gymnasium-robotics' own reset states (float64, unrounded), 50 steps agree to float32
    round-off, with identical rewards and successes."""
    task, env = native
    for seed in seeds:
        worst = run_side_by_side(task, env, _gym(task, seed), policy, seed=seed)
        assert max(worst.values()) < 1e-6, (seed, worst)


def test_reset_to_keeps_float64_state_exactly():
    """Float64 host input is kept bit for bit; JAX input takes the jittable float32 path."""
    env = make_env("FetchSlide", "mujoco", auto_reset=False)
    genv = _gym("FetchSlide", 1234)
    qpos, qvel, goal = genv.data.qpos.copy(), genv.data.qvel.copy(), genv.goal.copy()
    st = env.reset_to(qpos, qvel, goal)
    got_qpos, got_qvel = env.backend.qpos_qvel(st.data)
    np.testing.assert_array_equal(got_qpos, qpos)
    np.testing.assert_array_equal(got_qvel, qvel)
    assert st.obs["desired_goal"].dtype == jnp.float32
    np.testing.assert_array_equal(st.obs["desired_goal"], goal.astype(np.float32))
    # Under jit (or from JAX arrays) qpos/qvel are float32: the sampled object position rounds.
    st32 = jax.jit(env.reset_to)(jnp.asarray(qpos), jnp.asarray(qvel), jnp.asarray(goal))
    q32, _ = env.backend.qpos_qvel(st32.data)
    a = env.setup.object_qposadr
    np.testing.assert_array_equal(q32[a : a + 2], qpos[a : a + 2].astype(np.float32))
    assert not np.array_equal(q32[a : a + 2], qpos[a : a + 2])
    with pytest.raises(ValueError, match="one env"):
        env.reset_to(qpos[None], qvel[None], goal)


def test_setup_matches_gymnasium_robotics(native):
    task, env = native
    genv = gym.make(task_spec(task).gymnasium_id).unwrapped
    genv.reset(seed=0)
    np.testing.assert_array_equal(env.setup.initial_gripper_xpos, genv.initial_gripper_xpos)
    np.testing.assert_array_equal(env.setup.init_qpos, genv.initial_qpos)
    if env.spec.has_object:
        assert env.setup.height_offset == genv.height_offset
    o, _ = genv.reset(seed=3)
    st = env.reset(jax.random.PRNGKey(0))
    assert st.obs["observation"].shape == o["observation"].shape
    assert st.obs["desired_goal"].shape == o["desired_goal"].shape


def test_sampling_ranges_match(native):
    """Our reset sampling covers the same ranges as gymnasium-robotics' (checked on both)."""
    task, env = native
    spec, grip0 = env.spec, env.setup.initial_gripper_xpos
    keys = jax.random.split(jax.random.PRNGKey(1), 512)
    st = jax.jit(jax.vmap(env.reset))(keys)
    genv = gym.make(task_spec(task).gymnasium_id).unwrapped
    gym_obs = [genv.reset(seed=s)[0] for s in range(64)]

    def check(goals, objs):
        off = np.asarray(spec.target_offset)
        lo = grip0 + off - spec.target_range - 1e-6
        hi = grip0 + off + spec.target_range + 1e-6
        assert np.all(goals[:, :2] >= lo[:2]) and np.all(goals[:, :2] <= hi[:2])
        if spec.has_object:
            z = goals[:, 2] - env.setup.height_offset
            assert np.all(z >= -1e-6) and np.all(z <= 0.45 + 1e-6)
            in_air = np.mean(z > 1e-6)
            assert (0.3 < in_air < 0.7) if spec.target_in_the_air else in_air == 0
            d = np.linalg.norm(objs[:, :2] - grip0[:2], axis=-1)
            assert np.all(d >= 0.1 - 1e-6)
            assert np.all(np.abs(objs[:, :2] - grip0[:2]) <= spec.obj_range + 1e-6)
        else:
            assert np.all(goals[:, 2] >= lo[2]) and np.all(goals[:, 2] <= hi[2])

    objs = np.asarray(st.obs["observation"][:, 3:6]) if spec.has_object else None
    check(np.asarray(st.obs["desired_goal"]), objs)
    g_goals = np.stack([o["desired_goal"] for o in gym_obs])
    g_objs = np.stack([o["observation"][3:6] for o in gym_obs]) if spec.has_object else None
    check(g_goals, g_objs)


def test_unknown_task_lists_valid_names():
    with pytest.raises(ValueError, match="FetchReach, FetchPush, FetchSlide, FetchPickAndPlace"):
        make_env("FetchPull")
    with pytest.raises(ValueError, match="backend"):
        make_env("FetchReach", backend="bullet")


def test_vmapped_batch_equals_single_envs():
    env = make_env("FetchPush", "mujoco", auto_reset=False)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    acts = jax.random.uniform(jax.random.PRNGKey(1), (5, 3, 4), minval=-1, maxval=1)
    vstep, step = jax.jit(jax.vmap(env.step)), jax.jit(env.step)
    batch = jax.jit(jax.vmap(env.reset))(keys)
    singles = [jax.jit(env.reset)(k) for k in keys]
    for t in range(5):
        batch = vstep(batch, acts[t])
        singles = [step(s, acts[t, i]) for i, s in enumerate(singles)]
    for i, s in enumerate(singles):
        np.testing.assert_array_equal(batch.obs["observation"][i], s.obs["observation"])
        np.testing.assert_array_equal(batch.data.bits[i], s.data.bits)


def test_auto_reset_new_goal_and_no_nans():
    env = make_env("FetchPickAndPlace", "mujoco", auto_reset=True)
    n, T = 8, env.episode_length
    st = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(2), n))
    step = jax.jit(jax.vmap(env.step))
    goal0 = np.asarray(st.obs["desired_goal"])
    rng = np.random.default_rng(0)
    for t in range(T):
        prev_obs = st.obs
        st = step(st, jnp.asarray(rng.uniform(-1, 1, (n, 4)), jnp.float32))
        assert np.all(np.isfinite(np.asarray(st.obs["observation"])))
        assert np.all(np.isfinite(np.asarray(st.info["final_obs"]["observation"])))
        if t < T - 1:
            assert not np.any(st.done)
            np.testing.assert_array_equal(st.info["t"], t + 1)
            np.testing.assert_array_equal(st.obs["desired_goal"], goal0)
    # The 50th step ends the episode (truncation) and starts a fresh one.
    assert np.all(st.done)
    np.testing.assert_array_equal(st.info["t"], 0)
    assert np.all(np.abs(np.asarray(st.obs["desired_goal"]) - goal0).max(-1) > 1e-4)
    np.testing.assert_array_equal(st.info["final_obs"]["desired_goal"], goal0)
    assert not np.array_equal(st.info["final_obs"]["observation"], prev_obs["observation"])
    # The fresh episode starts at rest, at the settled gripper position.
    np.testing.assert_allclose(
        st.obs["observation"][:, :3],
        np.broadcast_to(env.setup.initial_gripper_xpos, (n, 3)),
        atol=1e-5,
    )
    st = step(st, jnp.zeros((n, 4)))
    assert not np.any(st.done)
    np.testing.assert_array_equal(st.info["t"], 1)


def test_compute_reward_is_pure_and_vmappable():
    env = make_env("FetchReach", "mujoco")
    ag = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    g = jnp.array([[0.0, 0.0, 0.049], [0.0, 0.0, 0.051], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(jax.vmap(env.compute_reward)(ag, g), [0.0, -1.0, -1.0])
    np.testing.assert_array_equal(jax.jit(env.compute_reward)(ag, g), [0.0, -1.0, -1.0])
