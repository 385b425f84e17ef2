"""Beyond the paper: is there an RDHER setting that beats HER on FetchPush under ``preset=fast``?

Under the one learner that learns FetchPush in CPU time (``preset=fast``), RDHER at the paper's
pair and the authors' DHER share ends 30 points below HER (``experiments/results/RESULTS.md``,
section 2; the benchmark's ``--profile cpu --tasks FetchPush``). This varies what RESULTS.md
suspects, one thing at a time, each setting one vmapped sweep of the profile's seeds at the
benchmark's budget (``cpu``: FetchPush ``preset=fast``, sequential, 500,000 env steps, 3 seeds):

- ``her``, ``rdher``: HER, and RDHER at the task's paper pair and the authors' share, read from
  the benchmark's sweeps of the same budget (or, where those are gone, its collected results),
  never run here.
- ``rdher_f0.2``, ``rdher_f0.05``: the paper's pair with a smaller cap on DHER's combined rows,
  ``dher_fraction`` (at most that times (1 − recent success) of a batch; the authors' 0.8).
- ``rdher_plain``, ``dher_plain``: the authors' plain mix, the rows that are not combined not
  relabelled (``replay_k=0``, as in mengf1/DHER ``dher_sample.py``), at their share; at
  ``--profile paper`` these are Table 2's DHER and RDHER rows with the authors' mix.
- ``rdher_f0.2_lr2_lh1``, ``rdher_f0.2_lr1_lh2``: other weights at the 0.2 share;
  ``dher_f0.2``: no weights at all (DHER, i.e. RDHER at (1, 1)).
- ``dher_f0.8``, ``rdher_f0.8``: DHER, and RDHER at the paper's pair, at the authors' share
  written out, for a profile whose budget takes another (``solve``: ``preset=fast``'s 0.2, so
  that its benchmark's DHER and RDHER are at 0.2 and these are the paper's).
- ``rdher_clip``: the paper's pair and share with every row's critic target clipped to
  baselines' [−1/(1−γ), 0] (``target_clip=unweighted``), what weighting the sampled rewards in
  the baselines-based code the authors built on would give, instead of each row's own range.

The settings run on any task and profile (``--tasks``, ``--profile``), against the benchmark's
HER and RDHER of that task and profile: e.g. ``--profile paper --tasks FetchSlide --seeds 3``.

Outputs as the other experiments (``experiments/profiles.py``, ``experiments/report.py``):
``<out>/beyond/<profile>/<task>/<setting>/s<seed>.csv`` with a ``run_info.json``, then
``summary.md`` (each setting against HER with Welch's test, mean success per env-step window,
the share of combined rows, the bias diagnostic) and the curves under ``<out>/beyond/<profile>/``.
Resumable: the sweeps live in ``<runs-dir>/beyond/<profile>/<task>/<setting>``.

    python experiments/beyond.py --profile cpu --settings her rdher rdher_f0.2 rdher_f0.2_lr2_lh1
"""

from __future__ import annotations

import argparse
import sys

from profiles import AUTHORS_SHARE, NamedSetting, add_common_args, named_sweeps, run_experiment

KIND = "beyond"

# name -> (label, algo, lambdas, the sweep's own key=value tokens, the experiment it is read
# from): profiles.NamedSetting. A share replaces the budget's dher_fraction=0.8.
SETTINGS: dict[str, NamedSetting] = {
    "her": ("HER", "her", None, (), "benchmark"),
    "rdher": ("RDHER {pair}, share 0.8 (the authors')", "rdher", None, (), "benchmark"),
    "rdher_plain": ("RDHER {pair}, share 0.8, plain mix (replay_k=0)", "rdher", None,
                    ("replay_k=0",), None),
    "rdher_f0.2": ("RDHER {pair}, share 0.2", "rdher", None,
                   ("dher_fraction=0.2",), None),
    "rdher_f0.05": ("RDHER {pair}, share 0.05", "rdher", None,
                    ("dher_fraction=0.05",), None),
    "rdher_f0.2_lr2_lh1": ("RDHER (2, 1), share 0.2", "rdher", ((2.0, 1.0),),
                           ("dher_fraction=0.2",), None),
    "rdher_f0.2_lr1_lh2": ("RDHER (1, 2), share 0.2", "rdher", ((1.0, 2.0),),
                           ("dher_fraction=0.2",), None),
    "dher_f0.2": ("DHER, share 0.2", "dher", None, ("dher_fraction=0.2",), None),
    **AUTHORS_SHARE,  # dher_f0.8, rdher_f0.8 (profiles.py)
    "dher_plain": ("DHER, share 0.8, plain mix (replay_k=0)", "dher", None, ("replay_k=0",),
                   None),
    "rdher_clip": ("RDHER (the paper's pair), share 0.8, unweighted clip", "rdher", None,
                   ("target_clip=unweighted",), None),
}
DEFAULT_SETTINGS = ("her", "rdher", "rdher_f0.2", "rdher_f0.2_lr2_lh1")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python experiments/beyond.py",
                                 description=__doc__.split("\n\n")[0])
    add_common_args(ap)
    ap.add_argument("--settings", nargs="+", choices=tuple(SETTINGS),
                    default=list(DEFAULT_SETTINGS),
                    help=f"settings, run in the order given (default: "
                    f"{' '.join(DEFAULT_SETTINGS)}); see the module docstring")
    args = ap.parse_args(argv)
    if args.tasks is None:
        args.tasks = ["FetchPush"]
    return run_experiment(KIND, "beyond.py", args, argv,
                          named_sweeps(SETTINGS, args.settings))


if __name__ == "__main__":
    sys.exit(main())
