"""The paper's reward-weight ablation (section 5.2, Figs. 4-8): RDHER's (λ_r, λ_h) against HER.

Per task, seven settings, each over the profile's seeds: vanilla HER, and RDHER with
(λ_r, λ_h) = (1, 2), (2, 1), (1, 4), (4, 1), (0.5, 4), (4, 0.5), i.e. the pairs {1, 2}, {1, 4}
and {0.5, 4} in both orders. The six weighted settings are ONE vmapped sweep
(``python -m rdher_jax.sweep algo=rdher 'lambdas=[[1,2],...]' seeds=N``: 6 x N runs, one
compiled program); vanilla HER is a second, seeds-only sweep (``algo=her``).

Why vanilla HER is ``algo=her`` and not ``algo=rdher`` with (1, 1): under ``rdher``, (1, 1) is
DHER (combined rows mixed with 'future' rows, unit weights), not HER. The paper compares the
weights with "Vanilla HER" (Figs. 5-8), names HER as Andrychowicz et al.'s method (section 5.3)
and lists HER and DHER as different methods with different results (Table 2: Push 39% against
21%), so its reference curve is HER. The algorithm is a static part of the compiled program, so
HER cannot share the rdher sweep; it is its own sweep of the same budget and seeds. DHER,
i.e. RDHER at (1, 1), is in the benchmark (``experiments/benchmark.py``) with the same budget.

Outputs (small text files; checkpoints stay in the sweep directories):
``<out>/ablation/<profile>/<task>/<setting>/s<seed>.csv`` (each run's metrics.csv) and
``run_info.json`` (command, budget, hardware, versions, seeds, wall clock), settings ``her`` and
``rdher_lr<λ_r>_lh<λ_h>``; then ``experiments/report.py`` writes ``summary.md``, ``summary.csv``
and the figures under ``<out>/ablation/<profile>/``.

Resumable: the sweeps live in ``<runs-dir>/ablation/<profile>/<task>/{rdher,her}``; running the
same command again continues an unfinished sweep from its last checkpoint and skips a finished
one (``--epochs N`` extends finished ones).

    python experiments/ablation.py --profile tiny                      # smoke test, ~1 min
    python experiments/ablation.py --profile cpu                       # FetchReach, 5 seeds
    python experiments/ablation.py --profile paper --tasks FetchPush   # on a GPU
"""

from __future__ import annotations

import argparse
import sys

from profiles import ABLATION_PAIRS, Setting, add_common_args, num, run_experiment

KIND = "ablation"


def setting_name(lr: float, lh: float) -> str:
    return f"rdher_lr{num(lr)}_lh{num(lh)}"


def sweeps(task: str) -> list[tuple[str, str, object, tuple[Setting, ...]]]:
    """(sweep name, algo, lambdas, settings) of one task's ablation."""
    weighted = tuple(Setting(setting_name(lr, lh), f"RDHER λ_r={num(lr)}, λ_h={num(lh)}",
                             "rdher", (lr, lh), i + 1)
                     for i, (lr, lh) in enumerate(ABLATION_PAIRS))
    her = (Setting("her", "vanilla HER", "her", None, 0),)
    return [("rdher", "rdher", ABLATION_PAIRS, weighted), ("her", "her", None, her)]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(
        prog="python experiments/ablation.py", description=__doc__.split("\n\n")[0],
        epilog="Vanilla HER is a separate algo=her sweep; see the module docstring.")
    add_common_args(ap)
    args = ap.parse_args(argv)
    return run_experiment(KIND, "ablation.py", args, argv, sweeps)


if __name__ == "__main__":
    sys.exit(main())
