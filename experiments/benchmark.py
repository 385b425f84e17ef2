"""The paper's benchmark (section 5.3, Fig. 9, Tables 2 and 3): algorithms x tasks x seeds.

One vmapped sweep per (algorithm, task), its seeds the run axis (``python -m rdher_jax.sweep
env=<task> algo=<algo> seeds=N``). RDHER gets no ``lambdas``, so the config resolves the paper's
pair for the task (Reach and PickAndPlace λ_r = 2, λ_h = 1; Push and Slide 4 and 0.5, chosen in
the paper's ablation); the others run at (1, 1).

Outputs (small text files; checkpoints stay in the sweep directories):
``<out>/benchmark/<profile>/<task>/<algo>/s<seed>.csv`` (each run's metrics.csv) and
``run_info.json`` (command, budget, hardware, versions, seeds, wall clock); then
``experiments/report.py`` writes ``summary.md`` (best-policy and final success beside the
paper's Table 2, wall clock beside its Table 3, the hindsight-bias diagnostic), ``summary.csv``
and the figures under ``<out>/benchmark/<profile>/``.

``--settings dher_f0.8 rdher_f0.8`` adds DHER, and RDHER at the task's paper pair, at the
authors' share of combined rows (``dher_fraction=0.8``) as rows of the same table, for a profile
whose budget takes another share (``solve``: ``preset=fast``'s 0.2, so that there the DHER and
RDHER rows are at 0.2 and these are the paper's).

Resumable: the sweeps live in ``<runs-dir>/benchmark/<profile>/<task>/<algo>``; running the same
command again continues an unfinished sweep from its last checkpoint and skips a finished one.

    python experiments/benchmark.py --profile tiny --algos her rdher   # smoke test
    python experiments/benchmark.py --profile cpu                      # FetchReach, 5 algos
    python experiments/benchmark.py --profile paper                    # on a GPU
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from profiles import (
    ALGO_LABELS,
    AUTHORS_SHARE,
    BENCHMARK_ALGOS,
    Setting,
    add_common_args,
    budget_for,
    named_sweeps,
    num,
    paper_pair,
    run_experiment,
)

from rdher_jax.config import Config, config_from_fields

KIND = "benchmark"

# Rows beside the five algorithms, tabled after them.
SETTINGS = AUTHORS_SHARE


def algo_label(algo: str, profile: str, task: str) -> str:
    """The algorithm's name in tables; DHER and RDHER name their share of combined rows where
    the profile's budget takes another than the authors' (solve: preset=fast's 0.2), so that a
    table beside the authors'-share rows (``--settings``) tells the two apart."""
    label = ALGO_LABELS[algo]
    if algo in ("dher", "rdher"):
        settings = budget_for(profile, task).settings  # the share needs no epoch count
        cfg = config_from_fields({"env": task, **{k: str(v) for k, v in settings.items()}})
        if cfg.dher_fraction != Config().dher_fraction:
            if algo == "rdher":  # as the authors'-share row names it: the task's paper pair
                label += " " + paper_pair(task)
            label += f", share {num(cfg.dher_fraction)}"
    return label


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python experiments/benchmark.py",
                                 description=__doc__.split("\n\n")[0])
    add_common_args(ap)
    ap.add_argument("--algos", nargs="+", choices=BENCHMARK_ALGOS, default=None,
                    help="algorithms, run in the order given (default: all five, or none "
                    "with --settings)")
    ap.add_argument("--settings", nargs="+", choices=tuple(SETTINGS), default=[],
                    help="rows beside the algorithms, run after them: DHER and RDHER at the "
                    "authors' share of combined rows (dher_fraction=0.8) where the profile "
                    "takes another (default: none)")
    args = ap.parse_args(argv)
    if args.algos is None:  # --settings alone runs those rows only
        args.algos = [] if args.settings else list(BENCHMARK_ALGOS)
    algos = list(dict.fromkeys(args.algos))
    named = named_sweeps(SETTINGS, args.settings)

    def sweeps(task: str) -> list[tuple]:
        out: list[tuple] = [(a, a, None, (Setting(a, algo_label(a, args.profile, task), a,
                                                  None, BENCHMARK_ALGOS.index(a)),))
                            for a in algos]
        for name, algo, lambdas, (setting,), *more in named(task):
            order = len(BENCHMARK_ALGOS) + setting.order
            out.append((name, algo, lambdas, (dataclasses.replace(setting, order=order),),
                        *more))
        return out

    return run_experiment(KIND, "benchmark.py", args, argv, sweeps)


if __name__ == "__main__":
    sys.exit(main())
