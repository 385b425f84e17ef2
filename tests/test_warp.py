"""The ``warp`` backend (MJX's Warp implementation) on CPU, against gymnasium-robotics'
``Fetch*-v4`` from their own reset states, and its contact buffers and errors.

Tolerance. The warp env differs from gymnasium-robotics in three known ways, none a bug: it is
float32 throughout (gymnasium-robotics is float64, and the reset state is rounded to float32);
it steps the ``warp`` scene (``envs/scene.py``: the MJX edits plus margin-0 finger-box pairs);
and MJX's dynamics of the mocap weld differ from native MuJoCo's (the weld's Jdot*qvel term,
``experiments/results/scene_edits.md``). Before the gripper touches the object these add up to
millimetres over 50 steps: we assert ``POS_TOL`` (2.5 cm, the mjx backend's own tolerance
against native MuJoCo in tests/test_mjx.py) on every position and velocity of the observation
and on the goal. Once the gripper strikes the object, its path depends on every detail of the
contacts and the deviations grow without bound: in a scripted Push episode (seed 0) the object
ends 0.4 m from gymnasium-robotics' on the warp backend and on the native backend stepping the
same warp scene alike (gymnasium-robotics pushes it off the table, the edited scenes do not).
So from the step on which gymnasium-robotics' object is first touched (it moves by more than
1 mm, or its angular velocity in the observation exceeds 1e-3 rad per step), only the gripper and
the goal are compared; a strike changes the object's velocities within that very step. Reward
and success are compared on every compared step whose achieved goal lies farther than
``POS_TOL`` from the success threshold (where no deviation within the tolerance can flip
them), and agree on at least 90% of the compared steps.

A known deviation past that point: when the PickAndPlace fingers close on the box (scripted
episode, seed 0, step 13), the box starts to spin about its x axis on the warp backend (0.09
rad per env step at once, 0.5 two steps later), where gymnasium-robotics' stays within 0.005
and native MuJoCo on the same warp scene within 0.03: it comes from the Warp implementation,
not from the scene edit (which part of it is not known yet). Grasps on backend=warp are not to
be trusted until it is understood.

The gymnasium-robotics tasks run from ``env.reset(seed=...)``; the moving-goal tasks run the
physics of the task each is modelled on (from that task's gymnasium reset) and are compared on
the observation, and on the goal trajectory, reward and success of DHER's goal logic
(``tests/test_moving.dher_goals``) applied to gymnasium-robotics' achieved goals.

Skipped, with the reason, where warp-lang is not installed (``pip install -e '.[warp]'``).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import scripted_action
from rdher_jax.envs import GYMNASIUM_TASK_NAMES, MOVING_TASK_NAMES, warp_available
from rdher_jax.envs.registry import task_spec

from rdher_jax import make_env

warnings.filterwarnings("ignore", category=UserWarning)

needs_warp = pytest.mark.skipif(warp_available() is not None,
                                reason=f"backend=warp unavailable: {warp_available()}")

POS_TOL = 0.025
STEPS = 50


def _gym_env(name, seed):
    gym = pytest.importorskip("gymnasium")
    gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
    gym.register_envs(gymnasium_robotics)
    genv = gym.make(task_spec(name).gymnasium_id).unwrapped
    genv.reset(seed=seed)
    return genv


@pytest.fixture(scope="module")
def warp_envs():
    cache = {}

    def get(task):
        if task not in cache:
            env = make_env(task, "warp", auto_reset=False, worlds=1)
            cache[task] = (env, jax.jit(env.step), jax.jit(env.reset_to))
        return cache[task]

    return get


def _compare(task, warp_envs, seed, policy):
    """Step gymnasium-robotics (the static task's) and the warp env with the same actions
    from gymnasium's reset state; return the largest deviations (before and after the object
    is struck), the share of compared steps whose reward agrees, and the disagreements that
    the tolerance cannot explain."""
    from test_moving import dher_goals

    env, step, reset_to = warp_envs(task)
    spec = env.spec
    genv = _gym_env(spec.scene_name, seed)
    o = genv._get_obs()
    goal = np.asarray(o["desired_goal"], np.float64)
    if spec.moving and spec.goal_z is not None:
        goal = goal.copy()
        goal[2] = spec.goal_z
    st = reset_to(jnp.asarray(genv.data.qpos), jnp.asarray(genv.data.qvel),
                  jnp.asarray(goal, jnp.float32))
    rng = np.random.default_rng(seed)
    obj0 = o["observation"][3:6].copy() if spec.has_object else None
    struck = None  # the step on which gymnasium-robotics' object first moved
    before, grip_goal, agree, compared, far = 0.0, 0.0, 0, 0, []
    ref_goal = goal
    for t in range(STEPS):
        if policy == "random":
            a = rng.uniform(-1, 1, 4).astype(np.float32)
        else:
            obs = {**o, "desired_goal": ref_goal}
            a = np.asarray(scripted_action(
                spec.scene_name, {k: jnp.asarray(v, jnp.float32) for k, v in obs.items()}),
                np.float32)
        ag_before = o["achieved_goal"]
        o, _, _, _, _ = genv.step(a)
        st = step(st, jnp.asarray(a))
        if spec.moving:
            ref_goal = dher_goals(ref_goal, [ag_before], spec.goal_direction, spec.goal_speed,
                                  spec.distance_threshold)[0]
        obs = np.asarray(st.obs["observation"])
        success = float(st.info["is_success"])
        assert float(st.reward) == success - 1.0
        grip_goal = max(grip_goal, float(np.abs(obs[:3] - o["observation"][:3]).max()),
                        float(np.abs(np.asarray(st.obs["desired_goal"]) - ref_goal).max()))
        if struck is None and spec.has_object and (
                np.abs(o["observation"][3:6] - obj0).max() > 1e-3
                or np.abs(o["observation"][17:20]).max() > 1e-3):  # moved, or set turning
            struck = t
        if struck is not None and t >= struck:
            continue
        before = max(before, float(np.abs(obs - o["observation"]).max()))
        d = np.linalg.norm(o["achieved_goal"] - ref_goal)
        ref_success = float(d < spec.distance_threshold)
        compared += 1
        agree += success == ref_success
        if success != ref_success and abs(d - spec.distance_threshold) > POS_TOL:
            far.append((t, d))
    return before, grip_goal, agree / compared if compared else 1.0, far, struck


@needs_warp
@pytest.mark.slow  # about a minute a task on one core (Warp's step, compiled per task)
@pytest.mark.parametrize("task", [*GYMNASIUM_TASK_NAMES, *MOVING_TASK_NAMES])
def test_warp_matches_gymnasium_robotics(task, warp_envs):
    """From gymnasium-robotics' own reset states, a random and a scripted episode stay within
    the stated tolerance; reward and success agree wherever the tolerance cannot flip them."""
    for seed, policy in ((1234, "random"), (0, "scripted")):
        before, grip_goal, agree, far, struck = _compare(task, warp_envs, seed, policy)
        print(f"{task} {policy}: observation {before:.1e} (object struck at step {struck}), "
              f"gripper and goal {grip_goal:.1e} m, reward/success agree {agree:.0%}")
        assert before < POS_TOL, (task, policy, before)
        assert grip_goal < POS_TOL, (task, policy, grip_goal)
        assert not far, (task, policy, far)
        assert agree >= 0.9, (task, policy, agree)


@needs_warp
def test_contact_buffers_are_sized_and_checked():
    """The buffers' capacity comes from the scene; too few constraint rows raise at run time
    instead of dropping constraints. (Too small a contact buffer is never built: on a CPU,
    Warp 1.14 crashes on a contact overflow, so the contact bound is a true upper bound.)"""
    from rdher_jax.envs.mjx_backend import contact_capacity
    from rdher_jax.envs.scene import load_model

    cap = contact_capacity(load_model("FetchPush", "warp"))
    assert cap.pairs >= 10 and cap.contacts >= cap.pairs and cap.rows > cap.contacts
    assert cap.contacts <= 8 * cap.pairs
    env = make_env("FetchPush", "warp", auto_reset=False, worlds=4)
    assert env.backend.naconmax == 4 * cap.contacts and env.backend.njmax == cap.rows

    from rdher_jax.envs.rollout import rollout

    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    run = jax.jit(lambda k: rollout(env, lambda _, s: jnp.zeros((4, 4)), k, steps=2))
    _, last, _ = run(keys)
    np.testing.assert_array_equal(env.backend.overflow(last.data), 0)
    # More envs than the buffers were sized for: refused before anything runs.
    with pytest.raises(ValueError, match="worlds=8"):
        rollout(env, lambda _, s: jnp.zeros((8, 4)), jax.random.split(keys[0], 8), steps=2)
    # Eight constraint rows for an env resting on the table (35 rows): an overflow, an error.
    from rdher_jax.envs.fetch import FetchEnv
    from rdher_jax.envs.mjx_backend import ContactCapacity, WarpBackend

    small = FetchEnv(env.setup, WarpBackend(env.setup, worlds=4, capacity=ContactCapacity(
        cap.pairs, cap.contacts, 8)), auto_reset=False)
    run = jax.jit(lambda k: rollout(small, lambda _, s: jnp.zeros((4, 4)), k, steps=2))
    with pytest.raises(Exception, match="ran out of buffer.*NEFC"):
        jax.block_until_ready(run(keys))


def test_warp_missing_is_a_one_line_config_error(monkeypatch):
    """backend=warp without warp-lang: a ConfigError naming the install command."""
    import sys

    from rdher_jax import envs
    from rdher_jax.config import Config, ConfigError
    from rdher_jax.executor import resolve_backend

    monkeypatch.setitem(sys.modules, "warp", None)  # `import warp` raises ImportError
    why = envs.warp_available()
    assert why is not None and "pip install -e '.[warp]'" in why and "\n" not in why
    with pytest.raises(ConfigError, match=r"pip install -e '\.\[warp\]'"):
        resolve_backend(Config(env="FetchReach", backend="warp"))
    with pytest.raises(RuntimeError, match="warp-lang"):
        make_env("FetchReach", "warp")
    # auto never picks warp without it.
    assert envs.default_backend() in ("mujoco", "mjx")


def test_warp_on_a_device_warp_cannot_use(monkeypatch):
    """JAX on a GPU that Warp sees no CUDA device for: the same one-line error."""
    pytest.importorskip("warp")
    import warp as wp

    from rdher_jax import envs

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(wp, "is_cuda_available", lambda: False)
    why = envs.warp_available()
    assert "cannot use" in why and "pip install -e '.[warp]'" in why
    assert envs.default_backend() == "mjx"
    monkeypatch.setattr(jax, "default_backend", lambda: "tpu")
    assert "'tpu'" in envs.warp_available()


def test_scene_for_warp_only_adds_margin_zero_pairs():
    """The warp scene is the mjx scene plus explicit margin-0 pairs (and names for unnamed
    geoms): same bodies, geoms, masses and options."""
    from rdher_jax.envs.scene import load_model

    for task in GYMNASIUM_TASK_NAMES:
        a, b = load_model(task, "mjx"), load_model(task, "warp")
        assert (a.nbody, a.ngeom, a.nq, a.nv) == (b.nbody, b.ngeom, b.nq, b.nv)
        np.testing.assert_array_equal(a.body_mass, b.body_mass)
        np.testing.assert_array_equal(a.geom_margin, b.geom_margin)
        assert a.opt.disableflags == b.opt.disableflags
        assert b.npair > a.npair or task == "FetchReach"
        assert not b.pair_margin[a.npair:].any()


@needs_warp
@pytest.mark.slow  # about 17 minutes on a shared core (Warp's CPU steps at 2 envs)
def test_fetch_reach_her_learns_on_warp(tmp_path):
    """The native backend's learning check (tests/test_train.py::test_fetch_reach_her_learns)
    on backend=warp: FetchReach with HER reaches >= 0.9 test success within the same 5,000
    env steps (5 epochs of 10 cycles x 2 episodes x 50 steps)."""
    import csv
    from pathlib import Path

    from rdher_jax import train as train_mod
    from rdher_jax.config import Config, resolve

    cfg = resolve(Config(env="FetchReach", backend="warp", epochs=5, buffer_size=100_000,
                         n_test_rollouts=20, run_dir=str(tmp_path / "reach"), progress=False))
    train_mod.train(cfg)
    with open(Path(cfg.run_dir) / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    best = max(float(r["test_success"]) for r in rows)
    assert int(rows[-1]["env_steps"]) == 5000
    assert best >= 0.9, [r["test_success"] for r in rows]
    assert np.isfinite([float(r["critic_loss"]) for r in rows]).all()
