"""HER against DHER (and RDHER) on the moving-goal tasks, with the DHER share and mix varied.

DHER was made for goals that move (Fang et al., ICLR 2019). This runs, per task, one vmapped
sweep per setting (its seeds the run axis) and writes the results as the paper's experiments do
(``experiments/profiles.py``, ``experiments/report.py``): each run's ``metrics.csv`` as
``<out>/moving/<profile>/<task>/<setting>/s<seed>.csv`` with a ``run_info.json``, then
``summary.md`` (best and final success with intervals, each setting against HER with Welch's
test, mean success per env-step window, the share of combined rows, the bias diagnostic, the
wall clock) and the curves under ``<out>/moving/<profile>/``.

Settings (``--settings``; default: her dher rdher):

- ``her``: ``algo=her``.
- ``dher``: ``algo=dher`` as the README runs it: the authors' share (``dher_fraction=0.8``, at
  most 0.8·(1 − recent success) of a batch combined), the other rows 'future'-relabelled
  (``replay_k=4``).
- ``dher_plain``: the authors' mix: the rows that are not combined are not relabelled
  (``replay_k=0``, as in mengf1/DHER ``dher_sample.py``).
- ``dher_f0.2``, ``dher_f0.4``: a smaller cap on the combined share.
- ``rdher``, ``rdher_f0.2``: RDHER at the task's pair (moving tasks: λ_r = 2, λ_h = 1).

Budgets (``--profile``): ``cpu`` is FetchReachMoving at the paper's learner for 8 epochs and
FetchPushMoving under ``preset=fast`` for 100 epochs (250,000 env steps); ``paper`` is the
paper's learner for 50 epochs (250,000 env steps on Push). Resumable: the sweeps live in
``<runs-dir>/moving/<profile>/<task>/<setting>``; the same command continues an unfinished
sweep and skips a finished one.

    python experiments/moving_goals.py --profile cpu --tasks FetchReachMoving
    python experiments/moving_goals.py --profile cpu --tasks FetchPushMoving \\
        --settings her dher dher_f0.2
"""

from __future__ import annotations

import argparse
import sys

from profiles import NamedSetting, add_common_args, named_sweeps, run_experiment

KIND = "moving"

# name -> profiles.NamedSetting: label, algo, λ pairs, the sweep's own key=value tokens, and
# the experiment it is read from (none here). The shares use a one-value grid so that the run
# names and summary carry the value; the authors' share is written out, since preset=fast
# takes another.
SETTINGS: dict[str, NamedSetting] = {
    "her": ("HER", "her", None, (), None),
    "dher": ("DHER (share 0.8, 'future' mix)", "dher", None, ("dher_fraction=0.8",), None),
    "dher_plain": ("DHER (share 0.8, authors' plain mix, replay_k=0)", "dher", None,
                   ("dher_fraction=0.8", "replay_k=0"), None),
    "dher_f0.4": ("DHER (share 0.4)", "dher", None, ("grid.dher_fraction=[0.4]",), None),
    "dher_f0.2": ("DHER (share 0.2)", "dher", None, ("grid.dher_fraction=[0.2]",), None),
    "rdher": ("RDHER (share 0.8)", "rdher", None, ("dher_fraction=0.8",), None),
    "rdher_f0.2": ("RDHER (share 0.2)", "rdher", None, ("grid.dher_fraction=[0.2]",), None),
}
DEFAULT_SETTINGS = ("her", "dher", "rdher")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python experiments/moving_goals.py",
                                 description=__doc__.split("\n\n")[0])
    add_common_args(ap)
    ap.add_argument("--settings", nargs="+", choices=tuple(SETTINGS),
                    default=list(DEFAULT_SETTINGS),
                    help="settings, run in the order given (default: her dher rdher); see the "
                    "module docstring")
    args = ap.parse_args(argv)
    if args.tasks is None:
        args.tasks = ["FetchReachMoving"]
    return run_experiment(KIND, "moving_goals.py", args, argv,
                          named_sweeps(SETTINGS, args.settings))


if __name__ == "__main__":
    sys.exit(main())
