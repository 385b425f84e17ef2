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
    python experiments/ablation.py --profile paper --tasks FetchPush --seeds 3 --split \
        --settings her rdher_lr4_lh0.5                                 # on a CPU, in pieces
"""

from __future__ import annotations

import argparse
import sys

from profiles import ABLATION_PAIRS, TASK_TABLE, Setting, add_common_args, num, run_experiment

KIND = "ablation"


def setting_name(lr: float, lh: float) -> str:
    return f"rdher_lr{num(lr)}_lh{num(lh)}"


SETTING_NAMES: tuple[str, ...] = ("her", *(setting_name(lr, lh) for lr, lh in ABLATION_PAIRS))


Sweep = tuple[str, str, object, tuple[Setting, ...]]


def sweeps(task: str, split: bool = False, only: tuple[str, ...] | None = None,
           her_from_benchmark: bool = False, pick_from_benchmark: bool = False) -> list[Sweep]:
    """(sweep name, algo, lambdas, settings) of one task's ablation. ``split``: one sweep per
    pair, named by its setting, in place of one sweep of all six; ``only``: these settings
    (of :data:`SETTING_NAMES`) alone, in the order given; ``her_from_benchmark``: vanilla HER
    is read from benchmark.py's HER sweep of the same profile and task (the same program and
    budget, at the benchmark's seeds), not run again; ``pick_from_benchmark`` (with
    ``split``): likewise the paper's own pair for the task, from benchmark.py's RDHER sweep,
    which runs that pair."""
    weighted = tuple(Setting(setting_name(lr, lh), f"RDHER λ_r={num(lr)}, λ_h={num(lh)}",
                             "rdher", (lr, lh), i + 1)
                     for i, (lr, lh) in enumerate(ABLATION_PAIRS))
    her: tuple = ("her", "her", None, (Setting("her", "vanilla HER", "her", None, 0),))
    if her_from_benchmark:
        her = (*her, (), "benchmark")
    if split:
        every = {s.name: (s.name, "rdher", (s.lambdas,), (s,)) for s in weighted}
        every["her"] = her
        if pick_from_benchmark:
            pick = setting_name(*TASK_TABLE[task].paper_lambdas)
            every[pick] = ("rdher", "rdher", None, every[pick][3], (), "benchmark")
        return [every[n] for n in (only or SETTING_NAMES)]
    out = [("rdher", "rdher", ABLATION_PAIRS, weighted), her]
    return out if only is None else [j for j in out if j[0] in only]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(
        prog="python experiments/ablation.py", description=__doc__.split("\n\n")[0],
        epilog="Vanilla HER is a separate algo=her sweep; see the module docstring.")
    add_common_args(ap)
    ap.add_argument("--split", action="store_true",
                    help="one sweep per weighted pair (named by its setting) in place of one "
                    "vmapped sweep of all six: on a CPU, where vmapping saves nothing "
                    "(experiments/results/bench_sweep.md), each finishes in a sitting")
    ap.add_argument("--settings", nargs="+", choices=SETTING_NAMES, default=None,
                    metavar="SETTING",
                    help=f"run only these settings, of {', '.join(SETTING_NAMES)} (a weighted "
                    "one needs --split); default: all seven")
    ap.add_argument("--her-from-benchmark", action="store_true",
                    help="read vanilla HER from experiments/benchmark.py's HER sweep of the "
                    "same profile and task (the same runs at the benchmark's seeds) instead of "
                    "running an HER sweep of its own; run benchmark.py first")
    ap.add_argument("--pick-from-benchmark", action="store_true",
                    help="with --split: read the paper's own pair for the task (FetchPush and "
                    "FetchSlide (4, 0.5), the others (2, 1)) from experiments/benchmark.py's "
                    "RDHER sweep, which runs that pair at the same budget, instead of running "
                    "it again")
    args = ap.parse_args(argv)
    only = None if args.settings is None else tuple(dict.fromkeys(args.settings))
    if only is not None and not args.split and any(n != "her" for n in only):
        print("error: --settings with a weighted setting needs --split (without it the six "
              "pairs are one sweep)", file=sys.stderr)
        return 2
    if args.pick_from_benchmark and not args.split:
        print("error: --pick-from-benchmark needs --split (without it the six pairs are one "
              "sweep)", file=sys.stderr)
        return 2
    return run_experiment(KIND, "ablation.py", args, argv,
                          lambda task: sweeps(task, args.split, only,
                                              args.her_from_benchmark,
                                              args.pick_from_benchmark))


if __name__ == "__main__":
    sys.exit(main())
