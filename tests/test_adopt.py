"""``experiments/benchmark.py --adopt``: a run of its own becomes one seed's sweep piece.

Is a one-seed sweep the same program as a ``train`` run of the same config and seed? Not bit
for bit: the sweep's epoch is ``vmap`` over one run and the run's is not, and XLA rounds the
two differently (on the tiny FetchReach run, seed 1, the first epoch's actor loss, mean Q and
bias columns differ in the 7th significant digit; the step counts and successes agree). So an
adopted piece is checked as follows: its adopted epoch is the run's, byte for byte, and the
epoch the benchmark then trains on from it agrees with the run continued by itself to within
the tolerance of ``tests/test_sweep.py``'s sweep-against-train check (rtol 1e-3, atol 1e-5),
for the same reason: the same learning, rounded by two programs.
"""

import csv
import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from rdher_jax import adopt as adopt_mod
from rdher_jax import sweep as sweep_mod
from rdher_jax import train as train_mod
from rdher_jax.config import ALGO_NAMES, FIELD_NAMES, Config, resolve

EXP = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXP))

import benchmark  # noqa: E402
import profiles  # noqa: E402
from helpers import assert_same_rows  # noqa: E402

TINY = [f"{k}={v}" for k, v in profiles.TINY.settings.items()]
PIECE = "benchmark/tiny/FetchReach/her.s1-1"
RUN = "lr1_lh1_s1"
quiet = lambda *a, **k: None  # noqa: E731


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def train(run_dir, *args):
    argv = ["env=FetchReach", "algo=her", *TINY, "progress=false", *args, f"run_dir={run_dir}"]
    train_mod.train(train_mod.parse_train_args(argv), argv, log=quiet)


def bench(runs, out, *extra):
    return benchmark.main(["--profile", "tiny", "--algos", "her", "--seeds", "2",
                           "--first-seed", "1", "--runs-dir", str(runs), "--out", str(out),
                           "--no-progress", "--eval-episodes", "0", *extra])


def tree(d):
    """The paths under ``d``, each checkpoint step a leaf (orbax's files inside it aside), but
    the ``.lock`` a process that drove it leaves (runlog.DirLock: not content)."""
    out = set()
    for p in d.rglob("*"):
        parts = p.relative_to(d).parts
        if parts == (".lock",):
            continue
        cut = next((i for i, x in enumerate(parts) if x.isdigit()), None)
        out.add("/".join(parts if cut is None else (*parts[:cut], "<step>")))
    return out


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Seed 1 trained for 1 epoch as a run of its own, adopted as piece s1 of the tiny
    benchmark and resumed there to its 2 epochs; beside it the same run continued by itself,
    and the piece as the benchmark runs it."""
    root = tmp_path_factory.mktemp("adopt")
    single = root / "single"
    train(single, "seed=1", "epochs=1")
    shutil.copytree(single, root / "source")  # as adopted, for the refusal tests
    runs, out = root / "runs", root / "out"
    assert bench(runs, out, "--adopt", str(single)) == 0
    shutil.copytree(runs / PIECE, root / "adopted")  # the piece as adopting wrote it
    assert bench(runs, out) == 0  # resumed to the profile's 2 epochs, and collected
    shutil.copytree(single, root / "continued")
    argv = [f"resume={root / 'continued'}", "epochs=2", "progress=false"]
    train_mod.train(train_mod.parse_train_args(argv), argv, log=quiet)
    assert bench(root / "direct-runs", root / "direct-out") == 0
    return {"root": root, "single": single, "runs": runs, "out": out,
            "adopted": root / "adopted", "piece": runs / PIECE,
            "direct": root / "direct-runs" / PIECE, "direct_out": root / "direct-out"}


def test_adopted_piece_has_the_sweep_layout(made):
    """What adopting writes is what the benchmark's own sweep of that seed holds: the same
    files, the latest state with a run axis of length 1 (the sweep's unpadded run axis) and
    the run's own arrays, the configs of a sweep run with --epochs 1; the source named."""
    from rdher_jax.checkpoint import Checkpointer

    adopted, direct = made["adopted"], made["direct"]
    assert tree(adopted) == tree(direct)
    e, state, meta = Checkpointer(adopted, read_only=True, best=False).restore_latest(None)
    _, ref, ref_meta = Checkpointer(direct, read_only=True, best=False).restore_latest(None)
    _, own, own_meta = Checkpointer(made["root"] / "source", read_only=True).restore_latest(None)
    assert e == 1 and meta["runs"] == ref_meta["runs"] == [RUN]
    assert {k: v for k, v in meta.items() if k != "runs"} == \
        {k: v for k, v in own_meta.items() if k != "runs"}
    import jax

    shapes = lambda t: jax.tree.map(lambda x: (x.shape, x.dtype), t)  # noqa: E731
    assert shapes(state) == shapes(ref)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(own), strict=True):
        assert a.shape == (1, *b.shape) and np.array_equal(a[0], b, equal_nan=True)
    for f in ("base_config.yaml", f"{RUN}/config.yaml"):
        got, want = ((d / f).read_text().splitlines() for d in (adopted, direct))
        diff = [(a, b) for a, b in zip(got, want, strict=True) if a != b]
        assert [a.split(":")[0] for a, _ in diff] == ["epochs", "run_dir"], diff
        assert dict(diff)["epochs: 1"] == "epochs: 2"
    assert (adopted / "sweep.yaml").read_text() == (direct / "sweep.yaml").read_text()
    info = json.loads((adopted / "run_info.json").read_text())
    ref_info = json.loads((direct / "run_info.json").read_text())
    assert set(info) == set(ref_info) | {"adopted"}
    assert info["adopted"]["from"] == str(made["single"].resolve())
    assert info["adopted"]["epochs"] == 1
    assert info["adopted"]["command"].startswith("python -m rdher_jax.train")
    assert info["state_bytes_per_run"] == ref_info["state_bytes_per_run"]
    assert info["n_padded"] == ref_info["n_padded"] == 1
    assert info["command"].startswith("python -m rdher_jax.sweep ")
    assert " epochs=1 " in info["command"]
    run_info = json.loads((adopted / RUN / "run_info.json").read_text())
    assert run_info["run"] == RUN and run_info["sweep_dir"].endswith(PIECE)
    summary = json.loads((adopted / "summary.json").read_text())["runs"]
    assert [(r["run"], r["epochs"], r["seed"]) for r in summary] == [(RUN, 1, 1)]


def test_adopted_piece_resumes_and_is_collected(made):
    """The benchmark resumes the adopted piece to the profile's epochs: its first epoch is
    the run's, byte for byte; its second is the run continued by itself, and the benchmark's
    own piece, to the rounding of the two programs. Collected like any piece."""
    rows = read_csv(made["piece"] / RUN / "metrics.csv")
    single = read_csv(made["single"] / "metrics.csv")
    assert [r["epoch"] for r in rows] == ["1", "2"]
    assert rows[0] == single[0]
    assert_same_rows(rows, read_csv(made["root"] / "continued" / "metrics.csv"))
    assert_same_rows(rows, read_csv(made["direct"] / RUN / "metrics.csv"))
    collected = made["out"] / "benchmark/tiny/FetchReach/her"
    assert (collected / "s1.csv").read_text() == (made["piece"] / RUN / "metrics.csv").read_text()
    meta = json.loads((collected / "run_info.json").read_text())
    assert meta["seeds"] == [1] and meta["runs"]["s1"]["epochs"] == 2
    assert meta["sweep"]["adopted"]["from"] == str(made["single"].resolve())
    got = read_csv(made["out"] / "benchmark/tiny/summary.csv")
    want = read_csv(made["direct_out"] / "benchmark/tiny/summary.csv")
    assert len(got) == len(want) == 1 and got[0].keys() == want[0].keys()
    for k, v in want[0].items():
        if k.startswith("wall_clock"):
            continue
        try:
            np.testing.assert_allclose(float(got[0][k]), float(v), rtol=1e-3, atol=1e-5,
                                       equal_nan=True, err_msg=k)
        except ValueError:  # a label
            assert got[0][k] == v, k


@pytest.mark.parametrize("edit, fragments", [
    ({"batch_size": "64", "n_critics": "2"}, ["batch_size: 64 -> 32", "n_critics: 2 -> 1"]),
    ({"epochs": "3"}, ["epochs: 3 -> 2"]),
    ({"seed": "0"}, ["seed: 0 -> 1"]),
])
def test_another_program_is_refused(made, tmp_path, capsys, edit, fragments):
    """A run whose config differs in a key that matters (or has more epochs than the
    profile's): one line naming each differing key, exit 2, nothing written."""
    src = tmp_path / "src"
    shutil.copytree(made["root"] / "source", src)
    text = (src / "config.yaml").read_text()
    for k, v in edit.items():
        text = "\n".join(f"{k}: {v}" if ln.split(":")[0] == k else ln
                         for ln in text.splitlines()) + "\n"
    (src / "config.yaml").write_text(text)
    capsys.readouterr()
    assert bench(tmp_path / "runs", tmp_path / "out", "--adopt", str(src)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: cannot adopt") and "\n" not in err
    assert "not the same program" in err and all(f in err for f in fragments), err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "out").exists()


def test_an_existing_piece_is_never_overwritten(made, capsys):
    before = {p: p.read_bytes() for p in made["piece"].rglob("*") if p.is_file()}
    capsys.readouterr()
    assert bench(made["runs"], made["out"], "--adopt", str(made["root"] / "source")) == 2
    err = capsys.readouterr().err
    assert "exists; adopting never overwrites" in err and str(made["piece"]) in err
    assert {p: p.read_bytes() for p in made["piece"].rglob("*") if p.is_file()} == before


def test_a_run_past_its_checkpoint_is_refused(made, tmp_path, capsys):
    """metrics.csv past the latest checkpoint: the run is still training, or stopped between
    the two."""
    src = tmp_path / "src"
    shutil.copytree(made["root"] / "source", src)
    text = (src / "metrics.csv").read_text()
    (src / "metrics.csv").write_text(text + text.splitlines()[-1].replace("1,", "2,", 1) + "\n")
    capsys.readouterr()
    assert bench(tmp_path / "runs", tmp_path / "out", "--adopt", str(src)) == 2
    assert "ends at epoch 2 and its latest checkpoint at 1" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_a_failure_midway_leaves_nothing(made, tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(adopt_mod.summary, "write", boom)  # the last file written
    runs = tmp_path / "runs"
    with pytest.raises(RuntimeError, match="disk full"):
        bench(runs, tmp_path / "out", "--adopt", str(made["root"] / "source"))
    task_dir = runs / "benchmark/tiny/FetchReach"
    assert task_dir.is_dir() and list(task_dir.iterdir()) == []


def test_allowed_differences():
    base = resolve(Config(algo="her", seed=1, epochs=2, run_dir="a"))
    same = lambda **kw: adopt_mod.differences(dataclasses.replace(base, **kw), base)  # noqa: E731
    assert same(epochs=1, run_dir="b", progress=False, dher_fraction=0.2, preset="fast") == []
    assert same(epochs=3) == ["epochs: 3 -> 2"]
    assert same(seed=2, gamma=0.9) == ["seed: 2 -> 1", "gamma: 0.9 -> 0.98"]
    dher = dataclasses.replace(base, algo="dher")
    assert adopt_mod.differences(dataclasses.replace(dher, dher_fraction=0.2), dher) == \
        ["dher_fraction: 0.2 -> 0.8"]


def _sans_wall(rows):
    return [{k: v for k, v in r.items() if k != "wall_time"} for r in rows]


@pytest.mark.parametrize(  # her in the default suite, the others with -m slow (8 s each)
    "algo", [a if a == "her" else pytest.param(a, marks=pytest.mark.slow) for a in ALGO_NAMES
             if "dher_fraction" in adopt_mod.unused_keys(Config(algo=a))])
def test_dher_fraction_is_unused_without_dher(algo, tmp_path):
    """Two runs that differ only in dher_fraction (one sweep, grid.dher_fraction) give the
    same metrics under every algorithm that adopting lets it differ for."""
    argv = ["env=FetchReach", f"algo={algo}", *TINY, "epochs=1", "progress=false",
            "grid.dher_fraction=[0.8,0.2]", f"sweep_dir={tmp_path / 'sweep'}"]
    out = sweep_mod.sweep(sweep_mod.parse_sweep_args(argv).plan, argv, log=quiet)
    a, b = (tmp_path / "sweep" / n for n in out.names)
    assert [resolve(Config()).dher_fraction, 0.2] == [
        float(ln.split(": ")[1]) for d in (a, b) for ln in (d / "config.yaml").read_text()
        .splitlines() if ln.startswith("dher_fraction:")]
    assert _sans_wall(read_csv(a / "metrics.csv")) == _sans_wall(read_csv(b / "metrics.csv"))


def test_preset_is_unused_once_expanded(tmp_path):
    """A run with preset=fast and one with preset=null and the preset's values written out:
    the same config but for the preset's name, and the same metrics."""
    argv = ["env=FetchReach", "algo=her", *TINY, "epochs=1", "progress=false", "preset=fast",
            "overlap=false", "select_top=1", "retest=0"]
    a = train_mod.parse_train_args([*argv, f"run_dir={tmp_path / 'a'}"])
    b = dataclasses.replace(a, preset=None, run_dir=str(tmp_path / "b"))
    assert [k for k in FIELD_NAMES if getattr(a, k) != getattr(b, k)] == ["preset", "run_dir"]
    assert a.n_critics == 1 and a.policy_delay == 2  # the preset's values, in both
    for cfg in (a, b):
        train_mod.train(cfg, log=quiet)
    assert _sans_wall(read_csv(tmp_path / "a/metrics.csv")) == \
        _sans_wall(read_csv(tmp_path / "b/metrics.csv"))


def test_every_unused_key_is_tested():
    """The keys adopting lets differ as unused are those the two tests above train on."""
    assert set().union(*(adopt_mod.unused_keys(Config(algo=a)) for a in ALGO_NAMES)) == \
        {"preset", "dher_fraction"}
