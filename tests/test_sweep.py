"""The sweep: lambda pairs x seeds as one program, equal to separate runs, sharded, resumable."""

import copy
import csv
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import assert_same_rows

from rdher_jax import driver, executor, outputs
from rdher_jax import sweep as sweep_mod
from rdher_jax import train as train_mod
from rdher_jax.config import Config, resolve

# rdher: the runs differ in the DDPG hyperparameters and in the relabelling parameters.
TINY = dict(env="FetchReach", algo="rdher", n_cycles=2, n_batches=4, batch_size=32,
            buffer_size=2000, num_envs=2, n_test_rollouts=2, hidden=32, progress=False,
            epochs=3, checkpoint_every=2)
TINY_ARGS = [f"{k}={v}" for k, v in TINY.items()]
LAMBDAS = "lambdas=[[1,1],[2,0.5]]"
RUNS = ["lr1_lh1_s0", "lr1_lh1_s1", "lr2_lh0.5_s0", "lr2_lh0.5_s1"]
PAIRS_SEEDS = [(1, 1, 0), (1, 1, 1), (2, 0.5, 0), (2, 0.5, 1)]


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def run_sweep(sweep_dir, *extra, **kw):
    spec = sweep_mod.parse_sweep_args([*TINY_ARGS, LAMBDAS, "seeds=2",
                                       f"sweep_dir={sweep_dir}", *extra]).plan
    kw.setdefault("log", lambda *a: None)
    return sweep_mod.sweep(spec, **kw)


def _popen(args, **kw):
    return subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


@pytest.fixture(scope="module")
def ref(tmp_path_factory):
    """An uninterrupted 2 x 2 sweep on one device, in this process; meanwhile the same sweep
    on three host devices in a subprocess."""
    root = tmp_path_factory.mktemp("ref")
    env = {**os.environ, "JAX_NUM_CPU_DEVICES": "3"}
    sharded = _popen(["rdher_jax.sweep", *TINY_ARGS, LAMBDAS, "seeds=2",
                      f"sweep_dir={root / 'sharded'}"], env=env)
    try:
        out = run_sweep(root / "sweep")
        yield {"dir": root / "sweep", "out": out, "sharded": (sharded, root / "sharded")}
    finally:
        if sharded.poll() is None:
            sharded.kill()
            sharded.wait()


def _finished(proc):
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, (proc.args, err[-3000:])
    return out


def test_sweep_outputs(ref):
    d, out = ref["dir"], ref["out"]
    assert out.names == RUNS and out.diverged == {}
    for name in ("summary.csv", "summary.md", "summary.json", "sweep.yaml",
                 "base_config.yaml", "run_info.json"):
        assert (d / name).stat().st_size > 0
    assert [p.name for p in (d / "checkpoints" / "latest").iterdir()] == ["3"]
    for run in RUNS:
        for name in ("config.yaml", "run_info.json", "metrics.csv", "success.png"):
            assert (d / run / name).stat().st_size > 0
        assert [int(r["epoch"]) for r in read_csv(d / run / "metrics.csv")] == [1, 2, 3]
        assert not (d / run / "checkpoints" / "latest").exists()  # the sweep holds it
    from rdher_jax.evaluate import evaluate

    r = evaluate(d / RUNS[3], episodes=2)
    assert r["epoch"] >= 1 and 0.0 <= r["success"] <= 1.0


def test_summary_rows(ref):
    d = ref["dir"]
    rows = read_csv(d / "summary.csv")
    assert [r["run"] for r in rows] == RUNS
    assert [(float(r["lambda_r"]), float(r["lambda_h"]), int(r["seed"])) for r in rows] == [
        (1.0, 1.0, 0), (1.0, 1.0, 1), (2.0, 0.5, 0), (2.0, 0.5, 1)]
    for r in rows:
        m = read_csv(d / r["run"] / "metrics.csv")
        tests = [float(x["test_success"]) for x in m]
        assert float(r["best_test_success"]) == max(tests)
        assert float(r["final_test_success"]) == tests[-1]
        assert int(r["env_steps"]) == int(m[-1]["env_steps"]) == 3 * 2 * 2 * 50
        assert int(r["epochs"]) == 3 and r["status"] == "ok"
    for pair in (rows[:2], rows[2:]):
        best = [float(r["best_test_success"]) for r in pair]
        for r in pair:
            assert int(r["setting_seeds"]) == 2
            assert math.isclose(float(r["setting_best_mean"]), np.mean(best))
            assert math.isclose(float(r["setting_best_std"]), np.std(best, ddof=1), abs_tol=1e-12)
    md = (d / "summary.md").read_text()
    assert "| 1 | 1 | 2 |" in md and "| 2 | 0.5 | 2 |" in md
    assert all(f"| {run} |" in md for run in RUNS)


def test_sweep_equals_separate_train_runs(ref, tmp_path):
    """The vmapped sweep gives each run the metrics a separate ``train`` run gives it (each
    built from its own config, so a per-run value that bypassed the hyperparameters, which the
    sweep takes from its first run, would show here)."""
    for run, (lr, lh, seed) in zip(RUNS, PAIRS_SEEDS, strict=True):
        cfg = resolve(Config(**{**TINY, "lambda_r": lr, "lambda_h": lh, "seed": seed,
                                "run_dir": str(tmp_path / run)}))
        train_mod.train(cfg, log=lambda *a: None)
        assert_same_rows(read_csv(ref["dir"] / run / "metrics.csv"),
                         read_csv(tmp_path / run / "metrics.csv"))


def test_sharded_sweep_equals_unsharded(ref):
    """Three host devices, each stepping its own runs (and making its own physics callbacks);
    the 4 runs are padded to 6 with copies of the first."""
    proc, sharded = ref["sharded"]
    out = _finished(proc)
    assert "shard_map over mesh ('runs',) of 3 devices, 2 runs per device, padded from 4" in out
    for run in RUNS:
        assert_same_rows(read_csv(ref["dir"] / run / "metrics.csv"),
                         read_csv(sharded / run / "metrics.csv"))


class Interrupted(Exception):
    pass


def test_resume_equals_uninterrupted(ref, tmp_path, monkeypatch):
    """A sweep stopped after epoch 3's rows but before its checkpoint (the last one is after
    epoch 2) resumes from epoch 2 and ends exactly as the uninterrupted sweep."""
    d = ref["dir"]
    real = outputs.Checkpointer.save_latest

    def stop_at_3(self, epoch, state, meta):
        if epoch == 3:
            raise Interrupted
        return real(self, epoch, state, meta)

    monkeypatch.setattr(outputs.Checkpointer, "save_latest", stop_at_3)
    with pytest.raises(Interrupted):
        run_sweep(tmp_path / "s")
    monkeypatch.undo()
    assert len(read_csv(tmp_path / "s" / RUNS[0] / "metrics.csv")) == 3
    spec = sweep_mod.parse_sweep_args([f"resume={tmp_path / 's'}"]).plan
    logs = []
    out = sweep_mod.sweep(spec, log=logs.append)
    assert logs == [f"resuming {tmp_path / 's'} after epoch 2"]
    assert out.names == RUNS
    for run in RUNS:
        assert_same_rows(read_csv(d / run / "metrics.csv"),
                         read_csv(tmp_path / "s" / run / "metrics.csv"), exact=True)
    a, b = read_csv(d / "summary.csv"), read_csv(tmp_path / "s" / "summary.csv")
    assert a == b


def _poison(monkeypatch, which):
    """Make the losses of runs ``which`` NaN from epoch 2 on, around the cached program (no
    new compilation: the ref sweep's program is reused)."""
    import jax.numpy as jnp

    real = executor.executor_for

    def executor_for(runs, devices=None, vmapped=True):
        env, trainer, prog = real(runs, devices, vmapped)
        poisoned = copy.copy(prog)

        def epoch(ts, hps):
            ts, m = prog.epoch(ts, hps)
            hit = jnp.isin(jnp.arange(len(m.critic_loss)), jnp.array(which)) & (ts.epoch >= 2)
            return ts, m.replace(critic_loss=jnp.where(hit, jnp.nan, m.critic_loss))

        poisoned.epoch = epoch
        return env, trainer, poisoned

    monkeypatch.setattr(driver, "executor_for", executor_for)


def test_a_diverged_run_stops_alone(ref, tmp_path, monkeypatch):
    _poison(monkeypatch, [1])
    logs = []
    out = run_sweep(tmp_path / "s", log=logs.append)
    assert out.diverged == {RUNS[1]: 2}
    assert any(ln.startswith(f"{RUNS[1]}: critic_loss became non-finite in epoch 2") for ln in logs)
    for run in RUNS:
        epochs = [int(r["epoch"]) for r in read_csv(tmp_path / "s" / run / "metrics.csv")]
        assert epochs == ([1] if run == RUNS[1] else [1, 2, 3])
    status = {r["run"]: r["status"] for r in read_csv(tmp_path / "s" / "summary.csv")}
    assert status == {**dict.fromkeys(RUNS, "ok"), RUNS[1]: "diverged in epoch 2"}


def test_all_runs_diverged_stops_the_sweep(ref, tmp_path, monkeypatch):
    _poison(monkeypatch, [0, 1, 2, 3])
    with pytest.raises(train_mod.TrainingDiverged, match="every run.*epoch 2.*No checkpoint"):
        run_sweep(tmp_path / "s")


@pytest.mark.parametrize("args, fragment", [
    (["lambdas=[[1,1],[1]]"], "is not a pair of numbers"),
    (["lambdas=[1,2]"], "write lambdas=[[1,2]]"),
    (["lambdas=[[1,-1]]"], "must be finite and >= 0"),
    (["lambdas=[[1,1],[1,1]]"], "duplicate runs"),
    (["lambdas=[[1,1"], "cannot parse lambdas"),
    (["lambdas=[]"], "must be a list of"),
    (["lambdas=[[1,1]]", "lambda_r=2"], "not both"),
    (["seeds=0"], "seeds must be a positive count"),
    (["seeds=two"], "seeds must be a positive count"),
    (["seeds=[1,1]"], "duplicate runs"),
    (["seeds=[1,2]", "seed=3"], "not both"),
    (["lamdas=[[1,1]]"], "unknown key 'lamdas' (did you mean lambdas?)"),
    (["epochs=-1"], "epochs must be a positive integer"),
    (["run_dir=x"], "pass sweep_dir="),
    (["sweep_dir=/proc/x"], "cannot create sweep_dir"),
    (["sweep_dir="], "non-empty path"),
    (["resume=/proc/x"], "does not exist"),
    (["nokey"], "expected key=value"),
])
def test_bad_arguments_are_one_line_errors(args, fragment, capsys, tmp_path):
    own_dir = any(a.startswith(("sweep_dir=", "resume=")) for a in args)
    with pytest.raises(SystemExit) as e:
        sweep_mod.main(args if own_dir else [*args, f"sweep_dir={tmp_path / 'x'}"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and fragment in err, err
    assert not (tmp_path / "x").exists()


def test_bad_sweep_dirs(ref, tmp_path, capsys):
    d = ref["dir"]
    (tmp_path / "file").write_text("")
    cases = [([f"sweep_dir={tmp_path / 'file'}"], "not a directory"),
             ([f"sweep_dir={d}"], "not empty; pass resume="),
             ([f"resume={d / RUNS[0]}"], "has no sweep.yaml"),
             ([f"resume={d}", "seeds=3"], "holds seeds [0, 1], asked for [0, 1, 2]"),
             ([f"resume={d}", "hidden=64"], "cannot change hidden")]
    for args, fragment in cases:
        with pytest.raises(SystemExit) as e:
            sweep_mod.main(args)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("\n") == 1 and fragment in err, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_cli_error_and_help():
    p = subprocess.run([sys.executable, "-m", "rdher_jax.sweep", "seeds=0"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr.startswith("error: ") and p.stderr.count("\n") == 1
    p = subprocess.run([sys.executable, "-m", "rdher_jax.sweep", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0
    for key in [*sweep_mod.SWEEP_KEYS, "lambda_r", "checkpoint_every", "algo"]:
        assert f"  {key}" in p.stdout

