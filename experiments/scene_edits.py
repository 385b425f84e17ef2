"""What the MJX scene edits do to the Fetch dynamics, and why MJX and MuJoCo differ.

1. Each edit of ``envs/scene.py`` (alone, then all together) against the original scene, in
   native MuJoCo. Both models are driven through a replica of gymnasium-robotics' ``Fetch*-v4``
   step (checked against ``env.step``; the largest difference is in the results) with the
   same episodes: closed-loop scripted
   ones (reach; push the object to the goal; grasp, lift and carry; strike the puck) and
   open-loop random-action ones, 50 env steps of 20 substeps. Reported: worst and median over
   episodes of the largest gripper and object deviation over the 50 steps, next to the
   sensitivity floor of the original scene (initial object moved by 1e-6 m; 1e-6 added to every
   action).
2. The Slide puck: polygon sides and radius, which contact pair deviates, a launch test.
3. ``--mjx``: one ``mjx.step`` against one ``mj_step`` from identical states, field by field, and
   whole episodes, in float64.

    python experiments/scene_edits.py          # ~1 minute, writes results/scene_edits.md
    python experiments/scene_edits.py --mjx    # + ~1 minute, + 0.5-2 minutes of jit compile

Without ``--mjx`` an MJX section written by an earlier run is kept. Section 4 of the results,
the findings, is prose written by hand from the tables; every rerun keeps it as it is. Set
``JAX_COMPILATION_CACHE_DIR`` to reuse the compiled ``mjx.step`` between runs.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

# MJX on CPU: XLA's fusion emitters make mjx.step far slower; the flag must be set before jax is
# first imported (the mjx scene variant imports it).
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from rdher_jax.envs import scene  # noqa: E402
from rdher_jax.envs.notices import quiet_gymnasium_robotics  # noqa: E402
from rdher_jax.envs.physics import N_SUBSTEPS  # noqa: E402
from rdher_jax.envs.registry import GYMNASIUM_TASK_NAMES, task_spec  # noqa: E402

REPLICA_STEPS, REPLICA_SEED = 20, 3  # the replica check: random steps after reset(seed=...)
LAUNCH_XY, LAUNCH_SPEED = (1.2, 0.75), 1.0  # the Slide puck's launch test: start (m), speed (m/s)
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "scene_edits.md")


# The task constants (gymnasium-robotics' MujocoFetch*Env arguments) are the task registry's.
TASKS = {name: task_spec(name) for name in GYMNASIUM_TASK_NAMES}
# Steps per episode: one length for the four tasks (the studies' arrays assume it).
(N_STEPS,) = {spec.episode_length for spec in TASKS.values()}


# ---------------------------------------------------------------------------------------------
# Native replica of the gymnasium-robotics Fetch step
# ---------------------------------------------------------------------------------------------


Physics = Callable[[mujoco.MjModel, mujoco.MjData], None]


def native_physics(m: mujoco.MjModel, d: mujoco.MjData) -> None:
    """One env step of physics: 20 ``mj_step`` substeps, as gymnasium-robotics runs them."""
    mujoco.mj_step(m, d, nstep=N_SUBSTEPS)


class FetchSim:
    """gymnasium-robotics' ``MujocoFetchEnv`` dynamics on any compiled Fetch model."""

    def __init__(self, model: mujoco.MjModel, task: str, physics: Physics | None = None):
        self.m, self.cfg = model, TASKS[task]
        self.physics = physics or native_physics
        self.d = mujoco.MjData(model)
        self.grip_site = model.site("robot0:grip").id
        self.gripper_body = model.body("robot0:gripper_link").id
        self.fingers = [
            model.jnt_qposadr[model.joint(f"robot0:{s}_gripper_finger_joint").id] for s in "lr"
        ]
        self.obj_site = model.site("object0").id if self.cfg.has_object else -1
        self.obj_qpos = (
            model.jnt_qposadr[model.joint("object0:joint").id] if self.cfg.has_object else -1
        )
        self._env_setup()

    def _set_joint(self, name: str, value: float | list[float]) -> None:
        adr = self.m.jnt_qposadr[self.m.joint(name).id]
        value = np.atleast_1d(value)
        self.d.qpos[adr : adr + value.size] = value

    def _env_setup(self) -> None:
        m, d = self.m, self.d
        for name, value in self.cfg.initial_qpos.items():
            self._set_joint(name, value)
        # reset_mocap_welds: the weld's relative pose becomes the identity; it runs mj_forward,
        # and _env_setup runs it once more.
        for i in range(m.neq):
            if m.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                m.eq_data[i, :7] = [0, 0, 0, 0, 0, 0, 1]
        mujoco.mj_forward(m, d)
        mujoco.mj_forward(m, d)
        target = np.array([-0.498, 0.005, -0.431 + self.cfg.gripper_extra_height])
        d.mocap_pos[0] = target + d.site_xpos[self.grip_site]
        d.mocap_quat[0] = [1.0, 0.0, 1.0, 0.0]
        for _ in range(10):
            mujoco.mj_step(m, d, nstep=N_SUBSTEPS)
        self.initial_gripper_xpos = d.site_xpos[self.grip_site].copy()
        self.height_offset = d.site_xpos[self.obj_site][2] if self.cfg.has_object else 0.0
        self.initial = (d.time, d.qpos.copy(), d.qvel.copy())

    def reset(self, object_xy: np.ndarray | None) -> None:
        """``_reset_sim``: back to the settled state, object at ``object_xy``."""
        m, d = self.m, self.d
        mujoco.mj_resetData(m, d)
        d.time, qpos, qvel = self.initial
        d.qpos[:], d.qvel[:] = qpos, qvel
        if object_xy is not None:
            d.qpos[self.obj_qpos : self.obj_qpos + 2] = object_xy
        mujoco.mj_forward(m, d)

    def step(self, action: np.ndarray, nudge: np.ndarray | None = None) -> None:
        """``env.step`` without the observation; ``nudge`` is added after clipping."""
        m, d = self.m, self.d
        a = np.clip(action, -1.0, 1.0)
        if nudge is not None:
            a = a + nudge
        grip_ctrl = 0.0 if self.cfg.block_gripper else a[3]
        # ctrl_set_action: position actuators track finger qpos + command.
        for i in range(m.nu):
            if m.actuator_biastype[i] == 0:
                d.ctrl[i] = grip_ctrl
            else:
                d.ctrl[i] = d.qpos[m.jnt_qposadr[m.actuator_trnid[i, 0]]] + grip_ctrl
        # mocap_set_action: mocap reset to the welded body's pose, then moved by the deltas.
        d.mocap_pos[0] = d.xpos[self.gripper_body] + 0.05 * a[:3]
        d.mocap_quat[0] = d.xquat[self.gripper_body] + np.array([1.0, 0.0, 1.0, 0.0])
        self.physics(m, d)
        if self.cfg.block_gripper:
            d.qpos[self.fingers] = 0.0
            mujoco.mj_forward(m, d)

    @property
    def grip(self) -> np.ndarray:
        return self.d.site_xpos[self.grip_site].copy()

    @property
    def obj(self) -> np.ndarray:
        if not self.cfg.has_object:
            return np.zeros(3)
        return self.d.site_xpos[self.obj_site].copy()

    @property
    def finger_width(self) -> float:
        return float(self.d.qpos[self.fingers].sum())


def sample_episode(sim: FetchSim, rng: np.random.Generator) -> tuple[np.ndarray | None, np.ndarray]:
    """Object xy and goal as ``_reset_sim`` and ``_sample_goal`` draw them."""
    cfg, g0 = sim.cfg, sim.initial_gripper_xpos
    object_xy = None
    if cfg.has_object:
        object_xy = g0[:2].copy()
        while np.linalg.norm(object_xy - g0[:2]) < 0.1:
            object_xy = g0[:2] + rng.uniform(-cfg.obj_range, cfg.obj_range, size=2)
    goal = g0 + rng.uniform(-cfg.target_range, cfg.target_range, size=3)
    if cfg.has_object:
        goal += np.asarray(cfg.target_offset)
        goal[2] = sim.height_offset
        if cfg.target_in_the_air and rng.uniform() < 0.5:
            goal[2] += rng.uniform(0, 0.45)
    return object_xy, goal


# ---------------------------------------------------------------------------------------------
# Scripted controllers (closed loop: each model runs its own loop)
# ---------------------------------------------------------------------------------------------

Policy = Callable[[FetchSim, np.ndarray], np.ndarray]


def _toward(target: np.ndarray, grip: np.ndarray, gain: float = 10.0) -> np.ndarray:
    return np.clip(gain * (target - grip), -1.0, 1.0)


def _over(grip: np.ndarray, point: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """5 cm above ``point``; straight up first while the gripper is low, so it clears the object."""
    if grip[2] < obj[2] + 0.04:
        return np.r_[grip[:2], obj[2] + 0.05]
    return point + [0, 0, 0.05]


def make_scripted(task: str) -> Policy:
    """A phase-based controller for ``task``; phases only advance."""
    phase = {"k": 0, "t": 0}

    def reach(sim: FetchSim, goal: np.ndarray) -> np.ndarray:
        return np.r_[_toward(goal, sim.grip), 0.0]

    def push(sim: FetchSim, goal: np.ndarray) -> np.ndarray:
        grip, obj = sim.grip, sim.obj
        u = goal[:2] - obj[:2]
        u = np.r_[u / (np.linalg.norm(u) + 1e-9), 0.0]
        behind = obj - 0.06 * u
        if phase["k"] == 0:  # above the point behind the object, rising first
            target = _over(grip, behind, obj)
        elif phase["k"] == 1:  # down beside it
            target = behind
        else:  # push along the line to the goal, slowing down near it
            dist = np.linalg.norm(goal[:2] - obj[:2])
            target = obj + (min(dist, 0.04) - 0.045) * u
        if phase["k"] < 2 and np.linalg.norm(target - grip) < 0.01:
            phase["k"] += 1
        return np.r_[_toward(target, grip), 0.0]

    def pick(sim: FetchSim, goal: np.ndarray) -> np.ndarray:
        grip, obj = sim.grip, sim.obj
        k = phase["k"]
        if k == 0:
            target, fingers = obj + [0, 0, 0.08], 1.0
        elif k == 1:
            target, fingers = obj, 1.0
        elif k == 2:  # close and wait
            target, fingers = obj, -1.0
            phase["t"] += 1
        else:
            target, fingers = goal, -1.0
        if (k < 2 and np.linalg.norm(target - grip) < 0.01) or (k == 2 and phase["t"] >= 5):
            phase["k"] += 1
        return np.r_[_toward(target, grip), fingers]

    def slide(sim: FetchSim, goal: np.ndarray) -> np.ndarray:
        grip, obj = sim.grip, sim.obj
        u = goal[:2] - obj[:2]
        u = np.r_[u / (np.linalg.norm(u) + 1e-9), 0.0]
        k = phase["k"]
        if k == 0:
            target = _over(grip, obj - 0.08 * u, obj)
        elif k == 1:
            target = obj - 0.08 * u
        elif k == 2:  # strike: full speed along the line for 6 steps
            phase["t"] += 1
            if phase["t"] >= 6:
                phase["k"] = 3
            return np.r_[u, 0.0]
        else:  # back off upwards
            return np.array([0.0, 0.0, 1.0, 0.0])
        if np.linalg.norm(target - grip) < 0.01:
            phase["k"] += 1
        return np.r_[_toward(target, grip), 0.0]

    return {"FetchReach": reach, "FetchPush": push, "FetchPickAndPlace": pick, "FetchSlide": slide}[
        task
    ]


# ---------------------------------------------------------------------------------------------
# Episodes and deviations
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Episode:
    """One episode's start, goal and, for open-loop episodes, its actions."""

    kind: str  # "scripted" or "random"
    object_xy: np.ndarray | None
    goal: np.ndarray
    actions: np.ndarray | None  # open-loop actions for "random"


def make_episodes(task: str, n: int, seed: int = 0) -> list[Episode]:
    """``n`` scripted then ``n`` random-action episodes, starts and goals drawn as the env does."""
    sim = FetchSim(scene.load_model(task), task)
    rng = np.random.default_rng(seed)
    episodes = []
    for kind in ("scripted", "random"):
        for _ in range(n):
            object_xy, goal = sample_episode(sim, rng)
            actions = rng.uniform(-1, 1, (N_STEPS, 4)) if kind == "random" else None
            episodes.append(Episode(kind, object_xy, goal, actions))
    return episodes


def rollout(
    sim: FetchSim, task: str, ep: Episode, obj_shift: float = 0.0, nudge: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Gripper and object positions (N_STEPS, 3) after each step."""
    object_xy = None if ep.object_xy is None else ep.object_xy + [obj_shift, 0.0]
    sim.reset(object_xy)
    policy = make_scripted(task)
    nudge_vec = np.full(4, nudge) if nudge else None
    grips, objs = [], []
    for t in range(N_STEPS):
        a = ep.actions[t] if ep.actions is not None else policy(sim, ep.goal)
        sim.step(a, nudge_vec)
        grips.append(sim.grip)
        objs.append(sim.obj)
    return np.array(grips), np.array(objs)


def deviations(
    ref: list[tuple[np.ndarray, np.ndarray]], other: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """(episodes, 2): the largest gripper and object deviation over each episode."""
    return np.array(
        [
            [np.linalg.norm(g1 - g0, axis=1).max(), np.linalg.norm(o1 - o0, axis=1).max()]
            for (g0, o0), (g1, o1) in zip(ref, other, strict=True)
        ]
    )


def run_all(sim: FetchSim, task: str, eps: list[Episode], **kw) -> list:
    """``rollout`` of every episode."""
    return [rollout(sim, task, ep, **kw) for ep in eps]


def check_replica(task: str, n_steps: int = REPLICA_STEPS) -> float:
    """Largest |obs difference| between the replica and gymnasium-robotics ``env.step``."""
    import gymnasium as gym

    quiet_gymnasium_robotics()
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make(TASKS[task].gymnasium_id).unwrapped
    env.reset(seed=REPLICA_SEED)
    sim = FetchSim(scene.load_model(task), task)
    obj = None
    if sim.cfg.has_object:
        obj = env._utils.get_joint_qpos(env.model, env.data, "object0:joint")[:2]
    sim.reset(obj)
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(n_steps):
        a = rng.uniform(-1.2, 1.2, 4)
        obs, *_ = env.step(a)
        sim.step(a)
        worst = max(worst, float(np.abs(obs["observation"][:3] - sim.grip).max()))
        if sim.cfg.has_object:
            worst = max(worst, float(np.abs(obs["observation"][3:6] - sim.obj).max()))
    env.close()
    return worst


# ---------------------------------------------------------------------------------------------
# Study 1: each edit against the original, next to the sensitivity floor
# ---------------------------------------------------------------------------------------------


def load_variant(task: str, name: str) -> mujoco.MjModel:
    """The models the edit table compares with the original."""
    if name == "prune, base contact dropped":
        spec = scene.load_spec(task)
        scene.prune_collisions(spec, task, base_pads=False)
        return spec.compile()
    if name == "all (mjx variant)":
        return scene.load_model(task, "mjx")
    if name == "all, finger margin 0":
        model = scene.load_model(task, "mjx")
        for geom in ("robot0:r_gripper_finger_link", "robot0:l_gripper_finger_link"):
            model.geom_margin[model.geom(geom).id] = 0.0
        return model
    return scene.load_edited(task, tuple(name.split(" + ")))


def edit_rows(task: str) -> list[str]:
    rows = ["prune", "prune, base contact dropped", "margins", "prune + margins"]
    if task == "FetchSlide":
        rows += ["puck", "prune + puck"]
    return rows + ["all (mjx variant)", "all, finger margin 0"]


def summarise(dev: np.ndarray, n: int) -> list[float]:
    """Worst and median over episodes of gripper and object deviation, scripted then random."""
    out = []
    for part in (dev[:n], dev[n:]):
        out += [part[:, 0].max(), np.median(part[:, 0]), part[:, 1].max(), np.median(part[:, 1])]
    return out


def edit_study(n: int) -> dict[str, list[tuple[str, list[float]]]]:
    """Per task: (row name, summary) for the sensitivity floor and every edit."""
    table = {}
    for task in TASKS:
        eps = make_episodes(task, n)
        base = FetchSim(scene.load_model(task), task)
        ref = run_all(base, task, eps)
        rows = []
        if base.cfg.has_object:
            dev = deviations(ref, run_all(base, task, eps, obj_shift=1e-6))
            rows.append(("floor: object x + 1e-6 m", summarise(dev, n)))
        dev = deviations(ref, run_all(base, task, eps, nudge=1e-6))
        rows.append(("floor: action + 1e-6", summarise(dev, n)))
        for name in edit_rows(task):
            sim = FetchSim(load_variant(task, name), task)
            rows.append((name, summarise(deviations(ref, run_all(sim, task, eps)), n)))
        table[task] = rows
    return table


# ---------------------------------------------------------------------------------------------
# Study 2: where the Slide puck's deviation comes from
# ---------------------------------------------------------------------------------------------


def prism_model(sides: int, radius: str) -> mujoco.MjModel:
    """The original Slide scene with only the puck replaced, at a chosen polygon radius."""
    spec = scene.load_spec("FetchSlide")
    scene.puck_to_prism(spec, "FetchSlide", sides=sides)
    mesh = spec.mesh(scene.PUCK_MESH)
    verts = np.array(mesh.uservert).reshape(-1, 3)
    r = 0.025  # the cylinder's radius
    target = {
        "equal area": np.linalg.norm(verts[0, :2]),
        "inscribed": r,
        "circumscribed": r / np.cos(np.pi / sides),
    }[radius]
    verts[:, :2] *= target / np.linalg.norm(verts[0, :2])
    mesh.uservert = verts.ravel().tolist()
    return spec.compile()


def split_contact_model(prism_against: str) -> mujoco.MjModel:
    """Puck with both shapes: the prism touches only ``prism_against``, the cylinder the rest.

    The second (massless) geom and explicit pairs with the original contact parameters make
    each contact pair use one shape, so the two pairs' contributions can be told apart.
    """
    task = "FetchSlide"
    spec = scene.load_spec(task)
    ref = spec.copy().compile()
    scene.puck_to_prism(spec, task)
    body = spec.body("object0")
    cyl = body.add_geom(
        name="object0:cylinder",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.025, 0.02, 0],
        friction=[0.1, 0.005, 0.0001],
        mass=0.0,
        contype=0,
        conaffinity=0,
    )
    prism = spec.geom("object0")
    prism.contype = prism.conaffinity = 0
    gripper = [
        "robot0:r_gripper_finger_link",
        "robot0:l_gripper_finger_link",
        "robot0:gripper_link",
    ]
    ground = ["table0", "floor0"]
    prism_side = gripper if prism_against == "gripper" else ground
    puck = ref.geom("object0").id
    for other in gripper + ground:
        mine = "object0" if other in prism_side else cyl.name
        scene._add_matching_pair(spec, ref, puck, ref.geom(other).id, names=(mine, other))
    return spec.compile()


def launch_test(models: dict[str, mujoco.MjModel], angles: tuple[float, ...]) -> list[list]:
    """Puck launched at LAUNCH_SPEED along the table, no gripper motion: final xy per model."""
    rows = []
    for angle in angles:
        row = [f"{np.degrees(angle):.0f}"]
        for model in models.values():
            sim = FetchSim(model, "FetchSlide")
            sim.reset(np.array(LAUNCH_XY))
            dof = model.jnt_dofadr[model.joint("object0:joint").id]
            sim.d.qvel[dof : dof + 3] = [LAUNCH_SPEED * np.cos(angle), LAUNCH_SPEED * np.sin(angle),
                                         0.0]
            for _ in range(N_STEPS):
                sim.step(np.zeros(4))
            row.append(sim.obj)
        rows.append(row)
    return rows


def slide_study(n: int) -> dict:
    task = "FetchSlide"
    eps = make_episodes(task, n)
    ref = run_all(FetchSim(scene.load_model(task), task), task, eps)
    shapes = []
    for sides, radius in [
        (16, "equal area"),
        (16, "inscribed"),
        (16, "circumscribed"),
        (19, "equal area"),
        (32, "equal area"),
        (64, "equal area"),
        (128, "equal area"),
    ]:
        sim = FetchSim(prism_model(sides, radius), task)
        shapes.append(
            (f"{sides} sides, {radius}", summarise(deviations(ref, run_all(sim, task, eps)), n))
        )
    for against in ("gripper", "table"):
        sim = FetchSim(split_contact_model(against), task)
        dev = deviations(ref, run_all(sim, task, eps))
        shapes.append((f"prism only against the {against}", summarise(dev, n)))
    models = {"cylinder": scene.load_model(task), "16-prism": prism_model(16, "equal area")}
    launches = launch_test(models, tuple(np.radians([0, 20, 45, 70])))
    return {"shapes": shapes, "launches": launches}


# ---------------------------------------------------------------------------------------------
# Study 3: MJX against native MuJoCo on the same edited model, float64
# ---------------------------------------------------------------------------------------------


def native_physics_no_jdotv(m: mujoco.MjModel, d: mujoco.MjData) -> None:
    """Native substeps with the weld's reference acceleration as MJX computes it.

    MuJoCo 3.11 subtracts the Jdot*qvel term of connect/weld constraints from efc_aref
    (``mj_referenceConstraint`` -> ``mj_Jdotv``); MJX 3.11 uses -B*vel - K*I*pos only. Between
    ``mj_step1`` (which computes efc_aref) and ``mj_step2`` (solve and integrate) the equality
    rows are reset to that plain formula.
    """
    eq = mujoco.mjtConstraint.mjCNSTR_EQUALITY
    for _ in range(N_SUBSTEPS):
        mujoco.mj_step1(m, d)
        rows = d.efc_type == eq
        k = d.efc_KBIP[rows]
        d.efc_aref[rows] = -k[:, 1] * d.efc_vel[rows] - k[:, 0] * k[:, 2] * (
            d.efc_pos[rows] - d.efc_margin[rows]
        )
        mujoco.mj_step2(m, d)


def native_physics_split(m: mujoco.MjModel, d: mujoco.MjData) -> None:
    """``mj_step1`` + ``mj_step2`` unmodified (checks that the split equals ``mj_step``)."""
    for _ in range(N_SUBSTEPS):
        mujoco.mj_step1(m, d)
        mujoco.mj_step2(m, d)


def exact_qp(M, a0, J, D, aref, eq) -> np.ndarray:  # noqa: N803 (MuJoCo's names)
    """Exact minimiser of MuJoCo's primal problem for pyramidal cones (no frictionloss rows).

    0.5 (a - a0)' M (a - a0) + sum_active 0.5 D_i (J_i a - aref_i)^2, where equality rows are
    always active and the others when J_i a < aref_i; solved by iterating the active set.
    """
    a = a0.copy()
    for _ in range(200):
        act = eq | (J @ a - aref < 0)
        H = M + J[act].T @ (D[act, None] * J[act])  # noqa: N806
        a_new = np.linalg.solve(H, M @ a0 + J[act].T @ (D[act] * aref[act]))
        if np.abs(a_new - a).max() < 1e-13:
            break
        a = a_new
    return a_new


def air_episode(rng: np.random.Generator) -> np.ndarray:
    """Actions that lift the gripper off the table first and then wander in the air."""
    actions = np.c_[
        rng.uniform(-1, 1, (N_STEPS, 2)), rng.uniform(-0.3, 0.3, N_STEPS), np.zeros(N_STEPS)
    ]
    actions[:6] = [0.0, 0.0, 1.0, 0.0]
    return actions


def mjx_study(task: str = "FetchPush") -> dict:
    import jax
    from rdher_jax.envs.notices import quiet_mjx

    quiet_mjx()
    from mujoco import mjx

    jax.config.update("jax_enable_x64", True)
    m = scene.load_model(task, "mjx")
    sim = FetchSim(m, task)  # its setup resets the weld's eq_data: put the model after it
    mx = mjx.put_model(m)
    jit_step = jax.jit(mjx.step)
    t0 = time.perf_counter()
    jax.block_until_ready(jit_step(mx, mjx.put_data(m, mujoco.MjData(m))))
    compile_s = time.perf_counter() - t0

    # -- single steps from identical states taken along a random-action episode
    eps = make_episodes(task, 1, seed=1)
    rand_ep = eps[1]
    states = []

    def record(mm: mujoco.MjModel, d: mujoco.MjData) -> None:
        for k in range(N_SUBSTEPS):
            if k in (0, 10):
                snap = mujoco.MjData(mm)
                mujoco.mj_copyData(snap, mm, d)
                states.append(snap)
            mujoco.mj_step(mm, d)

    sim.physics = record
    sim.reset(rand_ep.object_xy)
    for t in range(0, N_STEPS, 5):
        sim.step(rand_ep.actions[t])
    robot_geoms = {m.geom(n).id for n in scene.COLLIDING_ROBOT_GEOMS}
    singles = []
    for snap in states:
        dx = jit_step(mx, mjx.put_data(m, snap))
        nf = mujoco.MjData(m)
        mujoco.mj_copyData(nf, m, snap)
        mujoco.mj_forward(m, nf)
        ns = mujoco.MjData(m)
        mujoco.mj_copyData(ns, m, snap)
        mujoco.mj_step(m, ns)
        M = np.zeros((m.nv, m.nv))  # noqa: N806
        mujoco.mj_fullM(m, nf, M)
        J = nf.efc_J.reshape(nf.nefc, m.nv)  # noqa: N806
        eq = nf.efc_type == 0
        k = nf.efc_KBIP
        plain = -k[:, 1] * nf.efc_vel - k[:, 0] * k[:, 2] * (nf.efc_pos - nf.efc_margin)
        xJ, xD = np.asarray(dx._impl.efc_J), np.asarray(dx._impl.efc_D)  # noqa: N806
        xaref, xtype = np.asarray(dx._impl.efc_aref), np.asarray(dx._impl.efc_type)
        xeq = xtype == 0
        fixed = xaref.copy()
        fixed[xeq] = nf.efc_aref[eq]
        a_native = exact_qp(M, nf.qacc_smooth, J, nf.efc_D, nf.efc_aref, eq)
        a_fixed = exact_qp(M, np.asarray(dx.qacc_smooth), xJ, xD, fixed, xeq)
        touching = any(
            c.geom1 in robot_geoms or c.geom2 in robot_geoms for c in nf.contact[: nf.ncon]
        )
        singles.append(
            {
                "robot contact": touching,
                "nefc native": int(nf.nefc),
                "rows MJX": int((np.abs(xJ).sum(1) > 0).sum()),
                "qacc_smooth": np.abs(np.asarray(dx.qacc_smooth) - nf.qacc_smooth).max(),
                "weld aref MJX - native": np.abs(xaref[xeq] - nf.efc_aref[eq]).max(),
                "weld aref MJX - plain": np.abs(xaref[xeq] - plain[eq]).max(),
                "other aref native - plain": np.abs(nf.efc_aref[~eq] - plain[~eq]).max(initial=0),
                "qfrc_constraint": np.abs(
                    np.asarray(dx.qfrc_constraint) - nf.qfrc_constraint
                ).max(),
                "qacc": np.abs(np.asarray(dx.qacc) - nf.qacc).max(),
                "qvel after": np.abs(np.asarray(dx.qvel) - ns.qvel).max(),
                "native solver vs exact": np.abs(nf.qacc - a_native).max(),
                "MJX + native weld aref vs native": np.abs(a_fixed - a_native).max(),
            }
        )

    # -- whole episodes: MJX physics (env glue native) vs native, vs native without Jdot*v
    def mjx_physics_for(mjx_model) -> Physics:
        def physics(mm: mujoco.MjModel, d: mujoco.MjData) -> None:
            dx = mjx.put_data(mm, d)
            for _ in range(N_SUBSTEPS):
                dx = jit_step(mjx_model, dx)
            d.qpos[:], d.qvel[:] = np.asarray(dx.qpos), np.asarray(dx.qvel)
            d.qacc_warmstart[:], d.time = np.asarray(dx.qacc_warmstart), float(dx.time)
            mujoco.mj_forward(mm, d)

        return physics

    # Same scene with the finger boxes' margin at 0: MJX's box-box collision reports only
    # penetrating points, so a margin there acts differently from MuJoCo's (see the findings).
    m0 = scene.load_model(task, "mjx")
    for name in ("robot0:r_gripper_finger_link", "robot0:l_gripper_finger_link"):
        m0.geom_margin[m0.geom(name).id] = 0.0
    FetchSim(m0, task)  # weld reset before put_model, as above
    mx0 = mjx.put_model(m0)

    air = Episode("air", rand_ep.object_xy, rand_ep.goal, air_episode(np.random.default_rng(2)))
    cases = (
        ("random actions", m, mx, rand_ep),
        ("gripper in the air", m, mx, air),
        ("random actions, finger margin 0", m0, mx0, rand_ep),
    )
    trajectories = []
    t0 = time.perf_counter()
    for label, mm, mmx, ep in cases:
        runs = {}
        for name, phys in (
            ("native", native_physics),
            ("native, step1/step2", native_physics_split),
            ("native without Jdot*v", native_physics_no_jdotv),
            ("MJX", mjx_physics_for(mmx)),
        ):
            runs[name] = rollout(FetchSim(mm, task, phys), task, ep)
        dev = {k: deviations([runs["native"]], [v])[0] for k, v in runs.items() if k != "native"}
        dev["MJX vs native without Jdot*v"] = deviations(
            [runs["native without Jdot*v"]], [runs["MJX"]]
        )[0]
        trajectories.append((label, dev))
    return {
        "task": task,
        "compile_s": compile_s,
        "episodes_s": time.perf_counter() - t0,
        "singles": singles,
        "trajectories": trajectories,
    }


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------

MJX_BEGIN, MJX_END = "<!-- mjx-study -->", "<!-- /mjx-study -->"

# Section 4 holds the findings: prose written from the tables above it, kept in the results file
# (never here) and carried over verbatim when the tables are regenerated.
FINDINGS_HEAD = "## 4. Findings"
FINDINGS_MISSING = (
    FINDINGS_HEAD + "\n\n(none yet: write what the tables show here; reruns keep this section)\n"
)


def _fmt(x: float) -> str:
    return "0" if x == 0 else f"{x:.1e}"


def edits_markdown(table: dict, n: int) -> str:
    head = (
        "| model vs original | scripted grip worst | median | scripted obj worst | median "
        "| random grip worst | median | random obj worst | median |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    out = [
        f"Deviation in metres: per episode the largest distance between the two runs' gripper "
        f"(grip site) or object positions over the 50 steps; worst and median over {n} scripted "
        f"and {n} random-action episodes per task. Floor rows: the original scene against itself "
        f"with the start or the actions perturbed.\n"
    ]
    for task, rows in table.items():
        out.append(f"\n### {task}\n\n{head}")
        for name, vals in rows:
            out.append(f"| {name} | " + " | ".join(_fmt(v) for v in vals) + " |\n")
    return "".join(out)


def slide_markdown(study: dict, n: int) -> str:
    head = (
        "| puck shape vs cylinder | scripted obj worst | median | random obj worst | median |\n"
        "|---|---|---|---|---|\n"
    )
    out = [f"Object deviation against the original scene ({n} + {n} episodes as above).\n\n", head]
    for name, v in study["shapes"]:
        out.append(f"| {name} | {_fmt(v[2])} | {_fmt(v[3])} | {_fmt(v[6])} | {_fmt(v[7])} |\n")
    out.append(
        f"\nPuck launched at {LAUNCH_SPEED:g} m/s along the table from {LAUNCH_XY}, gripper "
        f"still, {N_STEPS} steps "
        "(the table ends at y = 1.2; a z near 0.02 means the puck fell off):\n\n"
        "| direction (deg) | cylinder final xyz | 16-prism final xyz |\n|---|---|---|\n"
    )
    for angle, *finals in study["launches"]:
        out.append(f"| {angle} | " + " | ".join(np.array2string(f, precision=3) for f in finals))
        out.append(" |\n")
    return "".join(out)


def mjx_markdown(study: dict) -> str:
    s = study["singles"]
    keys = [k for k in s[0] if k != "robot contact"]
    out = [
        f"{study['task']}, mjx variant, float64 (`jax_enable_x64`), XLA fusion emitters off. "
        f"jit of `mjx.step`: {study['compile_s']:.0f} s; episodes: {study['episodes_s']:.0f} s.\n\n"
        f"One `mjx.step` against one `mj_step` from {len(s)} identical states along a "
        "random-action episode (largest absolute difference; counts are rows):\n\n"
        "| states | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys) + "\n"
    ]
    for touching in (False, True):
        sel = [r for r in s if r["robot contact"] == touching]
        if not sel:
            continue
        label = f"{len(sel)} with robot contacts" if touching else f"{len(sel)} without"
        cells = []
        for k in keys:
            vals = [r[k] for r in sel]
            if k.startswith("nefc") or k.startswith("rows"):
                cells.append(f"{min(vals)}-{max(vals)}")
            else:
                cells.append(_fmt(max(vals)))
        out.append(f"| {label} | " + " | ".join(cells) + " |\n")
    out.append(
        "\nWhole episodes, 50 env steps: MJX runs the 20 substeps, the env glue (mocap target, "
        "finger reset, forward) is native; deviation of gripper / object, metres:\n\n"
        "| episode | comparison | gripper worst | object worst |\n|---|---|---|---|\n"
    )
    for label, dev in study["trajectories"]:
        for name, (g, o) in dev.items():
            ref = name if name.startswith("MJX vs") else f"{name} vs native"
            out.append(f"| {label} | {ref} | {_fmt(g)} | {_fmt(o)} |\n")
    return "".join(out)


def replica_markdown(replica: dict[str, float]) -> str:
    return (
        "Largest absolute observation difference between the replica and gymnasium-robotics'\n"
        f"`env.step` over {REPLICA_STEPS} random-action steps from `reset(seed={REPLICA_SEED})` "
        "(gripper and object position):\n\n| task | difference |\n|---|---|\n"
        + "".join(f"| {task} | {_fmt(d)} |\n" for task, d in replica.items())
    )


def write_report(replica: str, edits: str, slide: str, mjx_section: str | None,
                 path: str = RESULTS) -> str:
    """Write the markdown. An MJX section from an earlier ``--mjx`` run is kept if not redone;
    the findings section of the existing file is always kept."""
    findings = FINDINGS_MISSING
    if os.path.exists(path):
        old = open(path).read()
        if mjx_section is None and MJX_BEGIN in old:
            mjx_section = old[old.index(MJX_BEGIN) + len(MJX_BEGIN) : old.index(MJX_END)].strip()
        if FINDINGS_HEAD in old:
            findings = old[old.index(FINDINGS_HEAD) :]
    text = (
        "# What the MJX scene edits do to the Fetch dynamics\n\n"
        "Sections 1-3 are generated by `experiments/scene_edits.py` (`--mjx` adds the MJX\n"
        "section); section 4, the findings, is written from them by hand and kept by reruns.\n"
        "Native runs use a replica of gymnasium-robotics' `Fetch*-v4` step, checked against\n"
        "`env.step`.\n\n"
        + replica
        + "\n## 1. Each edit against the original scene (native MuJoCo)\n\n"
        + edits
        + "\n## 2. The Slide puck\n\n"
        + slide
        + "\n## 3. MJX against native MuJoCo on the same edited scene\n\n"
        + MJX_BEGIN
        + "\n"
        + (mjx_section or "(not run yet: `python experiments/scene_edits.py --mjx`)").strip()
        + "\n"
        + MJX_END
        + "\n\n"
        + findings
    )
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=8, help="scripted (and random) per task")
    parser.add_argument("--mjx", action="store_true", help="also run the MJX study (~3 min)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    replica = {task: check_replica(task) for task in TASKS}
    print("replica vs env.step, largest |obs difference|:", replica)
    edits = edits_markdown(edit_study(args.episodes), args.episodes)
    slide = slide_markdown(slide_study(args.episodes), args.episodes)
    print(f"native studies: {time.perf_counter() - t0:.0f} s")
    mjx_section = mjx_markdown(mjx_study()) if args.mjx else None
    print(write_report(replica_markdown(replica), edits, slide, mjx_section))
    print(f"total: {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
