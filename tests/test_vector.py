"""``rdher_jax.make_vector_env``: the gymnasium ``VectorEnv`` contract, SAME_STEP autoreset,
seeding, ``compute_reward`` against gymnasium-robotics, and SB3's HER buffer on top of it."""

import warnings

import numpy as np
import pytest
from gymnasium.utils import env_checker, passive_env_checker
from gymnasium.vector import AutoresetMode, VectorEnv

from rdher_jax import make_vector_env
from rdher_jax.vector import OBS_KEYS, FetchVectorEnv, to_sb3

warnings.filterwarnings("ignore", category=UserWarning)
gym = pytest.importorskip("gymnasium")
gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
gym.register_envs(gymnasium_robotics)

T = 50


@pytest.fixture(scope="module")
def push():
    return make_vector_env("FetchPush", 2, "mujoco")


@pytest.fixture(scope="module")
def reach():
    return make_vector_env("FetchReach-v4", 1, "mujoco", seed=7)


@pytest.fixture(scope="module")
def gym_push():
    return gym.make("FetchPush-v4")


def _rollout(venv, seed, steps, action_seed=0):
    """Random actions from a seeded reset; every returned array, in order."""
    rng = np.random.default_rng(action_seed)
    out = [venv.reset(seed=seed)]
    for _ in range(steps):
        out.append(venv.step(rng.uniform(-1, 1, venv.action_space.shape)))
    return out


def _toward_goal(obs):
    """A proportional reach controller: FetchReach succeeds within a few steps."""
    a = np.zeros(obs["achieved_goal"].shape[:-1] + (4,), np.float32)
    a[..., :3] = np.clip(10.0 * (obs["desired_goal"] - obs["achieved_goal"]), -1, 1)
    return a


def test_spaces_match_gymnasium_robotics(push, reach, gym_push):
    assert isinstance(push, VectorEnv) and push.num_envs == 2
    assert push.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert push.single_observation_space == gym_push.observation_space
    assert push.single_action_space == gym_push.action_space
    assert push.observation_space["observation"].shape == (2, 25)
    assert reach.observation_space["observation"].shape == (1, 10)
    assert push.action_space.shape == (2, 4) and push.action_space.dtype == np.float32
    for venv in (push, reach):
        passive_env_checker.check_observation_space(venv.single_observation_space)
        passive_env_checker.check_action_space(venv.single_action_space)
        env_checker.check_space_limit(venv.single_action_space, "action")

    obs, info = push.reset(seed=0)
    assert obs in push.observation_space and info == {}
    assert {k: v.dtype for k, v in obs.items()} == {k: np.float64 for k in OBS_KEYS}
    obs, reward, term, trunc, info = push.step(push.action_space.sample())
    assert obs in push.observation_space
    assert reward.shape == (2,) and reward.dtype == np.float64
    assert term.dtype == np.bool_ and trunc.dtype == np.bool_ and not term.any() and not trunc.any()
    assert info["is_success"].shape == (2,) and info["is_success"].dtype == np.float32
    assert info["_is_success"].all() and "final_obs" not in info
    with pytest.raises(ValueError, match="shape"):
        push.step(np.zeros((3, 4)))


def test_gymnasium_env_checker(reach):
    """The checks of ``gymnasium.utils.env_checker`` that apply to a vector env (the step
    determinism check asserts ``truncated is False``, a scalar, so it is done by hand below)."""
    env_checker.check_reset_return_type(reach)
    env_checker.check_reset_options(reach)
    env_checker.check_reset_seed_determinism(reach)
    env_checker.check_returned_data_not_reused(reach)
    env_checker.check_reset_return_info_deprecation(reach)


def test_seeding_is_deterministic(push, reach):
    a, b = _rollout(push, 3, 60), _rollout(push, 3, 60)
    assert env_checker.data_equivalence(a, b, exact=True)
    c = _rollout(push, 4, 0)
    assert not np.array_equal(a[0][0]["desired_goal"], c[0][0]["desired_goal"])
    goals = a[0][0]["desired_goal"]
    assert not np.array_equal(goals[0], goals[1])  # each env draws its own episode

    # reset() continues the seeded key stream; large seeds are not truncated to 32 bits
    push.reset(seed=3)
    o1, _ = push.reset()
    push.reset(seed=3)
    o2, _ = push.reset()
    assert env_checker.data_equivalence(o1, o2, exact=True)
    big = push.reset(seed=2**32)[0]["desired_goal"]
    assert not np.array_equal(big, push.reset(seed=0)[0]["desired_goal"])

    # make_vector_env(seed=7) seeds the first reset() that passes none
    seeded = FetchVectorEnv(reach.env, 1, seed=7)
    first, _ = seeded.reset()
    assert env_checker.data_equivalence(first, seeded.reset(seed=7)[0], exact=True)


def test_truncation_and_same_step_autoreset(push):
    obs0, _ = push.reset(seed=1)
    obs = obs0
    rng = np.random.default_rng(1)
    for t in range(1, 2 * T + 1):
        prev = obs
        obs, reward, term, trunc, info = push.step(rng.uniform(-1, 1, (2, 4)))
        assert not term.any()
        if t % T:
            assert not trunc.any() and "final_obs" not in info
            np.testing.assert_array_equal(obs["desired_goal"], prev["desired_goal"])
            continue
        assert trunc.all()
        assert info["_final_obs"].all() and info["_final_info"].all()
        for i in range(2):
            final = info["final_obs"][i]
            assert final in push.single_observation_space
            # the final observation closes the old episode (its goal) ...
            np.testing.assert_array_equal(final["desired_goal"], prev["desired_goal"][i])
            assert reward[i] == push.compute_reward(final["achieved_goal"],
                                                    final["desired_goal"], {})
            assert info["final_info"]["is_success"][i] == info["is_success"][i]
        # ... and the returned one starts the next: a new goal, the gripper at its reset pose
        assert not np.array_equal(obs["desired_goal"], prev["desired_goal"])
        np.testing.assert_array_equal(obs["observation"][:, :3], obs0["observation"][:, :3])


def test_reset_mask_resets_only_masked_envs(push):
    push.reset(seed=2)
    zero = np.zeros((2, 4))
    for _ in range(10):
        obs, *_ = push.step(zero)
    new, _ = push.reset(options={"reset_mask": np.array([True, False])})
    np.testing.assert_array_equal(new["desired_goal"][1], obs["desired_goal"][1])
    assert not np.array_equal(new["desired_goal"][0], obs["desired_goal"][0])
    ends = []
    for t in range(11, 61):
        _, _, _, trunc, info = push.step(zero)
        if trunc.any():
            ends.append((t, trunc.tolist(), [f is not None for f in info["final_obs"]]))
    # env 1 ends at its 50th step (t = 50), env 0 fifty steps after its reset (t = 60)
    assert ends == [(50, [False, True], [False, True]), (60, [True, False], [True, False])]
    with pytest.raises(ValueError, match="reset_mask"):
        push.reset(options={"reset_mask": np.array([1, 0])})


def test_compute_reward_matches_env_and_gymnasium_robotics(push, reach, gym_push):
    """Rewards from ``step`` equal ``compute_reward`` on the returned goals (the final ones
    where an episode ended), which equals gymnasium-robotics' on the same arrays; success is
    reward + 1 at every step."""
    gcr = gym_push.unwrapped.compute_reward
    for venv, policy in ((push, None), (reach, _toward_goal)):
        rng = np.random.default_rng(0)
        obs, _ = venv.reset(seed=5)
        rewards = []
        for _ in range(T):
            a = policy(obs) if policy else rng.uniform(-1, 1, venv.action_space.shape)
            obs, reward, _, trunc, info = venv.step(a)
            ag, dg = obs["achieved_goal"].copy(), obs["desired_goal"].copy()
            for i in np.flatnonzero(trunc):
                ag[i], dg[i] = info["final_obs"][i]["achieved_goal"], info["final_obs"][i][
                    "desired_goal"]
            ours = venv.compute_reward(ag, dg, info)
            np.testing.assert_array_equal(reward, ours)
            np.testing.assert_array_equal(ours, gcr(ag, dg, info))
            np.testing.assert_array_equal(info["is_success"], reward + 1.0)
            rewards.append(reward)
        if policy:
            assert np.mean(rewards) > -0.5  # the controller reaches: both values occur

    # relabelling-shaped arrays, distances spread across the threshold
    ag = rng.uniform(1.0, 1.5, (7, 16, 3))
    direction = rng.normal(size=ag.shape)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    dg = ag + direction * rng.uniform(0.0, 0.1, ag.shape[:-1] + (1,))
    r = push.compute_reward(ag, dg, None)
    assert r.shape == (7, 16) and r.dtype == np.float32 and 0 < -r.mean() < 1
    np.testing.assert_array_equal(r, gcr(ag, dg, {}))
    assert push.unwrapped.compute_reward(ag[0, 0], dg[0, 0], {}) == gcr(ag[0, 0], dg[0, 0], {})


def test_jit_traces_once_and_wrappers(push):
    """Seeded and unseeded resets, masked resets, float64 and list actions reuse one compiled
    reset and one step; gymnasium's vector wrappers see the SAME_STEP mode."""
    wrapped = gym.wrappers.vector.RecordEpisodeStatistics(push)
    wrapped.reset(seed=0)
    wrapped.reset()
    for t in range(1, T + 1):
        action = np.zeros((2, 4)) if t % 2 else [[0.0] * 4] * 2
        obs, reward, _, trunc, info = wrapped.step(action)
    assert trunc.all()
    np.testing.assert_array_equal(info["episode"]["l"], [T, T])
    np.testing.assert_array_equal(info["episode"]["r"], -T * np.ones(2))  # zero actions: no push
    assert push._reset_fn._cache_size() == 1 and push._step_fn._cache_size() == 1
    final = info["final_obs"]
    np.testing.assert_array_equal(wrapped.unwrapped.compute_reward(
        np.stack([f["achieved_goal"] for f in final]),
        np.stack([f["desired_goal"] for f in final]), info), reward)
    wrapped.close()
    with pytest.raises(gym.error.ResetNeeded):
        push.step(np.zeros((2, 4)))


def test_sb3_her_replay_buffer():
    """SB3's DDPG with ``HerReplayBuffer`` trains on ``to_sb3(make_vector_env(...))``: the buffer
    stores whole episodes whose last next-observation is the final one (not the next reset),
    and relabelled rewards come from the env's ``compute_reward``."""
    sb3 = pytest.importorskip("stable_baselines3")
    import torch

    torch.set_num_threads(1)
    venv = to_sb3(make_vector_env("FetchReach", 2, "mujoco"))
    rewards = venv.env_method("compute_reward", np.zeros((5, 3)), np.ones((5, 3)), {},
                              indices=[0])
    assert len(rewards) == 1 and rewards[0].shape == (5,)
    model = sb3.DDPG(
        "MultiInputPolicy", venv, replay_buffer_class=sb3.HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=2 * T, batch_size=32, buffer_size=1000, train_freq=10, gradient_steps=2,
        policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu",
    )
    model.learn(total_timesteps=6 * T)
    buf = model.replay_buffer
    assert buf.pos == 3 * T  # 3 episodes of each of the 2 envs
    np.testing.assert_array_equal(buf.ep_length[: 3 * T], T)
    # within an episode next_obs is the next step's obs; at its end, the final observation,
    # whose goal is still the episode's
    np.testing.assert_array_equal(buf.next_observations["observation"][: T - 1],
                                  buf.observations["observation"][1:T])
    np.testing.assert_array_equal(buf.next_observations["desired_goal"][T - 1],
                                  buf.observations["desired_goal"][T - 1])
    assert not np.array_equal(buf.next_observations["observation"][T - 1],
                              buf.observations["observation"][T])
    batch = buf.sample(64)
    assert set(np.unique(batch.rewards.numpy())) <= {-1.0, 0.0}
