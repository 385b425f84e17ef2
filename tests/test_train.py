"""The trainer: traced once, resumable after SIGKILL, stops on NaN, learns FetchReach."""

import csv
import dataclasses
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from rdher_jax import train as train_mod
from rdher_jax.checkpoint import Checkpointer
from rdher_jax.config import Config, resolve

TINY = dict(env="FetchReach", n_cycles=2, n_batches=4, batch_size=32, buffer_size=2000,
            num_envs=2, n_test_rollouts=2, hidden=32, progress=False)
TINY_ARGS = [f"{k}={v}" for k, v in TINY.items()]


def tiny_cfg(tmp_path, **kw) -> Config:
    return resolve(Config(**{**TINY, "run_dir": str(tmp_path / "run"), **kw}))


def read_csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_epoch_traces_once(tmp_path):
    cfg = tiny_cfg(tmp_path, epochs=3)
    env, trainer = train_mod.build(cfg)
    traces = []

    def epoch(ts, hp):
        traces.append(1)  # runs only while tracing
        return trainer.epoch(ts, hp)

    f = jax.jit(epoch)
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), trainer.hparams)
    for _ in range(3):
        ts, m = f(ts, trainer.hparams)
    assert len(traces) == 1
    assert int(ts.epoch) == 3
    assert int(m.env_steps) == 3 * cfg.n_cycles * cfg.num_envs * env.episode_length
    assert int(m.updates) == 3 * cfg.n_cycles * cfg.n_batches
    assert int(ts.buffer.num_episodes) == 3 * cfg.n_cycles * cfg.num_envs


def _cli(args, **kw):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "rdher_jax.train", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_resume_after_sigkill_equals_uninterrupted(tmp_path):
    args = [*TINY_ARGS, "epochs=8", "n_cycles=4", "n_batches=16", "seed=3"]
    ref = _cli([*args, f"run_dir={tmp_path / 'ref'}"])
    killed_dir = tmp_path / "killed"
    victim = _cli([*args, f"run_dir={killed_dir}"])
    latest = killed_dir / "checkpoints" / "latest"
    deadline = time.time() + 600
    while time.time() < deadline and victim.poll() is None:
        # Complete steps are plain integer directories (orbax renames them into place).
        steps = [int(p.name) for p in latest.glob("*") if p.name.isdigit()]
        if max(steps, default=0) >= 2:
            break
        time.sleep(0.01)
    assert victim.poll() is None, "the run ended before it could be killed"
    victim.send_signal(signal.SIGKILL)
    victim.wait()
    rows_at_kill = read_csv(killed_dir / "metrics.csv")
    assert 2 <= len(rows_at_kill) < 8
    resumed = _cli([f"resume={killed_dir}"])
    out, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    assert "resuming" in out
    ref_out, ref_err = ref.communicate(timeout=600)
    assert ref.returncode == 0, ref_err
    a, b = read_csv(tmp_path / "ref" / "metrics.csv"), read_csv(killed_dir / "metrics.csv")
    assert len(a) == len(b) == 8
    for ra, rb in zip(a, b, strict=True):
        ra.pop("wall_time"), rb.pop("wall_time")
        assert ra == rb


def test_nan_loss_stops_run_and_keeps_last_checkpoint(tmp_path, monkeypatch):
    real_build = train_mod.build

    def build(cfg):
        env, trainer = real_build(cfg)

        def epoch(ts, hp):
            ts, m = trainer.epoch(ts, hp)
            poison = jax.numpy.where(ts.epoch >= 2, jax.numpy.nan, 0.0)
            return ts, m.replace(critic_loss=m.critic_loss + poison)

        return env, trainer._replace(epoch=epoch)

    monkeypatch.setattr(train_mod, "build", build)
    cfg = tiny_cfg(tmp_path, epochs=4)
    with pytest.raises(train_mod.TrainingDiverged, match="critic_loss.*epoch 2.*epoch 1"):
        train_mod.train(cfg)
    assert len(read_csv(Path(cfg.run_dir) / "metrics.csv")) == 1
    assert Checkpointer(cfg.run_dir, read_only=True).latest_epoch() == 1


def test_cli_errors_exit_2_with_one_line():
    for args in (["foo=1"], ["env=FetchPull"], ["epochs=-3"], ["num_envs=two"], ["epochs"]):
        p = _cli(args)
        out, err = p.communicate(timeout=120)
        assert p.returncode == 2, (args, err)
        lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
        assert len(lines) == 1, err
    p = _cli(["--help"])
    out, _ = p.communicate(timeout=120)
    assert p.returncode == 0
    for field in dataclasses.fields(Config):
        assert field.name in out


def test_run_outputs_and_evaluate(tmp_path):
    from rdher_jax.evaluate import evaluate

    cfg = tiny_cfg(tmp_path, epochs=2)
    out = train_mod.train(cfg)
    run = Path(out["run_dir"])
    for name in ("config.yaml", "metrics.csv", "success.png", "run_info.json"):
        assert (run / name).stat().st_size > 0
    rows = read_csv(run / "metrics.csv")
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    r = evaluate(run, episodes=4)
    assert 0.0 <= r["success"] <= 1.0 and r["episodes"] == 4 and r["backend"] == "mujoco"


def test_fetch_reach_her_learns(tmp_path):
    """FetchReach with HER reaches >= 0.9 test success within 5,000 env steps (5 epochs of
    10 cycles x 2 episodes x 50 steps) for this seed; the whole run is deterministic."""
    cfg = resolve(Config(env="FetchReach", epochs=5, buffer_size=100_000, n_test_rollouts=20,
                         run_dir=str(tmp_path / "reach"), progress=False))
    train_mod.train(cfg)
    rows = read_csv(Path(cfg.run_dir) / "metrics.csv")
    best = max(float(r["test_success"]) for r in rows)
    assert int(rows[-1]["env_steps"]) == 5000
    assert best >= 0.9, [r["test_success"] for r in rows]
    assert np.isfinite([float(r["critic_loss"]) for r in rows]).all()


def test_vmapped_hparams_equal_separate_runs(tmp_path):
    """The epoch function vmaps over seeds x hyperparameters (the sweep axis) and gives the
    same results as separate runs: what makes one compiled program per sweep possible."""
    cfg = tiny_cfg(tmp_path, epochs=1)
    _, trainer = train_mod.build(cfg)
    hp = trainer.hparams
    hps = jax.tree.map(lambda x: jax.numpy.stack([x, x]), hp)
    hps = hps.replace(ddpg=hps.ddpg.replace(critic_lr=jax.numpy.array([1e-3, 3e-3]),
                                            lambda_r=jax.numpy.array([1.0, 2.0])))
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    vts = jax.jit(jax.vmap(trainer.init))(keys, hps)
    vts, vm = jax.jit(jax.vmap(trainer.epoch))(vts, hps)
    init, epoch = jax.jit(trainer.init), jax.jit(trainer.epoch)
    for i in range(2):
        hp_i = jax.tree.map(lambda x, i=i: x[i], hps)
        ts, m = epoch(init(keys[i], hp_i), hp_i)
        np.testing.assert_allclose(vm.critic_loss[i], m.critic_loss, rtol=1e-4)
        np.testing.assert_allclose(vm.test_success[i], m.test_success)
        # Batched matmuls round differently from unbatched ones: equal to float tolerance.
        np.testing.assert_allclose(vts.buffer.obs[i][: cfg.n_cycles * 2],
                                   ts.buffer.obs[: cfg.n_cycles * 2], atol=1e-4)
    assert not np.allclose(vm.critic_loss[0], vm.critic_loss[1])
