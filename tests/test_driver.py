"""The run driver: sweeps over any traced key (grid.<key>), what may and may not vary in one
program, and GPU-sized runs at config time."""

import csv
import dataclasses

import jax
import numpy as np
import pytest

from rdher_jax import executor, outputs
from rdher_jax import sweep as sweep_mod
from rdher_jax import train as train_mod
from rdher_jax.config import TRACED_KEYS, Config, ConfigError, parse_args, resolve

TINY = dict(env="FetchReach", algo="rdher", n_cycles=2, n_batches=4, batch_size=32,
            buffer_size=2000, num_envs=2, n_test_rollouts=2, hidden=32, progress=False, epochs=2)
TINY_ARGS = [f"{k}={v}" for k, v in TINY.items()]


def read_rows(path):
    with open(path, newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


@pytest.mark.slow  # the default suite's sweep-equals-separate-runs check: tests/test_sweep.py
def test_grid_sweep_runs_each_value_as_a_separate_run_would(tmp_path):
    d = tmp_path / "sweep"
    plan = sweep_mod.parse_sweep_args([*TINY_ARGS, "grid.dher_fraction=[0.8,0.2]",
                                       "grid.noise_eps=[0.1]", "seeds=1", f"sweep_dir={d}"]).plan
    names = ["dher_fraction0.8_noise_eps0.1_lr2_lh1_s0", "dher_fraction0.2_noise_eps0.1_lr2_lh1_s0"]
    assert list(plan.names) == names
    assert [(c.dher_fraction, c.noise_eps) for c in plan.runs] == [(0.8, 0.1), (0.2, 0.1)]
    out = sweep_mod.sweep(plan, log=lambda *a: None)
    assert out.names == names
    rows = list(csv.DictReader(open(d / "summary.csv")))
    assert [(r["dher_fraction"], r["noise_eps"]) for r in rows] == [("0.8", "0.1"), ("0.2", "0.1")]
    md = (d / "summary.md").read_text()
    assert "| dher_fraction | noise_eps | lambda_r | lambda_h | seeds |" in md
    # The run with the non-default value equals a train run given that value directly.
    cfg = resolve(Config(**{**TINY, "dher_fraction": 0.2, "noise_eps": 0.1,
                            "run_dir": str(tmp_path / "one")}))
    train_mod.train(cfg, log=lambda *a: None)
    a, b = read_rows(d / names[1] / "metrics.csv"), read_rows(tmp_path / "one" / "metrics.csv")
    assert len(a) == len(b) == 2
    for ra, rb in zip(a, b, strict=True):
        for k in ra:
            np.testing.assert_allclose(float(ra[k]), float(rb[k]), rtol=1e-3, atol=1e-5,
                                       equal_nan=True, err_msg=k)
    # Resuming reads the grid back from sweep.yaml; changing it is refused.
    again = sweep_mod.parse_sweep_args([f"resume={d}", "epochs=3"]).plan
    assert again.names == plan.names and again.runs[1].dher_fraction == 0.2
    with pytest.raises(ConfigError, match="cannot change the grid"):
        sweep_mod.parse_sweep_args([f"resume={d}", "grid.dher_fraction=[0.5]"])


@pytest.mark.parametrize("args, fragment", [
    (["grid.hidden=[32,64]"], "hidden fixes the compiled program"),
    (["grid.algo=[her,dher]"], "algo fixes the compiled program"),
    (["grid.num_envs=[1,2]"], "a sweep over it is separate runs"),
    (["grid.seed=[1,2]"], "sweep seeds with seeds="),
    (["grid.dher_frac=[0.1]"], "unknown key 'grid.dher_frac' (did you mean grid.dher_fraction?)"),
    (["grid.dher_fraction=0.2"], "must be a non-empty list"),
    (["grid.dher_fraction=[0.2,0.2]"], "duplicate runs"),
    (["grid.dher_fraction=[2]"], "dher_fraction must be in [0, 1]"),
    (["grid.polyak=[abc]"], "invalid value 'abc' for polyak"),
    (["grid.dher_fraction=[0.2]", "dher_fraction=0.3"], "not both"),
    (["grid.lambda_r=[1,2]", "lambdas=[[1,1]]"], "not both"),
])
def test_bad_grids_are_one_line_errors(args, fragment, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        sweep_mod.main([*args, f"sweep_dir={tmp_path / 'x'}"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and fragment in err, err
    assert not (tmp_path / "x").exists()


def test_traced_keys_are_exactly_what_reaches_the_hyperparameters():
    from rdher_jax.program import hparams_from_config

    base = resolve(parse_args(["algo=rdher", "env=FetchPush"]))
    ref = jax.tree.leaves(hparams_from_config(base))
    for key in TRACED_KEYS:
        v = getattr(base, key)
        new = dataclasses.replace(base, **{key: v + 1 if key == "replay_k" else v * 0.5})
        leaves = jax.tree.leaves(hparams_from_config(new))
        assert any(float(a) != float(b) for a, b in zip(ref, leaves, strict=True)), key
    # Runs that differ in anything else are not one program.
    with pytest.raises(ConfigError, match="differ only in traced keys and seeds, not in hidden"):
        executor.executor_for([base, dataclasses.replace(base, hidden=64)])


@pytest.mark.parametrize("algo", ["her", "rdher"])  # config checks: test_config.py
def test_a_4096_env_run_has_the_state_eval_shape_predicts(algo):
    """GPU-sized runs pass config checks for every algorithm, and the state they allocate is the
    size ``jax.eval_shape`` gives (docs/performance.md's memory figures are read this way)."""
    cfg = resolve(parse_args([f"algo={algo}", "num_envs=4096", "buffer_size=204800",
                              "hidden=16", "layers=1"]))
    _, trainer = executor.build(cfg)
    shape = jax.eval_shape(trainer.init, jax.random.PRNGKey(0), trainer.hparams)
    state = jax.jit(trainer.init)(jax.random.PRNGKey(0), trainer.hparams)
    assert executor.tree_bytes(state) == executor.tree_bytes(shape)
    assert state.buffer.obs.shape[0] == 204800 // 50
    if algo == "rdher":  # the ring holds every match one cycle of 4096 envs can record
        assert state.relabel.rec_i.shape == (2 * 4096 * 51 * 8,) == (cfg.dher_records,)


def test_compiled_ahead_runs_its_executable_and_falls_back_to_jit():
    """CompiledAhead compiles from shapes on a thread; calls run that executable (the jitted
    function is never traced for them), and an input it does not take goes to jit."""
    traced = []

    def f(x, y):
        traced.append(x.shape)
        return x * 2 + y, (x ** 2).sum()

    ahead = executor.CompiledAhead(jax.jit(f, donate_argnums=0))
    ahead.start(jax.ShapeDtypeStruct((3,), np.float32), np.float32(1))
    assert len(traced) <= 1  # the background thread traces once
    x = jax.numpy.arange(3, dtype=np.float32)
    want = f(x, np.float32(1))
    n = len(traced)
    got = ahead(x + 0, np.float32(1))
    np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(want[0]))
    assert ahead._compiled is not None and len(traced) == n  # the executable ran, no jit trace
    out = ahead(jax.numpy.ones(4, np.float32), np.float32(1))  # another shape: jit
    np.testing.assert_array_equal(np.asarray(out[0]), np.full(4, 3.0, np.float32))
    assert ahead._compiled is None and traced[-1] == (4,)


def test_the_plot_is_drawn_when_due_and_when_the_run_ends(tmp_path, monkeypatch):
    """success.png is redrawn at most every PLOT_EVERY_S while rows come, and always by
    close(); a row recorded since the last plot is never left undrawn at the end."""
    drawn = []
    monkeypatch.setattr(outputs, "plot_success", lambda csv_path, png, title: drawn.append(
        len(read_rows(csv_path))))
    cfg = resolve(Config(**TINY, run_dir=str(tmp_path / "run")))
    out = outputs.RunOutputs(cfg)
    out.start({})
    fields = outputs.csv_fields()

    def row(epoch):
        return {k: (epoch if k == "epoch" else 0.5 if k == "test_success" else 0)
                for k in fields}

    monkeypatch.setattr(outputs, "PLOT_EVERY_S", 3600.0)
    out._plot_due = outputs.time.monotonic() + 3600.0
    policy = {"w": np.zeros(2, np.float32)}
    out.write(row(1), policy)
    out.plot_if_due()
    assert drawn == []  # not due yet
    out._plot_due = outputs.time.monotonic() - 1.0
    out.write(row(2), policy)
    out.plot_if_due()
    assert drawn == [2]
    out.plot_if_due()  # due again only after PLOT_EVERY_S
    assert drawn == [2]
    out.write(row(3), policy)
    out.close()
    assert drawn == [2, 3]


@pytest.mark.parametrize("n_batches, kept", [(4, True), (3, False)])
def test_a_sweeps_skipped_actor_steps_stay_skipped_under_vmap(n_batches, kept):
    """With policy_delay > 1 the actor's step is a lax.cond. Under a sweep's vmap a per-run
    predicate turns it into a select that computes the actor's gradient on every step (a
    preset=fast sweep ran 1.2x slower than the same run alone); when policy_delay divides
    n_batches the predicate is the scan's shared index and the cond stays a cond."""
    cfg = resolve(Config(**{**TINY, "algo": "her", "policy_delay": 2, "n_batches": n_batches}))
    _, program = executor.build(cfg)
    hps = executor.stack([program.hparams] * 2)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states = jax.eval_shape(jax.vmap(program.init), keys, hps)
    text = str(jax.make_jaxpr(jax.vmap(program.epoch))(states, hps))
    assert ("cond[" in text) == kept


def test_a_directory_another_process_writes_is_refused(tmp_path):
    """While one process holds a run directory (DirLock, taken by every drive on process 0),
    a resume of it is a one-line error naming that process, before anything is compiled or
    rewound; the lock goes with its holder, and a run resumes once it is released."""
    import os

    from rdher_jax.runlog import DirLock

    d = tmp_path / "run"
    cfg = resolve(Config(**{**TINY, "algo": "her", "epochs": 1, "run_dir": str(d)}))
    train_mod.train(cfg, log=lambda *a: None)
    assert (d / ".lock").is_file()  # left behind, unlocked: the next run takes it
    before = (d / "metrics.csv").read_bytes()
    resume = train_mod.parse_train_args([f"resume={d}", "epochs=2"])
    other = DirLock()
    other.hold(d)
    with pytest.raises(ConfigError, match=rf"run_dir {d} is in use by another process "
                                          rf"\(pid {os.getpid()}\)"):
        train_mod.train(resume, log=lambda *a: None)
    assert (d / "metrics.csv").read_bytes() == before
    other.hold(d)  # held already: nothing happens
    other.release()
    train_mod.train(resume, log=lambda *a: None)
    assert len(read_rows(d / "metrics.csv")) == 2
