"""experiments/report.py's numbers on hand-made metrics CSVs, against values worked out by hand.

The layout is what ``experiments/profiles.py``'s ``collect`` writes:
``<results>/<kind>/<profile>/<task>/<setting>/s<seed>.csv`` and ``run_info.json``. Every run has
4 epochs; "final" is the mean of the last 3, "over all epochs" (AUC) the mean of all 4.

The data are chosen so that every expected number has a closed form:

- HER (3 seeds) and RDHER (3 seeds): RDHER's seeds are HER's plus 0.3 at every epoch, permuted,
  so both have the same per-seed sample variance (0.01, std 0.1) in best, final and AUC, and
  Welch's degrees of freedom are exactly 2 * (3 - 1) = 4.
- DDPG (2 seeds): identical seeds, variance 0, so Welch's df against HER is 3 - 1 = 2.
- CHER (1 seed): no std, no interval, no p.

Student's t with 2 and 4 degrees of freedom has closed forms:

- quantile, df = 2: F(t) = 1/2 + t / (2 sqrt(2 + t^2)) gives
  t(0.975, 2) = (2 * 0.975 - 1) / sqrt(2 * 0.975 * 0.025) = 0.95 / sqrt(0.04875) = 4.302653;
  95% half-width for std 0.1 over 3 seeds: 4.302653 * 0.1 / sqrt(3) = 0.248414.
- two-sided p, with x = |t| / sqrt(t^2 + df): df = 2: p = 1 - x; df = 4: p = 1 - x (3 - x^2) / 2.
"""

import csv
import json
import math
import sys
from pathlib import Path

import pytest

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))

import report  # noqa: E402

TASK = "FetchPush"
EPOCHS = 4
# test_success per epoch, per seed.
RUNS = {
    "her": {0: [0.1, 0.3, 0.4, 0.5],  # best 0.5, final 0.4, AUC 1.3 / 4 = 0.325
            1: [0.0, 0.2, 0.3, 0.4],  # best 0.4, final 0.3, AUC 0.9 / 4 = 0.225
            2: [0.2, 0.4, 0.5, 0.6]},  # best 0.6, final 0.5, AUC 1.7 / 4 = 0.425
    "rdher": {0: [0.5, 0.7, 0.8, 0.9],  # HER s2 + 0.3: best 0.9, final 0.8, AUC 0.725
              1: [0.4, 0.6, 0.7, 0.8],  # HER s0 + 0.3: best 0.8, final 0.7, AUC 0.625
              2: [0.3, 0.5, 0.6, 0.7]},  # HER s1 + 0.3: best 0.7, final 0.6, AUC 0.525
    "ddpg": {0: [0.0, 0.1, 0.1, 0.1],  # best 0.1, final 0.1, AUC 0.075
             1: [0.0, 0.1, 0.1, 0.1]},
    "cher": {0: [0.2, 0.2, 0.3, 0.4]},  # best 0.4, final 0.3, AUC 1.1 / 4 = 0.275
}
# HER's bias_real per epoch and seed (the others have no bias columns): per seed the mean of the
# finite values among the last 3 epochs: s0 (1 + 2 + 3) / 3 = 2, s1 (3 + 4 + 5) / 3 = 4,
# s2 (6 + 6) / 2 = 6 (one epoch had no real rows); over seeds 4 ± 2.
BIAS = {0: ["9", "1", "2", "3"], 1: ["9", "3", "4", "5"], 2: ["9", "", "6", "6"]}
META = {  # algo, label, order, (lambda_r, lambda_h)
    "ddpg": ("ddpg", "DDPG", 0, (1.0, 1.0)),
    "her": ("her", "HER", 1, (1.0, 1.0)),
    "cher": ("cher", "CHER", 2, (1.0, 1.0)),
    "rdher": ("rdher", "RDHER", 4, (4.0, 0.5)),
}
HARDWARE = {"processor": "cpu-x", "machine": "x86_64", "cpu_count": 2, "jax_backend": "cpu",
            "devices": ["cpu:0"], "backend": "mujoco"}

HALF = 0.248414  # 95% half-width, std 0.1 over 3 seeds (module docstring)
# Welch, final and AUC alike:
# RDHER vs HER: diff 0.3, se = sqrt(0.01/3 + 0.01/3) = 0.081650, t = 3.674235, df 4,
#   x = sqrt(13.5 / 17.5) = 0.878310, p = 1 - x * (3 - 27/35) / 2 = 0.021312.
P_RDHER = 0.021312
# DDPG vs HER: se = sqrt(0 + 0.01/3) = 0.057735, df 2.
#   final: diff 0.1 - 0.4 = -0.3, t = -5.196152, p = 1 - 5.196152 / sqrt(29) = 0.035099.
#   AUC:  diff 0.075 - 0.325 = -0.25, t = -4.330127, p = 1 - 4.330127 / sqrt(20.75) = 0.049414.
P_DDPG_FINAL, P_DDPG_AUC = 0.035099, 0.049414
NAN = math.nan
# summary.csv, by hand; paper_best is the paper's Table 2 for FetchPush (%/100).
EXPECTED_CSV = {
    "her": dict(seeds=3, best_mean=0.5, best_std=0.1, best_ci_lo=0.5 - HALF,
                best_ci_hi=0.5 + HALF, final_mean=0.4, final_std=0.1, final_ci_lo=0.4 - HALF,
                final_ci_hi=0.4 + HALF, auc_mean=0.325, auc_std=0.1, final_vs_her=NAN,
                final_vs_her_p=NAN, auc_vs_her=NAN, auc_vs_her_p=NAN, paper_best=0.39,
                bias_real=4.0, bias_her=NAN),
    "rdher": dict(seeds=3, best_mean=0.8, best_std=0.1, best_ci_lo=0.8 - HALF,
                  best_ci_hi=0.8 + HALF, final_mean=0.7, final_std=0.1, final_ci_lo=0.7 - HALF,
                  final_ci_hi=0.7 + HALF, auc_mean=0.625, auc_std=0.1, final_vs_her=0.3,
                  final_vs_her_p=P_RDHER, auc_vs_her=0.3, auc_vs_her_p=P_RDHER,
                  paper_best=0.58, bias_real=NAN),
    "ddpg": dict(seeds=2, best_mean=0.1, best_std=0.0, best_ci_lo=0.1, best_ci_hi=0.1,
                 final_mean=0.1, final_std=0.0, final_ci_lo=0.1, final_ci_hi=0.1,
                 auc_mean=0.075, auc_std=0.0, final_vs_her=-0.3, final_vs_her_p=P_DDPG_FINAL,
                 auc_vs_her=-0.25, auc_vs_her_p=P_DDPG_AUC, paper_best=0.15),
    "cher": dict(seeds=1, best_mean=0.4, best_std=NAN, best_ci_lo=NAN, best_ci_hi=NAN,
                 final_mean=0.3, final_std=NAN, auc_mean=0.275, final_vs_her=-0.1,
                 final_vs_her_p=NAN, auc_vs_her=-0.05, auc_vs_her_p=NAN, paper_best=0.14),
}
# summary.md's per-task rows (percent, one decimal; intervals clipped to [0, 100]).
EXPECTED_ROWS = [
    "| FetchPush | DDPG | 1 / 1 | 2 | 4 | 400 | 10.0 ± 0.0 | [10.0, 10.0] | 10.0 ± 0.0 "
    "| [10.0, 10.0] | 7.5 ± 0.0 | -30.0 (p 0.035) | -25.0 (p 0.049) | 15 | ok |",
    "| FetchPush | HER | 1 / 1 | 3 | 4 | 400 | 50.0 ± 10.0 | [25.2, 74.8] | 40.0 ± 10.0 "
    "| [15.2, 64.8] | 32.5 ± 10.0 | - | - | 39 | ok |",
    "| FetchPush | CHER | 1 / 1 | 1 | 4 | 400 | 40.0 (1 seed) | - | 30.0 (1 seed) | - "
    "| 27.5 (1 seed) | -10.0 | -5.0 | 14 | ok |",
    "| FetchPush | RDHER | 4 / 0.5 | 3 | 4 | 400 | 80.0 ± 10.0 | [55.2, 100.0] | 70.0 ± 10.0 "
    "| [45.2, 94.8] | 62.5 ± 10.0 | +30.0 (p 0.021) | +30.0 (p 0.021) | 58 | ok |",
]


def write_setting(root: Path, kind: str, name: str, runs: dict, algo: str, label: str,
                  order: int, lambdas: tuple[float, float], bias: dict | None = None,
                  wall: float = 3723.0) -> None:
    d = root / kind / "hand" / TASK / name
    d.mkdir(parents=True)
    for seed, succ in runs.items():
        with open(d / f"s{seed}.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["epoch", "env_steps", "test_success", *(["bias_real"] if bias else [])])
            for e, s in enumerate(succ):
                w.writerow([e + 1, 100 * (e + 1), s, *([bias[seed][e]] if bias else [])])
    meta = {"algo": algo, "label": label, "order": order, "lambda_r": lambdas[0],
            "lambda_h": lambdas[1], "budget": {"settings": {"epochs": EPOCHS}, "seeds": 3},
            "sweep": {"name": name, "runs": len(runs)}, "hardware": HARDWARE,
            "wall_clock_s": wall, "wall_clock_per_run_s": wall / len(runs),
            "runs": {f"s{s}": {"status": "ok"} for s in runs}}
    (d / "run_info.json").write_text(json.dumps(meta), encoding="utf-8")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    for name, runs in RUNS.items():
        algo, label, order, lam = META[name]
        write_setting(root, "benchmark", name, runs, algo, label, order, lam,
                      bias=BIAS if name == "her" else None)
    # An ablation: HER and two RDHER pairs, one of them the paper's pick for FetchPush (4, 0.5).
    write_setting(root, "ablation", "her", RUNS["her"], "her", "HER", 0, (1.0, 1.0))
    write_setting(root, "ablation", "rdher_lr1_lh2", RUNS["ddpg"], "rdher", "RDHER 1/2", 1,
                  (1.0, 2.0))
    write_setting(root, "ablation", "rdher_lr4_lh0.5", RUNS["rdher"], "rdher", "RDHER 4/0.5", 6,
                  (4.0, 0.5))
    written = report.write_reports(root)
    assert len(written) == 9  # per kind: 2 tables and 2 figures; and cost.md
    return root


def test_cost_sums_the_hand_written_wall_clocks(results):
    # Every setting here is its own sweep, of its runs at a known wall clock (write_setting).
    rows = {(e, t): (n, r, h)
            for e, t, n, r, h, _ in report.cost_rows(report.profiles_data(results))}
    metas = {kind: [json.loads(p.read_text()) for p in (results / kind).rglob("run_info.json")]
             for kind in ("ablation", "benchmark")}
    for kind, ms in metas.items():
        n, runs, hours = rows[(f"{kind}/hand", "FetchPush")]
        assert (n, runs) == (len(ms), sum(m["sweep"]["runs"] for m in ms))
        assert hours == pytest.approx(sum(m["wall_clock_s"] for m in ms) / 3600)
    md = (results / "cost.md").read_text(encoding="utf-8")
    total = sum(h for _, (_, _, h) in rows.items())
    assert md.rstrip().endswith(f"| **{total:.2f}** |  |")


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as f:
        return {r["setting"]: r for r in csv.DictReader(f)}


def section(md: str, title: str) -> list[str]:
    text = md.split(f"## {title}", 1)[1].split("\n## ", 1)[0]
    return [ln for ln in text.splitlines() if ln.startswith("| ")][1:]  # rows, no header


def test_summary_csv_numbers(results):
    rows = read_csv(results / "benchmark/hand/summary.csv")
    assert list(rows) == ["ddpg", "her", "cher", "rdher"]  # by the settings' order
    for name, want in EXPECTED_CSV.items():
        r = rows[name]
        for col, v in want.items():
            got = float(r[col])
            if math.isnan(v):
                assert math.isnan(got), (name, col, got)
            else:
                assert got == pytest.approx(v, abs=1.5e-6), (name, col)
        assert int(r["epochs_min"]) == int(r["epochs_max"]) == EPOCHS
        assert int(r["env_steps"]) == 400
        assert float(r["wall_clock_s"]) == 3723.0


def test_summary_markdown_rows(results):
    md = (results / "benchmark/hand/summary.md").read_text(encoding="utf-8")
    assert section(md, "Per task: best and final success (%)") == EXPECTED_ROWS
    # Best-policy means beside the paper's Table 2 for FetchPush.
    assert section(md, "Best-policy test success (%)") == [
        "| FetchPush | 10.0 (15) | 50.0 (39) | 40.0 (14) | 80.0 (58) |"]
    # Wall clock: 3723 s = 01:02:03; per run 3723 / 3 = 1241 s = 00:20:41; the paper's Table 3
    # for HER on FetchPush is 03:30:32.
    her = [r for r in section(md, "Wall clock") if r.startswith("| FetchPush | her |")]
    assert len(her) == 1
    cells = [c.strip() for c in her[0].strip("|").split("|")]
    assert cells[2:5] == ["3", "01:02:03", "00:20:41"] and cells[-1] == "03:30:32"
    bias = [r for r in section(md, "Hindsight-bias diagnostic") if "| HER |" in r]
    assert bias == ["| FetchPush | HER | 1 / 1 | 4.00 ± 2.00 | - | - | - | - | - |"]


def test_ablation_marks_the_papers_pick(results):
    md = (results / "ablation/hand/summary.md").read_text(encoding="utf-8")
    pick = {r.split("|")[2].strip(): r.rstrip(" |").rsplit("|", 2)[1].strip()
            for r in section(md, "Per task: best and final success (%)")}
    # The last-but-one column: 'yes' for the paper's (lambda_r, lambda_h) of FetchPush only.
    assert pick == {"HER": "", "RDHER 1/2": "", "RDHER 4/0.5": "yes"}
    rows = read_csv(results / "ablation/hand/summary.csv")
    assert rows["rdher_lr4_lh0.5"]["paper_best"] == ""  # Table 2 only beside the benchmark


def test_solve_profile_times_each_seed_to_the_goal_threshold():
    """The solve profile's 'Against the goal' rows: the first trailing mean of 3 at the task's
    threshold (Slide 0.8: float32 7/10-style rates a hair under count as reached), per seed."""
    def rows(succ):
        return [{"epoch": str(i + 1), "env_steps": str(2500 * (i + 1)),
                 "wall_time": str(60.0 * (i + 1)), "test_success": str(x)}
                for i, x in enumerate(succ)]

    s = report.SettingData("FetchSlide", "her", {"label": "HER", "runs": {
        "s0": {"best_policy": {"success": 0.83}}}},
        {0: rows([0.5, 0.9, 0.8, 0.7, 0.9]),          # (0.9+0.8+0.7)/3 = 0.8 at epoch 4
         1: rows([0.7999999, 0.8, 0.8000001, 0.1])})  # mean a hair under 0.8: epoch 3
    lines = report._goal_lines([s])
    assert lines[0] == "## Against the goal"
    table = [line for line in lines if line.startswith("| FetchSlide")]
    assert table == ["| FetchSlide | HER | 0 | 80.0 | 83.0 | 80.0 | 10,000 | 4.0 |",
                     "| FetchSlide | HER | 1 | 80.0 | - | 80.0 | 7,500 | 3.0 |",
                     # the verdict over the seeds retested so far, against the goal
                     "| FetchSlide | HER | 80.0 | 83.0 (1 seed) | met at 1 of 2 seeds |"]
    never = report.SettingData("FetchPush", "her", {"runs": {
        "s0": {"best_policy": {"success": 0.99}}, "s1": {"best_policy": {"success": 0.9}}}},
        {0: rows([0.9, 0.9, 0.8]), 1: rows([0.1])})
    lines = report._goal_lines([never])
    assert "| FetchPush | her | 0 | 97.0 | 99.0 | 90.0 | - | - |" in lines
    assert lines[-2] == "| FetchPush | her | 97.0 | 94.5 ± 6.4 | missed at 2 of 2 seeds |"
    # A mean of exactly the goal meets it, though the float32 means of 100 test episodes are a
    # hair off (99 of 100 as a run's retest stored it).
    f32 = [1.0, 0.9300000071525574, 0.9899999499320984, 1.0, 0.9300000071525574]
    assert sum(f32) / 5 < 0.97
    at = report.SettingData("FetchPush", "her", {"runs": {
        f"s{k}": {"best_policy": {"success": x}} for k, x in enumerate(f32)}},
        {k: rows([0.9]) for k in range(5)})
    assert report._goal_lines([at])[-2].endswith("| met at 5 of 5 seeds |")


def test_table2_layout_marks_means_over_unfinished_runs():
    """A Table 2 cell whose mean includes runs still short of the budget says how many; the
    retested table (finished runs only) does not; a finished setting is not marked."""
    def rows(succ):
        return [{"epoch": str(i + 1), "env_steps": str(2500 * (i + 1)), "wall_time": "1.0",
                 "test_success": str(x)} for i, x in enumerate(succ)]

    meta = {"label": "HER", "algo": "her", "budget": {"settings": {"epochs": 3}},
            "runs": {"s0": {"best_policy": {"success": 0.9, "episodes": 100}}}}
    late = report.SettingData("FetchPush", "her", meta, {0: rows([0.2, 1.0, 0.8]), 1: rows([0.4])})
    assert report.unfinished(late) == 1
    md = report.summary_markdown("benchmark", "solve", [late])
    cells = section(md, "Best-policy test success (%)")
    assert cells[0] == "| FetchPush | 70.0 (39), 1 of 2 runs unfinished |"
    assert cells[1:] == ["| task | HER |", "| FetchPush | 90.0 (39) |"]  # retest: finished runs
    done = report.SettingData("FetchPush", "her", meta, {0: rows([0.2, 1.0, 0.8])})
    assert report.unfinished(done) == 0
    md = report.summary_markdown("benchmark", "solve", [done])
    assert section(md, "Best-policy test success (%)")[0] == "| FetchPush | 100.0 (39) |"


def test_figure_curves_smooth_long_runs_per_seed_before_the_median():
    """A long run's figure curve: each seed's trailing mean over epochs / 40 tests (a plain loop
    here), then the median and quartiles over seeds; short runs (the paper's 50 epochs) are
    plotted as tested."""
    assert [report.smoothing_window(n) for n in (4, 50, 79, 80, 200, 240, 400)] == \
        [1, 1, 1, 2, 5, 6, 10]
    y = [0.0, 1.0, 0.5, 0.2, 0.9, 0.4, 0.3]
    for w in (1, 2, 3, 7, 9):
        want = [sum(y[max(0, i - w + 1):i + 1]) / len(y[max(0, i - w + 1):i + 1])
                for i in range(len(y))]
        assert report.trailing_mean(y, w) == pytest.approx(want)

    def rows(succ):
        return [{"epoch": str(i + 1), "env_steps": str(100 * (i + 1)), "test_success": str(x)}
                for i, x in enumerate(succ)]

    s = report.SettingData(TASK, "her", {}, {0: rows([0.0, 0.4, 0.8]), 1: rows([0.2, 0.2, 0.2]),
                                             2: rows([1.0, 0.0])})  # seed 2: unfinished
    x, med, q1, q3 = report._curve(s, "env_steps", 2)
    assert x == [100.0, 200.0, 300.0]
    # seed means: epoch 1 (0, 0.2, 1), epoch 2 (0.2, 0.2, 0.5), epoch 3 (0.6, 0.2): the median
    assert med == pytest.approx([0.2, 0.2, 0.4])
    assert q1 == pytest.approx([0.1, 0.2, 0.3]) and q3 == pytest.approx([0.6, 0.35, 0.5])
    assert report._curve(s, "epoch")[1] == pytest.approx([0.2, 0.2, 0.5])  # unsmoothed


def test_legend_names_a_weighted_settings_pair_once():
    named = report.SettingData("FetchPush", "rdher_f0.8", {
        "label": "RDHER (4, 0.5), share 0.8", "algo": "rdher", "lambda_r": 4.0,
        "lambda_h": 0.5}, {0: [], 1: []})
    plain = report.SettingData("FetchPush", "rdher", {
        "label": "RDHER", "algo": "rdher", "lambda_r": 4.0, "lambda_h": 0.5}, {0: []})
    assert report.legend_label("benchmark", named, False) == "RDHER (4, 0.5), share 0.8"
    assert report.legend_label("benchmark", plain, False) == "RDHER (λ 4 / 0.5)"
    assert report.legend_label("benchmark", named, True) == "RDHER (4, 0.5), share 0.8, 2 seeds"
    assert report.legend_label("ablation", plain, False) == "RDHER"


def test_holm_steps_down_and_stops_at_the_first_failure():
    # sorted p 0.01 <= 0.05/3 rejects; 0.03 > 0.05/2 stops, so 0.04 is not tested
    assert report.holm([0.01, 0.04, 0.03]) == [True, False, False]
    assert report.holm([0.012, math.nan, 0.02]) == [True, False, True]  # 0.012 <= .025, .02 <= .05
    assert report.holm([]) == []


def test_verdict_never_reads_stronger_than_the_paired_test():
    assert report.verdict(report.stat([0.2, 0.3, 0.25])) == "holds"
    assert report.verdict(report.stat([-0.2, -0.3, -0.25])) == "reversed"
    assert report.verdict(report.stat([0.0, 0.0, 0.0])) == "level on every seed"
    assert report.verdict(report.stat([0.3])) == "undecided"  # one seed
    # the same difference on every seed: a point interval, but the t-test gives no p
    assert math.isnan(report.paired({0: 0.5, 1: 0.6}, {0: 0.4, 1: 0.5})[1])
    assert report.verdict(report.stat([0.1, 0.1, 0.1])) == "undecided"


def test_table2_order_claims_pair_settings_by_seed_and_share():
    """The paper's Table 2 order for FetchPush (RDHER 58 > HER 39 > DHER 21 > DDPG 15 > CHER 14)
    tested claim by claim on hand-made retests: RDHER and DHER are paired only at the same share,
    a setting without retests is compared on its best epoch, and each verdict follows the 95%
    paired interval."""
    def setting(name, algo, policy, best=None, extra=()):
        runs = {f"s{k}": {"best_policy": {"success": x, "episodes": 100}}
                for k, x in enumerate(policy or [])}
        rows = {k: [{"epoch": "1", "env_steps": "100", "test_success": str(x)}]
                for k, x in enumerate(best or [0.5] * len(policy or []))}
        return report.SettingData(TASK, name, {"label": name, "algo": algo, "runs": runs,
                                               "extra": list(extra)}, rows)

    data = [setting("her", "her", [0.9, 0.8, 0.7]),
            setting("rdher", "rdher", [0.5, 0.4, 0.35]),
            setting("rdher_f0.8", "rdher", [0.9, 0.8, 0.7], extra=("dher_fraction=0.8",)),
            setting("dher", "dher", [0.9, 0.7, 0.8]),
            setting("ddpg", "ddpg", None, best=[0.1, 0.2, 0.0])]
    rows = {(r["a"].name, r["b"].name): r for r in report.order_claims(TASK, data)}
    # no DHER at the authors' share: RDHER at it meets DHER nowhere; CHER was not run
    assert set(rows) == {("rdher", "her"), ("rdher_f0.8", "her"), ("rdher", "dher"),
                         ("rdher", "ddpg"), ("rdher_f0.8", "ddpg"), ("her", "dher"),
                         ("her", "ddpg"), ("dher", "ddpg")}
    r = rows[("rdher", "her")]
    assert r["claim"] == "RDHER 58 > HER 39" and r["measure"] == "policy" and r["n"] == 3
    # differences -0.4, -0.4, -0.35: mean -0.38333, std 0.028868, half-width t(.975, 2) sd/√3
    sd = math.sqrt(((0.4 - 0.38333333) ** 2 * 2 + (0.35 - 0.38333333) ** 2) / 2)
    half = 4.302653 * sd / math.sqrt(3)
    assert r["diff"] == pytest.approx(-0.383333, abs=1e-6)
    assert (r["lo"], r["hi"]) == pytest.approx((-0.383333 - half, -0.383333 + half), abs=1e-5)
    t = 0.383333 / (sd / math.sqrt(3))
    assert r["p"] == pytest.approx(1 - t / math.sqrt(t * t + 2), rel=1e-4)
    assert r["verdict"] == "reversed"
    assert rows[("rdher_f0.8", "her")]["verdict"] == "level on every seed"
    assert rows[("her", "dher")]["verdict"] == "undecided"  # 0, +0.1, -0.1
    # DDPG has no retest: both sides on their best epochs, HER's 0.5 against 0.1, 0.2, 0.0
    d = rows[("her", "ddpg")]
    assert d["measure"] == "best" and d["diff"] == pytest.approx(0.4)
    assert d["verdict"] == "holds"
    md = report.summary_markdown("benchmark", "solve", data)
    table = section(md, "The paper's Table 2 order, claim by claim")
    assert "| FetchPush | RDHER 58 > HER 39 | rdher − her | retest | -38.3 | " in table[0]
    # Holm corrects over the rows with a p: all but RDHER at 0.8 - HER (level, no p)
    assert {r["family"] for r in rows.values()} == {7}
    assert table[0].endswith("| 3 | reversed at 3 seeds | yes (of 7) |")
    assert "## The paper's Table 2 order" not in report.summary_markdown("ablation", "solve",
                                                                          data)
