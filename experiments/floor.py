"""The floor of Table 2: the test success of a policy that does nothing, and the best epoch it
would report.

A Fetch episode counts as a success when the goal is within 5 cm of the object (of the gripper
on FetchReach) at its last step, so some episodes succeed with no action at all: the goal was
sampled next to where the object already lies. This script measures that rate on
gymnasium-robotics' own ``Fetch*-v4`` (zero actions for 50 steps from ``env.reset(seed=i)``,
``info['is_success']`` at the last step), and from it, for a run that never learns, the
expected best of ``--epochs`` epochs each tested on ``n`` episodes: the 'best 10-episode
epoch' column of RESULTS.md (n = 10, ours) and the paper's protocol (n = 20), and the
expected retest on 100 episodes. A Table 2 cell at or below that floor says nothing about
learning.

    python experiments/floor.py                 # all four tasks, 1,000 episodes each (~5 min)

It writes ``experiments/results/floor.md`` and a JSON file beside it (``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from rdher_jax.envs.notices import quiet_gymnasium_robotics
from rdher_jax.envs.registry import GYMNASIUM_TASK_NAMES, task_spec

HERE = Path(__file__).resolve().parent
TASKS = GYMNASIUM_TASK_NAMES
DEFAULT_OUT = HERE / "results" / "floor.md"


def zero_action_success(task: str, episodes: int, first_seed: int = 0) -> np.ndarray:
    """is_success at the last of an episode's zero-action steps, one episode per reset seed."""
    import gymnasium as gym

    quiet_gymnasium_robotics()
    import gymnasium_robotics

    spec = task_spec(task)
    gym.register_envs(gymnasium_robotics)
    env = gym.make(spec.gymnasium_id)
    zero = np.zeros(env.action_space.shape, dtype=np.float32)
    out = np.zeros(episodes, dtype=bool)
    for i in range(episodes):
        env.reset(seed=first_seed + i)
        info = {}
        for _ in range(spec.episode_length):
            _, _, _, _, info = env.step(zero)
        out[i] = bool(info["is_success"])
    env.close()
    return out


def expected_best(p: float, n: int, epochs: int) -> float:
    """E[max over ``epochs`` of Binomial(n, p)] / n: the expected best epoch's success of a
    run whose every epoch succeeds with probability p per test episode."""
    cdf = np.cumsum([math.comb(n, k) * p ** k * (1 - p) ** (n - k) for k in range(n + 1)])
    return float(sum(1.0 - min(cdf[k - 1], 1.0) ** epochs for k in range(1, n + 1)) / n)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS, metavar="TASK")
    ap.add_argument("--episodes", type=int, default=1000, help="episodes per task")
    ap.add_argument("--epochs", type=int, default=50, help="epochs of a run (the paper's 50)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    a = ap.parse_args(argv)
    if a.episodes < 1 or a.epochs < 1:
        print("error: --episodes and --epochs must be >= 1", file=sys.stderr)
        return 2
    rows = []
    for task in a.tasks:
        s = zero_action_success(task, a.episodes)
        p = float(s.mean())
        half = 1.96 * math.sqrt(max(p * (1 - p), 1e-12) / a.episodes)
        rows.append({"task": task, "episodes": a.episodes, "zero_action_success": p,
                     "ci95": [max(p - half, 0.0), min(p + half, 1.0)],
                     "best_of_epochs_10": expected_best(p, 10, a.epochs),
                     "best_of_epochs_20": expected_best(p, 20, a.epochs)})
        print(f"{task}: {100 * p:.1f}% of {a.episodes} zero-action episodes succeed", flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps({"epochs": a.epochs, "rows": rows},
                                                     indent=1) + "\n", encoding="utf-8")
    lines = ["# Table 2's floor: a policy that does nothing (`experiments/floor.py`)", "",
             f"Zero actions for 50 steps on gymnasium-robotics' `Fetch*-v4`, one episode per "
             f"reset seed 0..{a.episodes - 1}; success at the last step. The expected best of "
             f"{a.epochs} epochs is E[max of {a.epochs} Binomial(n, p)] / n for a run that never "
             "learns; its retest on 100 new episodes is p.", "",
             "| task | zero-action success % (95% interval) | expected best of "
             f"{a.epochs} epochs, 10 test episodes each | the same, 20 each (the paper's "
             "Table 1) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['task']} | {100 * r['zero_action_success']:.1f} "
                     f"[{100 * r['ci95'][0]:.1f}, {100 * r['ci95'][1]:.1f}] | "
                     f"{100 * r['best_of_epochs_10']:.1f} | {100 * r['best_of_epochs_20']:.1f} |")
    a.out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
