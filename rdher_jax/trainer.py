"""The training program: ``make_trainer(cfg, env)`` fixes shapes and returns pure functions.

- ``init(key, hparams) -> TrainState``
- ``cycle(ts, hparams) -> (ts, CycleMetrics)``: rollout of ``num_envs`` episodes, store, normaliser
  update, ``n_batches`` relabelled gradient steps, one target update. One compiled function.
- ``epoch(ts, hparams) -> (ts, EpochMetrics)``: ``lax.scan`` over ``n_cycles`` cycles, then
  ``n_test_rollouts`` deterministic test episodes. This is what the CLI jits once and calls per
  epoch; a sweep vmaps it over seeds and hyperparameters.

Everything a user may sweep is in ``ddpg.HParams`` (arrays, traced); everything that fixes a
shape is in the frozen ``config.Config``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from . import buffer as rb
from .config import ALGO_NAMES
from .ddpg import DDPGState, HParams, make_ddpg
from .her import relabel_prob_from_k, sample_her


@struct.dataclass
class TrainState:
    """Everything a run needs to continue: learner, replay buffer, PRNG key and counters."""

    ddpg: DDPGState
    buffer: rb.BufferState
    key: jax.Array
    env_steps: jax.Array  # int32, total over all parallel envs
    updates: jax.Array  # int32 gradient steps
    epoch: jax.Array  # int32 completed epochs


@struct.dataclass
class EpochMetrics:
    test_success: jax.Array
    train_success: jax.Array
    critic_loss: jax.Array
    actor_loss: jax.Array
    q_mean: jax.Array
    env_steps: jax.Array
    updates: jax.Array


class Trainer(NamedTuple):
    init: Any
    cycle: Any
    epoch: Any
    evaluate: Any
    hparams: Any
    ddpg: Any


def hparams_from_config(cfg) -> HParams:
    """The traced hyperparameters of a (resolved) config."""
    relabel = relabel_prob_from_k(cfg.replay_k) if cfg.algo != "ddpg" else 0.0
    return HParams.default(
        actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, polyak=cfg.polyak,
        action_l2=cfg.action_l2, noise_eps=cfg.noise_eps, random_eps=cfg.random_eps,
        relabel_prob=relabel, lambda_r=cfg.lambda_r, lambda_h=cfg.lambda_h, gamma=cfg.gamma,
    )


def make_trainer(cfg, env) -> Trainer:
    """Build the pure training functions for a resolved ``Config`` and an env without
    auto-reset (episodes are reset explicitly at the start of each cycle, all in step)."""
    if cfg.algo not in ALGO_NAMES:
        raise ValueError(f"unknown algo {cfg.algo!r}; valid: {', '.join(ALGO_NAMES)}")
    T = env.episode_length
    obs_dim, goal_dim, act_dim = env.obs_size, env.goal_size, env.action_size
    agent = make_ddpg(obs_dim, goal_dim, act_dim, hidden=(cfg.hidden,) * cfg.layers)
    n_envs, n_test = cfg.num_envs, cfg.n_test_rollouts
    v_reset, v_step = jax.vmap(env.reset), jax.vmap(env.step)

    def rollout(key, ds: DDPGState, hp: HParams, n: int, explore: bool) -> rb.Episode:
        """``n`` episodes of T steps from fresh resets; returns them episode-major."""
        k_reset, k_act = jax.random.split(key)
        state = v_reset(jax.random.split(k_reset, n))

        def step(state, k):
            o, g = state.obs["observation"], state.obs["desired_goal"]
            a = agent.explore(k, ds, o, g, hp) if explore else agent.act(ds, o, g)
            nxt = v_step(state, a)
            return nxt, (o, state.obs["achieved_goal"], g, a)

        last, (o, ag, g, a) = jax.lax.scan(step, state, jax.random.split(k_act, T))

        def with_last(x, y):  # (T, n, d) + final (n, d) -> (n, T+1, d)
            return jnp.swapaxes(jnp.concatenate([x, y[None]], 0), 0, 1)

        return rb.Episode(
            obs=with_last(o, last.obs["observation"]),
            ag=with_last(ag, last.obs["achieved_goal"]),
            g=with_last(g, last.obs["desired_goal"]),
            action=jnp.swapaxes(a, 0, 1),
        ), last.info["is_success"]

    def init(key, hp: HParams) -> TrainState:
        k_agent, k_run = jax.random.split(key)
        return TrainState(
            ddpg=agent.init(k_agent, hp),
            buffer=rb.init(cfg.buffer_size, T, obs_dim, goal_dim, act_dim),
            key=k_run,
            env_steps=jnp.zeros((), jnp.int32),
            updates=jnp.zeros((), jnp.int32),
            epoch=jnp.zeros((), jnp.int32),
        )

    def cycle(ts: TrainState, hp: HParams):
        key, k_roll, k_norm, k_upd = jax.random.split(ts.key, 4)
        ep, success = rollout(k_roll, ts.ddpg, hp, n_envs, explore=True)
        buf = rb.add(ts.buffer, ep)
        # Normaliser: statistics of relabelled transitions of the new episodes (baselines).
        new = rb.add(rb.init(n_envs * T, T, obs_dim, goal_dim, act_dim), ep)
        norm_batch = sample_her(k_norm, new, n_envs * T, hp.relabel_prob, env.compute_reward)
        ds = agent.update_normaliser(ts.ddpg, norm_batch.obs, norm_batch.goal)

        def update(ds, k):
            batch = sample_her(k, buf, cfg.batch_size, hp.relabel_prob, env.compute_reward)
            return agent.update(ds, batch, hp)

        ds, m = jax.lax.scan(update, ds, jax.random.split(k_upd, cfg.n_batches))
        ds = agent.target_update(ds, hp)
        ts = ts.replace(
            ddpg=ds, buffer=buf, key=key,
            env_steps=ts.env_steps + n_envs * T,
            updates=ts.updates + cfg.n_batches,
        )
        metrics = {k: v.mean() for k, v in m.items()}
        metrics["train_success"] = success.mean()
        return ts, metrics

    def evaluate(key, ds: DDPGState, hp: HParams, n: int = n_test):
        """Mean final-step success of ``n`` deterministic episodes."""
        _, success = rollout(key, ds, hp, n, explore=False)
        return success.mean()

    def epoch(ts: TrainState, hp: HParams):
        ts, m = jax.lax.scan(lambda s, _: cycle(s, hp), ts, None, length=cfg.n_cycles)
        key, k_test = jax.random.split(ts.key)
        test = evaluate(k_test, ts.ddpg, hp)
        ts = ts.replace(key=key, epoch=ts.epoch + 1)
        return ts, EpochMetrics(
            test_success=test,
            train_success=m["train_success"].mean(),
            critic_loss=m["critic_loss"].mean(),
            actor_loss=m["actor_loss"].mean(),
            q_mean=m["q_mean"].mean(),
            env_steps=ts.env_steps,
            updates=ts.updates,
        )

    return Trainer(init=init, cycle=cycle, epoch=epoch, evaluate=evaluate,
                   hparams=hparams_from_config(cfg), ddpg=agent)
