"""The task registry: every physical fact of every Fetch task, in one table.

``TASKS`` maps a task's name to its ``TaskSpec``: the scene it loads, its episode length, the
reset ranges, goal sampling and success threshold of gymnasium-robotics' ``Fetch*-v4`` and, for
DHER's moving-goal tasks (see ``fetch``), the task each is modelled on and how its goal moves.
The scenes, the physics setup and the task logic read a task from here, and so does anything
above the package; nothing else names one.

Importing this module imports neither JAX nor MuJoCo, so a command line can check a task's name
before they load.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

# gymnasium-robotics' version of the Fetch tasks these reproduce (``FetchPush-v4``).
GYMNASIUM_VERSION = "v4"


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """One Fetch task, as gymnasium-robotics' ``Fetch*-v4`` (and, for the moving tasks, as
    DHER's ``DyFetchEnv``) defines it.

    Attributes:
      name: the task's name, as ``make_env`` takes it.
      xml: the scene's MJCF file in gymnasium_robotics' ``envs/assets/fetch``.
      has_object, block_gripper, gripper_extra_height, target_in_the_air, target_offset,
        obj_range, target_range, initial_qpos, distance_threshold: gymnasium-robotics'
        ``MujocoFetchEnv`` arguments (the threshold is the reward's and success's).
      episode_length: env steps per episode (gymnasium-robotics' ``max_episode_steps``).

    The moving tasks' fields (their defaults keep a goal still):
      static: the gymnasium-robotics task whose scene and ``_env_setup`` the task uses ("" for
        the gymnasium-robotics tasks themselves).
      goal_speed: metres per env step the goal moves along ``goal_direction``.
      goal_direction: unit direction of the goal's motion, the same for every episode.
      goal_z: if set, every sampled goal gets this height (Dy-Reaching: 0.5).
      object_x_offset: if set, the object starts at the gripper's xy + (offset, U(+-obj_range)),
        without rejection sampling (Dy-Pushing: 0.1).
    """

    name: str
    xml: str
    has_object: bool
    block_gripper: bool
    gripper_extra_height: float
    target_in_the_air: bool
    target_offset: tuple[float, float, float]
    obj_range: float
    target_range: float
    initial_qpos: Mapping[str, float | list[float]]
    distance_threshold: float = 0.05
    episode_length: int = 50
    static: str = ""
    goal_speed: float = 0.0
    goal_direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    goal_z: float | None = None
    object_x_offset: float | None = None

    @property
    def scene_name(self) -> str:
        """The task whose scene and setup this one uses: ``static``, or itself."""
        return self.static or self.name

    @property
    def moving(self) -> bool:
        return any(self.goal_direction)

    @property
    def gymnasium_id(self) -> str | None:
        """gymnasium's id of the task (``FetchPush-v4``); None for a moving task."""
        return None if self.static else f"{self.name}-{GYMNASIUM_VERSION}"


_PUSH_QPOS = {
    "robot0:slide0": 0.405,
    "robot0:slide1": 0.48,
    "robot0:slide2": 0.0,
    "object0:joint": [1.25, 0.53, 0.4, 1.0, 0.0, 0.0, 0.0],
}

_REACH = TaskSpec(
    "FetchReach", "reach.xml", has_object=False, block_gripper=True, gripper_extra_height=0.2,
    target_in_the_air=True, target_offset=(0.0, 0.0, 0.0), obj_range=0.15, target_range=0.15,
    initial_qpos={"robot0:slide0": 0.4049, "robot0:slide1": 0.48, "robot0:slide2": 0.0},
)
_PUSH = TaskSpec(
    "FetchPush", "push.xml", has_object=True, block_gripper=True, gripper_extra_height=0.0,
    target_in_the_air=False, target_offset=(0.0, 0.0, 0.0), obj_range=0.15, target_range=0.15,
    initial_qpos=_PUSH_QPOS,
)
_SLIDE = TaskSpec(
    "FetchSlide", "slide.xml", has_object=True, block_gripper=True, gripper_extra_height=-0.02,
    target_in_the_air=False, target_offset=(0.4, 0.0, 0.0), obj_range=0.1, target_range=0.3,
    initial_qpos={"robot0:slide0": 0.05, "robot0:slide1": 0.48, "robot0:slide2": 0.0,
                  "object0:joint": [1.7, 1.1, 0.41, 1.0, 0.0, 0.0, 0.0]},
)
_PICK_AND_PLACE = TaskSpec(
    "FetchPickAndPlace", "pick_and_place.xml", has_object=True, block_gripper=False,
    gripper_extra_height=0.2, target_in_the_air=True, target_offset=(0.0, 0.0, 0.0),
    obj_range=0.15, target_range=0.15, initial_qpos=_PUSH_QPOS,
)
# DHER's Dy-Reaching and Dy-Pushing (mengf1/DHER, dygym/dygym/envs/robotics/{reach,push}.py and
# the DyReachEnv-v0 registration in dher/dher/ddpg_dher/experiment/train_dyreach.py): the scene,
# setup and constants of the task each is modelled on, but for these.
_REACH_MOVING = dataclasses.replace(
    _REACH, name="FetchReachMoving", static=_REACH.name, target_range=0.10,
    distance_threshold=0.01, goal_speed=0.011, goal_direction=(1.0, 0.0, 0.0), goal_z=0.5,
)
_PUSH_MOVING = dataclasses.replace(
    _PUSH, name="FetchPushMoving", static=_PUSH.name, distance_threshold=0.01, goal_speed=0.005,
    goal_direction=(0.0, 1.0, 0.0), object_x_offset=0.1,
)

TASKS: dict[str, TaskSpec] = {
    t.name: t
    for t in (_REACH, _PUSH, _SLIDE, _PICK_AND_PLACE, _REACH_MOVING, _PUSH_MOVING)
}
# gymnasium-robotics' four (the paper's, in its order), conformance-tested against Fetch*-v4.
GYMNASIUM_TASK_NAMES: tuple[str, ...] = tuple(n for n, t in TASKS.items() if not t.static)
# DHER's Dy-Reaching and Dy-Pushing.
MOVING_TASK_NAMES: tuple[str, ...] = tuple(n for n, t in TASKS.items() if t.static)
TASK_NAMES: tuple[str, ...] = tuple(TASKS)


def task_spec(name: str) -> TaskSpec:
    """The entry of ``name`` (a ``-v4`` suffix is accepted); a ValueError naming the valid
    tasks otherwise."""
    spec = TASKS.get(name.removesuffix(f"-{GYMNASIUM_VERSION}"))
    if spec is None:
        raise ValueError(f"unknown Fetch task {name!r}; valid: {', '.join(TASKS)}")
    return spec
