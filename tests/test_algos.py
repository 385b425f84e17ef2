"""Every algorithm trains end to end; RDHER learns FetchReach."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import jax
import numpy as np
import pytest

from rdher_jax import executor
from rdher_jax import train as train_mod
from rdher_jax.config import ALGO_NAMES, Config, resolve

TINY = dict(env="FetchReach", n_cycles=3, n_batches=4, batch_size=32, buffer_size=2000,
            num_envs=2, n_test_rollouts=2, hidden=32, progress=False, dher_tol=0.1)


# archer and dher are her and rdher with other reward weights (the same programs but for a
# traced weight); ddpg trains in tests/test_experiments.py's fixture and cher in
# tests/test_cher_trainer.py: slow here, to keep the default suite's compilations down.
@pytest.mark.parametrize("algo", [
    pytest.param(a, marks=pytest.mark.slow) if a in ("archer", "dher", "ddpg", "cher") else a
    for a in ALGO_NAMES])
def test_every_algo_trains_a_few_cycles(tmp_path, algo):
    cfg = resolve(Config(**{**TINY, "algo": algo, "run_dir": str(tmp_path / algo)}))
    env, trainer = executor.build(cfg)
    hp = trainer.hparams
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    epoch = jax.jit(trainer.epoch)
    for _ in range(2):
        ts, m = epoch(ts, hp)
    m = jax.device_get(m)
    for name in ("critic_loss", "actor_loss", "q_mean", "bias_real"):
        assert math.isfinite(float(getattr(m, name))), name
    assert int(m.updates) == 2 * cfg.n_cycles * cfg.n_batches
    frac_her, frac_dher = float(m.frac_her), float(m.frac_dher)
    if algo == "ddpg":
        assert frac_her == 0.0 and frac_dher == 0.0 and math.isnan(float(m.bias_her))
    else:
        assert frac_her + frac_dher > 0.5
    if algo in ("dher", "rdher"):
        # A 10 cm matching cell makes cross-episode matches certain within a few cycles.
        assert int(ts.relabel.rec_count) > 0 and frac_dher > 0.0
    else:
        assert frac_dher == 0.0
    # The weighted and unweighted biases differ exactly when the real weight is not 1.
    if algo in ("archer", "rdher"):
        assert (cfg.lambda_r, cfg.lambda_h) == (2.0, 1.0)
        assert float(m.bias_real) != pytest.approx(float(m.bias_unw_real))
    else:
        assert float(m.bias_real) == pytest.approx(float(m.bias_unw_real))


def test_fetch_reach_rdher_learns(tmp_path):
    """RDHER (the paper's FetchReach weights 2 / 1) reaches >= 0.9 test success within 5,000
    env steps (5 epochs of 10 cycles x 2 episodes x 50 steps) for this seed."""
    cfg = resolve(Config(env="FetchReach", algo="rdher", epochs=5, buffer_size=100_000,
                         n_test_rollouts=20, run_dir=str(tmp_path / "reach"), progress=False))
    train_mod.train(cfg)
    with open(Path(cfg.run_dir) / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert int(rows[-1]["env_steps"]) == 5000
    best = max(float(r["test_success"]) for r in rows)
    assert best >= 0.9, [r["test_success"] for r in rows]
    assert np.isfinite([float(r["critic_loss"]) for r in rows]).all()


# ("her", "success") is ("rdher", "success")'s learner without the combined rows: slow.
@pytest.mark.parametrize("algo,terminal", [
    pytest.param("her", "success", marks=pytest.mark.slow), ("rdher", "success"),
    ("her", "exact")])
def test_fast_preset_learner_options_train(tmp_path, algo, terminal):
    """The optional learner changes (all at once: n-step, TD3 smoothing and delay, targets
    inside the cycle, LayerNorm, terminal on success, a critic ensemble with a drawn target
    subset) compile and train with HER and RDHER."""
    opts = dict(n_step=3 if terminal != "exact" else 1, target_noise=0.2, policy_delay=2,
                target_every=2, polyak=0.99, layer_norm=True, terminal=terminal, n_critics=3,
                target_critics=2)
    cfg = resolve(Config(**{**TINY, **opts, "algo": algo, "run_dir": str(tmp_path / algo)}))
    env, trainer = executor.build(cfg)
    hp = trainer.hparams
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    ts, m = jax.jit(trainer.epoch)(ts, hp)
    m = jax.device_get(m)
    for name in ("critic_loss", "actor_loss", "q_mean"):
        assert math.isfinite(float(getattr(m, name))), name
    assert int(m.updates) == cfg.n_cycles * cfg.n_batches
    # Each option took effect: the delayed actor stepped on every 2nd update only (Adam's
    # step counts), and the critic carries LayerNorm (the actor never does).
    assert _adam_count(ts.ddpg.critic_opt_state) == int(m.updates)
    assert _adam_count(ts.ddpg.actor_opt_state) == int(m.updates) // 2
    assert "norm_0" in _param_names(ts.ddpg.critic_params)
    assert "norm_0" not in _param_names(ts.ddpg.actor_params)
    # Three critics, each with its own target network, and every one of the targets moved.
    ts0 = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    new, old = (np.asarray(t.ddpg.target_critic_params["params"]["ensemble"]["mlp"]["out"]
                           ["kernel"]) for t in (ts, ts0))
    assert new.shape[0] == 3 and (np.abs(new - old).reshape(3, -1).max(1) > 0).all()


def _param_names(params) -> str:
    return " ".join(jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(params))


def _adam_count(opt_state) -> int:
    """The step count of Adam's state in an optax chain (its ``count`` leaf)."""
    found = [int(leaf) for path, leaf in jax.tree_util.tree_leaves_with_path(opt_state)
             if jax.tree_util.keystr(path).endswith(".count")]
    assert found, opt_state
    return max(found)
