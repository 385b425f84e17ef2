"""experiments/ablation.py, benchmark.py and report.py end to end on the tiny profile.

The sweeps run in this process (the scripts' ``main``), so programs compiled by one sweep are
reused by the next one with the same shapes: the ablation's HER sweep and the benchmark's are
the same program, and the benchmark's second call resumes first the algorithm compiled last.
"""

import csv
import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_same_rows

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))

import ablation  # noqa: E402
import benchmark  # noqa: E402
import beyond  # noqa: E402
import moving_goals  # noqa: E402
import profiles  # noqa: E402
import report  # noqa: E402

ABLATION_SETTINGS = ["her", "rdher_lr1_lh2", "rdher_lr2_lh1", "rdher_lr1_lh4", "rdher_lr4_lh1",
                     "rdher_lr0.5_lh4", "rdher_lr4_lh0.5"]
EVAL_EPISODES = 4  # the best-policy test of the benchmark's runs (the ablation's: none)
REPORT_FILES = ["summary.md", "summary.csv", "success_epochs.png", "success_env_steps.png"]


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("experiments")
    out, runs = root / "results", root / "runs"
    common = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(runs), "--no-progress"]
    assert ablation.main([*common, "--eval-episodes", "0"]) == 0
    # One epoch, then the same command at the profile's two epochs resumes both sweeps.
    bench = [*common, "--eval-episodes", str(EVAL_EPISODES)]
    assert benchmark.main([*bench, "--algos", "her", "ddpg", "--epochs", "1"]) == 0
    first = {a: read_csv(out / "benchmark/tiny/FetchReach" / a / "s0.csv") for a in ("her", "ddpg")}
    assert benchmark.main([*bench, "--algos", "ddpg", "her"]) == 0
    return {"out": out, "runs": runs, "common": common, "first": first}


def test_ablation_layout(results):
    task_dir = results["out"] / "ablation/tiny/FetchReach"
    assert sorted(p.name for p in task_dir.iterdir()) == sorted(ABLATION_SETTINGS)
    pairs = dict(zip(ABLATION_SETTINGS, [(1, 1), *profiles.ABLATION_PAIRS], strict=True))
    for name in ABLATION_SETTINGS:
        d = task_dir / name
        assert sorted(p.name for p in d.iterdir()) == ["run_info.json", "s0.csv", "s1.csv"]
        for seed in (0, 1):
            rows = read_csv(d / f"s{seed}.csv")
            assert [r["epoch"] for r in rows] == ["1", "2"]
            assert {"test_success", "env_steps", "wall_time", "bias_real", "bias_unw_her"} \
                <= set(rows[0])
        meta = json.loads((d / "run_info.json").read_text())
        assert meta["algo"] == ("her" if name == "her" else "rdher")
        assert (meta["lambda_r"], meta["lambda_h"]) == pairs[name]
        assert meta["profile"] == "tiny" and meta["seeds"] == [0, 1]
        assert meta["budget"]["settings"] == dict(profiles.TINY.settings)
        assert meta["command"].startswith("python experiments/ablation.py --profile tiny")
        assert meta["sweep"]["runs"] == (2 if name == "her" else 12)
        assert meta["sweep"]["name"] == ("her" if name == "her" else "rdher")
        assert meta["hardware"]["cpu_count"] >= 1 and meta["versions"]["jax"]
        assert meta["wall_clock_s"] > 0
        assert all(r["status"] == "ok" and r["epochs"] == 2 for r in meta["runs"].values())
    # Small text files only: no checkpoints next to the results.
    suffixes = {p.suffix for p in results["out"].rglob("*") if p.is_file()}
    assert suffixes <= {".csv", ".json", ".md", ".png"}
    assert (results["runs"] / "ablation/tiny/FetchReach/rdher/checkpoints").is_dir()


def test_benchmark_resumed_to_the_profile_epochs(results):
    for algo in ("her", "ddpg"):
        d = results["out"] / "benchmark/tiny/FetchReach" / algo
        rows = read_csv(d / "s0.csv")
        assert [r["epoch"] for r in rows] == ["1", "2"]
        assert rows[0] == results["first"][algo][0]  # continued, not restarted
        meta = json.loads((d / "run_info.json").read_text())
        assert meta["budget"]["settings"]["epochs"] == 2
        assert meta["sweep"]["runs"] == 2 and meta["seeds"] == [0, 1]


def test_best_policy_retested_on_fresh_episodes(results):
    """Each finished benchmark run's best policy is tested on fresh episodes (seeded apart from
    training) and the result lands in run_info.json, summary.csv and summary.md."""
    from rdher_jax.checkpoint import Checkpointer
    from rdher_jax.evaluate import evaluate

    rows = {r["setting"]: r for r in read_csv(results["out"] / "benchmark/tiny/summary.csv")}
    for algo in ("her", "ddpg"):
        meta = json.loads((results["out"] / "benchmark/tiny/FetchReach" / algo
                           / "run_info.json").read_text())
        sweep_dir = results["runs"] / "benchmark/tiny/FetchReach" / algo
        names = {r["seed"]: r["run"] for r in
                 json.loads((sweep_dir / "summary.json").read_text())["runs"]}
        got = []
        for seed in (0, 1):
            ev = meta["runs"][f"s{seed}"]["best_policy"]
            run = sweep_dir / names[seed]
            assert ev["epoch"] == Checkpointer(run, read_only=True).best_epoch()
            assert ev["episodes"] == EVAL_EPISODES
            assert ev["seed"] == profiles.EVAL_SEED + seed
            again = evaluate(run, episodes=EVAL_EPISODES, seed=profiles.EVAL_SEED + seed)
            assert again["success"] == ev["success"] and again["epoch"] == ev["epoch"]
            got.append(ev["success"])
        assert float(rows[algo]["best_policy_mean"]) == pytest.approx(sum(got) / 2, abs=1e-6)
        assert rows[algo]["best_policy_episodes"] == str(EVAL_EPISODES)
    abl = json.loads((results["out"] / "ablation/tiny/FetchReach/her/run_info.json").read_text())
    assert all("best_policy" not in r for r in abl["runs"].values())
    md = (results["out"] / "benchmark/tiny/summary.md").read_text()
    assert "best policy retested" in md
    # Table 2's layout again on the retests: one row per task, the mean of each algorithm's.
    second = md.split("The same with each run's best policy retested")[1].split("\n\n")[1]
    row = next(ln for ln in second.splitlines() if ln.startswith("| FetchReach"))
    means = {a: 100 * float(r["best_policy_mean"]) for a, r in rows.items()}
    assert row == f"| FetchReach | {means['ddpg']:.1f} (100) | {means['her']:.1f} (88) |", row
    assert "best policy retested" not in (results["out"] / "ablation/tiny/summary.md").read_text()


def test_precise_episodes_retest_the_same_policy_on_a_stream_of_their_own(results, tmp_path):
    """--precise-episodes N (here with --collect-only, as on a finished study): each finished
    run's best policy tested on N episodes seeded PRECISE_SEED + seed, beside the unchanged
    retest, in run_info.json, summary.csv and the solve table's column; kept by a later
    collect without the flag; refused below 0."""
    from rdher_jax.evaluate import evaluate

    out = tmp_path / "out"
    shutil.copytree(results["out"], out)
    d = out / "benchmark/tiny/FetchReach/her"
    before = json.loads((d / "run_info.json").read_text())
    common = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(results["runs"]),
              "--no-progress", "--algos", "her", "--collect-only"]
    assert benchmark.main([*common, "--eval-episodes", str(EVAL_EPISODES),
                           "--precise-episodes", "3"]) == 0
    meta = json.loads((d / "run_info.json").read_text())
    sweep_dir = results["runs"] / "benchmark/tiny/FetchReach/her"
    names = {r["seed"]: r["run"] for r in
             json.loads((sweep_dir / "summary.json").read_text())["runs"]}
    got = []
    for seed in (0, 1):
        run = meta["runs"][f"s{seed}"]
        assert run["best_policy"] == before["runs"][f"s{seed}"]["best_policy"]
        ev = run["best_policy_precise"]
        assert ev["episodes"] == 3 and ev["seed"] == profiles.PRECISE_SEED + seed
        assert ev["epoch"] == run["best_policy"]["epoch"]
        again = evaluate(sweep_dir / names[seed], episodes=3, seed=profiles.PRECISE_SEED + seed)
        assert again["success"] == ev["success"]
        got.append(ev["success"])
    row = next(r for r in read_csv(out / "benchmark/tiny/summary.csv") if r["setting"] == "her")
    assert float(row["precise_mean"]) == pytest.approx(sum(got) / 2, abs=1e-6)
    assert row["precise_seeds"] == "2" and row["precise_episodes"] == "3"
    # Kept by a collect that does not ask for it (the runs have not changed).
    assert benchmark.main([*common, "--eval-episodes", str(EVAL_EPISODES)]) == 0
    assert json.loads((d / "run_info.json").read_text())["runs"] == meta["runs"]
    # The solve profile's goal table shows it beside the retest.
    s = report.read_setting(d)
    lines = "\n".join(report._goal_lines([s]))
    assert "retest, more episodes" in lines and ", 3 episodes |" in lines
    assert "more episodes" not in "\n".join(report._goal_lines(
        [dataclasses.replace(s, meta={**s.meta, "runs": before["runs"]})]))
    assert benchmark.main([*common, "--precise-episodes", "-1"]) == 2


def test_ablation_reads_her_from_the_benchmark(results, tmp_path, capsys):
    """--her-from-benchmark: the ablation's HER curve is the benchmark's HER sweep, read and
    never run; the same program and budget as the ablation's own HER sweep, so the same rows."""
    out = tmp_path / "out"
    args = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(results["runs"]),
            "--no-progress", "--eval-episodes", "0", "--split", "--settings", "her",
            "--her-from-benchmark"]
    assert ablation.main(args) == 0
    printed = capsys.readouterr().out
    assert "read from the benchmark sweep" in printed and "start" not in printed
    got = out / "ablation/tiny/FetchReach/her"
    bench = results["out"] / "benchmark/tiny/FetchReach/her"
    own = results["out"] / "ablation/tiny/FetchReach/her"
    for seed in (0, 1):
        assert (got / f"s{seed}.csv").read_bytes() == (bench / f"s{seed}.csv").read_bytes()
        strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_time"} for r in rows]  # noqa: E731
        assert strip(read_csv(got / f"s{seed}.csv")) == strip(read_csv(own / f"s{seed}.csv"))
    meta = json.loads((got / "run_info.json").read_text())
    assert meta["kind"] == "ablation"
    assert meta["sweep"]["dir"].endswith("benchmark/tiny/FetchReach/her")


def test_borrowed_setting_read_from_the_results_when_its_sweep_is_gone(results, tmp_path,
                                                                     capsys):
    """A borrowed setting whose sweep directory is gone (checkpoints are never committed) is
    copied from the other experiment's collected results: the CSVs byte for byte, run_info.json
    relabelled as this experiment's with its source named; with no results either, nothing."""
    out = tmp_path / "out"
    shutil.copytree(results["out"] / "benchmark", out / "benchmark")
    args = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(tmp_path / "no-runs"),
            "--no-progress", "--eval-episodes", "0", "--split", "--settings", "her",
            "--her-from-benchmark"]
    assert ablation.main(args) == 0
    assert "its sweep directory is gone" in capsys.readouterr().out
    got, src = out / "ablation/tiny/FetchReach/her", out / "benchmark/tiny/FetchReach/her"
    assert sorted(p.name for p in got.iterdir()) == ["run_info.json", "s0.csv", "s1.csv"]
    for seed in (0, 1):
        assert (got / f"s{seed}.csv").read_bytes() == (src / f"s{seed}.csv").read_bytes()
    meta, orig = (json.loads((d / "run_info.json").read_text()) for d in (got, src))
    assert (meta["kind"], meta["setting"], meta["label"], meta["order"]) == \
        ("ablation", "her", "vanilla HER", 0)
    assert meta["borrowed_from"]["kind"] == "benchmark"
    assert meta["borrowed_from"]["results"].endswith("benchmark/tiny/FetchReach/her")
    assert meta["runs"] == orig["runs"] and meta["command"] == orig["command"]
    rows = {r["setting"]: r for r in read_csv(out / "ablation/tiny/summary.csv")}
    assert set(rows) == {"her"} and rows["her"]["seeds"] == "2"
    # Neither the sweep nor its results: a message, nothing written.
    shutil.rmtree(out)
    assert ablation.main(args) == 0
    assert "nothing to collect: neither the benchmark sweep" in capsys.readouterr().out
    assert not (out / "ablation/tiny/FetchReach/her").exists()


def test_a_setting_run_in_pieces_is_collected_as_one(results, tmp_path, capsys):
    """--first-seed K: seeds K..N-1 run as a sweep of their own (<sweep>.s<K>-<N-1>) beside the
    whole sweep's seeds; collecting merges them into one setting, the earlier seeds' CSVs
    unchanged, the wall clock summed over the pieces, each piece recorded."""
    runs, out = tmp_path / "runs", tmp_path / "out"
    shutil.copytree(results["runs"] / "benchmark", runs / "benchmark")  # HER's seeds 0-1
    args = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(runs), "--no-progress",
            "--eval-episodes", "0", "--algos", "her"]
    assert benchmark.main([*args, "--seeds", "3", "--first-seed", "2"]) == 0
    assert (runs / "benchmark/tiny/FetchReach/her.s2-2/sweep.yaml").is_file()
    d = out / "benchmark/tiny/FetchReach/her"
    whole = results["out"] / "benchmark/tiny/FetchReach/her"
    assert sorted(p.name for p in d.glob("s*.csv")) == ["s0.csv", "s1.csv", "s2.csv"]
    for name in ("s0.csv", "s1.csv"):
        assert (d / name).read_text() == (whole / name).read_text()
    assert [r["epoch"] for r in read_csv(d / "s2.csv")] == ["1", "2"]
    meta = json.loads((d / "run_info.json").read_text())
    assert meta["seeds"] == [0, 1, 2] and meta["sweep"]["runs"] == 3
    assert [p["runs"] for p in meta["pieces"]] == [2, 1]
    assert meta["pieces"][1]["dir"].endswith("her.s2-2")
    assert meta["wall_clock_s"] == pytest.approx(sum(p["wall_clock_s"] for p in meta["pieces"]))
    assert meta["wall_clock_per_run_s"] == pytest.approx(meta["wall_clock_s"] / 3)
    capsys.readouterr()
    assert benchmark.main([*args, "--seeds", "3", "--first-seed", "2", "--dry-run"]) == 0
    assert "finished (2 epochs)" in capsys.readouterr().out
    assert benchmark.main([*args, "--seeds", "5", "--first-seed", "3", "--dry-run"]) == 0
    line = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln][0]
    assert "'seeds=[3,4]'" in line and line.endswith("/benchmark/tiny/FetchReach/her.s3-4")
    assert benchmark.main([*args, "--seeds", "2", "--first-seed", "2", "--dry-run"]) == 2
    assert "--first-seed 2 leaves no seed" in capsys.readouterr().err
    # A collect names its seeds: with --seeds 2 the later piece (it may still be running)
    # is left out, its CSV and its wall clock with it.
    assert benchmark.main([*args, "--seeds", "2", "--collect-only"]) == 0
    assert "not collected: seed(s) 2, beyond --seeds 2" in capsys.readouterr().out
    assert sorted(p.name for p in d.glob("s*.csv")) == ["s0.csv", "s1.csv"]
    two = json.loads((d / "run_info.json").read_text())
    assert two["seeds"] == [0, 1] and "pieces" not in two
    assert two["wall_clock_s"] == pytest.approx(meta["pieces"][0]["wall_clock_s"])


def test_keep_collected_keeps_seeds_whose_sweep_directories_are_gone(results, tmp_path,
                                                                     capsys):
    """A setting run in pieces on machines that do not share a runs directory: with
    --keep-collected, seeds collected before whose sweep directory is gone stay as they were
    (CSV, run record), the new piece's seed is added, and the old piece keeps its share of the
    wall clock; without it, they are removed."""
    src = results["runs"] / "benchmark/tiny/FetchReach/her"  # seeds 0-1, one sweep
    out = tmp_path / "out"
    args = ["--profile", "tiny", "--out", str(out), "--no-progress", "--eval-episodes", "0",
            "--algos", "her", "--seeds", "2", "--collect-only"]
    first = tmp_path / "machine1"
    shutil.copytree(src, first / "benchmark/tiny/FetchReach/her")
    assert benchmark.main([*args, "--runs-dir", str(first)]) == 0
    d = out / "benchmark/tiny/FetchReach/her"
    old = json.loads((d / "run_info.json").read_text())
    s0 = (d / "s0.csv").read_bytes()
    # Another machine ran seed 1 again as a piece of its own; machine 1's directory is gone.
    second = tmp_path / "machine2"
    piece = second / "benchmark/tiny/FetchReach/her.s1-1"
    shutil.copytree(src, piece)
    shutil.rmtree(piece / "lr1_lh1_s0")
    summary = json.loads((piece / "summary.json").read_text())
    summary["runs"] = [r for r in summary["runs"] if r["seed"] == 1]
    (piece / "summary.json").write_text(json.dumps(summary))
    info = json.loads((piece / "run_info.json").read_text())
    (piece / "run_info.json").write_text(json.dumps({**info, "n_runs": 1}))
    shutil.rmtree(first)
    capsys.readouterr()
    assert benchmark.main([*args, "--runs-dir", str(second), "--keep-collected"]) == 0
    assert "kept s0, collected before from" in capsys.readouterr().out
    meta = json.loads((d / "run_info.json").read_text())
    assert (d / "s0.csv").read_bytes() == s0 and meta["runs"]["s0"] == old["runs"]["s0"]
    assert meta["seeds"] == [0, 1]
    assert [p["seeds"] for p in meta["pieces"]] == [[0], [1]]
    assert [p["runs"] for p in meta["pieces"]] == [1, 1]
    assert meta["pieces"][0]["wall_clock_s"] == pytest.approx(old["wall_clock_s"] / 2)
    assert meta["pieces"][1]["dir"].endswith("her.s1-1")
    assert meta["wall_clock_s"] == pytest.approx(sum(p["wall_clock_s"] for p in meta["pieces"]))
    assert meta["wall_clock_per_run_s"] == pytest.approx(meta["wall_clock_s"] / 2)
    # Collected again on the same machine: the kept piece stays as it is.
    assert benchmark.main([*args, "--runs-dir", str(second), "--keep-collected"]) == 0
    assert json.loads((d / "run_info.json").read_text())["pieces"] == meta["pieces"]
    # Without --keep-collected, the seed no sweep directory holds is removed.
    assert benchmark.main([*args, "--runs-dir", str(second)]) == 0
    assert sorted(p.name for p in d.glob("s*.csv")) == ["s1.csv"]
    assert json.loads((d / "run_info.json").read_text())["seeds"] == [1]


def test_a_seed_rerun_as_a_piece_is_read_from_the_piece_and_status_shows_both(results, tmp_path,
                                                                             capsys):
    """A seed held both by an abandoned whole sweep (fewer epochs) and by a piece that ran it
    again is collected from the piece; --status lists every seed with the directories that
    hold it, most epochs first, and the seeds no directory holds."""
    runs, out = tmp_path / "runs", tmp_path / "out"
    shutil.copytree(results["runs"] / "benchmark", runs / "benchmark")  # HER's seeds 0-1
    whole = runs / "benchmark/tiny/FetchReach/her"
    # Seed 1 of the whole sweep stopped after its first epoch.
    summary = json.loads((whole / "summary.json").read_text())
    for r in summary["runs"]:
        if r["seed"] == 1:
            r["epochs"] = 1
    (whole / "summary.json").write_text(json.dumps(summary))
    stale = whole / "lr1_lh1_s1/metrics.csv"
    stale.write_text("".join(stale.read_text().splitlines(keepends=True)[:2]))
    args = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(runs), "--no-progress",
            "--eval-episodes", "0", "--algos", "her"]
    assert benchmark.main([*args, "--seeds", "3", "--first-seed", "1"]) == 0
    log = capsys.readouterr().out
    assert "seed 1 is in" in log and "reading" in log and log.rstrip().count("her.s1-2") >= 1
    d = out / "benchmark/tiny/FetchReach/her"
    assert [r["epoch"] for r in read_csv(d / "s1.csv")] == ["1", "2"]
    assert (d / "s1.csv").read_text() == (runs / "benchmark/tiny/FetchReach/her.s1-2/"
                                          "lr1_lh1_s1/metrics.csv").read_text()
    assert (d / "s0.csv").read_text() == (whole / "lr1_lh1_s0/metrics.csv").read_text()
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    assert benchmark.main([*args, "--seeds", "4", "--status"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "[FetchReach her] 4 seeds x 2 epochs"
    body = [ln.split("(updated")[0].split() for ln in lines[1:]]
    assert body[0][:2] == ["s0:", "done"] and body[0][2].endswith("FetchReach/her")
    assert body[1][:2] == ["s1:", "done"] and body[1][2].endswith("her.s1-2")
    assert body[2][:3] == ["1/2", "epochs", body[2][2]] and body[2][2].endswith("FetchReach/her")
    assert body[3][:2] == ["s2:", "done"] and body[3][2].endswith("her.s1-2")
    assert body[4] == ["s3:", "missing"] and len(body) == 5
    # Only the unfinished run says how long it has left (its one epoch's pace).
    assert [("left at" in ln) for ln in lines[1:5]] == [False, False, True, False]
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before  # --status writes nothing


def test_seconds_per_epoch_is_the_median_of_the_last_epochs_across_a_resume():
    from profiles import seconds_per_epoch

    def rows(pairs):
        return [{"epoch": str(e), "wall_time": str(t)} for e, t in pairs]

    # Epoch 1 holds the compile; a resume after epoch 3 continues the cumulative clock.
    assert seconds_per_epoch(rows([(1, 60.0), (2, 70.0), (3, 81.0), (4, 93.0), (5, 103.0)])) \
        == pytest.approx(10.5)
    assert seconds_per_epoch(rows([(1, 60.0), (2, 70.0), (3, 82.0)]), last=1) == 12.0
    # A gap of several epochs or a clock that steps back is no epoch's pace.
    assert seconds_per_epoch(rows([(1, 60.0), (4, 70.0), (5, 65.0), (6, 73.0)])) == 8.0
    assert seconds_per_epoch(rows([(2, 50.0)])) == 25.0
    assert seconds_per_epoch([]) is None


def test_rerun_skips_finished_sweeps(results, capsys):
    csv_path = results["out"] / "ablation/tiny/FetchReach/her/s0.csv"
    before = csv_path.read_bytes()
    # The fixture's own command again (its best policies were not retested: --eval-episodes 0).
    assert ablation.main([*results["common"], "--eval-episodes", "0"]) == 0
    out = capsys.readouterr().out
    assert out.count("finished (2 epochs)") == 2
    assert "start" not in out and "resume" not in out
    assert csv_path.read_bytes() == before


def test_collect_only_trains_nothing(results, capsys):
    d = results["out"] / "benchmark/tiny/FetchReach/her"
    (d / "s1.csv").unlink()
    args = [*results["common"], "--algos", "her", "cher", "--collect-only"]
    assert benchmark.main(args) == 0
    out = capsys.readouterr().out
    assert "start" not in out and "resume" not in out and "[FetchReach cher] nothing to" in out
    assert (d / "s1.csv").is_file() and not (d.parent / "cher").exists()


def test_report_files(results):
    for kind, n in (("ablation", 7), ("benchmark", 2)):
        d = results["out"] / kind / "tiny"
        for name in REPORT_FILES:
            assert (d / name).is_file() and (d / name).stat().st_size > 0
        for name in REPORT_FILES[2:]:
            assert (d / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        rows = read_csv(d / "summary.csv")
        assert len(rows) == n and {r["task"] for r in rows} == {"FetchReach"}
        for r in rows:
            assert r["seeds"] == "2" and r["epochs_max"] == "2"
            for col in ("best_mean", "final_mean", "best_ci_lo", "best_ci_hi", "auc_mean"):
                assert 0.0 <= float(r[col]) <= 1.0
            assert float(r["wall_clock_s"]) > 0 and math.isfinite(float(r["bias_real"]))
        md = (d / "summary.md").read_text(encoding="utf-8")
        for head in ("## Best-policy test success", "## Per task", "## Wall clock",
                     "## Hindsight-bias diagnostic", "success_epochs.png"):
            assert head in md
        for section in ("Per task", "Hindsight-bias diagnostic"):
            text = md.split(f"## {section}", 1)[1].split("\n## ", 1)[0]
            table = [ln for ln in text.splitlines() if ln.startswith("|")]
            assert len(table) == 2 + n  # header, rule, one row per setting
            assert len({ln.count("|") for ln in table}) == 1
    bench = (results["out"] / "benchmark/tiny/summary.md").read_text(encoding="utf-8")
    assert "| FetchReach | " in bench and "(88)" in bench and "00:46:55" in bench  # Tables 2, 3
    abl = (results["out"] / "ablation/tiny/summary.md").read_text(encoding="utf-8")
    assert "vanilla HER" in abl and "`algo=her`" in abl


def test_cost_counts_each_sweep_once_and_borrowed_settings_not_at_all(results, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(results["out"], copy)
    info = {s: json.loads((copy / "ablation/tiny/FetchReach" / s / "run_info.json").read_text())
            for s in ("her", "rdher_lr1_lh2", "rdher_lr2_lh1")}
    # The λ pairs are one vmapped sweep: its wall clock once, its runs once.
    assert info["rdher_lr1_lh2"]["sweep"]["name"] == info["rdher_lr2_lh1"]["sweep"]["name"]
    pairs = info["rdher_lr1_lh2"]
    row = {(e, t): (n, r, h) for e, t, n, r, h, _ in report.cost_rows(report.profiles_data(copy))}
    cores = {s: report.cores_used(m["hardware"]) for s, m in info.items()}  # as the run saw
    assert cores["her"] == len(os.sched_getaffinity(0))
    want = (info["her"]["wall_clock_s"] * cores["her"]
            + pairs["wall_clock_s"] * cores["rdher_lr1_lh2"]) / 3600
    assert row[("ablation/tiny", "FetchReach")][:2] == (2, 2 + pairs["sweep"]["runs"])
    assert row[("ablation/tiny", "FetchReach")][2] == pytest.approx(want)
    # HER read from the benchmark: counted there, not here.
    her = copy / "ablation/tiny/FetchReach/her/run_info.json"
    her.write_text(json.dumps({**info["her"], "borrowed_from": {"kind": "benchmark"}}))
    row = {(e, t): (n, r, h) for e, t, n, r, h, _ in report.cost_rows(report.profiles_data(copy))}
    assert row[("ablation/tiny", "FetchReach")][2] == pytest.approx(
        pairs["wall_clock_s"] * cores["rdher_lr1_lh2"] / 3600)
    md = report.cost_markdown(report.profiles_data(copy))
    total = sum(h for *_, h, _ in report.cost_rows(report.profiles_data(copy)))
    assert "| **total** |  |  | " in md and f"**{total:.2f}**" in md


def test_cost_and_hardware_read_each_piece_with_its_cores(results, tmp_path):
    """A setting run in pieces on two machines: cost.md counts each piece's wall clock times the
    cores it could use (one where the record predates ``cpu_affinity``: pinned runs), and the
    hardware column names each machine with its seeds."""
    copy = tmp_path / "results"
    shutil.copytree(results["out"], copy)
    path = copy / "ablation/tiny/FetchReach/her/run_info.json"
    meta = json.loads(path.read_text())
    old = {k: v for k, v in meta["hardware"].items() if k != "cpu_affinity"}
    new = {**old, "processor": "Other CPU", "cpu_affinity": 2}
    before = {(e, t): h for e, t, _, _, h, _ in report.cost_rows(report.profiles_data(copy))}
    meta["pieces"] = [{"wall_clock_s": 3600.0, "hardware": old, "seeds": [0]},
                      {"wall_clock_s": 1800.0, "hardware": new, "seeds": [1, 2]}]
    path.write_text(json.dumps({**meta, "wall_clock_s": 5400.0}))
    rows = {(e, t): (h, cpu) for e, t, _, _, h, cpu in report.cost_rows(report.profiles_data(copy))}
    hours, cpus = rows[("ablation/tiny", "FetchReach")]
    assert hours == pytest.approx(before[("ablation/tiny", "FetchReach")]
                                  - meta["wall_clock_s"] * report.cores_used(meta["hardware"])
                                  / 3600 + 1.0 + 2 * 0.5)
    assert "Other CPU" in cpus and (old.get("processor") or "?") in cpus
    text = report.hardware({**meta, "wall_clock_s": 5400.0})
    assert "(seed 0)" in text and "Other CPU" in text and "2 of " in text and "(seeds 1, 2)" in text
    # One machine: one description, the cores it could use where they are recorded.
    one = report.hardware({"hardware": {**new, "cpu_count": 2}})
    assert one.startswith("Other CPU") and "2 of 2 CPU cores" in one and "seed" not in one
    assert "2 CPU cores" in report.hardware({"hardware": {**old, "cpu_count": 2}})


def test_host_info_records_the_usable_cores():
    from rdher_jax.outputs import host_info

    info = host_info()
    assert info["cpu_affinity"] == len(os.sched_getaffinity(0))
    assert 1 <= info["cpu_affinity"] <= info["cpu_count"]


def test_lever_cost_counts_a_continued_run_once(tmp_path):
    """cost.md's bench_learning rows: each setting's runs summed, and a run continued from
    another setting's (the same seed, its curve beginning with that run's) only for what it
    added."""
    d = tmp_path / "bench_learning"
    d.mkdir()
    first = [[2500, 10.0, 0.0], [5000, 20.0, 0.1]]
    more = [*first, [7500, 31.0, 0.2], [10000, 40.0, 0.3]]

    def write(name, results, env="FetchSlide"):
        (d / f"{name}.json").write_text(json.dumps({
            "settings": [f"env={env}", "epochs=4"], "seeds": list(results),
            "results": {str(k): {"wall_s": c[-1][1], "curve": c} for k, c in results.items()}}))

    write("short", {1: first, 2: [[2500, 7.0, 0.0]]})
    write("long", {1: more})
    write("other", {3: first}, env="FetchPush")  # same curve, another seed: its own run
    (d / "notes.json").write_text("[]")  # not a setting
    rows = {n: (t, r, h) for n, t, r, h in report.lever_cost_rows(tmp_path)}
    assert rows == {"short": ("FetchSlide", 2, pytest.approx(27.0 / 3600)),
                    "long": ("FetchSlide", 1, pytest.approx(20.0 / 3600)),
                    "other": ("FetchPush", 1, pytest.approx(20.0 / 3600))}


def test_report_regenerates_byte_identical_from_the_results_alone(results, tmp_path):
    # A copy of the results, far from the sweep directories: the report needs nothing else.
    copy = tmp_path / "results"
    shutil.copytree(results["out"], copy)
    before = {p.relative_to(copy): p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    proc = subprocess.run([sys.executable, str(EXP / "report.py"), "--results", str(copy)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("wrote ") == 9  # 2 x (2 tables, 2 figures), cost.md
    after = {p.relative_to(copy): p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    assert after.keys() == before.keys()
    for k in after:  # tables and inputs; the PNGs too, as matplotlib writes them without dates
        assert after[k] == before[k], k


def test_committed_tables_regenerate_from_the_committed_csvs(tmp_path):
    # Every summary.md / summary.csv under experiments/results is what report.py makes from the
    # committed per-run CSVs and run_info.json files (figures: regenerated, not compared, as
    # font rendering may differ between machines).
    src = EXP / "results"
    tables = sorted(p.relative_to(src) for kind in report.KINDS
                    for p in (src / kind).glob("*/summary.*") if p.suffix in (".md", ".csv"))
    if not tables:
        pytest.skip("no committed experiment results")
    copy = tmp_path / "results"
    for kind in report.KINDS:
        if (src / kind).is_dir():
            shutil.copytree(src / kind, copy / kind,
                            ignore=shutil.ignore_patterns("summary.*", "*.png"))
    (copy / "bench_learning").mkdir()
    for f in (src / "bench_learning").glob("*.json"):  # the lever runs' rows of cost.md
        shutil.copy(f, copy / "bench_learning" / f.name)
    report.write_reports(copy)
    tables.append(Path("cost.md"))
    for rel in tables:
        assert (copy / rel).read_bytes() == (src / rel).read_bytes(), \
            f"{rel} is stale: run python experiments/report.py"


def test_dry_run_plans_every_algorithm_and_task(tmp_path, capsys):
    args = ["--out", str(tmp_path / "out"), "--runs-dir", str(tmp_path / "runs"), "--dry-run"]
    assert benchmark.main(["--profile", "paper", *args]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]
    assert len(lines) == 4 * 5
    for task in profiles.TASKS:
        for algo in profiles.BENCHMARK_ALGOS:
            (ln,) = [x for x in lines if f"env={task} algo={algo} " in x]
            assert "seeds=5" in ln and "epochs=50" in ln and "lambdas" not in ln
            assert f"n_cycles={10 if task == 'FetchReach' else 50}" in ln
    assert ablation.main(["--profile", "paper", "--tasks", "FetchSlide", *args]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]
    assert len(lines) == 2
    assert "'lambdas=[[1,2],[2,1],[1,4],[4,1],[0.5,4],[4,0.5]]'" in lines[0]
    assert "algo=her" in lines[1] and "lambdas" not in lines[1]
    assert not (tmp_path / "out").exists() and not (tmp_path / "runs").exists()


def test_benchmark_settings_add_the_authors_share_as_rows(tmp_path, capsys):
    """--settings dher_f0.8 rdher_f0.8: DHER and RDHER at dher_fraction=0.8 on top of the
    profile's budget (solve: preset=fast's 0.2), each its own sweep in the benchmark's tree;
    alone they run without the five algorithms, with --algos after them."""
    args = ["--profile", "solve", "--tasks", "FetchPush", "--out", str(tmp_path / "out"),
            "--runs-dir", str(tmp_path / "runs"), "--dry-run"]
    assert benchmark.main([*args, "--settings", "dher_f0.8", "rdher_f0.8"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]
    assert len(lines) == 2
    for ln, (name, algo) in zip(lines, [("dher_f0.8", "dher"), ("rdher_f0.8", "rdher")],
                                strict=True):
        assert f" algo={algo} " in ln and "preset=fast" in ln and "dher_fraction=0.8" in ln
        assert ln.endswith(f"/benchmark/solve/FetchPush/{name}") and "seeds=5" in ln
    assert benchmark.main([*args, "--algos", "her", "--settings", "dher_f0.8"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]
    assert [ln.rsplit("/", 1)[1] for ln in lines] == ["her", "dher_f0.8"]
    assert "dher_fraction" not in lines[0]
    # Tabled after the five algorithms, beside the paper's row of their algorithm.
    rows = [{"epoch": "1", "env_steps": "2500", "wall_time": "1.0", "test_success": "0.5"}]
    data = [report.SettingData("FetchPush", n, {"label": n, "algo": a, "order": o}, {0: rows})
            for n, a, o in [("her", "her", 1), ("dher_f0.8", "dher", 5)]]
    md = report.summary_markdown("benchmark", "solve", data)
    assert "| FetchPush | 50.0 (39) | 50.0 (21) |" in md


def test_benchmark_names_the_share_where_the_profile_takes_another():
    """DHER and RDHER name their share of combined rows where the profile's budget differs
    from the authors' 0.8 (solve: preset=fast's 0.2), with RDHER's pair as its authors'-share
    row has it; where the budget keeps 0.8 they stay 'DHER' / 'RDHER'."""
    assert benchmark.algo_label("dher", "solve", "FetchPush") == "DHER, share 0.2"
    assert benchmark.algo_label("rdher", "solve", "FetchPush") == "RDHER (4, 0.5), share 0.2"
    assert benchmark.algo_label("rdher", "solve", "FetchPickAndPlace") == \
        "RDHER (2, 1), share 0.2"
    assert benchmark.algo_label("her", "solve", "FetchPush") == "HER"
    for profile, task in [("paper", "FetchSlide"), ("cpu", "FetchPush")]:
        assert [benchmark.algo_label(a, profile, task) for a in ("dher", "rdher")] == \
            ["DHER", "RDHER"]


def test_budget_lines_count_the_seeds_each_setting_has():
    """One budget line per task and budget, whatever seeds each setting was collected with;
    its count is the usual number of seeds collected, naming the settings that have another."""
    rows = [{"epoch": "1", "env_steps": "2500", "wall_time": "1.0", "test_success": "0.5"}]
    budget = {"settings": {"epochs": 200}, "note": "n"}

    def setting(name, seeds, n_budget):
        meta = {"label": name, "algo": name, "budget": {**budget, "seeds": n_budget}}
        return report.SettingData("FetchPush", name, meta, {k: rows for k in range(seeds)})

    lines = report._budget_lines([setting("her", 5, 5), setting("dher", 1, 1),
                                  setting("cher", 5, 5)])
    assert lines == ["- FetchPush: 5 seeds (dher 1), `epochs=200` (n)"]
    assert report._budget_lines([setting("her", 1, 5)]) == ["- FetchPush: 1 seed, `epochs=200` (n)"]


def test_ablation_split_is_one_sweep_per_setting(tmp_path, capsys, one_line_error):
    """--split: the same seven settings (names, labels, order, pairs), each its own sweep named
    by the setting; --settings picks some, in the order given."""
    whole = [o for *_, outs in ablation.sweeps("FetchPush") for o in outs]
    split = ablation.sweeps("FetchPush", split=True)
    assert set(whole) == {o for *_, outs in split for o in outs} and len(whole) == 7
    assert all(len(outs) == 1 and name == outs[0].name for name, _, _, outs in split)
    args = ["--profile", "paper", "--tasks", "FetchPush", "--seeds", "3", "--out",
            str(tmp_path / "out"), "--runs-dir", str(tmp_path / "runs"), "--dry-run", "--split"]
    assert ablation.main([*args, "--settings", "rdher_lr4_lh0.5", "her"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]
    assert len(lines) == 2 and "seeds=3" in lines[0] and "seeds=3" in lines[1]
    assert "algo=rdher" in lines[0] and "'lambdas=[[4,0.5]]'" in lines[0]
    assert lines[0].endswith("/ablation/paper/FetchPush/rdher_lr4_lh0.5")
    assert "algo=her" in lines[1] and lines[1].endswith("/ablation/paper/FetchPush/her")
    assert ablation.main(args) == 0
    assert len([ln for ln in capsys.readouterr().out.splitlines() if "(dry run)" in ln]) == 7
    p = subprocess.Popen([sys.executable, str(EXP / "ablation.py"), *args[:-1], "--settings",
                          "rdher_lr1_lh2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    assert "needs --split" in one_line_error(p)


def test_cpu_push_budget_is_preset_fast(tmp_path, capsys):
    args = ["--profile", "cpu", "--tasks", "FetchPush", "--out", str(tmp_path / "out"),
            "--runs-dir", str(tmp_path / "runs"), "--dry-run"]
    assert benchmark.main([*args, "--algos", "rdher"]) == 0
    (ln,) = [x for x in capsys.readouterr().out.splitlines() if "(dry run)" in x]
    assert "preset=fast" in ln and "seeds=3" in ln and "epochs=200" in ln
    assert benchmark.main([*args, "--epochs", "3", "--algos", "rdher"]) == 0
    (ln,) = [x for x in capsys.readouterr().out.splitlines() if "(dry run)" in x]
    assert "epochs=3" in ln


def test_moving_goals_plans_each_setting_with_its_own_keys(tmp_path, capsys):
    args = ["--profile", "cpu", "--tasks", "FetchPushMoving", "--out", str(tmp_path / "out"),
            "--runs-dir", str(tmp_path / "runs"), "--dry-run", "--settings", "her", "dher_plain",
            "dher_f0.2"]
    assert moving_goals.main(args) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if "(dry run)" in x]
    assert len(lines) == 3
    for ln in lines:
        assert "env=FetchPushMoving" in ln and "preset=fast" in ln and "epochs=100" in ln
        assert "seeds=3" in ln
    assert "algo=her" in lines[0] and "replay_k" not in lines[0] and "grid" not in lines[0]
    assert "algo=dher" in lines[1] and "replay_k=0" in lines[1]
    assert "'grid.dher_fraction=[0.2]'" in lines[2]
    sweep_dir = tmp_path / "runs" / "moving" / "cpu" / "FetchPushMoving" / "dher_f0.2"
    assert f"sweep_dir={sweep_dir}" in lines[2]
    # A task without a budget in the profile is a one-line error, exit 2.
    assert moving_goals.main(["--profile", "tiny", "--tasks", "FetchPushMoving", "--dry-run",
                              "--runs-dir", str(tmp_path / "runs")]) == 2
    assert "profile tiny has no budget for FetchPushMoving" in capsys.readouterr().err


def test_ablation_reads_the_papers_pair_from_the_benchmark(tmp_path, capsys, one_line_error):
    args = ["--profile", "paper", "--tasks", "FetchSlide", "FetchPickAndPlace", "--seeds", "3",
            "--out", str(tmp_path / "out"), "--runs-dir", str(tmp_path / "runs"), "--dry-run",
            "--split", "--pick-from-benchmark", "--settings", "rdher_lr4_lh0.5",
            "rdher_lr2_lh1"]
    assert ablation.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    # Slide's pick is (4, 0.5), PickAndPlace's (2, 1): read; the other pair of each: run.
    read = [ln for ln in lines if "read from the benchmark sweep" in ln]
    run = [ln for ln in lines if "(dry run)" in ln]
    assert [ln.split("]")[0] for ln in read] == ["[FetchSlide rdher", "[FetchPickAndPlace rdher"]
    assert "/benchmark/paper/FetchSlide/rdher (run by benchmark.py" in read[0]
    assert len(run) == 2 and "'lambdas=[[2,1]]'" in run[0] and "env=FetchSlide" in run[0]
    assert "'lambdas=[[4,0.5]]'" in run[1] and "env=FetchPickAndPlace" in run[1]
    p = subprocess.Popen([sys.executable, str(EXP / "ablation.py"), "--profile", "paper",
                          "--dry-run", "--pick-from-benchmark"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert "--pick-from-benchmark needs --split" in one_line_error(p)


def test_beyond_plans_each_setting_with_its_own_keys(tmp_path, capsys):
    args = ["--profile", "cpu", "--out", str(tmp_path / "out"), "--runs-dir",
            str(tmp_path / "runs"), "--dry-run", "--settings", "her", "rdher", "rdher_f0.2",
            "rdher_f0.2_lr2_lh1", "rdher_plain", "dher_f0.2"]
    assert beyond.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    read = [ln for ln in lines if "read from the benchmark sweep" in ln]
    assert [ln.split("]")[0] for ln in read] == ["[FetchPush her", "[FetchPush rdher"]
    run = {ln.split("]")[0][len("[FetchPush "):]: ln for ln in lines if "(dry run)" in ln}
    assert list(run) == ["rdher_f0.2", "rdher_f0.2_lr2_lh1", "rdher_plain", "dher_f0.2"]
    for name, ln in run.items():
        # The benchmark's budget (preset=fast, sequential, 500,000 steps, 3 seeds), one value
        # per key: a setting's own dher_fraction replaces the budget's 0.8 in place.
        assert "env=FetchPush" in ln and "preset=fast" in ln and "epochs=200" in ln
        assert "overlap=False" in ln and "seeds=3" in ln and ln.count("dher_fraction=") == 1
        assert ln.endswith(f"/beyond/cpu/FetchPush/{name}")
    assert "algo=rdher" in run["rdher_f0.2"] and "dher_fraction=0.2" in run["rdher_f0.2"]
    assert "lambdas" not in run["rdher_f0.2"]
    assert "'lambdas=[[2,1]]'" in run["rdher_f0.2_lr2_lh1"]
    assert "dher_fraction=0.8" in run["rdher_plain"] and "replay_k=0" in run["rdher_plain"]
    assert "algo=dher" in run["dher_f0.2"] and "dher_fraction=0.2" in run["dher_f0.2"]
    assert not (tmp_path / "out").exists() and not (tmp_path / "runs").exists()


def test_windows_of_a_moving_goal_table():
    # Two seeds of 5 epochs of 100 steps: windows (0, 200], (200, 400], (400, 500].
    rows = {s: [{"env_steps": str(100 * (i + 1)), "test_success": str(v)}
                for i, v in enumerate(vals)]
            for s, vals in {0: [0.0, 0.2, 0.4, 0.6, 1.0], 1: [0.2, 0.2, 0.6, 0.6, 0.8]}.items()}
    s = report.SettingData("FetchPushMoving", "her", {}, rows)
    (n0, w0), (n1, w1), (n2, w2) = report.windows(s)
    assert (n0, n1, n2) == ("0-200 steps", "200-400 steps", "400-500 steps")
    assert math.isclose(w0.mean, (0.1 + 0.2) / 2) and w0.n == 2
    assert math.isclose(w1.mean, (0.5 + 0.6) / 2)
    assert math.isclose(w2.mean, 0.9) and math.isclose(w2.std, math.sqrt(0.02))


def _declared_options(script: str) -> set[str]:
    """The --options a script's source (and the profiles' common arguments it adds) declare."""
    src = (EXP / script).read_text(encoding="utf-8")
    if "add_common_args(" in src:
        src += (EXP / "profiles.py").read_text(encoding="utf-8")
    return set(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"", src))


@pytest.mark.parametrize("script", ["ablation.py", "benchmark.py", "report.py",
                                    "moving_goals.py", "beyond.py"])
def test_help(script):
    """--help names the script's own command and documents every option it declares, and a
    wrong option is a usage error (exit 2), not a run."""
    proc = subprocess.run([sys.executable, str(EXP / script), "--help"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"usage: python experiments/{script}"), proc.stdout[:200]
    options = _declared_options(script)
    assert options, script
    missing = sorted(o for o in options if o not in proc.stdout)
    assert not missing, f"{script} --help does not list {missing}"
    bad = subprocess.run([sys.executable, str(EXP / script), "--no-such-option"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "error:" in bad.stderr and "Traceback" not in bad.stderr


def test_statistics():
    st = report.stat([0.5, 0.7, 0.9])
    assert math.isclose(st.mean, 0.7) and math.isclose(st.std, 0.2)
    # t(0.975, 2) in closed form: F(t) = 1/2 + t / (2 sqrt(2 + t^2)) inverts to
    # (2F - 1) / sqrt(2F(1 - F)) = 0.95 / sqrt(0.04875) = 4.302653.
    half = 0.95 / math.sqrt(0.04875) * 0.2 / math.sqrt(3)
    assert math.isclose(st.lo, 0.7 - half) and math.isclose(st.hi, 0.7 + half)
    # t(0.975, 1) = tan(0.475 pi) = 12.706205 (Cauchy): 0.3 +- 12.706205 * 0.1 / sqrt(2).
    two = report.stat([0.2, 0.4])
    half = math.tan(0.475 * math.pi) * math.sqrt(0.02) / math.sqrt(2)
    assert math.isclose(two.lo, 0.3 - half) and math.isclose(two.hi, 0.3 + half)
    assert report.ci(st) == "[20.3, 100.0]"  # clipped to [0, 100]
    one = report.stat([0.4])
    assert one.n == 1 and math.isnan(one.std) and report.pm(one) == "40.0 (1 seed)"
    assert report.hms(3 * 3600 + 53 * 60 + 16) == "03:53:16"
    # Welch by hand: [1, 2, 3] vs [4, 5, 6, 7]: se = sqrt(1/3 + (5/3)/4) = sqrt(0.75),
    # t = -3.5 / 0.866 = -4.04, df = 0.5625 / ((1/3)^2/2 + (5/12)^2/3) = 4.96, p = 0.0102.
    diff, p = report.welch([1, 2, 3], [4, 5, 6, 7])
    assert diff == -3.5 and 0.0095 < p < 0.0110
    assert report.vs_cell(diff / 100, p) == "-3.5 (p 0.01)"
    assert math.isnan(report.welch([1, 1], [2, 2])[1]) and math.isnan(report.welch([1], [2, 3])[1])
    assert report.vs_cell(math.nan, math.nan) == "-"
    # a tie whose float difference rounds from below zero is +0.0, not -0.0
    assert report.vs_cell(0.3 - 0.1 - 0.2, 1.0) == "+0.0 (p 1)"
    assert (report.n_seeds(1), report.n_seeds(3)) == ("1 seed", "3 seeds")
    # The same rates reached by two summation orders of float32 successes are one rate: a
    # paired test of equal finals has no variance (p nan), not a p of the rounding noise.
    f32 = [float(np.float32(v)) for v in (0.1, 0.3, 0.2)]
    same = {0: 0.0, 1: 0.1, 2: sum(f32) / 3}
    other = {0: 0.0, 1: float(np.float32(0.1)), 2: float(np.float32(0.2))}
    assert same[2] != other[2]
    diff, p, n = report.paired(same, other)
    assert n == 3 and math.isnan(p) and report.vs_cell(diff, p) == "+0.0"
    assert math.isnan(report.welch([0.2, 0.2], [f32[2], sum(f32) / 3])[1])
    diff, p, _ = report.paired({0: 0.1, 1: 0.2, 2: 0.4}, {0: 0.1, 1: 0.1, 2: 0.2})
    assert math.isclose(diff, 0.1) and 0.1 < p < 0.5  # a real difference still tests


def test_beyond_labels_name_each_tasks_own_paper_pair():
    """A setting at the paper's pair is labelled with the task's pair, which differs by task."""
    sweeps = profiles.named_sweeps(beyond.SETTINGS, ["rdher", "rdher_f0.2", "dher_f0.2"])
    for task, pair in (("FetchSlide", "(4, 0.5)"), ("FetchPickAndPlace", "(2, 1)")):
        labels = [s.label for *_, settings, _extra, _borrow in sweeps(task) for s in settings]
        assert labels[:2] == [f"RDHER {pair}, share 0.8 (the authors')",
                              f"RDHER {pair}, share 0.2"], labels
        assert labels[2] == "DHER, share 0.2"


def _setting_dir(root, name, finals, best_policy=None):
    """A setting's results directory with one CSV per seed: test success 0 for two epochs, then
    ``final`` for three (so best = final = the mean of the last 3, and the mean over all epochs
    is 3/5 of it)."""
    d = root / "benchmark/paper/FetchPush" / name
    d.mkdir(parents=True)
    runs = {}
    for seed, final in enumerate(finals):
        rows = ["epoch,test_success", "1,0", "2,0"] + [f"{e},{final}" for e in (3, 4, 5)]
        (d / f"s{seed}.csv").write_text("\n".join(rows) + "\n")
        if best_policy is not None:
            runs[f"s{seed}"] = {"best_policy": {"success": best_policy[seed], "episodes": 100}}
    (d / "run_info.json").write_text(json.dumps({"runs": runs}))
    return d


def test_against_her_paired_by_seed(tmp_path):
    """The summaries' 'Against HER, paired by seed' section: per measure the mean per-seed
    difference with scipy's paired t-test, over the seeds both settings hold, and the seeds a
    paired test needs for 80% power (fewer where the differences vary less)."""
    from scipy import stats as sps

    her = report.read_setting(_setting_dir(tmp_path, "her", [0.5, 0.7, 0.4, 0.6],
                                           best_policy=[0.5, 0.6, 0.4, 0.7]))
    a = report.read_setting(_setting_dir(tmp_path, "a", [0.9, 0.8, 1.0],
                                         best_policy=[0.85, 0.8, 0.95]))
    vs = report.vs_her_paired(a, [her, a])
    assert report.vs_her_paired(her, [her, a]) is None
    for k, xs, ys in (("final", [0.9, 0.8, 1.0], [0.5, 0.7, 0.4]),
                      ("policy", [0.85, 0.8, 0.95], [0.5, 0.6, 0.4])):
        diff, p, n, need = vs[k]
        assert n == 3 and math.isclose(diff, sum(xs) / 3 - sum(ys) / 3)
        assert math.isclose(p, sps.ttest_rel(xs, ys).pvalue)
        d = [x - y for x, y in zip(xs, ys, strict=True)]
        assert need == report.seeds_for_power(sum(d) / 3, float(np.std(d, ddof=1)), None)
        assert 2 <= need < 10
    md = "\n".join(report._paired_lines([her, a]))
    assert "## Against HER, paired by seed" in md
    diff, p, _, need = vs["final"]
    assert f"| {report.vs_cell(diff, p)} | {need:.0f} |" in md
    assert report._paired_lines([a]) == []  # no HER on the task: no section
    assert "within one SE of 5%" in md


def test_near_significance_is_one_standard_error_short_of_the_threshold():
    """Table 2's rule (3 seeds, 5 where the difference is within one standard error of
    significance): |t| at least t_crit - 1 and p not below 5%, checked against t itself."""
    from scipy import stats as sps

    crit = float(sps.t.ppf(0.975, 2))  # 3 seeds
    just_in = 2 * float(sps.t.sf(crit - 0.99, 2))
    just_out = 2 * float(sps.t.sf(crit - 1.01, 2))
    assert report.near_significance(just_in, 3)
    assert not report.near_significance(just_out, 3)
    assert not report.near_significance(0.01, 3)  # significant already: no more seeds
    assert not report.near_significance(0.5, 1) and not report.near_significance(math.nan, 3)
    # More seeds, a lower threshold: the same p can be near at 5 seeds and not at 3.
    assert report.near_significance(0.1, 5) and not report.near_significance(0.1, 3)


def test_compare_is_welch_between_any_two_settings(tmp_path, capsys, one_line_error):
    from scipy import stats as sps

    a = _setting_dir(tmp_path, "a", [0.9, 0.8, 1.0], best_policy=[0.85, 0.8, 0.95])
    b = _setting_dir(tmp_path, "b", [0.5, 0.7, 0.4, 0.6])
    assert report.main(["--compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "| benchmark/paper/FetchPush/a | 3 | 90.0 ± 10.0 | 86.7 ± 7.6 | 90.0 ± 10.0 | " \
        "54.0 ± 6.0 |" in out
    assert "| benchmark/paper/FetchPush/b | 4 | 55.0 ± 12.9 | - |" in out
    p_final = sps.ttest_ind([0.9, 0.8, 1.0], [0.5, 0.7, 0.4, 0.6], equal_var=False).pvalue
    p_mean = sps.ttest_ind([0.54, 0.48, 0.6], [0.3, 0.42, 0.24, 0.36], equal_var=False).pvalue
    row = next(ln for ln in out.splitlines() if ln.startswith("| benchmark/paper/FetchPush/a −"))
    assert row == (f"| benchmark/paper/FetchPush/a − benchmark/paper/FetchPush/b | "
                   f"+35.0 (p {p_final:.2g}) | - | +35.0 (p {p_final:.2g}) | "
                   f"+21.0 (p {p_mean:.2g}) |")
    # Paired by seed, over the 3 seeds both hold (b's seed 3 has no partner).
    pp_final = sps.ttest_rel([0.9, 0.8, 1.0], [0.5, 0.7, 0.4]).pvalue
    pp_mean = sps.ttest_rel([0.54, 0.48, 0.6], [0.3, 0.42, 0.24]).pvalue
    rows = [ln for ln in out.splitlines() if ln.startswith("| benchmark/paper/FetchPush/a −")]
    assert len(rows) == 2 and rows[1] == (
        f"| benchmark/paper/FetchPush/a − benchmark/paper/FetchPush/b | 3 | "
        f"+36.7 (p {pp_final:.2g}) | - | +36.7 (p {pp_final:.2g}) | +22.0 (p {pp_mean:.2g}) |")
    # Not a setting's directory, or only one: a one-line error and exit 2.
    for args, why in (([a, tmp_path], "no run_info.json"), ([a], "at least two")):
        p = subprocess.Popen([sys.executable, str(EXP / "report.py"), "--compare",
                              *map(str, args)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        assert why in one_line_error(p)


def test_bench_gpu_target_rule_and_bad_input(capsys):
    """bench_gpu.py's target check (bench_learning.first_hit's trailing mean of 3 epochs, the
    trainer's stop_success rule), and a bad stage name is a one-line error with exit status 2."""
    import bench_gpu  # noqa: PLC0415

    rows = [{"epoch": str(i + 1), "env_steps": str(1000 * (i + 1)),
             "wall_time": str(10.0 * (i + 1)), "test_success": str(s)}
            for i, s in enumerate([0.2, 1.0, 1.0, 0.8, 1.0, 0.9, 1.0])]
    # 3-epoch means ending at epochs 3..7: 0.733, 0.933, 0.933, 0.9, 0.967
    assert bench_gpu.first_hit(rows, 0.95, 3)["window"] == {"epoch": 7, "env_steps": 7000,
                                                            "wall_s": 70.0}
    assert bench_gpu.first_hit(rows, 0.9, 3)["window"]["epoch"] == 4
    assert bench_gpu.first_hit(rows, 0.9, 3)["single"]["epoch"] == 2
    assert "window" not in (bench_gpu.first_hit(rows[:2], 0.1, 3) or {})  # under 3 epochs
    assert bench_gpu.main(["--stages", "reach,nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: unknown stage 'nope'") and "\n" not in err


def test_bench_learning_resume_passes_only_resumable_settings(tmp_path, monkeypatch):
    """A run bench_learning continues gets the settings a resume may change (a longer budget,
    a policy choice), not the ones its config fixed (those would be refused)."""
    import bench_learning  # noqa: PLC0415

    calls = []
    monkeypatch.setattr(bench_learning.subprocess, "run", lambda argv, **kw: calls.append(argv))
    (tmp_path / "config.yaml").write_text("env: FetchSlide\n")
    (tmp_path / "metrics.csv").write_text("epoch,env_steps,test_success\n1,2500,0.0\n")
    bench_learning.run_seed(tmp_path, 1, ["env=FetchSlide", "layers=2", "epochs=400",
                                          "select_top=5"], retest=100)
    (argv,) = calls
    assert argv[3:] == [f"resume={tmp_path}", "epochs=400", "select_top=5", "progress=false",
                        "retest=100"]


def test_bench_learning_hits_agree_with_the_stop_rule(tmp_path):
    """A success rate is a float32 ratio of counts: 7/10, 10/10, 10/10 average a hair under
    0.9, and the trainer's stop_success (outputs.reached_stop) counts it as 0.9; so does
    bench_learning, and --retabulate rewrites a table whose hits were found without it."""
    import bench_learning  # noqa: PLC0415

    from rdher_jax.config import parse_args  # noqa: PLC0415
    from rdher_jax.outputs import reached_stop  # noqa: PLC0415

    succ = [float(np.float32(k / 10)) for k in (2, 5, 7, 10, 10)]
    assert sum(succ[2:]) / 3 < 0.9  # the trap itself
    rows = [{"epoch": i + 1, "env_steps": 1000 * (i + 1), "wall_time": 10.0 * (i + 1),
             "test_success": s} for i, s in enumerate(succ)]
    assert bench_learning.first_hit(rows, 0.9, 3)["window"]["epoch"] == 5
    cfg = parse_args(["stop_success=0.9", "stop_window=3"])
    assert reached_stop(cfg, [succ], [0]) and not reached_stop(cfg, [succ[:4]], [0])
    # a table written before: no window hit recorded; --retabulate finds it from the curve
    data = {"settings": ["env=FetchPush"], "seeds": [0], "note": "",
            "results": {"0": {"epochs": 5, "env_steps": 5000, "wall_s": 50.0, "best": 1.0,
                              "hits": {"0.5": None, "0.9": None},
                              "curve": [[r["env_steps"], r["wall_time"], r["test_success"]]
                                        for r in rows]}}}
    (tmp_path / "old.json").write_text(json.dumps(data))
    (tmp_path / "old.md").write_text("")
    assert bench_learning.retabulate(tmp_path, 3) == ["old"]
    assert "| 5,000 steps, 0.8 min |" in (tmp_path / "old.md").read_text()
    assert bench_learning.retabulate(tmp_path, 3) == []  # nothing left to change
    # the summary's 'to 0.8, mean of 3' (Slide's goal) is found on the curve, hits or not
    succ = [float(np.float32(k / 10)) for k in (8, 8, 8, 9, 9, 9)]
    data["results"]["0"]["curve"] = [[1000 * (i + 1), 10.0 * (i + 1), s]
                                     for i, s in enumerate(succ)]
    (tmp_path / "old.json").write_text(json.dumps(data))
    bench_learning.retabulate(tmp_path, 3)
    row = bench_learning.summary(tmp_path, 3).splitlines()[-1]
    assert row.endswith("| 6,000 steps, 1.0 min | 3,000 steps, 0.5 min | - |"), row


def test_floor_expected_best_epoch_matches_simulation():
    """floor.py's expected best of E epochs (E[max of E Binomial(n, p)] / n, from the CDF)
    against a direct simulation of never-learning runs."""
    import floor  # noqa: PLC0415

    rng = np.random.default_rng(0)
    for p, n, epochs in [(0.055, 10, 50), (0.055, 20, 50), (0.3, 10, 5), (0.0, 10, 50)]:
        sim = rng.binomial(n, p, size=(40_000, epochs)).max(axis=1).mean() / n
        assert floor.expected_best(p, n, epochs) == pytest.approx(sim, abs=0.004)
    assert floor.expected_best(1.0, 10, 3) == pytest.approx(1.0)


def test_bench_harness_rotates_the_order_and_takes_medians():
    """harness.Bench: every group once per repeat, each in an order rotated by the repeat; the
    time kept is per call (over ``per``), its median, and paired ratios per repeat."""
    import harness  # noqa: PLC0415

    now, calls = [0.0], []
    cost = {"a": [5, 1, 3, 2], "b": [2, 2, 8, 4], "c": [9, 9, 9, 9], "x": [1, 1, 1, 1]}

    def fn(name):
        def f():
            k = len([c for c in calls if c == name]) - 1  # the compile call is call 0
            now[0] += cost[name][k] if k >= 0 else 100.0
            calls.append(name)
        return f

    bench = harness.Bench(log=None, clock=lambda: now[0])
    bench.add("a", fn("a"))
    bench.add("b", fn("b"), per=2)
    bench.add("c", fn("c"))
    bench.add("x", fn("x"), group="other")
    assert calls == ["a", "b", "c", "x"] and bench.compile_s["a"] == 100.0
    calls.clear()
    calls.extend(["a", "b", "c", "x"])  # keep each name's call count for the costs
    bench.run(4)
    assert calls[4:] == ["a", "b", "c", "x", "b", "c", "a", "x",
                         "c", "a", "b", "x", "a", "b", "c", "x"]
    assert bench.times["a"] == [5, 1, 3, 2] and bench.times["b"] == [1, 1, 4, 2]
    assert bench.med("a") == 2.5 and bench.best("a") == 1 and bench.med("b") == 1.5
    assert bench.ratios("b", "a") == [0.2, 1.0, 4 / 3, 1.0] and bench.ratio("b", "a") == 1.0
    assert bench.ratios(["a", "b"], "c")[2] == 7 / 9
    assert harness.rotated(["p", "q", "r"], 4) == ["q", "r", "p"]
    sp = harness.spread([4.0, 1.0, 3.0, 2.0])
    assert sp["median"] == 2.5 and sp["best"] == 1.0 and (sp["q1"], sp["q3"]) == (1.75, 3.25)
    got = harness.interleave(["u", "v"], 3, lambda n: n.upper())
    assert got == {"u": ["U", "U", "U"], "v": ["V", "V", "V"]}


def test_bench_harness_stamps_each_call_and_the_gaps_between_calls():
    """harness.Stamps: the time inside each call of the wrapped function and between one call's
    end and the next one's start, gaps across two groups of calls left out; harness.seconds
    times one call; harness.versions names a missing package None."""
    import harness  # noqa: PLC0415

    now = [0.0]

    def step(dt, out):
        now[0] += dt
        return out

    stamps = harness.Stamps(step, clock=lambda: now[0])
    assert math.isnan(stamps.mean_call()) and math.isnan(stamps.mean_gap())
    # Two groups of three calls: inside 1, 2, 3 | 4, 5, 6; between them 10, 20 | 30, 40 and
    # 100 from the first group's last call to the second's first.
    for inside, before in [(1, 0), (2, 10), (3, 20), (4, 100), (5, 30), (6, 40)]:
        now[0] += before
        assert stamps(inside, out=inside) == inside
    assert stamps.durations() == [1, 2, 3, 4, 5, 6] and stamps.mean_call() == 3.5
    assert stamps.gaps() == [10, 20, 100, 30, 40] and stamps.mean_gap() == 40
    assert stamps.gaps(group=3) == [10, 20, 30, 40] and stamps.mean_gap(3) == 25
    assert stamps.gaps(group=1) == [] and math.isnan(stamps.mean_gap(1))
    stamps.clear()
    assert stamps.durations() == [] and stamps.gaps() == []
    stamps(7, None)
    assert stamps.durations() == [7] and stamps.gaps() == []
    assert harness.seconds(step, 2.5, None, clock=lambda: now[0]) == 2.5
    got = harness.versions(("numpy", "no-such-package-rdher"))
    assert got == {"numpy": np.__version__, "no-such-package-rdher": None}


def test_bench_harness_writes_the_same_figures_to_markdown_and_json(tmp_path):
    import harness  # noqa: PLC0415

    rows = [{"case": "one", "ms": 1.25}, {"case": "two", "ms": 30.5}]
    text = harness.write_results(
        tmp_path / "sub" / "bench_x.md", "A title",
        ["`python experiments/bench_x.py` on a machine.",
         harness.table(["case", "ms"], [(r["case"], f"{r['ms']:.2f}") for r in rows])],
        {"rows": rows}, command="python experiments/bench_x.py", host={"cpu_count": 2},
        echo=False)
    md = (tmp_path / "sub" / "bench_x.md").read_text()
    data = json.loads((tmp_path / "sub" / "bench_x.json").read_text())
    assert md == text and md.startswith("# A title\n\n`python experiments/bench_x.py`")
    assert "| case | ms |\n|---|---|\n| one | 1.25 |\n| two | 30.50 |\n" in md
    assert data == {"command": "python experiments/bench_x.py", "host": {"cpu_count": 2},
                    "rows": rows}
    ap = harness.parser("bench_x.py", "d", repeats=3, quick="small", limits=True)
    a = ap.parse_args(["--quick"])
    assert (a.repeats, a.quick, a.limits_script) == (3, True, None)
    assert a.out == harness.RESULTS / "bench_x.md"
    assert harness.command("bench_x.py", ["--out", "/tmp/a/b.md", "k=v w"]) == (
        "python experiments/bench_x.py --out b.md 'k=v w'")


@pytest.mark.parametrize("script", ["bench_backends", "bench_cycle", "bench_envs", "bench_gpu",
                                    "bench_gpu_warp", "bench_overlap",
                                    "bench_processes", "bench_relabel", "bench_start",
                                    "bench_sweep", "bench_train", "bench_xla_flags"])
def test_bench_scripts_import_without_side_effects(script, monkeypatch):
    """Host devices and XLA flags are start-up's (rdher_jax.startup.setup, in main): importing a
    benchmark script changes no environment variable."""
    import importlib  # noqa: PLC0415
    import os  # noqa: PLC0415

    import jax  # noqa: F401, PLC0415  (its own import sets TF_CPP_MIN_LOG_LEVEL and, with no TPU,
    # TPU_SKIP_MDS_QUERY: not the script's doing; without this the test depends on the order)

    before = dict(os.environ)
    importlib.import_module(script)
    assert dict(os.environ) == before
    proc = subprocess.run([sys.executable, str(EXP / f"{script}.py"), "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and f"usage: python experiments/{script}.py" in proc.stdout


def test_bench_processes_layouts_interleaved_and_written(tmp_path, monkeypatch):
    """bench_processes.py: the three layouts in rotated order per repeat, medians in the table
    and the JSON, and the two-device child asks for its devices as start-up does."""
    import bench_processes  # noqa: PLC0415

    from rdher_jax import startup  # noqa: PLC0415

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    two = bench_processes.env(2)
    assert two["JAX_NUM_CPU_DEVICES"] == "2" and "XLA_FLAGS" not in two
    assert "JAX_NUM_CPU_DEVICES" not in bench_processes.env()
    launched = []

    def timed(cmds, envs):
        launched.append((len(cmds), envs[0].get("JAX_NUM_CPU_DEVICES")))
        return {(1, None): 10.0, (2, None): 6.0, (1, "2"): 8.0}[launched[-1]] + len(launched)

    monkeypatch.setattr(bench_processes, "timed", timed)
    monkeypatch.setattr(startup, "setup", lambda s: None)  # this process is set up already
    out = tmp_path / "bench_processes.md"
    bench_processes.main(["--repeats", "2", "--runs", "2", "--epochs", "1", "--out", str(out)])
    assert launched == [(1, None), (2, None), (1, "2"), (2, None), (1, "2"), (1, None)]
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["seconds"] == {"1 process, 1 core": [11.0, 16.0],
                               "2 processes, 1 core each": [8.0, 10.0],
                               "1 process, 2 cores, 2 devices": [11.0, 13.0]}
    assert "| 2 processes, 1 core each | 9.0 | 1.50x |" in out.read_text()


def test_bench_harness_machine_limits(tmp_path):
    """--limits-script: the script's table and the figures it writes to --json; a failing one
    stops the benchmark."""
    import harness  # noqa: PLC0415

    ok = tmp_path / "limits.py"
    ok.write_text("import json, sys\nprint('| core | 1.0 |')\n"
                  "json.dump({'gflops': 2.5}, open(sys.argv[sys.argv.index('--json') + 1], 'w'))\n")
    lim = harness.machine_limits(str(ok))
    assert (lim["script"], lim["table"], lim["figures"]) == ("limits.py", "| core | 1.0 |",
                                                             {"gflops": 2.5})
    assert harness.machine_limits(None) is None
    bad = tmp_path / "bad.py"
    bad.write_text("raise SystemExit(3)\n")
    with pytest.raises(subprocess.CalledProcessError):
        harness.machine_limits(str(bad))


def test_solve_profile_runs_the_tasks_recipe_and_budget(tmp_path):
    """The solve profile's sweeps are preset=fast with each task's own values (its budget: Push
    500,000 env steps, PickAndPlace 600,000, Slide 2,000,000), as ``train env=<task>
    preset=fast`` runs them but sequential, and parse as sweeps."""
    from rdher_jax import sweep
    from rdher_jax.config import episode_length, parse_args, resolve

    jobs = profiles.make_jobs("benchmark", "solve", profiles.SOLVE_TASKS, tmp_path, None, None,
                              lambda task: [("her", "her", None, ())])
    steps = {"FetchPush": 500_000, "FetchPickAndPlace": 600_000, "FetchSlide": 2_000_000}
    assert [j.task for j in jobs] == list(steps)
    for job in jobs:
        plan = sweep.parse_sweep_args(profiles.sweep_args(job, False)[0]).plan
        cfg = plan.base
        assert (cfg.epochs * cfg.n_cycles * cfg.num_envs * episode_length(cfg)
                == steps[job.task]) and job.seeds == 5 and not cfg.overlap
        one = resolve(parse_args([f"env={job.task}", "preset=fast", "overlap=false",
                                  "progress=false"]))
        assert dataclasses.replace(cfg, run_dir=None, seed=0) == dataclasses.replace(
            one, run_dir=None, seed=0), job.task
def test_bench_gpu_warp_runs_tiny_on_a_cpu(tmp_path):
    """The device check (experiments/bench_gpu_warp.py) at tiny sizes on this CPU, so that it
    cannot rot between the rare runs on a GPU: every stage ends and leaves its figures."""
    from rdher_jax.envs import warp_available  # noqa: PLC0415

    if warp_available():
        pytest.skip(warp_available())
    out = tmp_path / "gpu.md"
    proc = subprocess.run([sys.executable, str(EXP / "bench_gpu_warp.py"), "--tiny", "--out",
                           str(out)], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(out.with_suffix(".json").read_text())
    env, push = res["stages"]["env"], res["stages"]["push"]
    assert env["end"] == "ok" and push["end"] == "ok", (env["end"], push["end"])
    assert [r["batch"] for r in env["rows"].values()] == [4, 8, 16]
    assert all(r["steps_per_s"] > 0 and r["compile_s"] > 0 for r in env["rows"].values())
    assert push["compile_s"] > 0 and len(push["epochs"]) == 1
    assert push["epochs"][0]["env_steps"] == 4 * 50
    assert "Warp env steps" in out.read_text()


def test_pool_runs_each_seed_pinned_to_a_core_as_the_sweep_would(results, tmp_path, capsys):
    """--cores: each seed a one-seed piece in a process of its own pinned to a listed core
    (seed 0 in ``<sweep>``, seed 1 in ``<sweep>.s1-1``), lowest seed first across the
    settings, then collected; each seed's rows are
    the vmapped sweep's; the same command again runs nothing; a core this process may not use,
    or an unfinished sweep of several seeds where a piece would go, is a one-line error."""
    core = min(os.sched_getaffinity(0))
    out, runs = tmp_path / "out", tmp_path / "runs"
    args = ["--profile", "tiny", "--out", str(out), "--runs-dir", str(runs), "--no-progress",
            "--eval-episodes", "0", "--algos", "her", "--cores", str(core)]
    # lowest seed first across the settings, so matching seeds run side by side
    assert benchmark.main([*args[:-3], "her", "ddpg", "--cores", str(core), "--dry-run"]) == 0
    plan = [ln.split("]")[0] for ln in capsys.readouterr().out.splitlines() if ln.startswith("[")]
    assert plan == ["[FetchReach her s0", "[FetchReach ddpg s0", "[FetchReach her s1",
                    "[FetchReach ddpg s1"]
    assert benchmark.main(args) == 0
    printed = capsys.readouterr().out
    assert "pool: 2 one-seed piece(s)" in printed and printed.count(": done in") == 2
    # collected as its last piece ended (before the final collect of every setting)
    assert printed.index(": done in", printed.index(": done in") + 1) < \
        printed.index("[FetchReach her] collected") < printed.rindex("[FetchReach her] collected")
    task = runs / "benchmark/tiny/FetchReach"
    assert yaml_seeds(task / "her") == [0] and yaml_seeds(task / "her.s1-1") == [1]
    assert (task / "her.log").is_file() and (task / "her.s1-1.log").is_file()
    for seed in (0, 1):  # a run of its own against the vmapped sweep: equal to float rounding
        mine = read_csv(out / f"benchmark/tiny/FetchReach/her/s{seed}.csv")
        assert len(mine) == 2
        assert_same_rows(mine, read_csv(results["out"] /
                                        f"benchmark/tiny/FetchReach/her/s{seed}.csv"))
    assert benchmark.main(args) == 0
    assert "pool: 0 one-seed piece(s)" in capsys.readouterr().out
    # another machine: the sweep directories are gone, the collected results are not; with
    # --keep-collected the collected seeds are done, without it they would run again
    runs.rename(tmp_path / "runs.gone")
    assert benchmark.main([*args, "--keep-collected", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "pool: 0 one-seed piece(s)" in printed
    assert "[FetchReach her] seed(s) 0, 1 collected in" in printed
    assert benchmark.main([*args, "--dry-run"]) == 0
    assert "pool: 2 one-seed piece(s)" in capsys.readouterr().out
    (tmp_path / "runs.gone").rename(runs)
    bad = max(os.sched_getaffinity(0)) + 1
    assert benchmark.main([*args[:-1], str(bad)]) == 2
    assert f"--cores {bad}: this process may run on" in capsys.readouterr().err
    assert benchmark.main([*args, "--collect-only"]) == 2
    assert "not with --adopt, --status, --collect-only" in capsys.readouterr().err
    whole = runs / "benchmark/tiny/FetchReach/ddpg"
    whole.mkdir(parents=True)
    (whole / "sweep.yaml").write_text("seeds:\n- 0\n- 1\n")
    assert benchmark.main([*args[:-3], "ddpg", "--cores", str(core)]) == 2
    assert "not a one-seed piece" in capsys.readouterr().err


def yaml_seeds(d):
    return profiles.yaml_seeds(d / "sweep.yaml")
