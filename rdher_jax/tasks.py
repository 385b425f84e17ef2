"""The one table of per-task facts: what the config defaults, the help text, the experiment
profiles and the report read about a task.

Physics constants (reset ranges, thresholds, scenes) are the env package's
(``rdher_jax.envs.physics``), which checks at import that it knows exactly these tasks. This
module imports nothing heavy, so the command line can validate a config before JAX loads.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Task:
    """What the trainer and the experiments need to know about one task.

    Attributes:
      name: the task's name, as ``env=`` takes it.
      episode_length: env steps per episode (gymnasium-robotics' ``max_episode_steps``).
      epochs, n_cycles: the default budget of ``python -m rdher_jax.train``.
      paper_lambdas: RDHER's (lambda_r, lambda_h), the paper's choice for the task (section
        5.3); the moving tasks take those of their static counterparts.
      paper_table2: the paper's Table 2, best-policy test success (%) per algorithm (empty for
        tasks the paper did not run).
      paper_table3: the paper's Table 3, wall clock of one run (h:mm:ss) per algorithm.
      static: the gymnasium-robotics task a moving-goal task is modelled on ("" if static).
    """

    name: str
    episode_length: int
    epochs: int
    n_cycles: int
    paper_lambdas: tuple[float, float]
    paper_table2: Mapping[str, int] = field(default_factory=dict)
    paper_table3: Mapping[str, str] = field(default_factory=dict)
    static: str = ""

    @property
    def moving(self) -> bool:
        return bool(self.static)


TASKS: dict[str, Task] = {
    t.name: t
    for t in (
        Task("FetchReach", 50, 5, 10, (2.0, 1.0),
             {"ddpg": 100, "her": 88, "cher": 89, "dher": 100, "rdher": 100},
             {"ddpg": "00:50:24", "her": "00:46:55", "cher": "01:45:13", "dher": "00:11:27",
              "rdher": "00:11:16"}),
        Task("FetchPush", 50, 50, 50, (4.0, 0.5),
             {"ddpg": 15, "her": 39, "cher": 14, "dher": 21, "rdher": 58},
             {"ddpg": "03:35:59", "her": "03:30:32", "cher": "06:43:20", "dher": "04:10:14",
              "rdher": "03:53:16"}),
        Task("FetchSlide", 50, 50, 50, (4.0, 0.5),
             {"ddpg": 2, "her": 24, "cher": 17, "dher": 41, "rdher": 50},
             {"ddpg": "01:53:53", "her": "01:49:18", "cher": "03:41:51", "dher": "01:57:47",
              "rdher": "01:43:58"}),
        Task("FetchPickAndPlace", 50, 50, 50, (2.0, 1.0),
             {"ddpg": 8, "her": 25, "cher": 33, "dher": 45, "rdher": 47},
             {"ddpg": "03:34:50", "her": "03:28:32", "cher": "07:50:02", "dher": "04:06:21",
              "rdher": "03:50:06"}),
        Task("FetchReachMoving", 50, 5, 10, (2.0, 1.0), static="FetchReach"),
        Task("FetchPushMoving", 50, 50, 50, (4.0, 0.5), static="FetchPush"),
    )
}
TASK_NAMES: tuple[str, ...] = tuple(TASKS)
# The paper's four tasks (gymnasium-robotics' Fetch*-v4), in the paper's order.
PAPER_TASKS: tuple[str, ...] = tuple(n for n, t in TASKS.items() if not t.moving)
MOVING_TASKS: tuple[str, ...] = tuple(n for n, t in TASKS.items() if t.moving)


def task(name: str) -> Task:
    """The entry of ``name``; a ValueError naming the valid tasks otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid: {', '.join(TASKS)}")
    return TASKS[name]


def defaults_doc() -> str:
    """One line for the help text: each task's default epochs x cycles."""
    return "; ".join(f"{n} {t.epochs}x{t.n_cycles}" for n, t in TASKS.items())
