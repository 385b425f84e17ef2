"""The trainer: traced once, resumable after SIGKILL, stops on NaN, learns FetchReach."""

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from rdher_jax import executor, outputs, policy_test
from rdher_jax import train as train_mod
from rdher_jax.checkpoint import Checkpointer
from rdher_jax.config import Config, parse_args, resolve

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
    env, trainer = executor.build(cfg)
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


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs a process that may use two cores")
def test_one_core_and_every_core_give_the_same_rows(tmp_path):
    """A seed's rows do not depend on how many cores the process may use (the physics' and
    XLA's thread pools are sized from the affinity mask): the learner at its full size
    (preset=fast on FetchPush, 256-wide networks, batches of 256) trained pinned to one core and
    on every core. The solve study mixes both layouts (runs pinned one per core, and runs alone
    on the machine)."""
    args = ["env=FetchPush", "preset=fast", "epochs=1", "n_cycles=2", "n_batches=8",
            "n_test_rollouts=2", "progress=false", "seed=5"]
    every = os.sched_getaffinity(0)
    one = {min(every)}
    procs = {name: _cli([*args, f"run_dir={tmp_path / name}"],
                        preexec_fn=lambda cores=cores: os.sched_setaffinity(0, cores))
             for name, cores in (("one", one), ("every", every))}
    for p in procs.values():
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    a, b = (read_csv(tmp_path / name / "metrics.csv") for name in procs)
    assert len(a) == len(b) == 1
    for ra, rb in zip(a, b, strict=True):
        ra.pop("wall_time"), rb.pop("wall_time")
        assert ra == rb
    infos = [json.loads((tmp_path / name / "run_info.json").read_text()) for name in procs]
    assert [i["cpu_affinity"] for i in infos] == [1, len(every)]


def test_nan_loss_stops_run_and_keeps_last_checkpoint(tmp_path, monkeypatch):
    real_build = executor.build

    def build(cfg, **kw):
        env, trainer = real_build(cfg, **kw)

        def epoch(ts, hp):
            ts, m = trainer.epoch(ts, hp)
            poison = jax.numpy.where(ts.epoch >= 2, jax.numpy.nan, 0.0)
            return ts, m.replace(critic_loss=m.critic_loss + poison)

        return env, trainer._replace(epoch=epoch)

    monkeypatch.setattr(executor, "build", build)
    monkeypatch.setattr(executor, "_LAST_PROGRAM", {})
    cfg = tiny_cfg(tmp_path, epochs=4)
    with pytest.raises(train_mod.TrainingDiverged, match="critic_loss.*epoch 2.*epoch 1"):
        train_mod.train(cfg)
    assert len(read_csv(Path(cfg.run_dir) / "metrics.csv")) == 1
    assert Checkpointer(cfg.run_dir, read_only=True).latest_epoch() == 1


def test_stop_success_stops_after_the_window_and_resumes(tmp_path, monkeypatch):
    """stop_success ends a run once the trailing mean of stop_window test successes reaches it,
    with a checkpoint at that epoch even between checkpoint_every epochs; resuming it trains
    nothing more until stop_success=null."""
    schedule = jax.numpy.array([0.0, 0.5, 1.0, 0.75, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    real_build = executor.build

    def build(cfg, **kw):
        env, trainer = real_build(cfg, **kw)

        def epoch(ts, hp):
            ts, m = trainer.epoch(ts, hp)  # ts.epoch: the epochs done, this one included
            return ts, m.replace(test_success=schedule[ts.epoch - 1])

        return env, trainer._replace(epoch=epoch)

    monkeypatch.setattr(executor, "build", build)
    monkeypatch.setattr(executor, "_LAST_PROGRAM", {})
    logs = []
    cfg = tiny_cfg(tmp_path, epochs=9, checkpoint_every=4, stop_success=0.875, stop_window=2)
    out = train_mod.train(cfg, log=logs.append)
    # Trailing means of 2: 0.25, 0.75, 0.875 (epoch 4) -> stop after epoch 4.
    run = Path(cfg.run_dir)
    assert [float(r["test_success"]) for r in read_csv(run / "metrics.csv")] == \
        [0.0, 0.5, 1.0, 0.75]
    assert float(out.rows[0]["test_success"]) == 0.75
    assert any("stopped after epoch 4" in m for m in logs), logs
    assert Checkpointer(run, read_only=True).latest_epoch() == 4

    def resume(*extra):
        argv = [f"resume={run}", *extra]
        return train_mod.train(train_mod.load_resume_config(parse_args(argv), argv), argv,
                               log=logs.append)

    resume()  # still met: nothing more to train
    assert len(read_csv(run / "metrics.csv")) == 4
    assert "resume with stop_success=null" in logs[-1]
    resume("stop_success=null", "epochs=6")
    assert [float(r["test_success"]) for r in read_csv(run / "metrics.csv")] == \
        [0.0, 0.5, 1.0, 0.75, 1.0, 0.0]


def test_reached_stop_needs_every_live_run():
    cfg = Config(stop_success=0.9, stop_window=3)
    assert not outputs.reached_stop(Config(), [[1.0] * 3], [0])  # stop_success=null: never
    assert not outputs.reached_stop(cfg, [[1.0, 1.0]], [0])  # fewer epochs than the window
    assert outputs.reached_stop(cfg, [[0.8, 0.9, 1.0]], [0])
    # 9/10 in float32 is a hair below 0.9 (0.89999998): still met, while a real shortfall is not.
    nine = float(np.float32(9) / np.float32(10))
    assert nine < 0.9 and outputs.reached_stop(cfg, [[nine] * 3], [0])
    assert not outputs.reached_stop(cfg, [[nine, nine, 0.8]], [0])
    assert not outputs.reached_stop(cfg, [[0.8, 0.9, 1.0], [1.0, 1.0, 0.6]], [0, 1])
    assert outputs.reached_stop(cfg, [[0.8, 0.9, 1.0], [1.0, 1.0, 0.6]], [0])  # run 1 diverged
    assert not outputs.reached_stop(cfg, [[1.0] * 3], [])  # every run diverged


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
    run = Path(out.out_dir)
    for name in ("config.yaml", "metrics.csv", "success.png", "run_info.json"):
        assert (run / name).stat().st_size > 0
    rows = read_csv(run / "metrics.csv")
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    r = evaluate(run, episodes=4)
    assert 0.0 <= r["success"] <= 1.0 and r["episodes"] == 4 and r["backend"] == "mujoco"
    # The end-of-run retest (preset=fast sets retest=100): the same episodes as evaluate's,
    # written to retest.json, and the line that says so.
    line = policy_test.retest(run, 4)
    saved = json.loads((run / policy_test.RETEST_FILE).read_text())
    assert saved == r
    want = round(r["success"] * 4)
    assert line == (f"retest: the best policy (epoch {r['epoch']}) succeeds on {want} of 4 new "
                    f"episodes ({100 * r['success']:.0f}%)")


@pytest.mark.slow  # the default suite's learning check is test_algos' RDHER on the same task
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
    same results as separate runs: what makes one compiled program per sweep possible. Each
    run's hyperparameters come from its own Config; the pytree is never opened by name."""
    from rdher_jax.program import hparams_from_config

    cfg = tiny_cfg(tmp_path, epochs=1)
    _, trainer = executor.build(cfg)
    cfgs = [dataclasses.replace(cfg, critic_lr=1e-3, lambda_r=1.0, seed=7),
            dataclasses.replace(cfg, critic_lr=3e-3, lambda_r=2.0, seed=8)]
    hps = jax.tree.map(lambda *x: jax.numpy.stack(x), *[hparams_from_config(c) for c in cfgs])
    keys = jax.numpy.stack([jax.random.PRNGKey(c.seed) for c in cfgs])
    vts = jax.jit(jax.vmap(trainer.init))(keys, hps)
    vts, vm = jax.jit(jax.vmap(trainer.epoch))(vts, hps)
    init, epoch = jax.jit(trainer.init), jax.jit(trainer.epoch)
    for i, c in enumerate(cfgs):
        hp_i = hparams_from_config(c)
        ts, m = epoch(init(keys[i], hp_i), hp_i)
        np.testing.assert_allclose(vm.critic_loss[i], m.critic_loss, rtol=1e-4)
        np.testing.assert_allclose(vm.test_success[i], m.test_success)
        # Batched matmuls round differently from unbatched ones, and contact physics grows a
        # rounding difference in the actions: equal to float tolerance in the first cycle's
        # episodes (the initial policy), close in the later ones (a real difference is O(1)).
        n_first = cfg.num_envs
        np.testing.assert_allclose(vts.buffer.obs[i][:n_first], ts.buffer.obs[:n_first],
                                   atol=1e-4)
        np.testing.assert_allclose(vts.buffer.obs[i][: cfg.n_cycles * cfg.num_envs],
                                   ts.buffer.obs[: cfg.n_cycles * cfg.num_envs], atol=5e-3)
    assert not np.allclose(vm.critic_loss[0], vm.critic_loss[1])


def test_metrics_columns_follow_epoch_metrics(tmp_path):
    """metrics.csv has the historical columns first, then every other EpochMetrics field."""
    from rdher_jax.program import EpochMetrics
    from rdher_jax.runlog import LEADING_FIELDS

    names = [f.name for f in dataclasses.fields(EpochMetrics)]
    cols = outputs.csv_fields()
    assert cols[: len(LEADING_FIELDS)] == LEADING_FIELDS
    assert sorted(cols) == sorted({*names, "epoch", "wall_time"})
    m = EpochMetrics(**{n: np.float32(0.5) for n in names})
    row = outputs.epoch_row(3, m, 1.23456)
    assert list(row) == list(cols) and row["epoch"] == 3 and row["wall_time"] == 1.235
    assert outputs.loss_fields(cols)[:3] == ("critic_loss", "actor_loss", "q_mean")
    assert outputs.nonfinite_losses({**row, "actor_loss": float("inf")}) == ["actor_loss"]


def test_unusable_run_dir_or_resume_is_one_line_error(tmp_path, one_line_error):
    """Every unusable run_dir or resume exits 2 with one stderr line, before anything is built
    or written: no run directory is left behind."""
    (tmp_path / "file").write_text("")
    (tmp_path / "not-a-run").mkdir()
    (tmp_path / "list-config").mkdir()
    (tmp_path / "list-config" / "config.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "torn-config").mkdir()
    (tmp_path / "torn-config" / "config.yaml").write_text("env: [\n")
    (tmp_path / "bad-config").mkdir()
    (tmp_path / "bad-config" / "config.yaml").write_text("epochs: -5\n")
    cases = {
        "run_dir=/proc/x": "cannot create run_dir /proc/x",
        f"run_dir={tmp_path / 'file'}": "exists and is not a directory",
        f"run_dir={tmp_path / 'file' / 'sub'}": "is not a directory",
        "resume=/proc/x": "does not exist",
        f"resume={tmp_path / 'missing'}": "does not exist",
        f"resume={tmp_path / 'file'}": "is not a directory",
        f"resume={tmp_path / 'not-a-run'}": "has no config.yaml",
        f"resume={tmp_path / 'list-config'}": "is not a run config",
        f"resume={tmp_path / 'torn-config'}": "cannot read",
        f"resume={tmp_path / 'bad-config'}": "epochs must be a positive integer",
    }
    if os.geteuid() != 0:  # root writes anywhere
        (tmp_path / "ro").mkdir()
        (tmp_path / "ro-run").mkdir()
        (tmp_path / "ro-run" / "config.yaml").write_text("env: FetchReach\n")
        cases[f"run_dir={tmp_path / 'ro' / 'a' / 'b'}"] = "cannot create run_dir"
        cases[f"run_dir={tmp_path / 'ro'}"] = "is not writable"
        cases[f"resume={tmp_path / 'ro-run'}"] = "is not writable"
        (tmp_path / "ro").chmod(0o555)
        (tmp_path / "ro-run").chmod(0o555)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    procs = {arg: _cli([arg, "progress=false"]) for arg in cases}  # all at once: mostly startup
    try:
        for arg, fragment in cases.items():
            assert fragment in one_line_error(procs[arg]), arg
    finally:
        for name in ("ro", "ro-run"):
            if (tmp_path / name).exists():
                (tmp_path / name).chmod(0o755)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    assert not Path("/proc/x").exists()


def test_resume_with_damaged_checkpoint_is_one_line_error(tmp_path):
    cfg = tiny_cfg(tmp_path, epochs=1)
    train_mod.train(cfg, log=lambda *a: None)
    run = Path(cfg.run_dir)
    (run / "checkpoints" / "latest" / "1" / "state" / "_METADATA").write_text("garbage")
    err = _one_line_error_or_noise(_cli([f"resume={run}", "epochs=2"]))
    assert f"cannot resume {run}: its latest checkpoint is unusable" in err
    (run / "metrics.csv").write_text("epoch,other\n")
    err = _one_line_error_or_noise(_cli([f"resume={run}", "epochs=2"]))
    assert "belongs to a different version" in err


def _one_line_error_or_noise(p: subprocess.Popen) -> str:
    """The error line of a CLI that failed after building the env (whose imports may print
    their own warnings): exit 2, one ``error:`` line, no traceback."""
    out, err = p.communicate(timeout=300)
    assert p.returncode == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.slow
def test_target_every_moves_targets_inside_the_cycle(tmp_path):
    """target_every=k updates the targets after every k-th gradient step (counted over the
    run), instead of once after the cycle; polyak=0 makes 'updated' mean 'equal to online'."""
    def one_cycle(**kw):
        cfg = tiny_cfg(tmp_path, epochs=1, polyak=0.0, n_batches=4, **kw)
        _, trainer = executor.build(cfg)
        ts0 = jax.jit(trainer.init)(jax.random.PRNGKey(0), trainer.hparams)
        ts, _ = jax.jit(trainer.cycle)(ts0, trainer.hparams)
        return ts0.ddpg, ts.ddpg

    def same(a, b):
        return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b),
                                                        strict=True))

    start, end = one_cycle()  # baselines: one update after the cycle
    assert same(end.target_critic_params, end.critic_params)
    start, end = one_cycle(target_every=4)  # after the 4th step, which is the cycle's last
    assert same(end.target_critic_params, end.critic_params)
    start, end = one_cycle(target_every=5)  # not yet: targets are still the initial networks
    assert same(end.target_critic_params, start.critic_params)
    assert not same(end.critic_params, start.critic_params)
    start, end = one_cycle(target_every=3)  # after the 3rd step: neither start nor end
    assert not same(end.target_critic_params, start.critic_params)
    assert not same(end.target_critic_params, end.critic_params)


def _python(code: str) -> subprocess.CompletedProcess:
    """``python -c code`` in a fresh process; it must succeed."""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return p


def test_no_third_party_import_chatter():
    """MJX's Warp-absence notices and gymnasium-robotics' Adroit notice are dropped at their
    source (brax's and the MJX backend's import of MJX, and the scenes' of gymnasium-robotics,
    included); anything else those imports print would still show."""
    code = ("import rdher_jax.train, rdher_jax.sweep, rdher_jax.evaluate, rdher_jax.envs, "
            "rdher_jax.envs.native, rdher_jax.ddpg, brax; brax.State; "
            "from rdher_jax.envs import TASK_NAMES, scene; scene.asset_path(TASK_NAMES[0]); "
            "import rdher_jax.envs.mjx_backend; print('ok')")
    p = _python(code)
    assert p.stdout == "ok\n" and p.stderr == "", (p.stdout, p.stderr)


def test_native_training_never_imports_mjx(tmp_path):
    """A run on the native backend uses brax's normaliser without brax/__init__.py's import of
    MJX, trimesh and scipy (about 0.5 s of start-up); brax itself still loads in full, and
    quietly, when its package attributes are read."""
    code = (
        "import atexit, runpy, sys\n"
        "atexit.register(lambda: print('loaded', [m for m in ('mujoco.mjx', 'trimesh', 'scipy')"
        " if m in sys.modules]))\n"
        f"sys.argv = ['train', 'epochs=1', 'n_cycles=1', 'n_batches=2', 'run_dir={tmp_path}/r',"
        " 'backend=mujoco', 'progress=false']\n"
        "runpy.run_module('rdher_jax.train', run_name='__main__')\n"
    )
    p = _python(code)
    assert p.stdout.splitlines()[-1] == "loaded []", p.stdout
    code = ("import sys; from rdher_jax._quiet import defer_brax_init; defer_brax_init(); "
            "import rdher_jax.ddpg, brax; assert 'mujoco.mjx' not in sys.modules; "
            "print(brax.State.__module__, 'mujoco.mjx' in sys.modules, "
            "brax.training.acme.running_statistics is rdher_jax.ddpg.running_statistics)")
    p = _python(code)
    assert p.stdout == "brax.base True True\n" and p.stderr == "", (p.stdout, p.stderr)


def test_importing_the_learner_leaves_other_packages_alone():
    """Without start-up, importing the learner imports brax as brax imports itself: no
    stand-in package in sys.modules (start-up's deferral is the only place that makes one)."""
    code = ("import sys, types, rdher_jax.ddpg; "
            "print(type(sys.modules['brax']) is types.ModuleType, hasattr(sys.modules['brax'], "
            "'State'))")
    p = _python(code)
    assert p.stdout == "True True\n", (p.stdout, p.stderr)
