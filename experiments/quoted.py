"""Figures the hand-written prose quotes, each recomputed from the committed data.

    python experiments/quoted.py --check    # each checked figure against the data; exit 1 on a miss
    python experiments/quoted.py --write    # rewrite every checked figure from the data
    python experiments/quoted.py --list     # the named figures of the table below

In ``experiments/results/RESULTS.md``, ``README.md``, every ``experiments/results/**/README.md``
and ``docs/*.md``, prose and tables alike, a checked figure is a markdown link whose title starts
with ``q:`` and names the figure; the link goes to the committed data it comes from (relative to
the markdown file, as any link; a link inside code is an example, not a figure):

    [91.7](../benchmark/cpu/FetchPush/her "q:bc/push/her:final")

A figure not written so is hand-typed, and nothing checks it. The text of a numeric figure is
compared at its own precision (``92`` quotes 91.67 correctly, ``91.6`` does not; a p of
``0.032`` is 0.0317 to three decimals; ``1.5e-07`` to two significant digits); a text figure
(``not reached``) must match exactly, a wall clock in the style of its text (``33 min 16 s``,
``33:16``, ``1:45:13``), and the link must lead to the data the figure comes from
(:func:`source`). ``tests/test_quoted.py`` runs the check.

Names. A *setting* is ``<kind>/<task>/<setting>`` with the kind and profile abbreviated
(:data:`KINDS`: ``bp`` = ``benchmark/paper``, ...) and the task too (:data:`TASKS`: ``push`` =
``FetchPush``, ...), e.g. ``bp/slide/rdher`` is ``experiments/results/benchmark/paper/FetchSlide/
rdher``. A *measure* is one of report.py's per-seed figures (:func:`report.per_seed`): ``best``
(max over epochs of test success), ``final`` (mean of the last 3 epochs), ``mean`` (mean over
all epochs), ``policy`` (the best policy retested), ``precise`` (the same policy on more
episodes, ``--precise-episodes``); all in %. Also ``combined`` (the share of
DHER-combined rows in a batch, the CSVs' ``frac_dher``, mean of the last 3 epochs, %),
``combined_run`` (the same over every epoch), ``train`` (the training episodes' success, the
CSVs' ``train_success``, mean of the last 3 epochs, %) and the bias columns (``bias_real``,
``bias_unw_her``, ...: mean of the last 3 epochs, as summary.md's diagnostic). Also ``w1``,
``w2``, ``w3``: the mean test success over summary.md's env-step windows (report.windows: the
first 40%, the next 40%, the last 20% of the steps), %; ``to0.5``: the env steps to the first
test at 0.5 or above, ``to0.9m3`` to the first trailing mean of 3 tests at 0.9 (bench_learning's
rule; a seed that never gets there counts its last env steps, a lower bound); ``to0.9m3_min``
the same in minutes of the training clock.

- ``S:M`` the mean over seeds of measure M of setting S; ``S:M:sd`` its sample std, ``S:M:lo``
  / ``S:M:hi`` its 95% t interval clipped to [0, 100] (as summary.md prints it), ``S:M:n`` the
  seeds, ``S:M:s2`` seed 2's value, ``S:M:min`` / ``S:M:max`` the lowest / highest seed's,
  ``S:M:ge50`` / ``S:M:lt500000`` the number of seeds at 50 or above / below 500,000.
- ``S-T:M`` the mean of S minus the mean of T (Welch), ``S-T:M:p`` Welch's two-sided p;
  ``S-T:M:paired`` and ``S-T:M:paired:p`` the same paired by seed (:func:`report.paired`);
  ``S-T:M:paired:lo`` / ``:hi`` the 95% t interval of the mean per-seed difference,
  ``S-T:M:paired:sd`` the per-seed differences' std; ``S-T:M:seeds80`` (``:paired:seeds80``)
  the seeds per setting a two-sided t-test (paired t-test) at 5% needs to detect the
  difference with 80% power, at the spreads seen (:func:`seeds_for_power`);
  ``S-T:M:wins`` the seeds on which S is above T, ``S-T:M:common`` the seeds both hold. T is
  a setting, or a setting name alone for one of S's task (``bp/slide/rdher-her``).
- ``S:wall`` the wall clock per run of S (``run_info.json``, ``wall_clock_per_run_s``), written
  as its text is (``33 min 16 s``, ``33:16``, ``1:45:13``, ``1 h 45 min 13 s``: :func:`clock`);
  ``S:piece_wall:0`` the wall clock of S's first piece (``S:piece_min:0`` its minutes per
  run); ``S:wall_min`` the same in minutes (over a
  glob, ``:min`` or ``:max``); ``S-T:wall_ratio`` S's wall clock per run over T's;
  ``S:table3_ratio`` the paper's Table 3 time of one run over S's;
  ``S:piece_min:min`` / ``:max`` the fewest / most minutes per run of a one-seed piece of a
  setting run in pieces.
- A setting may be a glob over setting names (``ap/pnp/rdher_*``); then ``:min`` or ``:max``
  at the end takes the lowest or highest of the settings' figures
  (``ap/pnp/rdher_*:policy:min``).
- ``bl/<name>:<field>:s<seed>`` a figure of a ``bench_learning/<name>.json`` run (:func:`learning`).
- ``paper/<task>/<algo>:table2`` the paper's Table 2 figure (best-policy success, %),
  ``:table3`` its Table 3 wall clock of one run, both from ``rdher_jax/tasks.py``.
- Any other name is an entry of :data:`NAMED` below.

Numbers are as report.py's tables print them (100 · rate, Welch and paired tests on the
rounded rates), so a figure the prose takes from a summary.md table checks against the table.
A figure in thousands is written ``295k``; halves round up.
"""

from __future__ import annotations

import argparse
import builtins
import fnmatch
import functools
import json
import math
import re
import statistics
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import report  # noqa: E402

ROOT = HERE.parent
RESULTS = HERE / "results"
KINDS = {"ac": "ablation/cpu", "ap": "ablation/paper", "as": "ablation/solve",
         "bc": "benchmark/cpu", "bp": "benchmark/paper", "bs": "benchmark/solve",
         "yc": "beyond/cpu", "yp": "beyond/paper", "ys": "beyond/solve", "mc": "moving/cpu"}
TASKS = {"reach": "FetchReach", "push": "FetchPush", "slide": "FetchSlide",
         "pnp": "FetchPickAndPlace", "pushm": "FetchPushMoving", "reachm": "FetchReachMoving"}
MEASURES = ("best", "final", "mean", "policy", "precise")


def markdown_files(root: Path = ROOT) -> list[Path]:
    """The files whose prose may quote checked figures."""
    res = root / "experiments" / "results"
    return [root / "README.md", res / "RESULTS.md", *sorted(res.glob("**/README.md")),
            *sorted((root / "docs").glob("*.md"))]


# ------------------------------------------------------------------ the data

@functools.cache
def setting_dir(ref: str) -> Path:
    """``bp/push/her`` -> ``experiments/results/benchmark/paper/FetchPush/her``."""
    parts = ref.split("/")
    if len(parts) != 3 or parts[0] not in KINDS or parts[1] not in TASKS:
        raise KeyError(f"not a setting: {ref!r} (<{'|'.join(KINDS)}>/<{'|'.join(TASKS)}>/<name>)")
    path = RESULTS / KINDS[parts[0]] / TASKS[parts[1]] / parts[2]
    if not (path / "run_info.json").is_file():
        raise KeyError(f"no setting {ref!r}: {path.relative_to(ROOT)} has no run_info.json")
    return path


@functools.cache
def setting(ref: str) -> report.SettingData:
    return report.read_setting(setting_dir(ref))


def run_info(ref: str) -> dict:
    return setting(ref).meta


COLUMN_MEASURES = ("combined", "combined_run", "train", *report.BIAS_COLS)
HIT = re.compile(r"to(\d*\.?\d+)(m3)?")  # to0.5: first test at 0.5; to0.9m3: trailing mean of 3
# to0.9m3_min: the same, in minutes of the training clock (metrics.csv's wall_time)
HIT_MIN = re.compile(r"to(\d*\.?\d+)(m3)?_min")


def percent(measure: str) -> bool:
    """Whether ``measure`` is a rate the prose quotes in % (not env steps, not a bias)."""
    return measure in MEASURES or measure.startswith("combined") or bool(
        re.fullmatch(r"w\d", measure))


def first_hit(rows: list[dict[str, str]], threshold: float, window: int = 1,
              field: str = "env_steps") -> float | None:
    """bench_learning's rule: env steps (``field``; ``wall_s``: seconds of the training clock)
    of the first epoch whose test success (``window`` = 1) or trailing mean of ``window`` epochs
    reaches ``threshold``; None if none does."""
    import bench_learning

    got = bench_learning.first_hit(rows, threshold, window) or {}
    return float(got[key][field]) if (key := "single" if window == 1 else "window") in got \
        else None


def seeds(ref: str, measure: str) -> dict[int, float]:
    """Per seed, ``measure`` of setting ``ref``, in the units the prose quotes it in: report.py's
    rates in % (``best``, ``final``, ``mean``, ``policy``); ``combined``, the share of DHER-
    combined rows in a batch (``frac_dher``), mean of the last 3 epochs, in %, and ``combined_run``
    the same over every epoch; ``train`` the training episodes' success (``train_success``), mean of
    the last 3 epochs, in %; a bias column (``bias_real``, ...), mean of its finite values over the
    last 3 epochs, as summary.md's diagnostic; ``w1``-``w3`` the mean test success over summary.md's
    env-step windows, in %; ``to<x>`` the env steps to the first test at ``x`` or above, ``to<x>m3``
    to the first trailing mean of 3 tests there (a finished seed that never gets there counts its
    last env steps, a lower bound; one still short of its budget has no figure yet), ``to<x>_min`` /
    ``to<x>m3_min`` the same in minutes of the training clock.

    A run collected while still under way (:func:`report.under_way`) has no figure but the
    steps to a threshold it has already reached: its best, final, mean, windows and
    combined rows would change as it goes on, and a mean over seeds would mix it in."""
    late = report.under_way(setting(ref))
    if m := re.fullmatch(r"w(\d)", measure):
        ws = report.window_seeds(setting(ref))
        if not 1 <= int(m[1]) <= len(ws):
            raise KeyError(f"windows are w1-w{len(ws)}")
        return {k: 100 * v for k, v in ws[int(m[1]) - 1][1].items() if k not in late}
    if m := (HIT.fullmatch(measure) or HIT_MIN.fullmatch(measure)):
        s = setting(ref)
        want = report.budget_epochs(s)
        field, col, scale = (("wall_s", "wall_time", 1 / 60) if measure.endswith("_min")
                             else ("env_steps", "env_steps", 1))
        out = {}
        for k, rows in s.runs.items():
            hit = first_hit(rows, float(m[1]), 3 if m[2] else 1, field)
            if hit is None and want is not None and len(rows) < want:
                continue  # not reached yet: the run is still under way
            out[k] = scale * (hit if hit is not None else float(rows[-1][col]))
        return out
    if measure in MEASURES:
        return {k: 100 * v for k, v in report.per_seed(setting(ref))[measure].items()
                if k not in late}
    if measure not in COLUMN_MEASURES:
        raise KeyError(f"no measure {measure!r} (one of {', '.join(MEASURES + COLUMN_MEASURES)}, "
                       "w<k>, to<x>, to<x>m3, to<x>_min, to<x>m3_min)")
    col = ("frac_dher" if measure.startswith("combined") else
           "train_success" if measure == "train" else measure)
    scale = 100 if col in ("frac_dher", "train_success") else 1
    last = None if measure == "combined_run" else report.LAST
    out = {}
    for k, v in setting(ref).column(col).items():
        if k in late:
            continue
        xs = [x for x in (v if last is None else v[-last:]) if math.isfinite(x)]
        if xs:
            out[k] = scale * statistics.fmean(xs)
    return out


def _over_seeds(ref: str, measure: str, stat: str) -> float:
    xs = seeds(ref, measure)
    if not xs:
        raise KeyError(f"{ref} has no {measure!r} figures")
    st = report.stat(list(xs.values()))
    if stat == "mean":
        return st.mean
    if stat == "sd":
        return st.std
    if stat == "lo":
        return max(st.lo, 0.0)
    if stat == "hi":
        return min(st.hi, 100.0)
    if stat == "n":
        return len(xs)
    if stat == "min":
        return min(xs.values())
    if stat == "max":
        return max(xs.values())
    if re.fullmatch(r"ge\d+", stat):
        return sum(x >= int(stat[2:]) - 1e-4 for x in xs.values())
    if re.fullmatch(r"lt\d+", stat):
        return sum(x < int(stat[2:]) - 1e-4 for x in xs.values())
    if re.fullmatch(r"s\d+", stat):
        if int(stat[1:]) not in xs:
            raise KeyError(f"{ref} has no seed {stat[1:]}")
        return xs[int(stat[1:])]
    raise KeyError(f"no statistic {stat!r} (mean, sd, lo, hi, n, min, max, s<seed>, ge<x>, "
                   "lt<x>)")


def _versus(a: str, b: str, measure: str, test: list[str]) -> float:
    """As report.py tests two settings: on the rates (rounded as report.welch rounds them)."""
    scale = 100 if percent(measure) else 1
    xs = {k: v / scale for k, v in seeds(a, measure).items()}
    ys = {k: v / scale for k, v in seeds(b, measure).items()}
    if test in ([], ["p"]):
        diff, p = report.welch(list(xs.values()), list(ys.values()))
    elif test in (["paired"], ["paired", "p"]):
        diff, p, _ = report.paired(xs, ys)
    elif test in (["paired", "lo"], ["paired", "hi"], ["paired", "sd"], ["paired", "seeds80"]):
        st = report.paired_diffs(xs, ys)
        if test[1] == "seeds80":
            return seeds_for_power(st.mean, st.std, None)
        return scale * {"lo": st.lo, "hi": st.hi, "sd": st.std}[test[1]]
    elif test == ["seeds80"]:
        sx, sy = report.stat(list(xs.values())), report.stat(list(ys.values()))
        return seeds_for_power(sx.mean - sy.mean, sx.std, sy.std)
    elif test in (["wins"], ["common"]):
        common = sorted(set(xs) & set(ys))
        return float(len(common) if test == ["common"] else
                     sum(report._rate(xs[k]) > report._rate(ys[k]) for k in common))
    else:
        raise KeyError(f"no test {':'.join(test)!r} (nothing, p, paired, paired:p, "
                       "paired:lo, paired:hi, paired:sd, paired:seeds80, seeds80, wins, common)")
    return p if test[-1:] == ["p"] else scale * diff


seeds_for_power = report.seeds_for_power  # where the summaries' tables use it too


def _pieces(ref: str) -> list[float]:
    """Minutes per run of each one-seed piece of a setting that ran in pieces."""
    pieces = run_info(ref).get("pieces")
    if not pieces:
        raise KeyError(f"{ref} did not run in pieces (no 'pieces' in its run_info.json)")
    return [float(p["wall_clock_s"]) / int(p["runs"]) / 60 for p in pieces]


def _expand(ref: str) -> list[str]:
    """A setting reference, or every setting a glob over the last part names."""
    if not any(c in ref for c in "*?["):
        return [ref]
    head, pat = ref.rsplit("/", 1)
    kind, task = head.split("/")
    base = RESULTS / KINDS[kind] / TASKS[task]
    names = sorted(p.name for p in base.iterdir()
                   if (p / "run_info.json").is_file() and fnmatch.fnmatchcase(p.name, pat))
    if not names:
        raise KeyError(f"no setting matches {ref!r}")
    return [f"{head}/{n}" for n in names]


def systematic(name: str) -> float | str:
    """The value of a name of the grammar in the module's docstring."""
    parts = name.split(":")
    if len(parts) < 2:
        raise KeyError(f"unknown figure {name!r}")
    ref, measure, rest = parts[0], parts[1], parts[2:]
    if ref.startswith("paper/"):
        return paper(ref, measure, rest)
    if ref.startswith("bl/"):
        return learning(ref[3:], measure, rest)
    if measure == "wall" and not rest and "-" not in ref:
        return Duration(per_run_s(ref))
    if measure in ("piece_wall", "piece_min") and len(rest) == 1 and rest[0].isdigit() \
            and "-" not in ref:
        pieces = run_info(ref).get("pieces") or []
        if int(rest[0]) >= len(pieces):
            raise KeyError(f"{ref} has no piece {rest[0]}")
        return Duration(float(pieces[int(rest[0])]["wall_clock_s"])) if measure == "piece_wall" \
            else _pieces(ref)[int(rest[0])]
    if measure == "wall_ratio" and rest == [] and "-" in ref:
        a, b = ref.split("-", 1)
        return per_run_s(a) / per_run_s(b if "/" in b else a.rsplit("/", 1)[0] + "/" + b)
    if measure == "table3_ratio" and not rest and "-" not in ref:
        return _paper_s(ref) / per_run_s(ref)
    if measure == "wall_min" and "-" not in ref:
        vals = [per_run_s(x) / 60 for x in _expand(ref)]
        if len(vals) > 1 and rest not in (["min"], ["max"]) or len(vals) == 1 and rest:
            raise KeyError(f"{name!r}: wall_min takes :min or :max after a glob, else nothing")
        return getattr(builtins, rest[0])(vals) if rest else vals[0]
    if measure == "piece_min" and "-" not in ref:
        over = rest[1] if len(rest) == 2 else None
        if not rest or rest[0] not in ("min", "max") or over not in (None, "min", "max"):
            raise KeyError(f"{name!r}: piece_min takes :min or :max (then :min or :max over a "
                           "glob)")
        vals = [getattr(builtins, rest[0])(_pieces(x)) for x in _expand(ref)]
        return getattr(builtins, over)(vals) if over else vals[0]
    over = None
    if any(c in ref for c in "*?[") and rest[-1:] in (["min"], ["max"]):
        over, rest = rest[-1], rest[:-1]
    if "-" in ref:
        a, b = ref.split("-", 1)
        if "/" not in b:
            b = a.rsplit("/", 1)[0] + "/" + b
        vals = [_versus(x, y, measure, rest) for x in _expand(a) for y in _expand(b) if x != y]
    else:
        stat = rest[0] if rest else "mean"
        if len(rest) > 1:
            raise KeyError(f"unknown figure {name!r}")
        refs = _expand(ref)
        if len(refs) > 1:  # a glob: the settings that have the measure (HER has no DHER rows)
            refs = [x for x in refs if seeds(x, measure)] or refs
        vals = [_over_seeds(x, measure, stat) for x in refs]
    vals = [v for v in vals if not math.isnan(v)] or vals  # a test without variance has no p
    if len(vals) > 1 and over is None:
        raise KeyError(f"{name!r}: a glob needs :min or :max at the end")
    return min(vals) if over == "min" else max(vals) if over == "max" else vals[0]


def paper(ref: str, measure: str, rest: list[str]) -> float:
    """``paper/<task>/<algo>:table2`` (the paper's best-policy success, %) or ``:table3`` (its
    wall clock of one run), as ``rdher_jax/tasks.py`` holds them."""
    parts = ref.split("/")
    if len(parts) != 3 or parts[1] not in TASKS or measure not in ("table2", "table3") or rest:
        raise KeyError(f"not a figure of the paper: {ref}:{measure} "
                       f"(paper/<{'|'.join(TASKS)}>/<algo>:table2|table3)")
    task, algo = TASKS[parts[1]], parts[2]
    if measure == "table2":
        val = report.paper_best(task, algo)
        if val is None:
            raise KeyError(f"the paper's Table 2 has no {task} {algo}")
        return float(val)
    return Duration(_table3_s(task, algo))


def learning(name: str, field: str, rest: list[str]) -> float | str:
    """``bl/<name>:<field>:s<seed>``: a figure of ``bench_learning/<name>.json``'s run of that
    seed: ``best`` (a rate), ``env_steps``, ``minutes``, ``to0.5`` / ``to0.9`` (env steps to the
    first test there), ``to0.5m3`` / ``to0.9m3`` (to the first trailing mean of 3 there; the
    text ``not reached`` where none is), ``to0.5_min``, ``to0.9m3_min``, ...: the same in
    minutes of training; ``retest`` the best policy's retest at the end of the run, %;
    ``selected`` and ``selbest`` (runs with ``select_top``): the selection episodes' success
    (%) of the selected policy and of the best test epoch's policy (ties: the later);
    ``w<a>-<b>k`` the mean test success (%) of the epochs that end after a and by b thousand
    env steps (``w300-400k``)."""
    if len(rest) != 1 or not re.fullmatch(r"s\d+", rest[0]):
        raise KeyError(f"bl/{name}:{field}: the seed goes last (:s0)")
    seed = rest[0][1:]
    run = _bl(name)["results"].get(seed)
    if run is None:
        raise KeyError(f"bench_learning/{name}.json has no seed {seed}")
    if field == "retest":
        if not run.get("retest"):
            raise KeyError(f"bench_learning/{name}.json has no retest of seed {seed}")
        return 100 * float(run["retest"]["success"])
    if field in ("selected", "selbest"):
        sel = run.get("selection")
        if not sel:
            raise KeyError(f"bench_learning/{name}.json seed {seed} made no selection")
        c = sel["candidates"]
        epoch = str(sel["epoch"]) if field == "selected" else max(
            c, key=lambda e: (float(c[e]["test_success"]), int(e)))
        return 100 * float(c[epoch]["selection_success"])
    if field in ("best", "env_steps"):
        return float(run[field])
    if m := re.fullmatch(r"w(\d+)-(\d+)k", field):
        lo, hi = 1000 * int(m[1]), 1000 * int(m[2])
        window = [succ for steps, _, succ in run["curve"] if lo < steps <= hi]
        if not window:
            raise KeyError(f"bench_learning/{name}.json seed {seed} has no epoch in {field}")
        return 100 * statistics.fmean(window)
    if field == "minutes":
        return float(run["wall_s"]) / 60
    if m := re.fullmatch(HIT.pattern + "(_min)?", field):
        # From the run's curve, by bench_learning's rule, at any threshold (its stored hits
        # hold only its own thresholds, 0.5 and 0.9; Slide's goal is 0.8).
        import bench_learning

        hit = bench_learning.first_hit(bench_learning.curve_rows(run), float(m[1]),
                                       3 if m[2] else 1) or {}
        got = hit.get("window" if m[2] else "single")
        return "not reached" if got is None else \
            float(got["wall_s"]) / 60 if m[3] else float(got["env_steps"])
    raise KeyError(f"no bench_learning figure {field!r} (best, env_steps, minutes, to<x>, "
                   "to<x>m3, to<x>_min, to<x>m3_min, retest, selected, selbest, w<a>-<b>k)")


def _table3_s(task: str, algo: str | None) -> float:
    """The paper's Table 3 wall clock of one run of ``algo`` on ``task``, in seconds."""
    hms = report.paper_time(task, algo)
    if hms == "-":
        raise KeyError(f"the paper's Table 3 has no {task} {algo}")
    h, m, sec = hms.split(":")
    return 3600 * int(h) + 60 * int(m) + int(sec)


class Duration(float):
    """A wall clock in seconds, written in the style of the text that quotes it (:func:`clock`)."""


def clock(seconds: float, like: str) -> str:
    """``seconds`` to the second in the style of ``like``: ``1:45:13`` or ``33:16`` (as many
    colons as ``like``), ``1 h 45 min 13 s`` (if ``like`` has hours) or ``105 min 13 s``."""
    s = int(round(seconds))
    if ":" in like:
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if like.count(":") == 2 \
            else f"{s // 60}:{s % 60:02d}"
    if re.match(r"\d+ h ", like):
        return f"{s // 3600} h {s % 3600 // 60} min {s % 60} s"
    return f"{s // 60} min {s % 60} s"


# ------------------------------------------------------------------ named figures


def per_run_s(ref: str) -> float:
    return float(run_info(ref)["wall_clock_per_run_s"])


def read_rows(path: Path) -> list[dict[str, str]]:
    """The rows with a test success of a metrics CSV."""
    import csv

    with open(path, newline="", encoding="utf-8") as f:
        return [r for r in csv.DictReader(f) if r.get("test_success", "") != ""]


def success(rows: list[dict[str, str]]) -> list[float]:
    return [float(r["test_success"]) for r in rows]


def same_epochs(refs: list[str], seed: int) -> int:
    """Epochs of ``seed`` on which every setting of ``refs`` has the same test success."""
    curves = [success(setting(r).runs[seed]) for r in refs]
    return sum(len({round(c[i], 6) for c in curves}) == 1 for i in range(min(map(len, curves))))


def window_mean(rows: list[dict[str, str]], lo: float, hi: float, col: str = "test_success"
                ) -> float:
    """Mean of ``col`` over the epochs whose env steps end in (lo, hi]."""
    return statistics.fmean(float(r[col]) for r in rows if lo < float(r["env_steps"]) <= hi)




@dataclass(frozen=True)
class Named:
    fn: Callable[[], float | str]
    doc: str
    source: str  # under experiments/results


NAMED: dict[str, Named] = {}


def add(name: str, source: str, doc: str, fn: Callable[[], float | str]) -> None:
    if name in NAMED:  # a second definition would silently replace the first
        raise ValueError(f"figure {name!r} is defined twice")
    NAMED[name] = Named(fn, doc, source)


TASKS_PY = "../../rdher_jax/tasks.py"  # the paper's figures (a source is under experiments/results)
CARD = "design_card/FetchSlide"
PUSHM3 = "moving_goals/pushmoving_fast"
PUSH_FLOOR = ["bp/push/ddpg", "bp/push/dher", "bp/push/rdher", "bp/push/cher"]
PNP_PAIRS = [f"ap/pnp/{n}" for n in ("rdher_lr0.5_lh4", "rdher_lr1_lh2", "rdher_lr1_lh4",
                                     "rdher_lr2_lh1", "rdher_lr4_lh0.5", "rdher_lr4_lh1")]
TABLE2 = [f"bp/{t}/{a}" for t in ("slide", "pnp") for a in ("ddpg", "her", "cher", "dher",
                                                             "rdher")]


def _card() -> list[dict[str, str]]:
    return read_rows(RESULTS / CARD / "metrics.csv")


def _pushm3() -> list[dict[str, str]]:
    return read_rows(RESULTS / PUSHM3 / "dher_frac0.2_s3.csv")


def _bl(name: str) -> dict:
    return json.loads((RESULTS / "bench_learning" / f"{name}.json").read_text(encoding="utf-8"))


def _idle_pace() -> float:
    """Env steps a minute of push-fast-idle's seed 0, to 0.9 (mean of 3)."""
    w = _bl("push-fast-idle")["results"]["0"]["hits"]["0.9"]["window"]
    return w["env_steps"] / (w["wall_s"] / 60)


def _paced_minutes() -> list[float]:
    """Seeds 1-4 of preset=fast on FetchPush (timed beside other work): their steps to 0.9
    (mean of 3) at seed 0's idle pace, in minutes."""
    steps = [r["hits"]["0.9"]["window"]["env_steps"]
             for name in ("push-fast-overlap", "push-fast-overlap-more")
             for k, r in _bl(name)["results"].items() if k != "0"]
    return [n / _idle_pace() for n in steps]


def _her_hits() -> list[float | None]:
    return [first_hit(rows, 0.9, 3) for rows in setting("bc/push/her").runs.values()]


add("card:best", CARD, "design card: best 10-episode test success (a rate)",
    lambda: max(success(_card())))
add("card:best_epoch", CARD, "design card: the epoch (as logged, from 1) of the best test "
    "success", lambda: float(next(r["epoch"] for r in _card()
                                  if float(r["test_success"]) == max(success(_card())))))
add("card:last", CARD, "design card: the last epoch's test success (a rate)",
    lambda: success(_card())[-1])
add("card:final", CARD, "design card: mean of the last 3 epochs' test success (report.py's "
    "final; a rate)", lambda: statistics.fmean(success(_card())[-report.LAST:]))
add("card:last10", CARD, "design card: mean of the last 10 epochs' test success (a rate)",
    lambda: statistics.fmean(success(_card())[-10:]))
add("card:wall", CARD, "design card: the run's wall clock (wall_time of the last epoch)",
    lambda: Duration(float(_card()[-1]["wall_time"])))

for _lo, _hi, _key in ((0, 100_000, "w1"), (100_000, 200_000, "w2"), (200_000, 250_000, "w3")):
    add(f"pushm3:{_key}", PUSHM3, f"FetchPushMoving, DHER at a 0.2 share, seed 3: mean test "
        f"success over env steps ({_lo:,}, {_hi:,}] (a rate)",
        functools.partial(lambda lo, hi: window_mean(_pushm3(), lo, hi), _lo, _hi))
add("pushm3:best", PUSHM3, "the same run: best test success (a rate)",
    lambda: max(success(_pushm3())))
add("pushm3:last", PUSHM3, "the same run: the last epoch's test success (a rate)",
    lambda: success(_pushm3())[-1])
add("pushm3:final", PUSHM3, "the same run: mean of the last 3 epochs (a rate)",
    lambda: statistics.fmean(success(_pushm3())[-report.LAST:]))
add("pushm3:combined:min", PUSHM3, "the same run: lowest share of combined rows in a batch of "
    "any epoch, %", lambda: 100 * min(float(r["frac_dher"]) for r in _pushm3()))
add("pushm3:combined:max", PUSHM3, "the same run: highest share of combined rows, %",
    lambda: 100 * max(float(r["frac_dher"]) for r in _pushm3()))
add("pushm3:wall", PUSHM3, "the same run: its wall clock (wall_time of the last epoch)",
    lambda: Duration(float(_pushm3()[-1]["wall_time"])))

add("bp/push/*:wall_min:min", "benchmark/paper/FetchPush", "Push at the paper's budget: the "
    "fewest minutes per run of any algorithm (run_info.json, wall_clock_per_run_s)",
    lambda: min(per_run_s(r) for r in ["bp/push/her", *PUSH_FLOOR]) / 60)
add("bp/push/*:wall_min:max", "benchmark/paper/FetchPush", "the same: the most",
    lambda: max(per_run_s(r) for r in ["bp/push/her", *PUSH_FLOOR]) / 60)
for _cpu, _key in (("AMD EPYC", "epyc"), ("Intel(R) Xeon(R) Processor", "xeon")):
    for _f, _m in ((min, "min"), (max, "max")):
        add(f"bp/slide+pnp/{_key}:wall_min:{_m}", "benchmark/paper", f"Slide and PickAndPlace "
            f"Table 2 runs on the {_key}: the {'fewest' if _m == 'min' else 'most'} minutes per "
            "run of any algorithm", functools.partial(
                lambda f, cpu: f(per_run_s(r) for r in TABLE2
                                 if run_info(r)["hardware"]["processor"] == cpu) / 60, _f, _cpu))

for _seed in range(3):
    add(f"ap/pnp/*:same_epochs:s{_seed}", "ablation/paper/FetchPickAndPlace", f"PickAndPlace "
        f"ablation: epochs of seed {_seed} on which all six pairs' test success is the same",
        functools.partial(lambda k: same_epochs(PNP_PAIRS, k), _seed))

def _over(refs: list[str], measure: str, keep: Callable[[int], bool] = lambda k: True
          ) -> list[float]:
    """``measure`` of every seed ``keep`` takes of every setting of ``refs``."""
    return [v for r in refs for k, v in seeds(r, measure).items() if keep(k)]


PUSH_LEARNERS = ["bp/push/ddpg", "bp/push/dher", "bp/push/her", "bp/push/rdher"]
for _m in ("best", "policy"):
    for _f in (min, max):
        add(f"bp/push/ddpg+dher+her+rdher:{_m}:s0+s1:{_f.__name__}", "benchmark/paper/FetchPush",
            f"Push at the paper's budget, seeds 0 and 1 of DDPG, DHER, HER and RDHER: the "
            f"{'lowest' if _f is min else 'highest'} {_m}", functools.partial(
                lambda m, f: f(_over(PUSH_LEARNERS, m, lambda k: k in (0, 1))), _m, _f))
PUSH_MIXES = ["bp/push/dher", "bp/push/rdher", "yp/push/dher_plain", "yp/push/rdher_plain"]
for _seed in range(5):
    for _f in (min, max):
        add(f"bp+yp/push/dher+rdher+plain:final:s{_seed}:{_f.__name__}", "beyond/paper/FetchPush",
            f"Push at the paper's budget, DHER and RDHER with either mix, seed {_seed}: the "
            f"{'lowest' if _f is min else 'highest'} final",
            functools.partial(lambda k, f: f(_over(PUSH_MIXES, "final", lambda j: j == k)),
                              _seed, _f))
SLIDE_PNP_HER_RDHER = ["bp/slide/her", "bp/pnp/her", "bp/slide/rdher", "bp/pnp/rdher"]
for _f in (min, max):
    add(f"bp/slide+pnp/her+rdher:best-policy:{_f.__name__}", "benchmark/paper", "Slide and "
        "PickAndPlace at the paper's budget, HER and RDHER: the "
        f"{'smallest' if _f is min else 'largest'} gap of best epoch over best policy retested",
        functools.partial(lambda f: f(value(f"{r}:best") - value(f"{r}:policy")
                                      for r in SLIDE_PNP_HER_RDHER), _f))
PUSH_PAIRS = [p.replace("/pnp/", "/push/") for p in PNP_PAIRS]
for _seed in range(3):
    add(f"ap/push/*:same_epochs:s{_seed}", "ablation/paper/FetchPush", f"Push ablation: epochs "
        f"of seed {_seed} on which all six pairs' test success is the same",
        functools.partial(lambda k: same_epochs(PUSH_PAIRS, k), _seed))


def _paper_s(ref: str) -> float:
    """The paper's Table 3 wall clock of one run for ``ref``'s task and algorithm, in seconds."""
    return _table3_s(setting(ref).task, run_info(ref).get("algo"))


REACH_TABLE3 = ["bp/reach/ddpg", "bp/reach/her", "bp/reach/rdher"]
for _f in (min, max):
    add(f"bp/reach/ddpg+her+rdher:table3_ratio:{_f.__name__}", "benchmark/paper/FetchReach",
        "Reach at the paper's budget, DDPG, HER and RDHER: the paper's Table 3 time of one run "
        f"over ours, the {'smallest' if _f is min else 'largest'}", functools.partial(
            lambda f: f(_paper_s(r) / per_run_s(r) for r in REACH_TABLE3), _f))
    add(f"paper/slide+pnp/her+dher+rdher:table3:{_f.__name__}", TASKS_PY, "the paper's Table 3 "
        "on Slide and PickAndPlace, HER, DHER and RDHER: the "
        f"{'shortest' if _f is min else 'longest'} run", functools.partial(
            lambda f: Duration(f(_table3_s(TASKS[t], a) for t in ("slide", "pnp")
                                 for a in ("her", "dher", "rdher"))), _f))


SLIDE_PNP_DHER = ["bp/slide/dher", "bp/slide/rdher", "bp/pnp/dher", "bp/pnp/rdher"]
HARD = [f"bp/{t}/{a}" for t in ("push", "slide", "pnp")
        for a in ("ddpg", "her", "cher", "dher", "rdher")]
for _f in (min, max):
    add(f"bp/slide+pnp/dher+rdher:combined_run:{_f.__name__}", "benchmark/paper", "Slide and "
        "PickAndPlace at the paper's budget, DHER and RDHER: the "
        f"{'lowest' if _f is min else 'highest'} share of combined rows of a seed, mean over "
        "all its epochs, %", functools.partial(
            lambda f: f(_over(SLIDE_PNP_DHER, "combined_run")), _f))
    add(f"bp/push+slide+pnp/*:wall_min:{_f.__name__}", "benchmark/paper", "Push, Slide and "
        "PickAndPlace at the paper's budget, every algorithm: the "
        f"{'fewest' if _f is min else 'most'} minutes per run (run_info.json)",
        functools.partial(lambda f: f(per_run_s(r) for r in HARD) / 60, _f))


def _her_ahead_s012() -> list[tuple[float, float, int]]:
    """Push ablation: HER against each pair, paired over seeds 0-2 (the pairs' seeds)."""
    her = {k: v for k, v in seeds("ap/push/her", "final").items() if k < 3}
    return [report.paired({k: v / 100 for k, v in her.items()},
                          {k: v / 100 for k, v in seeds(r, "final").items() if k < 3})
            for r in _expand("ap/push/rdher_*")]


add("ap/push/her-rdher_*:final:paired:s0-2:min", "ablation/paper/FetchPush", "Push ablation: "
    "HER's final minus each pair's, paired over seeds 0-2, the smallest",
    lambda: 100 * min(d for d, _, _ in _her_ahead_s012()))
add("ap/push/her-rdher_*:final:paired:s0-2:max", "ablation/paper/FetchPush", "the same, the "
    "largest", lambda: 100 * max(d for d, _, _ in _her_ahead_s012()))
add("ap/push/her-rdher_*:final:paired:p:s0-2:min", "ablation/paper/FetchPush", "the same: the "
    "smallest paired p", lambda: min(p for _, p, _ in _her_ahead_s012()))


def _ablation_pieces() -> list[float]:
    """Minutes per run of every one-seed piece of the Push and PickAndPlace ablations."""
    return [m for t in ("push", "pnp") for r in _expand(f"ap/{t}/rdher_*")
            if run_info(r).get("pieces") for m in _pieces(r)]


for _f in (min, max):
    add(f"ap/push+pnp/*:piece_min:{_f.__name__}", "ablation/paper", "Push and PickAndPlace "
        f"ablations: the {'fewest' if _f is min else 'most'} minutes per run of a one-seed piece",
        functools.partial(lambda f: f(_ablation_pieces()), _f))


PIECES_NO_CHER = ["bp/push/ddpg", "bp/push/dher", "bp/push/her", "bp/pnp/ddpg"]
for _f in (min, max):
    add(f"bp/push+pnp/ddpg+dher+her:piece_min:{_f.__name__}", "benchmark/paper", "Push's DDPG, "
        "DHER and HER and PickAndPlace's DDPG at the paper's budget: the "
        f"{'fewest' if _f is min else 'most'} minutes per run of a one-seed piece",
        functools.partial(lambda f: f(m for r in PIECES_NO_CHER for m in _pieces(r)), _f))


def _cost(experiment: str | None, task: str | None, col: int) -> float:
    """cost.md's figure: sweeps' rows of ``experiment`` (and ``task``), or of the bench_learning
    settings (``experiment`` "bench_learning"); the total (None) is both, as cost.md's."""
    levers = [(n, t, r, h) for n, t, r, h in report.lever_cost_rows(RESULTS)]
    lever = sum(x[col - 1] for x in levers if task in (None, x[1]))
    if experiment == "bench_learning":
        return lever
    rows = report.cost_rows(report.profiles_data(RESULTS))
    return sum(r[col] for r in rows if experiment in (None, r[0]) and task in (None, r[1])) + (
        lever if experiment is None else 0)


for _exp, _task, _key in ((None, None, "total"), ("benchmark/paper", None, "benchmark/paper"),
                          ("beyond/paper", "FetchPush", "beyond/paper/FetchPush"),
                          ("bench_learning", None, "bench_learning")):
    add(f"cost:{_key}:hours", "cost.md", f"cost.md: core-hours of {_key}",
        functools.partial(_cost, _exp, _task, 4))
    add(f"cost:{_key}:runs", "cost.md", f"cost.md: runs of {_key}",
        functools.partial(_cost, _exp, _task, 3))
add("bl/push-fast:to_0.9:max", "bench_learning/push-fast.json", "preset=fast on Push, "
    "bench_learning's first three seeds: the most env steps to 0.9 (mean of 3)",
    lambda: max(r["hits"]["0.9"]["window"]["env_steps"]
                for r in _bl("push-fast")["results"].values()))


def _cycle(setting: str, key: str) -> float:
    rows = json.loads((RESULTS / "bench_cycle.json").read_text(encoding="utf-8"))
    return float(next(r for r in rows if r["setting"] == setting)[key])


for _set in ("default", "fast"):
    add(f"cycle/{_set}:update_ms", "bench_cycle.json", f"bench_cycle.md, FetchPush, {_set}: one "
        "sampled gradient step, ms", functools.partial(_cycle, _set, "update_ms"))


SLIDE_COMBINED = ["yp/slide/rdher", "yp/slide/rdher_clip", "bp/slide/dher"]
for _f in (min, max):
    add(f"yp/slide/rdher+rdher_clip+dher:combined_run:{_f.__name__}", "beyond/paper/FetchSlide",
        "Slide at the paper's budget, RDHER with either clip and DHER at the authors' share: "
        f"the {'lowest' if _f is min else 'highest'} share of combined rows of a seed, mean over "
        "all its epochs, %", functools.partial(
            lambda f: f(_over(SLIDE_COMBINED, "combined_run")), _f))


@functools.cache
def _claims(task: str) -> tuple[dict, ...]:
    """The solve benchmark's claim-by-claim rows for ``task``, as its summary.md has them."""
    ss = [s for s in report.load(RESULTS / "benchmark/solve") if s.task == task]
    return tuple(report.order_claims(task, ss))


for _abbr in ("push", "slide", "pnp"):
    add(f"bs/{_abbr}:claims", f"benchmark/solve/{TASKS[_abbr]}", f"{TASKS[_abbr]}, solve study: "
        "the claims of the paper's Table 2 order tested with a p (the family Holm corrects over)",
        functools.partial(lambda t: next((r["family"] for r in _claims(t)), 0), TASKS[_abbr]))
    add(f"bs/{_abbr}:claims:holm", f"benchmark/solve/{TASKS[_abbr]}", "the same: how many of "
        "them hold or are reversed after Holm's correction", functools.partial(
            lambda t: sum(bool(r["holm"]) and r["verdict"] in ("holds", "reversed")
                          for r in _claims(t)), TASKS[_abbr]))


def _floor(task: str) -> dict:
    rows = json.loads((RESULTS / "floor.json").read_text(encoding="utf-8"))["rows"]
    return next(r for r in rows if r["task"] == task)


for _abbr, _task in TASKS.items():
    if _abbr in ("reach", "push", "slide", "pnp"):
        add(f"floor/{_abbr}:zero", "floor.md", f"{_task}: success of a policy that does nothing "
            "on 1,000 episodes, %", functools.partial(
                lambda t: 100 * _floor(t)["zero_action_success"], _task))
        for _i, _end in enumerate(("lo", "hi")):
            add(f"floor/{_abbr}:zero:{_end}", "floor.md", f"{_task}: the 95% interval of that "
                f"success, its {'lower' if _end == 'lo' else 'upper'} end, %", functools.partial(
                    lambda t, i: 100 * _floor(t)["ci95"][i], _task, _i))
        for _n in (10, 20):
            add(f"floor/{_abbr}:best{_n}", "floor.md", f"{_task}: the expected best of 50 "
                f"epochs of {_n} test episodes of a policy that does nothing, %",
                functools.partial(lambda t, n: 100 * _floor(t)[f"best_of_epochs_{n}"], _task,
                                  _n))


add("bc/push/her:to_0.9:min", "benchmark/cpu/FetchPush/her", "preset=fast HER on Push: the "
    "fewest env steps of a seed to a trailing mean of 3 epochs of 0.9 (bench_learning's rule)",
    lambda: min(h for h in _her_hits() if h))
add("bc/push/her:to_0.9:max", "benchmark/cpu/FetchPush/her", "the same: the most",
    lambda: max(h for h in _her_hits() if h))
add("bc/push/her:to_0.9:n", "benchmark/cpu/FetchPush/her", "the same: seeds that get there",
    lambda: sum(h is not None for h in _her_hits()))
add("bc/push/her:to_0.9:never", "benchmark/cpu/FetchPush/her", "the same: the seeds that never "
    "do, as 'seed K' or 'seeds K, L'", lambda: (lambda ks: f"seed{'s' * (len(ks) > 1)} "
                                                + ", ".join(ks))(
    [str(k) for k, h in zip(setting("bc/push/her").runs, _her_hits(), strict=True) if not h]))
add("bl/push-fast-idle:to_0.9_min", "bench_learning/push-fast-idle.json", "preset=fast on Push, "
    "seed 0 alone on the idle Intel Xeon: minutes to a trailing mean of 3 epochs of 0.9",
    lambda: _bl("push-fast-idle")["results"]["0"]["hits"]["0.9"]["window"]["wall_s"] / 60)
add("bl/push-fast:paced_min:min", "bench_learning", "preset=fast on Push, seeds 1-4 (timed "
    "beside other work): the fewest minutes to 0.9 (mean of 3) at seed 0's idle pace",
    lambda: min(_paced_minutes()))
add("bl/push-fast:paced_min:max", "bench_learning", "the same: the most",
    lambda: max(_paced_minutes()))


def source(name: str) -> Path:
    """The committed file or directory figure ``name`` comes from (what its link must name): a
    setting's directory, for a glob its task's, for a named figure its own ``source``."""
    if name in NAMED:
        return RESULTS / NAMED[name].source
    if name.startswith("paper/"):
        return RESULTS / TASKS_PY
    if name.startswith("bl/"):
        bl, field = name[3:].split(":")[:2]
        return RESULTS / f"bench_learning/{bl}.json"
    ref = name.split(":")[0].split("-")[0]
    if any(c in ref for c in "*?["):
        kind, task, _ = ref.split("/")
        return RESULTS / KINDS[kind] / TASKS[task]
    return setting_dir(ref)


def value(name: str) -> float | str:
    """The figure ``name`` recomputed from the committed data.

    Raises:
        KeyError: ``name`` is no figure of the table nor of the grammar, or its data are missing.
    """
    if name in NAMED:
        return NAMED[name].fn()
    return systematic(name)


# ------------------------------------------------------------------ the markdown

MARK = re.compile(r'\[([^\[\]]*)\]\(([^()\s]*) "q:([^"]+)"\)')
NUMBER = re.compile(r"[+\u2212-]?\d[\d,]*(?:\.\d+)?(?:e[+-]?\d+)?k?")


@dataclass(frozen=True)
class Quote:
    path: Path
    line: int
    text: str
    target: str
    name: str
    start: int  # offsets of the text in the file
    end: int


# A link in code (a span may go on over a line break, not over a paragraph) is an example.
CODE = re.compile(r"```.*?```|`(?:[^`\n]|\n(?!\n))+`", re.DOTALL)


def quotes(path: Path) -> Iterator[Quote]:
    src = path.read_text(encoding="utf-8")
    code = [m.span() for m in CODE.finditer(src)]
    for m in MARK.finditer(src):
        if any(a <= m.start() < b for a, b in code):
            continue
        yield Quote(path, src.count("\n", 0, m.start()) + 1, m.group(1), m.group(2),
                    m.group(3), m.start(1), m.end(1))


def render(val: float | str, like: str) -> str:
    """``val`` written at the precision and in the style of the text ``like`` (its decimals or
    significant digits, thousands commas, a leading + on a signed figure, − or - for minus)."""
    if isinstance(val, str):
        return val
    if isinstance(val, Duration):
        return clock(val, like)
    if like.endswith("k"):  # in thousands
        return render(val / 1000, like[:-1]) + "k"
    body = like.lstrip("+\u2212-")
    if "e" in body:
        digits = len(body.split("e")[0].replace(".", "").lstrip("0"))
        mant, exp = f"{val:.{max(digits - 1, 0)}e}".split("e")
        out = f"{mant}e{int(exp):+03d}"
    else:
        places = len(body.split(".")[1]) if "." in body else 0
        # Halves round up, as a reader rounds 112,500 to 113k (float round() goes to even).
        half_up = Decimal(repr(float(val))).quantize(Decimal(1).scaleb(-places), ROUND_HALF_UP)
        out = f"{float(half_up) + 0.0:{',' if ',' in body else ''}.{places}f}"
        if float(out.replace(",", "")) == 0:
            out = out.lstrip("-")  # a tie reads 0.0 or +0.0, never -0.0
    if out.startswith("-"):
        return ("\u2212" if "\u2212" in like else "-") + out[1:]
    return ("+" if like[:1] in ("+", "-", "\u2212") else "") + out


def same(a: str, b: str) -> bool:
    """Two renderings of one figure, whatever the style of their minus and plus signs."""
    def norm(t: str) -> str:
        return t.replace("\u2212", "-").lstrip("+")
    return norm(a) == norm(b)


def problem(q: Quote, root: Path = ROOT) -> str | None:
    """What is wrong with the quoted figure ``q``, or None."""
    where = f"{q.path.relative_to(root) if q.path.is_relative_to(root) else q.path}:{q.line}"
    try:
        val = value(q.name)
        src = source(q.name)
    except KeyError as e:
        return f"{where}: {q.name}: {e.args[0] if e.args else e}"
    target = (q.path.parent / q.target.split("#")[0]).resolve()
    if target != src.resolve():
        return (f"{where}: {q.name}: the link goes to {q.target}, not to the data the figure "
                f"comes from ({src.resolve().relative_to(ROOT)})")
    if isinstance(val, float) and not math.isfinite(val):
        return (f"{where}: {q.name}: the data give {val!r} (e.g. no seed count detects a "
                "difference of zero), which no figure can quote: rewrite the sentence")
    if isinstance(val, str | Duration):
        ok = render(val, q.text) == q.text
    else:
        if not NUMBER.fullmatch(q.text):
            return f"{where}: {q.name}: the text {q.text!r} is not a number"
        ok = same(render(val, q.text), q.text)
    if ok:
        return None
    return (f"{where}: {q.name}: the text says {q.text!r}, the committed data give "
            f"{render(val, q.text)!r} ({val!r})")


def check(files: list[Path] | None = None, root: Path = ROOT) -> tuple[int, list[str]]:
    """(figures checked, what is wrong) over ``files`` (default: :func:`markdown_files`)."""
    found = [q for f in files or markdown_files(root) for q in quotes(f)]
    return len(found), [p for q in found if (p := problem(q, root)) is not None]


def write(files: list[Path] | None = None) -> int:
    """Rewrite every quoted figure's text from the data; returns how many changed."""
    changed = 0
    for f in files or markdown_files():
        src = f.read_text(encoding="utf-8")
        out, at = [], 0
        for q in quotes(f):
            val = value(q.name)
            if isinstance(val, float) and not math.isfinite(val):  # left for --check to name
                new = q.text
            else:
                new = render(val, q.text)
            if not same(new, q.text):
                changed += 1
            else:
                new = q.text
            out += [src[at:q.start], new]
            at = q.end
        out.append(src[at:])
        if "".join(out) != src:
            report.write_text_atomic(f, "".join(out))
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/quoted.py",
                                 description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--check", action="store_true", help="compare every checked figure with the "
                   "data (the default); exit 1 if any differs")
    g.add_argument("--write", action="store_true", help="rewrite every checked figure's text "
                   "from the data, at its precision")
    g.add_argument("--list", action="store_true", help="the named figures and their docs")
    args = ap.parse_args(argv)
    if args.list:
        for name, n in sorted(NAMED.items()):
            print(f"{name}: {n.doc}")
        return 0
    if args.write:
        print(f"{write()} figures rewritten")
        return 0
    n, bad = check()
    for line in bad:
        print(line)
    print(f"{n} checked figures, {len(bad)} differ from the committed data")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
