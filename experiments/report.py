"""Tables and figures of the paper's experiments, from the committed per-run CSVs alone.

    python experiments/report.py                       # every kind and profile present
    python experiments/report.py --results DIR
    python experiments/report.py --compare DIR_A DIR_B ...   # Welch tests between settings

Reads ``<results>/<ablation|benchmark>/<profile>/<task>/<setting>/s<seed>.csv`` and the
``run_info.json`` beside them (both written by ``experiments/ablation.py`` and
``experiments/benchmark.py``), never the run directories, and writes per ``<kind>/<profile>``:

- ``summary.md``: best-policy success (the max over epochs of ``test_success``, as the paper's
  Table 2 reports the best policy) and final success (mean of the last 3 epochs), each as mean ±
  sample std over seeds with a 95% t confidence interval; the wall clock of each sweep and its
  runs with the hardware it ran on; the hindsight-bias diagnostic (the ``bias_*`` columns, mean
  over the last 3 epochs and seeds). Benchmark tables carry the paper's Tables 2 and 3 beside.
- ``summary.csv``: the same numbers, one row per (task, setting).
- ``success_epochs.png``, ``success_env_steps.png``: test success against epochs and against
  env steps per run, median over seeds with the interquartile band (a long run's curve first a
  trailing mean over 1/40 of its epochs, :func:`smoothing_window`); one panel per task (the
  ablation's 7 settings or the benchmark's algorithms in each), as the paper's Figs. 5-9.

Deterministic: tasks and settings in a fixed order, fixed number formats, no dates; a second run
on the same files writes byte-identical tables (PNGs are written without a Software/date tag).
"""

from __future__ import annotations

import argparse
import csv
import io
import itertools
import json
import math
import statistics
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_learning import first_hit
from profiles import pair_label

from rdher_jax.runlog import write_text_atomic
from rdher_jax.tasks import PAPER_TASKS, SOLVE_GOALS, TASKS

HERE = Path(__file__).resolve().parent
KINDS = ("ablation", "benchmark", "moving", "beyond")
LAST = 3  # epochs averaged for "final" success and for the bias diagnostic
BIAS_COLS = ("bias_real", "bias_her", "bias_dher", "bias_unw_real", "bias_unw_her",
             "bias_unw_dher")


def paper_best(task: str, algo: str | None) -> int | None:
    """The paper's Table 2 (best-policy success, %, mean over 5 seeds) for ``task`` and ``algo``."""
    return TASKS[task].paper_table2.get(algo) if task in TASKS else None


def paper_time(task: str, algo: str | None) -> str:
    """The paper's Table 3 (wall clock of one run, one CPU core), or '-'."""
    return TASKS[task].paper_table3.get(algo, "-") if task in TASKS else "-"


def paper_pick(task: str) -> tuple[float, float] | None:
    """The (lambda_r, lambda_h) the paper picked for ``task`` from its ablation (section 5.3)."""
    return TASKS[task].paper_lambdas if task in PAPER_TASKS else None


@dataclass(frozen=True)
class Stat:
    n: int
    mean: float
    std: float  # sample std (ddof=1); nan for n < 2
    lo: float  # 95% t interval of the mean; nan for n < 2
    hi: float


def stat(xs: Sequence[float]) -> Stat:
    xs = [float(x) for x in xs if math.isfinite(float(x))]
    n = len(xs)
    if n == 0:
        return Stat(0, math.nan, math.nan, math.nan, math.nan)
    mean = statistics.fmean(xs)
    if n < 2:
        return Stat(1, mean, math.nan, math.nan, math.nan)
    from scipy import stats as sps

    sd = statistics.stdev(xs)
    half = float(sps.t.ppf(0.975, n - 1)) * sd / math.sqrt(n)
    return Stat(n, mean, sd, mean - half, mean + half)


# ------------------------------------------------------------------ reading

@dataclass
class SettingData:
    task: str
    name: str
    meta: dict[str, Any]
    runs: dict[int, list[dict[str, str]]]  # seed -> metrics rows

    @property
    def order(self) -> tuple[int, str]:
        return (int(self.meta.get("order", 99)), self.name)

    def column(self, col: str) -> dict[int, list[float]]:
        return {s: [_float(r.get(col, "")) for r in rows] for s, rows in self.runs.items()}


def _float(x: str) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _task_key(task: str) -> tuple[int, str]:
    return (PAPER_TASKS.index(task) if task in PAPER_TASKS else len(PAPER_TASKS), task)


def read_setting(sdir: Path) -> SettingData:
    """One setting's directory ``<kind>/<profile>/<task>/<setting>``: its ``run_info.json`` and
    the rows with a test success of each ``s<seed>.csv``."""
    meta = json.loads((sdir / "run_info.json").read_text(encoding="utf-8"))
    runs = {}
    for f in sdir.glob("s*.csv"):
        if not f.stem[1:].isdigit():
            continue
        with open(f, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("test_success", "") != ""]
        if rows:
            runs[int(f.stem[1:])] = rows
    return SettingData(sdir.parent.name, sdir.name, meta, dict(sorted(runs.items())))


def load(profile_dir: Path) -> list[SettingData]:
    """Every setting under ``<kind>/<profile>/``, tasks and settings in table order."""
    out = [read_setting(sdir)
           for task_dir in sorted(p for p in profile_dir.iterdir() if p.is_dir())
           for sdir in sorted(p for p in task_dir.iterdir() if p.is_dir())
           if (sdir / "run_info.json").is_file()]
    out.sort(key=lambda s: (_task_key(s.task), s.order))
    return out


# ------------------------------------------------------------------ numbers

def per_seed(s: SettingData) -> dict[str, dict[int, float]]:
    succ = s.column("test_success")
    return {
        "best": {k: max(v) for k, v in succ.items()},
        "final": {k: statistics.fmean(v[-LAST:]) for k, v in succ.items()},
        # The area under the success curve per epoch: learning speed, where best and final
        # both sit at the ceiling (FetchReach).
        "mean": {k: statistics.fmean(v) for k, v in succ.items()},
        # The best policy tested again on fresh episodes (profiles.best_policy_eval), where the
        # run has that test: the paper's "best-learned policy", without best-of-epochs luck.
        "policy": {k: float(ev["success"]) for k in succ
                   if (ev := s.meta.get("runs", {}).get(f"s{k}", {}).get("best_policy"))},
        # The same policy on many more episodes (--precise-episodes), where tested.
        "precise": {k: float(ev["success"]) for k in succ
                    if (ev := s.meta.get("runs", {}).get(f"s{k}", {})
                        .get("best_policy_precise"))},
    }


def policy_episodes(s: SettingData, key: str = "best_policy") -> int | None:
    """Episodes of the best-policy test ``key`` (``best_policy``, or ``best_policy_precise``;
    the same for every run of a setting), or None."""
    eps = {ev["episodes"] for r in s.meta.get("runs", {}).values() if (ev := r.get(key))}
    return eps.pop() if len(eps) == 1 else None


def bias(s: SettingData) -> dict[str, Stat]:
    """Each bias column over seeds: per seed the mean of its last LAST epochs (finite values only),
    then mean ± std over the seeds that have any."""
    out = {}
    for col in BIAS_COLS:
        per = [statistics.fmean(f) for v in s.column(col).values()
               if (f := [x for x in v[-LAST:] if math.isfinite(x)])]
        out[col] = stat(per)
    return out


def bias_cell(st: Stat) -> str:
    if not math.isfinite(st.mean):
        return "-"
    return f"{st.mean:.2f}" if not math.isfinite(st.std) else f"{st.mean:.2f} ± {st.std:.2f}"


def pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.1f}"


def pm(st: Stat) -> str:
    if st.n == 0:
        return "-"
    if st.n < 2:
        return f"{pct(st.mean)} (1 seed)"
    return f"{pct(st.mean)} ± {pct(st.std)}"


def ci(st: Stat) -> str:
    if st.n < 2:
        return "-"
    return f"[{pct(max(st.lo, 0.0))}, {pct(min(st.hi, 1.0))}]"


def _rate(x: float) -> float:
    """A per-run success figure as the t-tests see it: rounded to 1e-7. The figures are means
    of float32 test successes (0.1 is stored as 0.10000000149), so one rate reached by two
    summation orders differs by ~1e-9; unrounded, a paired test of two settings with the same
    finals on every seed reports a p of that noise instead of 'no variance'. Differences of
    means are taken from the figures as they are."""
    return round(float(x), 7)


def welch(xs: Sequence[float], ys: Sequence[float]) -> tuple[float, float]:
    """Mean of xs minus mean of ys, and the two-sided p of Welch's t-test (nan when it is not
    defined: fewer than 2 seeds on a side, or no variance on either)."""
    import warnings

    from scipy import stats as sps

    if not xs or not ys:
        return math.nan, math.nan
    diff = statistics.fmean(map(float, xs)) - statistics.fmean(map(float, ys))
    xs, ys = [_rate(x) for x in xs], [_rate(y) for y in ys]
    if len(xs) < 2 or len(ys) < 2 or (statistics.pstdev(xs) == 0 and statistics.pstdev(ys) == 0):
        return diff, math.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = float(sps.ttest_ind(xs, ys, equal_var=False).pvalue)
    return diff, p


def paired(xs: Mapping[int, float], ys: Mapping[int, float]) -> tuple[float, float, int]:
    """Over the seeds both hold: the mean of the per-seed differences xs - ys, the two-sided p
    of the paired t-test (nan under 2 common seeds or with no variance in the differences), and
    the number of common seeds. One seed gives the same test goals epoch by epoch whatever the
    algorithm, so a per-seed difference cancels the luck of the test set."""
    import warnings

    from scipy import stats as sps

    common = sorted(set(xs) & set(ys))
    if not common:
        return math.nan, math.nan, 0
    diff = statistics.fmean(float(xs[k]) - float(ys[k]) for k in common)
    x, y = [_rate(xs[k]) for k in common], [_rate(ys[k]) for k in common]
    if len(common) < 2 or statistics.pstdev([a - b for a, b in zip(x, y, strict=True)]) < 1e-9:
        return diff, math.nan, len(common)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = float(sps.ttest_rel(x, y).pvalue)
    return diff, p, len(common)


def paired_diffs(xs: Mapping[int, float], ys: Mapping[int, float]) -> Stat:
    """The per-seed differences xs - ys over the seeds both hold, on the rates as the t-tests
    see them (:func:`_rate`), as a :func:`stat`: its mean, std and 95% interval are those of
    :func:`paired`'s test."""
    return stat([_rate(xs[k]) - _rate(ys[k]) for k in sorted(set(xs) & set(ys))])


def seeds_for_power(diff: float, sd_a: float, sd_b: float | None, power: float = 0.8,
                    alpha: float = 0.05) -> float:
    """The fewest seeds per setting for a two-sided t-test at ``alpha`` to detect ``diff`` with
    ``power``, by the noncentral t: the two-sample test of two settings with sample stds ``sd_a``
    and ``sd_b`` at n seeds each (2n - 2 degrees of freedom, as statsmodels' TTestIndPower), or
    with ``sd_b`` None the paired test whose per-seed differences have std ``sd_a``."""
    from scipy import stats as sps

    for n in range(2, 10_000):
        if sd_b is None:
            se, df = sd_a / math.sqrt(n), n - 1
        else:
            se, df = math.sqrt((sd_a ** 2 + sd_b ** 2) / n), 2 * n - 2
        crit = float(sps.t.ppf(1 - alpha / 2, df))
        ncp = abs(diff) / se
        if float(sps.nct.sf(crit, df, ncp) + sps.nct.cdf(-crit, df, ncp)) >= power:
            return float(n)
    return math.inf


def near_significance(p: float, n: int, alpha: float = 0.05) -> bool:
    """Whether a paired difference over ``n`` seeds with two-sided p ``p`` is within one standard
    error of significance at ``alpha``: not significant, and its mean short of the threshold
    t(1 - alpha/2, n - 1) standard errors by at most one (|t| >= t_crit - 1). Table 2's rule
    raises a setting's seeds from 3 to 5 where this holds."""
    from scipy import stats as sps

    if n < 2 or not math.isfinite(p) or p < alpha:
        return False
    t = float(sps.t.isf(p / 2, n - 1))
    return t >= float(sps.t.ppf(1 - alpha / 2, n - 1)) - 1


def n_seeds(n: int) -> str:
    """'1 seed', '3 seeds'."""
    return f"{n} seed{'s' * (n != 1)}"


def vs_cell(diff: float, p: float) -> str:
    if not math.isfinite(diff):
        return "-"
    d = f"{round(diff * 100, 1) + 0.0:+.1f}"  # + 0.0: a tie prints +0.0, never -0.0
    return d if not math.isfinite(p) else f"{d} (p {p:.2g})"


def _her_of(s: SettingData, data: Sequence[SettingData]) -> SettingData | None:
    """The vanilla-HER setting of ``s``'s task in ``data`` (None for HER itself or none)."""
    return None if s.name == "her" else next(
        (r for r in data if r.task == s.task and r.name == "her" and r.runs), None)


def vs_her(s: SettingData, data: Sequence[SettingData]) -> dict[str, tuple[float, float]] | None:
    """``s`` against the vanilla-HER setting of the same task, per seed-level measure ('final',
    'mean'): (difference of means, Welch p). None for HER itself or where the task has no HER."""
    her = _her_of(s, data)
    if her is None:
        return None
    mine, ref = per_seed(s), per_seed(her)
    return {k: welch(list(mine[k].values()), list(ref[k].values())) for k in ("final", "mean")}


PAIRED_MEASURES = (("policy", "best policy retested"), ("final", "final"),
                   ("mean", "over all epochs"))


def vs_her_paired(s: SettingData, data: Sequence[SettingData]
                  ) -> dict[str, tuple[float, float, int, float]] | None:
    """``s`` against the vanilla-HER setting of its task paired by seed, per measure of
    :data:`PAIRED_MEASURES`: (mean per-seed difference, paired p, common seeds, seeds per
    setting a paired t-test at 5% needs to detect that difference with 80% power at the spread
    of the differences seen: nan where it cannot be said). None for HER itself or where the
    task has no HER."""
    her = _her_of(s, data)
    if her is None:
        return None
    mine, ref = per_seed(s), per_seed(her)
    out = {}
    for k, _ in PAIRED_MEASURES:
        diff, p, n = paired(mine[k], ref[k])
        st = paired_diffs(mine[k], ref[k])
        need = seeds_for_power(st.mean, st.std, None) \
            if n >= 2 and math.isfinite(st.std) and st.std > 0 and st.mean != 0 else math.nan
        out[k] = (diff, p, n, need)
    return out


def _paired_lines(data: Sequence[SettingData]) -> list[str]:
    """The 'Against HER, paired by seed' section (empty where no setting has a HER)."""
    rows = []
    # The retest's columns only where some run was retested.
    measures = [(k, h) for k, h in PAIRED_MEASURES
                if k != "policy" or any(policy_episodes(s) for s in data)]
    for s in data:
        vs = vs_her_paired(s, data)
        if vs is None:
            continue
        cells = []
        for k, _ in measures:
            diff, p, n, need = vs[k]
            cells += [vs_cell(diff, p) if n else "-",
                      "-" if not math.isfinite(need) else f"{need:.0f}"]
        near = [h for k, h in measures if near_significance(vs[k][1], vs[k][2])]
        rows.append([s.task, s.meta.get("label", s.name),
                     str(max(vs[k][2] for k, _ in measures)), *cells,
                     ", ".join(near) or "no"])
    if not rows:
        return []
    head = ["task", "setting", "seeds"]
    for _, h in measures:
        head += [f"{h}: vs HER (paired p)", "seeds for 80% power"]
    head.append("within one SE of 5%")
    return ["## Against HER, paired by seed", "",
            "Each setting minus HER on the same task over the seeds both hold (one seed gives "
            "the same test goals epoch by epoch whatever the setting, so a per-seed difference "
            "cancels the luck of the test set): the mean per-seed difference in points with the "
            "paired t-test's two-sided p, and the seeds per setting a paired t-test at 5% would "
            "need to detect a difference of that size with 80% power at the spread of the "
            "per-seed differences seen ('-' where it cannot be said: under 2 common seeds, no "
            "spread or no difference). 'Within one SE of 5%' names the measures whose "
            "difference is not significant but less than one standard error short of it "
            "(|t| at least the 5% critical t minus 1), where Table 2's rule asks for 5 seeds "
            "rather than 3.", "", *_md_table(head, rows), ""]


ALGO_NAMES = {"ddpg": "DDPG", "her": "HER", "cher": "CHER", "dher": "DHER", "rdher": "RDHER"}


def _share(s: SettingData) -> tuple[str, ...]:
    """The overrides that set ``s``'s share of DHER-combined rows (empty: the profile's)."""
    return tuple(x for x in s.meta.get("extra") or () if x.startswith("dher_fraction="))


def verdict(diffs: Stat) -> str:
    """A paper's claim 'A > B' against the per-seed differences A - B (their :func:`stat`):
    'holds' where the 95% interval of their mean lies above 0, 'reversed' where it lies below,
    'level on every seed' where every difference is 0, 'undecided' otherwise or under 2 seeds
    (the paired t-test at 5%, uncorrected). The same non-zero difference on every seed is
    'undecided' too: the t-test has no p there (:func:`paired`), so Holm could not pass it,
    and a verdict never reads stronger than its test."""
    if diffs.n < 2 or not (math.isfinite(diffs.lo) and math.isfinite(diffs.hi)):
        return "undecided"
    if diffs.std < 1e-9:
        return "level on every seed" if abs(diffs.mean) < 1e-9 else "undecided"
    return "holds" if diffs.lo > 0 else "reversed" if diffs.hi < 0 else "undecided"


def holm(ps: Sequence[float], alpha: float = 0.05) -> list[bool]:
    """Holm's step-down test over ``ps``: which reject at family-wise ``alpha`` (nan never)."""
    order = sorted((p, i) for i, p in enumerate(ps) if math.isfinite(p))
    out = [False] * len(ps)
    for rank, (p, i) in enumerate(order):
        if p > alpha / (len(order) - rank):
            break
        out[i] = True
    return out


def order_claims(task: str, ss: Sequence[SettingData]) -> list[dict[str, Any]]:
    """Every ordering the paper's Table 2 states for ``task`` ('A > B' where its A row is above
    its B row; ties state none), tested on ``ss``, the task's settings: one row per pair of
    settings of A and B (DHER and RDHER paired only at the same share), on each run's best
    policy retested (the paper's measure) where both have retests, else the best epoch. Row:
    claim, a and b (the settings), measure, diff (points), lo, hi, p, n, verdict, holm (whether
    Holm's correction over the task's rows keeps it) and family (how many rows have a p: the
    family Holm corrects over, which grows as a task's settings run)."""
    paper = TASKS[task].paper_table2 if task in TASKS else {}
    algos = sorted((a for a in paper if a in ALGO_NAMES), key=lambda a: -paper[a])
    rows: list[dict[str, Any]] = []
    for a, b in itertools.combinations(algos, 2):
        if paper[a] <= paper[b]:
            continue
        for sa in (s for s in ss if s.meta.get("algo") == a and s.runs):
            for sb in (s for s in ss if s.meta.get("algo") == b and s.runs):
                if {a, b} <= {"dher", "rdher"} and _share(sa) != _share(sb):
                    continue
                xa, xb = per_seed(sa), per_seed(sb)
                measure = "policy" if set(xa["policy"]) & set(xb["policy"]) else "best"
                diff, p, n = paired(xa[measure], xb[measure])
                st = paired_diffs(xa[measure], xb[measure])
                rows.append({"claim": f"{ALGO_NAMES[a]} {paper[a]} > {ALGO_NAMES[b]} {paper[b]}",
                             "a": sa, "b": sb, "measure": measure, "diff": diff,
                             "lo": st.lo, "hi": st.hi, "p": p, "n": n,
                             "verdict": verdict(st)})
    family = sum(math.isfinite(r["p"]) for r in rows)
    for r, ok in zip(rows, holm([r["p"] for r in rows]), strict=True):
        r["holm"], r["family"] = ok, family
    return rows


def _order_lines(data: Sequence[SettingData]) -> list[str]:
    """The 'The paper's Table 2 order, claim by claim' section (benchmarks only)."""
    rows = []
    for task, ss in _by_task(data).items():
        for r in order_claims(task, ss):
            iv = ("-" if not math.isfinite(r["lo"]) else
                  f"[{100 * r['lo'] + 0.0:+.1f}, {100 * r['hi'] + 0.0:+.1f}]")
            rows.append([task, r["claim"], f"{r['a'].meta.get('label', r['a'].name)} − "
                         f"{r['b'].meta.get('label', r['b'].name)}",
                         "retest" if r["measure"] == "policy" else "best epoch",
                         vs_cell(r["diff"], math.nan), iv,
                         "-" if not math.isfinite(r["p"]) else f"{r['p']:.2g}", str(r["n"]),
                         f"{r['verdict']} at {n_seeds(r['n'])}",
                         f"{'yes' if r['holm'] else 'no'} (of {r['family']})"
                         if r["verdict"] in ("holds", "reversed") else "-"])
    if not rows:
        return []
    return ["## The paper's Table 2 order, claim by claim", "",
            "Each ordering the paper's Table 2 states for a task ('A > B': its A row above its "
            "B row, with its figures), tested here on the same seeds of both settings: the "
            "mean per-seed difference A − B in points of each run's best policy retested (the "
            "paper's measure; the best epoch where a setting has no retest), its 95% t "
            "interval and the paired t-test's two-sided p. Verdict: 'holds' where the interval "
            "lies above 0, 'reversed' where it lies below, 'level' where every seed's "
            "difference is 0, 'undecided' otherwise (a paired t-test at 5%, uncorrected). "
            "'After Holm' says whether a 'holds' or 'reversed' survives Holm's correction "
            "over the task's rows that have a p (family-wise 5%; their number in brackets: "
            "the family grows as a task's settings run, and a 'yes' over a few rows can "
            "become a 'no' over all of them). DHER and RDHER are compared at the same "
            "share of combined rows; the paper ran the authors'.", "",
            *_md_table(["task", "paper's claim", "settings (A − B)", "measure",
                        "A − B, points", "95% interval", "p", "seeds", "verdict",
                        "after Holm"], rows), ""]


def window_seeds(s: SettingData) -> list[tuple[str, dict[int, float]]]:
    """Per env-step window (the fractions :data:`WINDOWS` of the longest run's steps): each
    seed's mean test success over the epochs that end in the window (seeds with such epochs)."""
    succ, steps = s.column("test_success"), s.column("env_steps")
    top = max((max(v) for v in steps.values() if v), default=0.0)
    out, lo = [], 0.0
    for frac in WINDOWS:
        hi = frac * top
        per = {k: statistics.fmean(x for x, n in zip(succ[k], steps[k], strict=True)
                                   if lo < n <= hi)
               for k in succ if any(lo < n <= hi for n in steps[k])}
        out.append((f"{_k(lo)}-{_k(hi)} steps", per))
        lo = hi
    return out


def windows(s: SettingData) -> list[tuple[str, Stat]]:
    """Per env-step window: the mean over seeds of :func:`window_seeds`."""
    return [(label, stat(list(per.values()))) for label, per in window_seeds(s)]


def _k(n: float) -> str:
    return f"{n / 1000:.3g}k" if n >= 1000 else f"{n:.0f}"


def hms(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "-"
    s = int(round(seconds))
    return f"{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def lam(s: SettingData) -> str:
    lr, lh = s.meta.get("lambda_r"), s.meta.get("lambda_h")
    return "-" if lr is None else f"{lr:g} / {lh:g}"


def pair_text(s: SettingData) -> str:
    """The (λ_r, λ_h) pair as a setting's label writes it, e.g. "(4, 0.5)"."""
    lr, lh = s.meta.get("lambda_r"), s.meta.get("lambda_h")
    return "" if lr is None else pair_label(lr, lh)  # as profiles.named_sweeps


def legend_label(kind: str, s: SettingData, with_seeds: bool) -> str:
    """A curve's legend entry: the setting's label, its λ pair on a benchmark's weighted
    algorithm unless the label names it already, and its seeds where ``with_seeds`` (the
    task's settings have unequal seeds)."""
    label = s.meta.get("label", s.name)
    if kind == "benchmark" and s.meta.get("algo") in ("rdher", "archer") and \
            pair_text(s) not in label:
        label += f" (λ {lam(s)})"
    return label + (f", {n_seeds(len(s.runs))}" if with_seeds else "")


def budget_epochs(s: SettingData) -> int | None:
    """The epochs of the setting's budget (None where its run_info names none)."""
    want = s.meta.get("budget", {}).get("settings", {}).get("epochs")
    return None if want is None else int(want)


def under_way(s: SettingData) -> set[int]:
    """The seeds whose runs have not reached the budget's epochs and did not stop early (a
    diverged run is finished short of its budget): collected while still running."""
    want = budget_epochs(s)
    if want is None:
        return set()
    status = {k: s.meta.get("runs", {}).get(f"s{k}", {}).get("status", "ok") for k in s.runs}
    return {k for k, v in s.runs.items() if len(v) < want and status[k] == "ok"}


def unfinished(s: SettingData) -> int:
    """How many of the setting's runs have not reached its budget's epochs yet."""
    return len(under_way(s))


def epochs_cell(s: SettingData) -> str:
    done = sorted(len(v) for v in s.runs.values())
    if not done:
        return "0"
    want = budget_epochs(s)
    cell = str(done[0]) if done[0] == done[-1] else f"{done[0]}-{done[-1]}"
    if want is not None and done[0] < want:
        cell += f" of {want} (unfinished)"
    return cell


def env_steps(s: SettingData) -> str:
    steps = [int(_float(v[-1]["env_steps"])) for v in s.runs.values()]
    return f"{max(steps):,}" if steps else "0"


def status(s: SettingData) -> str:
    bad = sorted(k for k, r in s.meta.get("runs", {}).items() if r.get("status", "ok") != "ok")
    return "ok" if not bad else "diverged: " + ", ".join(bad)


def sweep_parts(meta: Mapping[str, Any]) -> list[tuple[float, dict[str, Any], list[int]]]:
    """(wall clock in s, hardware, seeds) of each piece a setting ran in (``pieces``: its seeds
    run apart, perhaps on other machines), or of its one sweep."""
    pieces = meta.get("pieces") or [meta]
    return [(float(p.get("wall_clock_s") or 0.0), p.get("hardware") or meta.get("hardware") or {},
             [int(k) for k in p.get("seeds") or []]) for p in pieces]


def cores_used(h: Mapping[str, Any]) -> int:
    """The CPU cores a sweep could run on (``cpu_affinity``); one where its record predates
    that field: those sweeps ran pinned to one core (``taskset -c N``)."""
    return int(h.get("cpu_affinity") or 1)


def _hardware_one(h: Mapping[str, Any]) -> str:
    devices = h.get("devices") or []
    dev = f"{len(devices)} device{'s' if len(devices) != 1 else ''}"
    if devices and h.get("jax_backend") != "cpu":
        dev += f" ({devices[0]})"
    cores = (f"{h['cpu_affinity']} of {h.get('cpu_count')} CPU cores"
             if h.get("cpu_affinity") else f"{h.get('cpu_count')} CPU cores")
    return (f"{h.get('processor') or '?'} ({h.get('machine') or '?'}), {cores}; "
            f"JAX {h.get('jax_backend')}, {dev}; physics {h.get('backend')}")


def hardware(meta: dict[str, Any]) -> str:
    """Where a setting ran; a setting whose pieces ran on different machines (or on different
    numbers of cores) names each with its seeds."""
    seeds: dict[str, list[int]] = {}
    for _, h, ks in sweep_parts(meta):
        seeds.setdefault(_hardware_one(h), []).extend(ks)
    if len(seeds) == 1:
        return next(iter(seeds))
    return "; ".join(f"{d} (seed{'s' if len(ks) != 1 else ''} {', '.join(map(str, sorted(ks)))})"
                     for d, ks in seeds.items())


def _md_table(head: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


# ------------------------------------------------------------------ markdown and csv

TITLES = {"ablation": "Ablation of the reward weights (paper section 5.2, Figs. 4-8)",
          "benchmark": "Benchmark of the algorithms (paper section 5.3, Fig. 9, Tables 2-3)",
          "moving": "HER against DHER on the moving-goal tasks (experiments/moving_goals.py)",
          "beyond": "RDHER settings against HER beyond the paper (experiments/beyond.py)"}
WINDOWS = (0.4, 0.8, 1.0)  # moving: mean test success over these fractions of the env steps


def _budget_lines(data: Sequence[SettingData]) -> list[str]:
    lines = []
    seen: dict[str, dict[str, tuple[dict[str, Any], dict[str, int]]]] = {}
    for s in data:
        b = s.meta.get("budget", {})
        # The profile's description is said once, in the intro, and the seeds are counted from
        # the runs collected (a setting run in pieces is collected with its seeds so far): a
        # reworded description or another seed count is no new budget.
        key = json.dumps({k: v for k, v in b.items() if k not in ("profile_doc", "seeds")},
                         sort_keys=True)
        seen.setdefault(s.task, {}).setdefault(key, (b, {}))[1][s.name] = len(s.runs)
    for task, budgets in sorted(seen.items(), key=lambda kv: _task_key(kv[0])):
        for b, counts in budgets.values():
            settings = " ".join(f"{k}={v}" for k, v in b.get("settings", {}).items())
            mark = " **(placeholder budget)**" if b.get("placeholder") else ""
            lines.append(f"- {task}: {_seed_counts(counts)}, `{settings}`{mark} "
                         f"({b.get('note', '')})")
    return lines


def _seed_counts(counts: Mapping[str, int]) -> str:
    """'5 seeds' where every setting has 5; else the usual count and the settings that differ."""
    usual = max(sorted(set(counts.values())), key=list(counts.values()).count)
    text = f"{usual} seed{'s' if usual != 1 else ''}"
    odd = [f"{name} {n}" for name, n in counts.items() if n != usual]
    return text + (f" ({', '.join(odd)})" if odd else "")


def _intro(kind: str, profile: str, data: Sequence[SettingData]) -> list[str]:
    # The description most of the sweeps were written with (it was reworded over time).
    docs = [s.meta.get("budget", {}).get("profile_doc") or "" for s in data]
    doc = max(sorted(set(docs)), key=docs.count) if docs else ""
    commands = sorted({s.meta.get("command", "") for s in data})
    out = [f"# {TITLES[kind]}: profile `{profile}`", "",
           "Written by `python experiments/report.py` from the per-run CSVs and `run_info.json` "
           "files in the directories beside this file; rerun it rather than editing.", "",
           f"Profile `{profile}`: {doc}. Budget per task (the settings all its sweeps share; "
           "other keys at the trainer's defaults, which are the paper's Table 1):", "",
           *_budget_lines(data), "",
           "Commands:", "", *[f"- `{c}`" for c in commands], ""]
    if kind in ("moving", "beyond"):
        out += ["Each setting is one vmapped sweep of its seeds; the keys a setting adds to the "
                "budget's are in its `run_info.json` (`extra`).", ""]
    if kind == "ablation":
        out += ["Vanilla HER is `algo=her`, a sweep of its own: under `algo=rdher` the pair "
                "(1, 1) is DHER (combined rows mixed with 'future' rows), which the paper lists "
                "as a different method from HER (Table 2). The six weighted settings are one "
                "vmapped `algo=rdher` sweep. DHER (= RDHER at (1, 1)) is in the benchmark.", ""]
    out += [f"Best = max over epochs of a run's test success (each epoch's mean over its "
            "deterministic test episodes; the paper's Table 2 evaluates the best policy, so "
            "ours is the more optimistic of the two for few test episodes). Final = mean of a "
            f"run's last {LAST} epochs. Over all epochs = mean of a run's test success over every "
            "epoch (the area under its curve: learning speed, where best and final sit at the "
            "ceiling). 'vs HER': this setting's mean over seeds minus vanilla HER's on the same "
            "task, in points, with the two-sided p of Welch's t-test over seeds. Over seeds: "
            "mean ± sample std, and the 95% confidence interval of the mean, "
            "mean ± t(0.975, n−1)·std/√n, clipped to [0, 100]. In %.", ""]
    return out


def _by_task(data: Sequence[SettingData]) -> dict[str, list[SettingData]]:
    out: dict[str, list[SettingData]] = {}
    for s in data:
        out.setdefault(s.task, []).append(s)
    return out


def _wall_rows(data: Sequence[SettingData], paper: bool) -> list[list[str]]:
    rows, seen = [], set()
    for s in data:
        sw = s.meta.get("sweep", {})
        key = (s.task, sw.get("name"))
        if key in seen:  # the settings of one sweep share its program and wall clock
            continue
        seen.add(key)
        names = [t.name for t in data if t.task == s.task
                 and t.meta.get("sweep", {}).get("name") == sw.get("name")]
        row = [s.task, f"{sw.get('name')} ({', '.join(names)})" if len(names) > 1 else s.name,
               str(sw.get("runs")), hms(s.meta.get("wall_clock_s")),
               hms(s.meta.get("wall_clock_per_run_s")), hardware(s.meta)]
        if paper:
            row.append(paper_time(s.task, s.meta.get("algo")))
        rows.append(row)
    return rows


def _goal_lines(data: Sequence[SettingData]) -> list[str]:
    """Per seed of each setting: its retest against the task's goal, and the env steps and
    minutes (training clock) to the first trailing mean of 3 test epochs at the threshold."""
    out = ["## Against the goal", "",
           "The goal per task (`rdher_jax/tasks.py`, `SOLVE_GOALS`): the best policy retested on "
           "fresh episodes, mean over seeds, at or above the goal within the task's budget. Per "
           "seed, the first epoch whose trailing mean of 3 test evaluations reaches the "
           "threshold: env steps and minutes of the training clock ('-': never).", ""]
    rows, verdicts = [], []
    precise = any(per_seed(s)["precise"] for s in data)
    for s in data:
        goal, threshold = SOLVE_GOALS.get(s.task, (math.nan, math.nan))
        ps = per_seed(s)
        policy, more = ps["policy"], ps["precise"]
        st = stat(list(policy.values()))
        # Against the goal as the rates are (k of 100 episodes), not as float32 stores them:
        # 93 of 100 is kept as 0.9299999, which would put a mean of exactly 0.97 a hair under.
        at_goal = round(statistics.fmean(_rate(x) for x in policy.values()), 7) >= goal \
            if policy else False
        verdict = "-" if st.n == 0 or not math.isfinite(goal) else \
            ("met" if at_goal else "missed") + f" at {st.n} of {len(s.runs)} seeds"
        n = policy_episodes(s, "best_policy_precise")
        verdicts.append([s.task, s.meta.get("label", s.name), pct(goal), pm(st), verdict,
                         *([f"{pm(stat(list(more.values())))}, {n or '-'} episodes"
                            if more else "-"] if precise else [])])
        for seed, runs in s.runs.items():
            hit = (first_hit(runs, threshold, 3) or {}).get("window")
            rows.append([s.task, s.meta.get("label", s.name), str(seed), pct(goal),
                         pct(policy[seed]) if seed in policy else "-",
                         *([pct(more[seed]) if seed in more else "-"] if precise else []),
                         pct(threshold), f"{hit['env_steps']:,}" if hit else "-",
                         f"{hit['wall_s'] / 60:.1f}" if hit else "-"])
    head = ["task", "setting", "seed", "goal", "retest",
            *(["retest, more episodes"] if precise else []), "threshold (mean of 3)",
            "env steps", "minutes"]
    per_setting = ["Per setting: the retest's mean ± std over the seeds retested so far, against "
                   "the goal ('met' / 'missed' at n of the setting's seeds).", ""]
    if precise:
        out += ["'Retest, more episodes': the same policy tested again on more episodes of a "
                "seed stream of their own (`--precise-episodes`, `profiles.PRECISE_SEED`). The "
                "goal is read on the 100-episode retest, whose binomial standard error is about "
                "2 points near 95% per seed; the longer test tells a seed that plateaus below "
                "the goal from one whose retest was unlucky.", ""]
    return [*out, *_md_table(head, rows), "", *per_setting,
            *_md_table(["task", "setting", "goal", "retest", "verdict",
                        *(["retest, more episodes"] if precise else [])],
                       verdicts), ""]


def summary_markdown(kind: str, profile: str, data: Sequence[SettingData]) -> str:
    out = _intro(kind, profile, data)
    tasks = _by_task(data)
    stats = {(s.task, s.name): {k: stat(list(v.values())) for k, v in per_seed(s).items()}
             for s in data}
    bench = kind == "benchmark"

    out += ["## Best-policy test success (%)", ""]
    if bench:
        algos = sorted({s.name for s in data}, key=lambda a: min(s.order for s in data
                                                                 if s.name == a))
        out.append("Ours: mean over seeds; in parentheses the paper's Table 2.")
        out.append("")
        def table2(measure: str) -> list[str]:
            rows = []
            for task, ss in tasks.items():
                have = {s.name: s for s in ss}
                cells = []
                for a in algos:
                    st = stats[(task, a)][measure] if a in have else None
                    mine = pct(st.mean) if st is not None and st.n else "-"
                    # the paper's row of the setting's algorithm (DHER at either share)
                    ref = paper_best(task, have[a].meta.get("algo", a) if a in have else a)
                    mine += f" ({ref})" if ref is not None else ""
                    # A mean over runs still under way is not the cell's result: say so.
                    late = unfinished(have[a]) if a in have and measure != "policy" else 0
                    cells.append(mine + (f", {late} of {len(have[a].runs)} runs unfinished"
                                         if late and mine != "-" else ""))
                rows.append([task, *cells])
            return _md_table(["task", *[data_label(a, data) for a in algos]], rows)

        out += table2("best")
        if any(policy_episodes(s) for s in data):
            out += ["", "The same with each run's best policy retested on new episodes (the "
                    "paper's 'best-learned policy' without the luck of the best of many "
                    "10-episode tests; '-' where no run of the cell is retested yet):", "",
                    *table2("policy")]
    else:
        names = []
        for s in data:
            if s.name not in names:
                names.append(s.name)
        rows = []
        for n in names:
            first = next(s for s in data if s.name == n)
            cells = [pct(stats[(t, n)]["best"].mean) if (t, n) in stats else "-" for t in tasks]
            rows.append([first.meta.get("label", n), lam(first), *cells])
        out.append("Mean over seeds.")
        out.append("")
        out += _md_table(["setting", "λ_r / λ_h", *tasks], rows)
    out.append("")

    if profile == "solve":
        out += _goal_lines(data)
    out += ["## Per task: best and final success (%)", ""]
    tested = any(policy_episodes(s) for s in data)
    if tested:
        out += ["Best policy retested: each finished run's best-policy checkpoint (its best "
                "epoch by the 10-episode test during training) tested again on fresh episodes, "
                "seeded apart from every training run (`experiments/profiles.py`, "
                "`best_policy_eval`). Its gap to 'best' is the luck of a best of many "
                "10-episode tests.", ""]
    head = ["task", "setting", "λ_r / λ_h", "seeds", "epochs", "env steps per run",
            "best: mean ± std", "best: 95% CI"]
    head += ["best policy retested: mean ± std (episodes)"] if tested else []
    head += ["final: mean ± std", "final: 95% CI",
             "over all epochs: mean ± std", "vs HER: final (Welch p)",
             "vs HER: over all epochs (Welch p)"]
    head += ["paper, Table 2"] if bench else ["paper's pick"]
    head.append("status")
    rows = []
    for s in data:
        st = stats[(s.task, s.name)]
        row = [s.task, s.meta.get("label", s.name), lam(s), str(len(s.runs)), epochs_cell(s),
               env_steps(s), pm(st["best"]), ci(st["best"])]
        if tested:
            n = policy_episodes(s)
            row.append("-" if not n else
                       f"{pm(st['policy'])} ({n}; {n_seeds(len(per_seed(s)['policy']))})")
        row += [pm(st["final"]), ci(st["final"]), pm(st["mean"])]
        vs = vs_her(s, data)
        row += ["-", "-"] if vs is None else [vs_cell(*vs["final"]), vs_cell(*vs["mean"])]
        if bench:
            ref = paper_best(s.task, s.meta.get("algo"))
            row.append("-" if ref is None else str(ref))
        else:
            pick = paper_pick(s.task)
            row.append("yes" if s.meta.get("algo") == "rdher" and pick is not None
                       and (s.meta.get("lambda_r"), s.meta.get("lambda_h")) == pick else "")
        row.append(status(s))
        rows.append(row)
    out += _md_table(head, rows)
    out.append("")

    out += _paired_lines(data)
    if bench:
        out += _order_lines(data)

    if kind in ("moving", "beyond"):
        out += ["## Over the budget: mean test success per env-step window (%)", "",
                "Per seed the mean test success over the epochs that end in the window, then "
                "mean ± std over seeds. Combined rows: the share of each batch that DHER "
                f"combined, per seed the mean over its last {LAST} epochs (the cap is "
                "dher_fraction·(1 − success rate of the last 100 episodes)).", ""]
        # One table per task: the windows are fractions of each task's own budget.
        for ss in tasks.values():
            head, rows = None, []
            for s in ss:
                ws = windows(s)
                head = head or ["task", "setting", "seeds", *[w for w, _ in ws], "best",
                                "final", "combined rows"]
                share = [statistics.fmean(v[-LAST:]) for v in s.column("frac_dher").values()
                         if v and all(math.isfinite(x) for x in v[-LAST:])]
                rows.append([s.task, s.meta.get("label", s.name), str(len(s.runs)),
                             *[pm(st) for _, st in ws], pm(stats[(s.task, s.name)]["best"]),
                             pm(stats[(s.task, s.name)]["final"]),
                             "-" if s.meta.get("algo") not in ("dher", "rdher")
                             else pm(stat(share))])
            out += _md_table(head or [], rows)
            out.append("")

    out += ["## Wall clock", "",
            "Per sweep: its runs are one vmapped program and share its wall clock (from the "
            "sweep's start, first compilation included, process start and env build not; "
            "summed over resumes). Per run = sweep / runs: on a CPU, N vmapped runs cost about N "
            "single runs (experiments/results/bench_sweep.md), so it approximates one run's "
            "time; on a GPU the runs share the device and it is a throughput, not one run's "
            "time. HH:MM:SS."
            + (" The paper's Table 3 is one run at the paper's budget on one CPU core: compare "
               "with it at the paper profile only." if bench else ""), ""]
    head = ["task", "sweep (settings)", "runs", "sweep wall clock", "per run", "hardware"]
    head += ["paper, Table 3 (one run)"] if bench else []
    out += _md_table(head, _wall_rows(data, bench))
    out.append("")

    out += ["## Hindsight-bias diagnostic", "",
            f"Per seed the mean over its last {LAST} epochs, then mean ± std over seeds, of "
            "Q(s, a, g) minus the discounted return the row's goal received in its stored "
            "episode, per sample source (real, "
            "HER-relabelled, DHER-combined): weighted as the critic was trained (Q − λ·G) and "
            "unweighted (Q − G); '-' where a source had no rows (docs/algorithms.md, "
            "'Hindsight-bias diagnostic').", ""]
    head = ["task", "setting", "λ_r / λ_h", "real", "HER", "DHER", "real, unw.", "HER, unw.",
            "DHER, unw."]
    rows = []
    for s in data:
        b = bias(s)
        rows.append([s.task, s.meta.get("label", s.name), lam(s),
                     *[bias_cell(b[c]) for c in BIAS_COLS]])
    out += _md_table(head, rows)
    out += ["", "## Figures", "",
            "Test success, median over seeds with the interquartile band. Where a task's "
            f"runs have {2 * SMOOTH_EPOCHS} epochs or more, each seed's curve is first a "
            f"trailing mean of its last epochs / {SMOOTH_EPOCHS} tests (the panel's title "
            "says how many).", "",
            "![test success against epochs](success_epochs.png)", "",
            "![test success against env steps](success_env_steps.png)", ""]
    return "\n".join(out)


def data_label(name: str, data: Sequence[SettingData]) -> str:
    s = next(s for s in data if s.name == name)
    return str(s.meta.get("label", name))


CSV_FIELDS = ("task", "setting", "label", "algo", "lambda_r", "lambda_h", "seeds",
              "epochs_min", "epochs_max", "env_steps", "best_mean", "best_std", "best_ci_lo",
              "best_ci_hi", "best_policy_mean", "best_policy_std", "best_policy_seeds",
              "best_policy_episodes", "precise_mean", "precise_std", "precise_seeds",
              "precise_episodes", "final_mean", "final_std", "final_ci_lo", "final_ci_hi",
              "auc_mean", "auc_std", "final_vs_her", "final_vs_her_p", "auc_vs_her",
              "auc_vs_her_p", "paper_best", "sweep", "sweep_runs", "wall_clock_s",
              "wall_clock_per_run_s",
              *BIAS_COLS)


def _c(x: Any) -> str:
    if x is None:
        return ""
    if isinstance(x, float):
        return "nan" if not math.isfinite(x) else f"{x:.6f}"
    return str(x)


def summary_csv(kind: str, data: Sequence[SettingData]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_FIELDS)
    for s in data:
        ps = per_seed(s)
        b, f = stat(list(ps["best"].values())), stat(list(ps["final"].values()))
        pol = stat(list(ps["policy"].values()))
        more = stat(list(ps["precise"].values()))
        a = stat(list(ps["mean"].values()))
        against = vs_her(s, data)
        vs = [math.nan] * 4 if against is None else [*against["final"], *against["mean"]]
        done = [len(v) for v in s.runs.values()] or [0]
        steps = max((int(_float(v[-1]["env_steps"])) for v in s.runs.values()), default=0)
        paper = paper_best(s.task, s.meta.get("algo")) if kind == "benchmark" else None
        sw = s.meta.get("sweep", {})
        bi = bias(s)
        w.writerow([_c(x) for x in (
            s.task, s.name, s.meta.get("label"), s.meta.get("algo"),
            s.meta.get("lambda_r"), s.meta.get("lambda_h"), len(s.runs), min(done), max(done),
            steps, b.mean, b.std, b.lo, b.hi, pol.mean, pol.std, len(ps["policy"]),
            policy_episodes(s), more.mean, more.std, len(ps["precise"]),
            policy_episodes(s, "best_policy_precise"), f.mean, f.std, f.lo, f.hi, a.mean,
            a.std, *vs,
            None if paper is None else paper / 100, sw.get("name"), sw.get("runs"),
            s.meta.get("wall_clock_s"), s.meta.get("wall_clock_per_run_s"),
            *[bi[c].mean for c in BIAS_COLS])])
    return buf.getvalue()


# ------------------------------------------------------------------ figures

SMOOTH_EPOCHS = 40  # a long run's curve: a trailing mean over 1/40 of its epochs


def smoothing_window(n_epochs: int) -> int:
    """The test epochs each seed's curve averages over in a figure: ``n_epochs // 40``, at
    least 1 (none under 80 epochs: the paper's 50-epoch runs plot every test as it was).

    A test epoch is 10 episodes, so one point's binomial noise is up to 16 points; on a
    200-epoch run a trailing mean of 5 (50 episodes) shows the learning curve, not the noise.
    """
    return max(1, n_epochs // SMOOTH_EPOCHS)


def trailing_mean(y: Sequence[float], window: int) -> list[float]:
    """Mean of each value and the ``window - 1`` before it (fewer at the start)."""
    out, total = [], 0.0
    for i, v in enumerate(y):
        total += v
        if i >= window:
            total -= y[i - window]
        out.append(total / min(i + 1, window))
    return out


def _curve(s: SettingData, x_col: str, window: int = 1
           ) -> tuple[list[float], list[float], list[float], list[float]]:
    """x, median, 25th and 75th percentile over the seeds of test success per epoch, each
    seed's curve first a trailing mean over ``window`` epochs (:func:`trailing_mean`)."""
    import numpy as np

    runs = [(v, trailing_mean([_float(r["test_success"]) for r in v], window))
            for v in s.runs.values()]
    n = max((len(v) for v, _ in runs), default=0)
    xs, med, q1, q3 = [], [], [], []
    for i in range(n):
        y = np.array([ys[i] for v, ys in runs if len(v) > i])
        x = float(np.median([_float(v[i][x_col]) for v, _ in runs if len(v) > i]))
        xs.append(x)
        med.append(float(np.median(y)))
        q1.append(float(np.percentile(y, 25)))
        q3.append(float(np.percentile(y, 75)))
    return xs, med, q1, q3


def figure(kind: str, profile: str, data: Sequence[SettingData], x_col: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import EngFormatter

    tasks = list(_by_task(data))
    ncols = min(len(tasks), 2)
    nrows = math.ceil(len(tasks) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.6 * ncols, 4.0 * nrows), squeeze=False)
    cmap = plt.get_cmap("tab10")
    for ax, task in zip(axes.flat, tasks, strict=False):
        marked = False
        counts = {len(s.runs) for s in data if s.task == task and s.runs}
        window = smoothing_window(max((len(v) for s in data if s.task == task
                                       for v in s.runs.values()), default=0))
        for s in (s for s in data if s.task == task):
            x, med, q1, q3 = _curve(s, x_col, window)
            if not x:
                continue
            order = int(s.meta.get("order", 9))
            color = "black" if kind == "ablation" and s.name == "her" else cmap(order % 10)
            label = legend_label(kind, s, len(counts) > 1)
            ax.plot(x, med, color=color, lw=1.6, marker="o" if len(x) <= 60 else None, ms=2.5,
                    label=label,
                    ls="--" if s.name == "her" and kind == "ablation" else "-")
            ax.fill_between(x, q1, q3, color=color, alpha=0.15, lw=0)
            paper = paper_best(task, s.meta.get("algo")) if kind == "benchmark" else None
            if paper is not None:  # the paper's Table 2 (its best policy), at the curve's end
                # Above the legend (zorder 5): no legend placement may hide the paper's value.
                ax.plot([x[-1]], [paper / 100], color=color, marker="*", ms=10, ls="none",
                        mec="black", mew=0.5, clip_on=False, zorder=6)
                marked = True
        if kind == "benchmark" and marked:
            ax.plot([], [], color="grey", marker="*", ms=10, ls="none", mec="black", mew=0.5,
                    label="paper, Table 2 (best policy)")
        ax.set_title(task if window == 1 else f"{task} (trailing mean of {window} tests)")
        ax.set_xlabel("epoch" if x_col == "epoch" else "env steps per run")
        if x_col != "epoch":  # 500k, 1M, 2M on every panel, no shared 1e6 offset on some
            ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        late = sum(unfinished(s) for s in data if s.task == task)
        ax.set_ylabel(f"test success (median, IQR; "
                      f"{n_seeds(min(counts)) if len(counts) == 1 else 'over seeds'}"
                      f"{f', {late} unfinished' if late else ''})")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")  # where it covers the fewest curve and star points
    for ax in list(axes.flat)[len(tasks):]:
        ax.set_visible(False)
    fig.suptitle(f"{TITLES[kind].split(' (')[0]}, profile {profile}")
    fig.tight_layout()
    # No Software tag and no dates: the file depends on the data and matplotlib's version only.
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


# ------------------------------------------------------------------ driver

MEASURES = (("best", "best 10-episode epoch"), ("policy", "best policy retested"),
            ("final", "final"), ("mean", "over all epochs"))


def load_setting(path: Path) -> SettingData:
    """:func:`read_setting`, with a clear error for a directory that is not a setting's.

    Raises:
        ValueError: ``path`` holds no ``run_info.json`` or no per-run CSVs with test success.
    """
    path = Path(path)
    if not (path / "run_info.json").is_file():
        raise ValueError(f"{path} is not a setting's results directory (no run_info.json)")
    found = read_setting(path)
    if not found.runs:
        raise ValueError(f"{path} holds no per-run CSVs with test success (s<seed>.csv)")
    return found


def compare_markdown(paths: Sequence[Path]) -> str:
    """Every setting of ``paths`` against every other: per measure the difference of the means
    over seeds and the two-sided p of Welch's test, as RESULTS.md quotes them between settings
    that are not HER (which the summaries' 'vs HER' columns cover); then the same pairs paired
    by seed (:func:`paired`). In %."""
    sets = [load_setting(p) for p in paths]
    labels = ["/".join(Path(p).resolve().parts[-4:]) for p in paths]  # kind/profile/task/setting
    seeds = [per_seed(s) for s in sets]
    out = ["| setting | seeds | " + " | ".join(f"{h}: mean ± std" for _, h in MEASURES) + " |",
           "|---|---|" + "---|" * len(MEASURES)]
    for label, s, ps in zip(labels, sets, seeds, strict=True):
        cells = [pm(stat(list(ps[k].values()))) for k, _ in MEASURES]
        out.append(f"| {label} | {len(s.runs)} | " + " | ".join(cells) + " |")
    out += ["", "| A − B | " + " | ".join(h for _, h in MEASURES) + " |",
            "|---|" + "---|" * len(MEASURES)]
    for i, j in itertools.combinations(range(len(sets)), 2):
        cells = [vs_cell(*welch(list(seeds[i][k].values()), list(seeds[j][k].values())))
                 for k, _ in MEASURES]
        out.append(f"| {labels[i]} − {labels[j]} | " + " | ".join(cells) + " |")
    out += ["", "Paired by seed (over the seeds both hold; one seed gives the same test goals "
            "whatever the setting): mean of the per-seed differences (paired t-test p).", "",
            "| A − B | seeds | " + " | ".join(h for _, h in MEASURES) + " |",
            "|---|---|" + "---|" * len(MEASURES)]
    for i, j in itertools.combinations(range(len(sets)), 2):
        res = [paired(seeds[i][k], seeds[j][k]) for k, _ in MEASURES]
        n = max(r[2] for r in res)
        out.append(f"| {labels[i]} − {labels[j]} | {n} | "
                   + " | ".join(vs_cell(d, p) for d, p, _ in res) + " |")
    return "\n".join(out) + "\n"


def profiles_data(results: Path) -> list[tuple[str, Path, list[SettingData]]]:
    """``(kind, profile directory, its settings with runs)`` for every ``<kind>/<profile>``
    under ``results`` that holds any, in a fixed order."""
    out = []
    for kind in KINDS:
        kdir = Path(results) / kind
        if not kdir.is_dir():
            continue
        for pdir in sorted(p for p in kdir.iterdir() if p.is_dir()):
            data = [s for s in load(pdir) if s.runs]
            if data:
                out.append((kind, pdir, data))
    return out


def cost_rows(profiles: Sequence[tuple[str, Path, list[SettingData]]]
              ) -> list[tuple[str, str, int, int, float, str]]:
    """(experiment, task, sweeps, runs, core-hours, processors) per ``<kind>/<profile>/<task>``
    of ``profiles`` (:func:`profiles_data`), of what ran for it: each sweep once (the settings of
    one vmapped sweep share its wall clock), a borrowed setting (``borrowed_from``: read from
    another experiment) not at all, as its sweep is counted where it ran."""
    rows = []
    for kind, pdir, data in profiles:
        for task, settings in _by_task(data).items():
            sweeps: dict[str, SettingData] = {}
            for s in settings:
                if not s.meta.get("borrowed_from"):
                    sweeps.setdefault(str(s.meta.get("sweep", {}).get("name", s.name)), s)
            if not sweeps:
                continue
            parts = [p for s in sweeps.values() for p in sweep_parts(s.meta)]
            hours = sum(wall * cores_used(h) for wall, h, _ in parts)
            runs = sum(int(s.meta.get("sweep", {}).get("runs") or len(s.runs))
                       for s in sweeps.values())
            cpus = sorted({h.get("processor") or "?" for _, h, _ in parts})
            rows.append((f"{kind}/{pdir.name}", task, len(sweeps), runs, hours / 3600,
                         ", ".join(cpus)))
    return rows


def lever_cost_rows(results: Path) -> list[tuple[str, str, int, float]]:
    """(setting, task, runs, core-hours) per setting of ``experiments/bench_learning.py`` under
    ``results/bench_learning`` (each run pinned to one core; its wall clock from the start of
    training, summed over resumes). A run that continues another setting's run of the same
    seed (its curve begins with that run's whole curve) counts only what it added."""
    settings = {}
    for f in sorted((Path(results) / "bench_learning").glob("*.json")):
        data = json.loads(f.read_text(encoding="utf-8"))
        if isinstance(data, dict) and isinstance(data.get("results"), dict):
            settings[f.stem] = data
    curves = {(name, seed): r.get("curve") or []
              for name, d in settings.items() for seed, r in d["results"].items()}
    rows = []
    for name, d in settings.items():
        seconds = 0.0
        for seed, r in d["results"].items():
            curve = curves[(name, seed)]
            before = max((len(c) for (n, s), c in curves.items()
                          if s == seed and n != name and 0 < len(c) < len(curve)
                          and curve[:len(c)] == c), default=0)
            seconds += float(r["wall_s"]) - (float(curve[before - 1][1]) if before else 0.0)
        task = next((kv.split("=", 1)[1] for kv in d.get("settings", [])
                     if kv.startswith("env=")), "FetchReach")
        rows.append((name, task, len(d["results"]), seconds / 3600))
    return rows


def cost_markdown(profiles: Sequence[tuple[str, Path, list[SettingData]]],
                  levers: Sequence[tuple[str, str, int, float]] = ()) -> str | None:
    """``cost.md``: the core-hours each experiment's committed runs took (and, with
    ``levers``, each :func:`lever_cost_rows` setting's), and their total."""
    rows = cost_rows(profiles)
    if not rows:
        return None
    out = ["# Compute spent on the committed results", "",
           "Hours of one CPU core per experiment and task: the sum of the wall clocks of the "
           "sweeps (and one-seed pieces) that made the committed CSVs (`run_info.json`, "
           "`wall_clock_s`: from the sweep's start, compilation included, summed over resumes; "
           "process start, env build and the best-policy retest not), each times the cores it "
           "could run on (`cpu_affinity` in its hardware record; one where the record predates "
           "that field, as those sweeps ran pinned to one core). A setting read from another "
           "experiment (`borrowed_from`) is counted once, where it ran. Written by "
           "`python experiments/report.py`.", ""]
    body = [[e, t, str(n), str(r), f"{h:.2f}", c] for e, t, n, r, h, c in rows]
    for e, grouped in itertools.groupby(rows, key=lambda row: row[0]):  # rows come by experiment
        part = list(grouped)
        body.append([f"**{e}**", "all", "", str(sum(g[3] for g in part)),
                     f"**{sum(g[4] for g in part):.2f}**", ""])
    if levers:
        body.append(["**bench_learning**", "all", "", str(sum(r for _, _, r, _ in levers)),
                     f"**{sum(h for *_, h in levers):.2f}**", ""])
    body.append(["**total**", "", "",
                 str(sum(r for _, _, _, r, _, _ in rows) + sum(r for _, _, r, _ in levers)),
                 f"**{sum(h for *_, h, _ in rows) + sum(h for *_, h in levers):.2f}**", ""])
    out += _md_table(["experiment", "task", "sweeps", "runs", "core-hours", "CPU"], body)
    if levers:
        out += ["", "## Lever runs (`experiments/results/bench_learning/`)", "",
                "One row per setting of `python experiments/bench_learning.py`, one run per "
                "seed, pinned to one core but where its note says it ran alone on both (a few "
                "`overlap=true` runs): its wall clock from the start of training (compilation "
                "included, summed over resumes) counted as one core's; a run continued from "
                "another setting's counts only its own epochs. In the total above.", ""]
        out += _md_table(["setting", "task", "runs", "core-hours"],
                         [[f"`{n}`", t, str(r), f"{h:.2f}"] for n, t, r, h in levers])
    return "\n".join(out) + "\n"


def write_reports(results: Path, only: set[tuple[str, str]] | None = None) -> list[Path]:
    """Write the tables and figures of every ``<kind>/<profile>`` under ``results`` (or only
    those in ``only``); returns the files written."""
    written = []
    profiles = profiles_data(results)
    for kind, pdir, data in profiles:
        if only is not None and (kind, pdir.name) not in only:
            continue
        md = pdir / "summary.md"
        write_text_atomic(md, summary_markdown(kind, pdir.name, data))
        sc = pdir / "summary.csv"
        write_text_atomic(sc, summary_csv(kind, data))
        written += [md, sc]
        for x_col, name in (("epoch", "success_epochs.png"),
                            ("env_steps", "success_env_steps.png")):
            figure(kind, pdir.name, data, x_col, pdir / name)
            written.append(pdir / name)
    # Over every profile, not only those written now: the total is the whole results tree's.
    cost = cost_markdown(profiles, lever_cost_rows(results))
    if cost is not None and written:
        write_text_atomic(Path(results) / "cost.md", cost)
        written.append(Path(results) / "cost.md")
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/report.py",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=HERE / "results",
                    help="results root holding ablation/ and benchmark/ (default: "
                    "experiments/results)")
    ap.add_argument("--compare", type=Path, nargs="+", metavar="SETTING_DIR",
                    help="print, and write nothing: each setting's measures over seeds and "
                    "every pair's difference with Welch's p, for settings' results directories "
                    "(<kind>/<profile>/<task>/<setting>, from any kind or profile)")
    args = ap.parse_args(argv)
    if args.compare is not None:
        if len(args.compare) < 2:
            print("error: --compare needs at least two setting directories", file=sys.stderr)
            return 2
        try:
            print(compare_markdown(args.compare), end="")
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        return 0
    written = write_reports(args.results)
    if not written:
        print(f"no ablation or benchmark results under {args.results}", file=sys.stderr)
        return 1
    for p in written:
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
