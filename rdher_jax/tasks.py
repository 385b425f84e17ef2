"""The trainer's and the paper's facts per task: what the config defaults, the help text, the
experiment profiles and the report read about a task.

Keyed by the task registry's names (``rdher_jax.envs.registry``), which holds everything
physical about a task (scene, episode length, goal logic); this table re-lists none of it and
reads it from there. Imports nothing heavy, so the command line can validate a config before
JAX loads.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .envs import registry


@dataclass(frozen=True)
class Task:
    """What the trainer and the experiments need to know about one task beyond its physics.

    Attributes:
      name: the task's name in the registry, as ``env=`` takes it.
      epochs, n_cycles: the default budget of ``python -m rdher_jax.train``.
      paper_lambdas: RDHER's (lambda_r, lambda_h), the paper's choice for the task (section
        5.3); a moving task takes those of the task it is modelled on.
      paper_table2: the paper's Table 2, best-policy test success (%) per algorithm (empty for
        tasks the paper did not run).
      paper_table3: the paper's Table 3, wall clock of one run (h:mm:ss) per algorithm.
      preset_values: per preset name, the keys that preset takes for this task on top of its
        own values (config.PRESETS), such as its budget; explicit ``key=value`` arguments still
        override them.
    """

    name: str
    epochs: int
    n_cycles: int
    paper_lambdas: tuple[float, float]
    paper_table2: Mapping[str, int] = field(default_factory=dict)
    paper_table3: Mapping[str, str] = field(default_factory=dict)
    preset_values: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def spec(self) -> registry.TaskSpec:
        """The task's physics, from the registry."""
        return registry.TASKS[self.name]

    @property
    def episode_length(self) -> int:
        return self.spec.episode_length

    @property
    def static(self) -> str:
        """The gymnasium-robotics task a moving-goal task is modelled on ("" if static)."""
        return self.spec.static

    @property
    def moving(self) -> bool:
        return bool(self.static)


def _moving(name: str, epochs: int, n_cycles: int) -> Task:
    """A moving task, with the paper's weights of the task it is modelled on."""
    return Task(name, epochs, n_cycles, _PAPER[registry.TASKS[name].static].paper_lambdas)


# preset=fast's own values per task (docs/performance.md, 'Levers'). The budget: the env steps
# within which each task is to be solved (Push 500,000, PickAndPlace 600,000, Slide 2,000,000),
# in epochs of 50 cycles. Push and PickAndPlace: twin critics (TD3's clipped double Q). Slide:
# the paper's own learner (Table 1: two episodes then 40 updates per cycle, 3 x 256, action
# penalty, targets moved 5% per cycle, no TD3 smoothing or delay, no terminal rule), which learns
# Slide where the fast learner does not, with twin critics, which lift it further; only the
# preset's overlap, dher_fraction, retest and select_top stay.
FAST_VALUES: dict[str, dict[str, Any]] = {
    "FetchPush": {"epochs": 200, "n_critics": 2},
    "FetchPickAndPlace": {"epochs": 240, "n_critics": 2},
    "FetchSlide": {"epochs": 400, "num_envs": 2, "layers": 3, "action_l2": 1.0,
                   "target_every": 0, "polyak": 0.95, "target_noise": 0.0, "policy_delay": 1,
                   "terminal": "none", "n_critics": 2},
}

# What solving a task means under preset=fast (experiments' solve profile): the best policy's
# success on 100 new episodes to reach (mean over seeds), and the trailing mean of 3 test epochs
# whose first crossing the report times (Push and PickAndPlace 0.97 / 0.9, Slide 0.8 / 0.8).
SOLVE_GOALS: dict[str, tuple[float, float]] = {
    "FetchPush": (0.97, 0.9),
    "FetchPickAndPlace": (0.97, 0.9),
    "FetchSlide": (0.8, 0.8),
}

_PAPER: dict[str, Task] = {
    t.name: t
    for t in (
        Task("FetchReach", 5, 10, (2.0, 1.0),
             {"ddpg": 100, "her": 88, "cher": 89, "dher": 100, "rdher": 100},
             {"ddpg": "00:50:24", "her": "00:46:55", "cher": "01:45:13", "dher": "00:11:27",
              "rdher": "00:11:16"}),
        Task("FetchPush", 50, 50, (4.0, 0.5),
             {"ddpg": 15, "her": 39, "cher": 14, "dher": 21, "rdher": 58},
             {"ddpg": "03:35:59", "her": "03:30:32", "cher": "06:43:20", "dher": "04:10:14",
              "rdher": "03:53:16"},
             {"fast": FAST_VALUES["FetchPush"]}),
        Task("FetchSlide", 50, 50, (4.0, 0.5),
             {"ddpg": 2, "her": 24, "cher": 17, "dher": 41, "rdher": 50},
             {"ddpg": "01:53:53", "her": "01:49:18", "cher": "03:41:51", "dher": "01:57:47",
              "rdher": "01:43:58"},
             {"fast": FAST_VALUES["FetchSlide"]}),
        Task("FetchPickAndPlace", 50, 50, (2.0, 1.0),
             {"ddpg": 8, "her": 25, "cher": 33, "dher": 45, "rdher": 47},
             {"ddpg": "03:34:50", "her": "03:28:32", "cher": "07:50:02", "dher": "04:06:21",
              "rdher": "03:50:06"},
             {"fast": FAST_VALUES["FetchPickAndPlace"]}),
    )
}
# One row per registry task (tests/test_packaging.py checks that the two tables agree).
TASKS: dict[str, Task] = {
    **_PAPER,
    "FetchReachMoving": _moving("FetchReachMoving", 5, 10),
    "FetchPushMoving": _moving("FetchPushMoving", 50, 50),
}
TASK_NAMES: tuple[str, ...] = registry.TASK_NAMES
# The paper's four tasks (gymnasium-robotics' Fetch*-v4), in the paper's order.
PAPER_TASKS: tuple[str, ...] = registry.GYMNASIUM_TASK_NAMES
MOVING_TASKS: tuple[str, ...] = registry.MOVING_TASK_NAMES


def task(name: str) -> Task:
    """The entry of ``name``; a ValueError naming the valid tasks otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid: {', '.join(TASKS)}")
    return TASKS[name]


def defaults_doc() -> str:
    """One line for the help text: each task's default epochs x cycles."""
    return "; ".join(f"{n} {t.epochs}x{t.n_cycles}" for n, t in TASKS.items())
