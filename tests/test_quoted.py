"""The figures that RESULTS.md, README.md and the results READMEs quote in their prose, against
the committed data they come from (experiments/quoted.py)."""

import json
import math
import os
import sys
from pathlib import Path

import pytest

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))

import quoted  # noqa: E402
import report  # noqa: E402


def test_quoted_figures_match_the_committed_data():
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    n, bad = quoted.check()
    assert n > 0, "no checked figures found: is the q: link convention still in use?"
    assert not bad, (f"{len(bad)} of {n} quoted figures differ from the committed data "
                     "(fix the text, or run python experiments/quoted.py --write):\n"
                     + "\n".join(bad))


def test_the_check_names_file_line_figure_text_and_value(tmp_path):
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    md = tmp_path / "README.md"
    her = os.path.relpath(EXP / "results" / "benchmark" / "cpu" / "FetchPush" / "her", tmp_path)
    md.write_text(f"HER ends at\n[91.6]({her} \"q:bc/push/her:final\") and "
                  f"[92]({her}/ \"q:bc/push/her:final\"),\n"
                  f"[+1.0]({her} \"q:no/such:figure\"), [91.7](. \"q:bc/push/her:final\").\n",
                  encoding="utf-8")
    n, bad = quoted.check([md], root=tmp_path)
    assert n == 4
    assert bad[0] == ("README.md:2: bc/push/her:final: the text says '91.6', the committed data "
                      f"give '91.7' ({quoted.value('bc/push/her:final')!r})")
    assert bad[1].startswith("README.md:3: no/such:figure: ")
    assert bad[2] == ("README.md:3: bc/push/her:final: the link goes to ., not to the data the "
                      "figure comes from (experiments/results/benchmark/cpu/FetchPush/her)")
    assert len(bad) == 3


@pytest.mark.parametrize(("val", "like", "out"), [
    (-17.33, "−17.3", "−17.3"), (-17.33, "-17", "-17"), (3.33, "+0.0", "+3.3"),
    (-0.04, "+1.1", "+0.0"), (0.03215, "0.03", "0.03"), (0.000123, "0.0001", "0.0001"),
    (1.53e-7, "1.5e-07", "1.5e-07"), (490000.0, "495,000", "490,000"), (91.67, "92", "92"),
    ("33 min 16 s", "anything", "33 min 16 s")])
def test_render_writes_a_figure_in_the_style_of_its_text(val, like, out):
    assert quoted.render(val, like) == out


def test_the_write_command_mends_a_figure(tmp_path):
    if not (EXP / "results" / "benchmark").is_dir():
        pytest.skip("no committed experiment results")
    md = tmp_path / "x.md"
    rd = os.path.relpath(EXP / "results" / "benchmark" / "paper" / "FetchSlide" / "rdher",
                         tmp_path)
    md.write_text(f"final [−1.0]({rd} \"q:bp/slide/rdher-her:final\") (p [0.50]({rd} "
                  "\"q:bp/slide/rdher-her:final:p\"))\n", encoding="utf-8")
    assert quoted.write([md]) == 2
    assert md.read_text(encoding="utf-8") == (
        f"final [−17.3]({rd} \"q:bp/slide/rdher-her:final\") "
        f"(p [0.03]({rd} \"q:bp/slide/rdher-her:final:p\"))\n")
    assert quoted.check([md], root=tmp_path)[1] == []


@pytest.mark.parametrize(("seconds", "like", "out"), [
    (1996.4, "1 min 1 s", "33 min 16 s"), (1996.6, "0:00", "33:17"), (6313, "1:00:00", "1:45:13"),
    (6313, "1 h 0 min 0 s", "1 h 45 min 13 s"), (6313, "0 min 0 s", "105 min 13 s")])
def test_a_wall_clock_is_written_in_the_style_of_its_text(seconds, like, out):
    assert quoted.render(quoted.Duration(seconds), like) == out


@pytest.mark.parametrize(("val", "like", "out"), [
    (112500.0, "113k", "113k"), (112499.0, "113k", "112k"), (2.5, "3", "3"), (-2.5, "-3", "-3"),
    (0.0435, "0.044", "0.044"), (0.04349931, "0.044", "0.043")])
def test_halves_round_up_and_thousands_keep_their_k(val, like, out):
    assert quoted.render(val, like) == out


def test_the_papers_figures_are_checked_against_the_task_table(tmp_path):
    from rdher_jax.tasks import TASKS

    md = tmp_path / "x.md"
    tasks = os.path.relpath(EXP.parent / "rdher_jax" / "tasks.py", tmp_path)
    assert quoted.value("paper/push/rdher:table2") == TASKS["FetchPush"].paper_table2["rdher"]
    md.write_text(f"[58]({tasks} \"q:paper/push/rdher:table2\"), [3:53:16]({tasks} "
                  "\"q:paper/push/rdher:table3\"),\n"
                  f"[57]({tasks} \"q:paper/push/rdher:table2\"), [3 h 53 min 15 s]({tasks} "
                  "\"q:paper/push/rdher:table3\"), `[1](x \"q:paper/push/her:table2\")`\n",
                  encoding="utf-8")
    n, bad = quoted.check([md], root=tmp_path)
    assert n == 4  # the link in code is an example, not a figure
    assert [b.split(": ")[1] for b in bad] == ["paper/push/rdher:table2",
                                               "paper/push/rdher:table3"]
    assert "'3 h 53 min 16 s'" in bad[1]


def test_seeds_for_power_grows_with_the_spread_and_shrinks_with_the_difference():
    n = quoted.seeds_for_power(10.0, 10.0, 10.0)
    assert n == 17  # the two-sample t-test at d = 1: 17 per group (statsmodels' TTestIndPower)
    assert quoted.seeds_for_power(10.0, 20.0, 20.0) > n > quoted.seeds_for_power(20.0, 10.0, 10.0)
    assert quoted.seeds_for_power(10.0, 10.0, None) < n  # paired: the same spread per difference


def test_bench_learning_figures_and_retests():
    if not (EXP / "results" / "bench_learning" / "pnp-fast-600k.json").is_file():
        pytest.skip("no committed bench_learning results")
    assert quoted.value("bl/pnp-fast-600k:to0.9m3:s0") == "not reached"
    assert quoted.value("bl/pnp-fast-600k:to0.9m3:s2") == 582500.0
    assert quoted.value("bl/pnp-fast-600k:retest:s1") == pytest.approx(83.0)
    assert quoted.source("bl/pnp-fast-600k:retest:s1").name == "pnp-fast-600k.json"
    with pytest.raises(KeyError):
        quoted.value("bl/pnp-fast-600k:best")  # the seed goes last


def test_setting_minutes_to_a_threshold_are_the_hits_training_clock():
    """``to<x>m3_min`` of a setting: the training clock (wall_time) of the epoch where
    ``to<x>m3`` finds the first trailing mean of 3 at x, in minutes, as summary.md's goal table
    prints it."""
    ref = "bs/push/her"
    if not (EXP / "results" / "benchmark/solve/FetchPush/her").is_dir():
        pytest.skip("no committed solve results")
    rows = quoted.setting(ref).runs[0]
    steps = quoted.value(f"{ref}:to0.9m3:s0")
    hit = next(r for r in rows if float(r["env_steps"]) == steps)
    assert quoted.value(f"{ref}:to0.9m3_min:s0") == pytest.approx(float(hit["wall_time"]) / 60)
    md = (EXP / "results" / "benchmark/solve/summary.md").read_text()
    assert f"| {float(hit['wall_time']) / 60:.1f} |" in md


def test_bench_learning_selection_figures(tmp_path, monkeypatch):
    """``selected`` / ``selbest``: the selection episodes' success of the chosen policy and of
    the best test epoch's (of equal tests, the later), from the run's recorded selection."""
    (tmp_path / "bench_learning").mkdir()
    run = {"selection": {"epoch": 7, "selection_episodes": 100, "candidates": {
        "3": {"test_success": 0.9, "selection_success": 0.55},
        "5": {"test_success": 0.9, "selection_success": 0.6},
        "7": {"test_success": 0.8, "selection_success": 0.7}}}}
    (tmp_path / "bench_learning" / "sel.json").write_text(
        json.dumps({"results": {"1": run, "2": {"selection": None}}}))
    monkeypatch.setattr(quoted, "RESULTS", tmp_path)
    assert quoted.learning("sel", "selected", ["s1"]) == pytest.approx(70.0)
    assert quoted.learning("sel", "selbest", ["s1"]) == pytest.approx(60.0)  # epoch 5, not 3
    with pytest.raises(KeyError, match="made no selection"):
        quoted.learning("sel", "selected", ["s2"])


def test_bench_learning_hits_at_any_threshold(tmp_path, monkeypatch):
    """``to<x>`` / ``to<x>m3`` are found on the run's curve at any threshold, not only at the
    thresholds whose hits bench_learning stores (0.5 and 0.9): Slide's goal is 0.8."""
    (tmp_path / "bench_learning").mkdir()
    succ = [0.7, 0.8, 0.7, 0.8, 0.9, 0.8, 0.5]
    curve = [[5000 * (i + 1), 60.0 * (i + 1), s] for i, s in enumerate(succ)]
    run = {"curve": curve, "hits": {"0.5": None, "0.9": None}}
    (tmp_path / "bench_learning" / "h.json").write_text(json.dumps({"results": {"0": run}}))
    monkeypatch.setattr(quoted, "RESULTS", tmp_path)
    assert quoted.learning("h", "to0.8", ["s0"]) == 10000.0
    # trailing means of 3 from epoch 3: 0.733, 0.767, 0.8 (epoch 5) -> 25,000 steps, 5 minutes
    assert quoted.learning("h", "to0.8m3", ["s0"]) == 25000.0
    assert quoted.learning("h", "to0.8m3_min", ["s0"]) == pytest.approx(5.0)
    assert quoted.learning("h", "to0.9", ["s0"]) == 25000.0  # from the curve, not the stored None
    assert quoted.learning("h", "to0.9m3", ["s0"]) == "not reached"


def test_steps_to_a_threshold_leave_out_runs_still_under_way(monkeypatch):
    """A finished seed that never reaches the threshold counts its last env steps (a lower
    bound); a seed short of its budget that has not reached it yet has no figure, so a ':min'
    over seeds cannot pick up how far an unfinished run has got."""
    def rows(succ):
        return [{"epoch": str(i + 1), "env_steps": str(2500 * (i + 1)),
                 "wall_time": str(60.0 * (i + 1)), "test_success": str(x)}
                for i, x in enumerate(succ)]

    s = report.SettingData("FetchPush", "her", {"budget": {"settings": {"epochs": 4}}},
                           {0: rows([0.9, 0.9, 0.9, 1.0]),   # reached at epoch 3
                            1: rows([0.1, 0.2, 0.1, 0.2]),   # finished, never reached
                            2: rows([0.1]),                  # under way, not reached yet
                            3: rows([0.9, 0.9, 0.9])})       # under way, reached
    monkeypatch.setattr(quoted, "setting", lambda ref: s)
    assert quoted.seeds("x", "to0.9m3") == {0: 7500.0, 1: 10000.0, 3: 7500.0}
    assert quoted.seeds("x", "to0.9m3_min") == {0: 3.0, 1: 4.0, 3: 3.0}
    assert quoted.seeds("x", "to0.1") == {0: 2500.0, 1: 2500.0, 2: 2500.0, 3: 2500.0}


def test_figures_over_seeds_leave_out_runs_still_under_way(monkeypatch):
    """A run collected while still running (short of its budget, status ok) is in no best,
    final, mean, window or combined-row figure, so a mean over seeds cannot mix a run at
    epoch 2 with finished ones; a run that stopped early (diverged) is finished and counts."""
    def rows(succ, frac):
        return [{"epoch": str(i + 1), "env_steps": str(2500 * (i + 1)),
                 "wall_time": str(60.0 * (i + 1)), "test_success": str(x),
                 "frac_dher": str(frac), "train_success": str(x / 4)}
                for i, x in enumerate(succ)]

    meta = {"budget": {"settings": {"epochs": 4}},
            "runs": {"s0": {"status": "ok"}, "s1": {"status": "ok"},
                     "s2": {"status": "diverged"}}}
    s = report.SettingData("FetchPush", "dher", meta,
                           {0: rows([0.2, 0.4, 0.6, 0.8], 0.5),  # finished
                            1: rows([0.0, 0.0], 0.9),            # under way
                            2: rows([0.1, 0.3], 0.1)})           # diverged at epoch 2
    monkeypatch.setattr(quoted, "setting", lambda ref: s)
    assert report.under_way(s) == {1}
    assert quoted.seeds("x", "final") == pytest.approx({0: 60.0, 2: 20.0})
    assert quoted.seeds("x", "mean") == pytest.approx({0: 50.0, 2: 20.0})
    assert quoted.seeds("x", "best") == pytest.approx({0: 80.0, 2: 30.0})
    assert quoted.seeds("x", "combined") == pytest.approx({0: 50.0, 2: 10.0})
    # the training episodes' success, mean of the last 3 epochs: (0.4 + 0.6 + 0.8) / 4 / 3
    assert quoted.seeds("x", "train") == pytest.approx({0: 15.0, 2: 5.0})
    assert set(quoted.seeds("x", "w1")) == {0, 2}
    assert quoted.value("x:final:n") == 2


def test_a_figure_the_data_make_infinite_is_named_not_a_crash(tmp_path, monkeypatch):
    """A figure whose value is no longer finite (the seeds to detect a difference that has
    shrunk to zero) is left as written by --write and named by --check."""
    md = tmp_path / "x.md"
    md.write_text('n = [255](data "q:bs/pnp/x:policy:paired:seeds80")\n', encoding="utf-8")
    monkeypatch.setattr(quoted, "value", lambda name: math.inf)
    monkeypatch.setattr(quoted, "source", lambda name: tmp_path / "data")
    assert quoted.write([md]) == 0 and "[255]" in md.read_text(encoding="utf-8")
    n, bad = quoted.check([md], root=tmp_path)
    assert n == 1 and len(bad) == 1 and "which no figure can quote" in bad[0]
