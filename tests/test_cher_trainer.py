"""CHER through the trainer: the rows ``algo=cher`` trains on are CHER's greedy selection, with the
proximity weight ``cher_growth ** step`` at the right gradient step.

The trainer's relabeller is wrapped (at ``make_relabeller``) by a spy that passes every call
through unchanged and reports, for each batch, the candidates CHER draws from the same key and
buffer and the rows actually returned. The host then picks from those candidates with a plain
numpy stochastic greedy and checks that the returned rows are exactly its picks.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import cher_select_np

from rdher_jax import buffer as rb
from rdher_jax import make_env, relabel
from rdher_jax.config import Config, resolve
from rdher_jax.program import make_program
from rdher_jax.relabel import cher, her

GROWTH = 2.0  # lam = 2 ** step: a wrong step index changes the selection
N_CYCLES, N_BATCHES, EPOCHS = 3, 4, 2
CFG = dict(env="FetchReach", algo="cher", n_cycles=N_CYCLES, n_batches=N_BATCHES, batch_size=32,
           buffer_size=2000, num_envs=2, n_test_rollouts=2, hidden=32, progress=False,
           cher_growth=GROWTH, cher_sample=3, backend="mujoco", scene="original")
FIELDS = ("obs", "goal", "action", "reward", "ep", "t", "source")


@pytest.fixture(scope="module")
def calls():
    """Every relabeller call of EPOCHS epochs, in order: (step, candidates, noise, batch)."""
    cfg = resolve(Config(**CFG, run_dir="unused"))
    env = make_env(cfg.env, backend="mujoco", auto_reset=False)
    out = []
    make = relabel.make_relabeller

    def spy_factory(*args, **kwargs):
        inner = make(*args, **kwargs)
        cand_fns = cher.build_cher(env.compute_reward, cfg.batch_size, 2 * cfg.batch_size,
                                   cfg.cher_sample)

        def sample(*a):
            res = inner.sample(*a)
            batch = res[-1] if isinstance(res, tuple) else res
            key, step = a[0], a[-1]
            buf = next(x for x in a if isinstance(x, rb.BufferState))
            params = next(x for x in a if isinstance(x, relabel.RelabelParams))
            draws, noise = cand_fns.draw(key, buf, params.relabel_prob)
            cand = her.gather_her(buf, *draws, env.compute_reward)
            prox = jnp.linalg.norm(cand.goal - buf.ag[cand.ep, cand.t], axis=-1)
            got = {f: getattr(batch, f) for f in FIELDS}
            pool = {f: getattr(cand, f) for f in FIELDS}

            def record(step, prox, noise, pool, got):
                out.append((int(step), np.asarray(prox), np.asarray(noise),
                            jax.tree.map(np.asarray, pool), jax.tree.map(np.asarray, got)))

            jax.debug.callback(record, step, prox, noise, pool, got, ordered=True)
            return res

        return inner._replace(sample=sample)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(relabel, "make_relabeller", spy_factory)
        trainer = make_program(cfg, env)
    hp = trainer.hparams
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    epoch = jax.jit(trainer.epoch)
    for _ in range(EPOCHS):
        ts, _ = epoch(ts, hp)
    jax.effects_barrier()
    assert int(ts.updates) == EPOCHS * N_CYCLES * N_BATCHES
    return out


# Per cycle: its N_BATCHES gradient steps, numbered from the start of the epoch, then the bias
# diagnostic's fresh batch (drawn at step 0). Epoch 2 starts again at 0.
EXPECTED_STEPS = [0, 1, 2, 3, 0, 4, 5, 6, 7, 0, 8, 9, 10, 11, 0] * EPOCHS


def test_cher_receives_the_gradient_step_since_the_epoch_began(calls):
    assert [c[0] for c in calls] == EXPECTED_STEPS


def test_cher_trains_on_its_greedy_selection(calls):
    """Fails if algo=cher sampled like HER (other rows from the same key and buffer) or if the
    proximity weight used another step than EXPECTED_STEPS."""
    assert len(calls) == len(EXPECTED_STEPS)
    differs_at_other_step = 0
    for want_step, (_, prox, noise, pool, got) in zip(EXPECTED_STEPS, calls, strict=True):
        goals = pool["goal"].astype(np.float64)
        idx = cher_select_np(goals, prox, GROWTH**want_step, noise, CFG["cher_sample"])
        assert len(set(idx.tolist())) == len(idx)  # no candidate twice
        for f in FIELDS:
            np.testing.assert_array_equal(got[f], pool[f][idx], err_msg=f"{f} at {want_step}")
        other = cher_select_np(goals, prox, GROWTH ** (want_step + 4), noise, CFG["cher_sample"])
        differs_at_other_step += not np.array_equal(other, idx)
    # The weight matters at these settings: a step off by 4 picks other rows for most batches.
    assert differs_at_other_step > len(calls) // 2
