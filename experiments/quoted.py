"""Figures the hand-written prose quotes, each recomputed from the committed data.

    python experiments/quoted.py --check    # each checked figure against the data; exit 1 on a miss
    python experiments/quoted.py --write    # rewrite every checked figure from the data
    python experiments/quoted.py --list     # the named figures of the table below

In ``experiments/results/RESULTS.md``, ``README.md`` and every ``experiments/results/**/README.md``
a checked figure is a markdown link whose title starts with ``q:`` and names the figure; the
link goes to the committed data it comes from (relative to the markdown file, as any link):

    [91.7](../benchmark/cpu/FetchPush/her "q:bc/push/her:final")

A figure not written so is hand-typed, and nothing checks it. The text of a numeric figure is
compared at its own precision (``92`` quotes 91.67 correctly, ``91.6`` does not; a p of
``0.032`` is 0.0317 to three decimals; ``1.5e-07`` to two significant digits); a text figure
(a wall clock such as ``33 min 16 s``) must match exactly. ``tests/test_quoted.py`` runs the
check.

Names. A *setting* is ``<kind>/<task>/<setting>`` with the kind and profile abbreviated
(:data:`KINDS`: ``bp`` = ``benchmark/paper``, ...) and the task too (:data:`TASKS`: ``push`` =
``FetchPush``, ...), e.g. ``bp/slide/rdher`` is ``experiments/results/benchmark/paper/FetchSlide/
rdher``. A *measure* is one of report.py's per-seed figures (:func:`report.per_seed`): ``best``
(max over epochs of test success), ``final`` (mean of the last 3 epochs), ``mean`` (mean over
all epochs), ``policy`` (the best policy retested); all in %.

- ``S:M`` the mean over seeds of measure M of setting S; ``S:M:sd`` its sample std, ``S:M:lo``
  / ``S:M:hi`` its 95% t interval clipped to [0, 100] (as summary.md prints it), ``S:M:n`` the
  seeds, ``S:M:s2`` seed 2's value, ``S:M:min`` / ``S:M:max`` the lowest / highest seed's.
- ``S-T:M`` the mean of S minus the mean of T (Welch), ``S-T:M:p`` Welch's two-sided p;
  ``S-T:M:paired`` and ``S-T:M:paired:p`` the same paired by seed (:func:`report.paired`). T is
  a setting, or a setting name alone for one of S's task (``bp/slide/rdher-her``).
- A setting may be a glob over setting names (``ap/pnp/rdher_*``); then ``:min`` or ``:max``
  at the end takes the lowest or highest of the settings' figures
  (``ap/pnp/rdher_*:policy:min``).
- Any other name is an entry of :data:`NAMED` below.

Numbers are as report.py's tables print them (100 · rate, Welch and paired tests on the
rounded rates), so a figure the prose takes from a summary.md table checks against the table.
"""

from __future__ import annotations

import argparse
import fnmatch
import functools
import re
import statistics
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import report  # noqa: E402

ROOT = HERE.parent
RESULTS = HERE / "results"
KINDS = {"ac": "ablation/cpu", "ap": "ablation/paper", "bc": "benchmark/cpu",
         "bp": "benchmark/paper", "yc": "beyond/cpu", "yp": "beyond/paper", "mc": "moving/cpu"}
TASKS = {"reach": "FetchReach", "push": "FetchPush", "slide": "FetchSlide",
         "pnp": "FetchPickAndPlace", "pushm": "FetchPushMoving", "reachm": "FetchReachMoving"}
MEASURES = ("best", "final", "mean", "policy")


def markdown_files(root: Path = ROOT) -> list[Path]:
    """The files whose prose may quote checked figures."""
    res = root / "experiments" / "results"
    return [root / "README.md", res / "RESULTS.md", *sorted(res.glob("**/README.md"))]


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


def seeds(ref: str, measure: str) -> dict[int, float]:
    """Per seed, ``measure`` of setting ``ref`` (a rate in [0, 1])."""
    if measure not in MEASURES:
        raise KeyError(f"no measure {measure!r} (one of {', '.join(MEASURES)})")
    return report.per_seed(setting(ref))[measure]


def _over_seeds(ref: str, measure: str, stat: str) -> float:
    xs = seeds(ref, measure)
    if not xs:
        raise KeyError(f"{ref} has no {measure!r} figures")
    st = report.stat(list(xs.values()))
    if stat == "mean":
        return 100 * st.mean
    if stat == "sd":
        return 100 * st.std
    if stat == "lo":
        return 100 * max(st.lo, 0.0)
    if stat == "hi":
        return 100 * min(st.hi, 1.0)
    if stat == "n":
        return len(xs)
    if stat == "min":
        return 100 * min(xs.values())
    if stat == "max":
        return 100 * max(xs.values())
    if re.fullmatch(r"s\d+", stat):
        if int(stat[1:]) not in xs:
            raise KeyError(f"{ref} has no seed {stat[1:]}")
        return 100 * xs[int(stat[1:])]
    raise KeyError(f"no statistic {stat!r} (mean, sd, lo, hi, n, min, max, s<seed>)")


def _versus(a: str, b: str, measure: str, test: list[str]) -> float:
    if "/" not in b:
        b = a.rsplit("/", 1)[0] + "/" + b
    xs, ys = seeds(a, measure), seeds(b, measure)
    if test in ([], ["p"]):
        diff, p = report.welch(list(xs.values()), list(ys.values()))
    elif test in (["paired"], ["paired", "p"]):
        diff, p, _ = report.paired(xs, ys)
    else:
        raise KeyError(f"no test {':'.join(test)!r} (nothing, p, paired, paired:p)")
    return p if test[-1:] == ["p"] else 100 * diff


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


def systematic(name: str) -> float:
    """The value of a name of the grammar in the module's docstring."""
    parts = name.split(":")
    if len(parts) < 2:
        raise KeyError(f"unknown figure {name!r}")
    ref, measure, rest = parts[0], parts[1], parts[2:]
    over = None
    if any(c in ref for c in "*?[") and rest[-1:] in (["min"], ["max"]):
        over, rest = rest[-1], rest[:-1]
    if "-" in ref:
        a, b = ref.split("-", 1)
        vals = [_versus(x, b, measure, rest) for x in _expand(a)]
    else:
        stat = rest[0] if rest else "mean"
        if len(rest) > 1:
            raise KeyError(f"unknown figure {name!r}")
        vals = [_over_seeds(x, measure, stat) for x in _expand(ref)]
    if len(vals) > 1 and over is None:
        raise KeyError(f"{name!r}: a glob needs :min or :max at the end")
    return min(vals) if over == "min" else max(vals) if over == "max" else vals[0]


# ------------------------------------------------------------------ named figures

def minutes_seconds(seconds: float) -> str:
    """``2016.4`` -> ``'33 min 16 s'`` (rounded to the second; hours as minutes)."""
    s = int(round(seconds))
    return f"{s // 60} min {s % 60} s"


def per_run_s(ref: str) -> float:
    return float(run_info(ref)["wall_clock_per_run_s"])


def piece_minutes(ref: str) -> list[float]:
    """Minutes per run of each one-seed piece of a setting run in pieces."""
    return [float(p["wall_clock_s"]) / int(p["runs"]) / 60 for p in run_info(ref)["pieces"]]


def epochs_at(ref: str, seed: int, col: str = "test_success") -> list[float]:
    return [report._float(r.get(col, "")) for r in setting(ref).runs[seed]]


def same_epochs(refs: list[str], seed: int) -> int:
    """Epochs of ``seed`` on which every setting of ``refs`` has the same test success."""
    curves = [epochs_at(r, seed) for r in refs]
    return sum(len({round(c[i], 6) for c in curves}) == 1 for i in range(min(map(len, curves))))


def design_card() -> list[dict[str, str]]:
    import csv

    with open(RESULTS / "design_card" / "FetchSlide" / "metrics.csv", newline="",
              encoding="utf-8") as f:
        return [r for r in csv.DictReader(f) if r.get("test_success", "") != ""]


def _card_success() -> list[float]:
    return [float(r["test_success"]) for r in design_card()]


@dataclass(frozen=True)
class Named:
    fn: Callable[[], float | str]
    doc: str


NAMED: dict[str, Named] = {}


def named(name: str, doc: str) -> Callable[[Callable[[], float | str]], Callable[[], float | str]]:
    def deco(fn: Callable[[], float | str]) -> Callable[[], float | str]:
        NAMED[name] = Named(fn, doc)
        return fn
    return deco


# Sets of settings the prose quotes together.
PUSH_FLOOR = ["bp/push/ddpg", "bp/push/dher", "bp/push/rdher", "bp/push/cher"]
PNP_PAIRS = [f"ap/pnp/{n}" for n in ("rdher_lr0.5_lh4", "rdher_lr1_lh2", "rdher_lr1_lh4",
                                     "rdher_lr2_lh1", "rdher_lr4_lh0.5", "rdher_lr4_lh1")]


@named("card:best", "design card: best 10-episode test success (a rate)")
def _card_best() -> float:
    return max(_card_success())


@named("card:best_epoch", "design card: the epoch (as logged, from 1) of the best test success")
def _card_best_epoch() -> float:
    rows = design_card()
    best = max(_card_success())
    return float(next(r["epoch"] for r in rows if float(r["test_success"]) == best))


@named("card:last", "design card: the last epoch's test success (a rate)")
def _card_last() -> float:
    return _card_success()[-1]


@named("card:final", "design card: mean of the last 3 epochs' test success (report.py's final)")
def _card_final() -> float:
    return statistics.fmean(_card_success()[-report.LAST:])


@named("card:last10", "design card: mean of the last 10 epochs' test success")
def _card_last10() -> float:
    return statistics.fmean(_card_success()[-10:])


@named("card:wall", "design card: the run's wall clock (metrics.csv, wall_time of the last epoch)")
def _card_wall() -> str:
    return minutes_seconds(float(design_card()[-1]["wall_time"]))


for _ref in ("bp/push/her", "bp/push/ddpg", "bp/push/dher", "bp/push/rdher", "bp/push/cher",
             "bp/slide/her", "bp/slide/dher", "bp/slide/rdher", "bp/slide/ddpg",
             "bp/slide/cher", "bp/pnp/her", "bp/pnp/dher", "bp/pnp/rdher", "bp/pnp/ddpg",
             "bp/pnp/cher", "bp/reach/ddpg", "bp/reach/her", "bp/reach/rdher",
             "bp/reach/cher", "bp/reach/dher", "bc/push/her", "bc/push/rdher"):
    NAMED[f"{_ref}:wall"] = Named(functools.partial(lambda r: minutes_seconds(per_run_s(r)),
                                                    _ref),
                                  f"{_ref}: wall clock per run (run_info.json)")
    NAMED[f"{_ref}:wall_min"] = Named(functools.partial(lambda r: per_run_s(r) / 60, _ref),
                                      f"{_ref}: minutes per run (run_info.json)")


@named("bp/push/pieces:wall_min:min", "Push, paper budget: fewest minutes per run of any "
       "setting (per-setting wall clock per run)")
def _push_min() -> float:
    return min(per_run_s(r) for r in ["bp/push/her", *PUSH_FLOOR]) / 60


@named("bp/push/pieces:wall_min:max", "Push, paper budget: most minutes per run of any setting")
def _push_max() -> float:
    return max(per_run_s(r) for r in ["bp/push/her", *PUSH_FLOOR]) / 60


@named("bp/slide+pnp/epyc:wall_min:min", "Slide and PickAndPlace Table 2 runs on the AMD EPYC: "
       "fewest minutes per run")
def _epyc_min() -> float:
    return min(_epyc_slide_pnp()) / 60


@named("bp/slide+pnp/epyc:wall_min:max", "Slide and PickAndPlace Table 2 runs on the AMD EPYC: "
       "most minutes per run")
def _epyc_max() -> float:
    return max(_epyc_slide_pnp()) / 60


def _epyc_slide_pnp() -> list[float]:
    return [per_run_s(r) for t in ("slide", "pnp") for a in ("ddpg", "her", "cher", "dher",
                                                             "rdher")
            if run_info(r := f"bp/{t}/{a}")["hardware"]["processor"] == "AMD EPYC"]


@named("ap/pnp/pairs:same_epochs:s0", "PickAndPlace ablation: epochs of seed 0 on which the six "
       "pairs' test success is the same")
def _pnp_same0() -> float:
    return same_epochs(PNP_PAIRS, 0)


@named("ap/pnp/pairs:same_epochs:s1", "the same, seed 1")
def _pnp_same1() -> float:
    return same_epochs(PNP_PAIRS, 1)


@named("ap/pnp/pairs:same_epochs:s2", "the same, seed 2")
def _pnp_same2() -> float:
    return same_epochs(PNP_PAIRS, 2)


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
NUMBER = re.compile(r"[+\u2212-]?\d[\d,]*(?:\.\d+)?(?:e[+-]?\d+)?")


@dataclass(frozen=True)
class Quote:
    path: Path
    line: int
    text: str
    target: str
    name: str
    start: int  # offsets of the text in the file
    end: int


def quotes(path: Path) -> Iterator[Quote]:
    src = path.read_text(encoding="utf-8")
    for m in MARK.finditer(src):
        yield Quote(path, src.count("\n", 0, m.start()) + 1, m.group(1), m.group(2),
                    m.group(3), m.start(1), m.end(1))


def render(val: float | str, like: str) -> str:
    """``val`` written at the precision and in the style of the text ``like`` (its decimals or
    significant digits, thousands commas, a leading + on a signed figure, − or - for minus)."""
    if isinstance(val, str):
        return val
    body = like.lstrip("+\u2212-")
    if "e" in body:
        digits = len(body.split("e")[0].replace(".", "").lstrip("0"))
        mant, exp = f"{val:.{max(digits - 1, 0)}e}".split("e")
        out = f"{mant}e{int(exp):+03d}"
    else:
        places = len(body.split(".")[1]) if "." in body else 0
        out = f"{round(val, places) + 0.0:{',' if ',' in body else ''}.{places}f}"
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
    if q.target and not (q.path.parent / q.target.split("#")[0]).exists():
        return f"{where}: {q.name}: the link's target {q.target} does not exist"
    try:
        val = value(q.name)
    except KeyError as e:
        return f"{where}: {q.name}: {e.args[0] if e.args else e}"
    if isinstance(val, str):
        ok = q.text == val
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
