"""The training program: ``make_program(cfg, env)`` fixes shapes and returns pure functions.

- ``init(key, hparams) -> TrainState``
- ``cycle(ts, hparams) -> (ts, metrics)``: rollout of ``num_envs`` episodes, store, normaliser
  update, ``n_batches`` relabelled gradient steps, one target update. One compiled function;
  ``metrics`` is a dict of the cycle's means and the bias diagnostic's per-source sums.
- ``epoch(ts, hparams) -> (ts, EpochMetrics)``: ``lax.scan`` over ``n_cycles`` cycles, then
  ``n_test_rollouts`` deterministic test episodes. This is what the CLI jits once and calls per
  epoch; a sweep vmaps it over seeds and hyperparameters.
- ``collect``, ``learn``, ``finish``: the same cycle and epoch end in pieces, for
  ``overlap=true``, where the driver runs the next cycle's rollout on a second host device while
  the learner trains (``driver.OverlapEpoch``).

Everything a user may sweep is in ``Hyper`` (``ddpg.DDPGParams`` and ``relabel.RelabelParams``,
arrays, traced); everything that fixes a shape is in the frozen ``config.Config``. How goals are
relabelled is one ``relabel.Relabeller`` (HER, CHER or DHER) whose state lives in ``TrainState``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from . import buffer as rb
from . import relabel
from .config import ALGO_NAMES
from .ddpg import DDPGParams, DDPGState, make_ddpg
from .envs.rollout import rollout as env_rollout
from .relabel import SOURCE_NAMES, RelabelParams


@struct.dataclass
class Hyper:
    """Every traced hyperparameter of a run: the learner's and relabelling's."""

    ddpg: DDPGParams
    relabel: RelabelParams


@struct.dataclass
class TrainState:
    """Everything a run needs to continue: learner, replay buffer, PRNG key and counters."""

    ddpg: DDPGState
    buffer: rb.BufferState
    relabel: Any  # the relabelling strategy's state (``()`` for HER and CHER)
    key: jax.Array
    env_steps: jax.Array  # int32, total over all parallel envs
    updates: jax.Array  # int32 gradient steps
    epoch: jax.Array  # int32 completed epochs
    # overlap=true only: the episodes collected while the last cycle's learner ran, stored by
    # the next cycle (None, an empty subtree, otherwise).
    pending: Pending | None = None


@struct.dataclass
class Pending:
    """Episodes collected and not yet stored, with each one's final-step success."""

    episode: rb.Episode
    success: jax.Array


@struct.dataclass
class EpochMetrics:
    test_success: jax.Array
    train_success: jax.Array
    critic_loss: jax.Array
    actor_loss: jax.Array
    q_mean: jax.Array
    env_steps: jax.Array
    updates: jax.Array
    # Share of training rows per source (real, HER-relabelled, DHER-combined).
    frac_her: jax.Array
    frac_dher: jax.Array
    # Hindsight bias per source: mean Q(s, a, g) minus the discounted return the row's goal
    # received in its stored episode, weighted as the critic was trained (lambda_r / lambda_h)
    # and unweighted; NaN where a source had no rows.
    bias_real: jax.Array
    bias_her: jax.Array
    bias_dher: jax.Array
    bias_unw_real: jax.Array
    bias_unw_her: jax.Array
    bias_unw_dher: jax.Array


# The key of the episodes an overlap=true run stores in its first cycle: fold_in(run key, this),
# which nothing else uses ('overlap').
FIRST_COLLECT = 0x0E1A


class Program(NamedTuple):
    init: Any
    cycle: Any
    epoch: Any
    evaluate: Any
    hparams: Any
    ddpg: Any
    relabeller: Any
    # The halves of a cycle, for running them at the same time on two devices (overlap=true,
    # driver.OverlapEpoch): collect(ts, hp) -> Pending, the episodes of the cycle's rollout key
    # with the current actor; learn(ts, hp) -> (ts, metrics), the cycle with ts.pending as its
    # episodes; finish(ts, stacked cycle metrics, hp) -> (ts, EpochMetrics), the epoch's end.
    collect: Any = None
    learn: Any = None
    finish: Any = None
    # init without the first cycle's episodes (no host callback, so its compiled program can be
    # cached): init_overlap(key, hp) is init_state(key, hp) with pending = collect(that state,
    # hp, first=True), which driver.OverlapEpoch.init runs as two programs.
    init_state: Any = None


def hparams_from_config(cfg) -> Hyper:
    """The traced hyperparameters of a (resolved) config."""
    return Hyper(
        ddpg=DDPGParams.default(
            actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, polyak=cfg.polyak,
            action_l2=cfg.action_l2, noise_eps=cfg.noise_eps, random_eps=cfg.random_eps,
            lambda_r=cfg.lambda_r, lambda_h=cfg.lambda_h, gamma=cfg.gamma,
        ),
        relabel=relabel.params_from_config(cfg),
    )


def make_program(cfg, env) -> Program:
    """Build the pure training functions for a resolved ``Config`` and an env without
    auto-reset (episodes are reset explicitly at the start of each cycle, all in step)."""
    if cfg.algo not in ALGO_NAMES:
        raise ValueError(f"unknown algo {cfg.algo!r}; valid: {', '.join(ALGO_NAMES)}")
    T = env.episode_length
    obs_dim, goal_dim, act_dim = env.obs_size, env.goal_size, env.action_size
    agent = make_ddpg(
        obs_dim, goal_dim, act_dim, hidden=(cfg.hidden,) * cfg.layers,
        target_noise=cfg.target_noise, noise_clip=cfg.noise_clip,
        policy_delay=cfg.policy_delay, layer_norm=cfg.layer_norm,
        compute_dtype=cfg.compute_dtype, target_clip=cfg.target_clip,
        n_critics=cfg.n_critics, target_critics=cfg.target_critics,
    )
    n_envs, n_test = cfg.num_envs, cfg.n_test_rollouts
    capacity_episodes = rb.init(cfg.buffer_size, T, 1, 1, 1).capacity_episodes
    relabeller = relabel.make_relabeller(cfg, env.compute_reward, capacity_episodes, T, goal_dim)
    updates_per_epoch = cfg.n_cycles * cfg.n_batches

    def rollout(key, ds: DDPGState, hp: DDPGParams, n: int,
                explore: bool) -> tuple[rb.Episode, jax.Array]:
        """``n`` episodes of T steps from fresh resets: the episodes, episode-major, and each
        one's final-step success, ``(n,)``."""
        k_reset, k_act = jax.random.split(key)

        def policy(k, state):
            o, g = state.obs["observation"], state.obs["desired_goal"]
            return agent.explore(k, ds, o, g, hp) if explore else agent.act(ds, o, g)

        def record(state, a, _):
            obs = state.obs
            return obs["observation"], obs["achieved_goal"], obs["desired_goal"], a

        _, last, (o, ag, g, a) = env_rollout(env, policy, jax.random.split(k_reset, n),
                                             jax.random.split(k_act, T), record)

        def with_last(x, y):  # (T, n, d) + final (n, d) -> (n, T+1, d)
            return jnp.swapaxes(jnp.concatenate([x, y[None]], 0), 0, 1)

        return rb.Episode(
            obs=with_last(o, last.obs["observation"]),
            ag=with_last(ag, last.obs["achieved_goal"]),
            g=with_last(g, last.obs["desired_goal"]),
            action=jnp.swapaxes(a, 0, 1),
        ), last.info["is_success"]

    def init(key, hp: Hyper) -> TrainState:
        k_agent, k_run = jax.random.split(key)
        return TrainState(
            ddpg=agent.init(k_agent, hp.ddpg),
            buffer=rb.init(cfg.buffer_size, T, obs_dim, goal_dim, act_dim),
            relabel=relabeller.init(),
            key=k_run,
            env_steps=jnp.zeros((), jnp.int32),
            updates=jnp.zeros((), jnp.int32),
            epoch=jnp.zeros((), jnp.int32),
        )

    def bias(key, ts: TrainState, ds: DDPGState, hp: Hyper):
        """Per-source sums and counts of Q minus the observed return, on one fresh batch."""
        b = relabeller.sample(key, ts.relabel, ts.buffer, hp.relabel, jnp.int32(0))
        obs, goal = agent.normalise(ds, b.obs, b.goal)
        q = agent.q_value(ds.critic_params, obs, goal, b.action)
        ret = relabel.observed_return(ts.buffer, b, env.compute_reward, hp.ddpg.gamma)
        lam = jnp.where(b.hindsight, hp.ddpg.lambda_h, hp.ddpg.lambda_r)
        one_hot = (b.source[:, None] == jnp.arange(len(SOURCE_NAMES))[None, :]).astype(q.dtype)
        return {"w": (q - lam * ret) @ one_hot, "u": (q - ret) @ one_hot, "n": one_hot.sum(0)}

    def collect(ts: TrainState, hp: Hyper, first: jax.Array | bool = False) -> Pending:
        """The episodes ``cycle(ts, hp)`` would collect: its rollout key, ts's actor. ``first``
        (traced, so one program does both): those ``init_overlap`` adds to a fresh state."""
        k_roll = jnp.where(first, jax.random.fold_in(ts.key, FIRST_COLLECT),
                           jax.random.split(ts.key, 5)[1])
        ep, success = rollout(k_roll, ts.ddpg, hp.ddpg, n_envs, explore=True)
        return Pending(ep, success)

    def cycle(ts: TrainState, hp: Hyper):
        key, k_roll, k_norm, k_upd, k_bias = jax.random.split(ts.key, 5)
        ep, success = rollout(k_roll, ts.ddpg, hp.ddpg, n_envs, explore=True)
        return _learn(ts, hp, ep, success, key, k_norm, k_upd, k_bias)

    def learn(ts: TrainState, hp: Hyper):
        """A cycle whose episodes are ``ts.pending`` (collected beside the previous cycle)."""
        key, _, k_norm, k_upd, k_bias = jax.random.split(ts.key, 5)
        return _learn(ts, hp, ts.pending.episode, ts.pending.success, key, k_norm, k_upd,
                      k_bias)

    def actor_step_count(ts: TrainState, i: jax.Array) -> jax.Array:
        """The gradient-step counter the actor's ``policy_delay`` reads, for step ``i`` of a
        cycle. ``ts.updates`` is always a multiple of ``n_batches`` (it grows by ``n_batches``
        a cycle, and ``n_batches`` cannot change on resume), so when ``policy_delay`` divides
        ``n_batches``, ``(ts.updates + i) % policy_delay == i % policy_delay`` and the scan's
        own index gives the same steps. It matters under ``vmap`` (a sweep): ``ts.updates`` is
        one value per run there, and a ``lax.cond`` on a per-run predicate runs both branches
        (the actor's gradient on every step), while ``i`` is shared by all runs and keeps the
        skipped actor steps free."""
        if cfg.n_batches % cfg.policy_delay == 0:
            return i
        return ts.updates + i

    def _learn(ts: TrainState, hp: Hyper, ep: rb.Episode, success: jax.Array, key, k_norm,
               k_upd, k_bias):
        buf = rb.add(ts.buffer, ep)
        rs = relabeller.update(ts.relabel, buf, hp.relabel)
        # Normaliser: statistics of 'future'-relabelled transitions of the new episodes
        # (baselines, and the DHER and CHER code built on it, do this for every strategy).
        norm = relabel.sample_episodes(k_norm, ep, n_envs * T, hp.relabel.relabel_prob,
                                       env.compute_reward)
        ds = agent.update_normaliser(ts.ddpg, norm.obs, norm.goal)
        step0 = ts.updates % updates_per_epoch

        # Only the learner is carried: sampling reads the relabelling state and never changes
        # it, so DHER's whole-buffer index need not travel through every step.
        def update(ds, x):
            k, i = x
            k_sample, k_update = jax.random.split(k)
            batch = relabeller.sample(k_sample, rs, buf, hp.relabel, step0 + i)
            if cfg.n_step > 1:
                batch = relabel.n_step_returns(buf, batch, cfg.n_step, hp.ddpg.gamma,
                                               env.compute_reward,
                                               stop_at_success=cfg.terminal == "success")
            else:
                batch = relabel.mark_terminal(buf, batch, cfg.terminal, hp.ddpg.gamma)
            ds, m = agent.update(ds, batch, hp.ddpg, k_update, actor_step_count(ts, i))
            if cfg.target_every:
                ds = agent.target_update(ds, hp.ddpg, (ts.updates + i + 1) % cfg.target_every == 0)
            m["frac_her"] = jnp.mean(batch.source == relabel.HER)
            m["frac_dher"] = jnp.mean(batch.source == relabel.DHER)
            return ds, m

        xs = (jax.random.split(k_upd, cfg.n_batches), jnp.arange(cfg.n_batches, dtype=jnp.int32))
        ds, m = jax.lax.scan(update, ds, xs)
        if not cfg.target_every:
            ds = agent.target_update(ds, hp.ddpg)
        ts = ts.replace(
            ddpg=ds, buffer=buf, relabel=rs, key=key,
            env_steps=ts.env_steps + n_envs * T,
            updates=ts.updates + cfg.n_batches,
        )
        # nanmean: with policy_delay > 1 the skipped actor steps report NaN actor losses.
        metrics = {k: jnp.nanmean(v) for k, v in m.items()}
        metrics["train_success"] = success.mean()
        metrics["bias"] = bias(k_bias, ts, ds, hp)
        return ts, metrics

    def evaluate(key, ds: DDPGState, hp: Hyper, n: int = n_test):
        """Mean final-step success of ``n`` deterministic episodes."""
        _, success = rollout(key, ds, hp.ddpg, n, explore=False)
        return success.mean()

    def epoch(ts: TrainState, hp: Hyper):
        ts, m = jax.lax.scan(lambda s, _: cycle(s, hp), ts, None, length=cfg.n_cycles)
        return finish(ts, m, hp)

    def finish(ts: TrainState, m, hp: Hyper):
        """The end of an epoch: test episodes and the metrics of its cycles (``m``, stacked)."""
        key, k_test = jax.random.split(ts.key)
        test = evaluate(k_test, ts.ddpg, hp)
        ts = ts.replace(key=key, epoch=ts.epoch + 1)
        b = jax.tree.map(lambda x: x.sum(0), m["bias"])
        mean = {}
        for i, name in enumerate(SOURCE_NAMES):
            n = b["n"][i]
            mean[f"bias_{name}"] = jnp.where(n > 0, b["w"][i] / jnp.maximum(n, 1), jnp.nan)
            mean[f"bias_unw_{name}"] = jnp.where(n > 0, b["u"][i] / jnp.maximum(n, 1), jnp.nan)
        return ts, EpochMetrics(
            test_success=test,
            train_success=m["train_success"].mean(),
            critic_loss=m["critic_loss"].mean(),
            actor_loss=m["actor_loss"].mean(),
            q_mean=m["q_mean"].mean(),
            env_steps=ts.env_steps,
            updates=ts.updates,
            frac_her=m["frac_her"].mean(),
            frac_dher=m["frac_dher"].mean(),
            **mean,
        )

    def init_overlap(key, hp: Hyper) -> TrainState:
        """``init``, then the episodes the first cycle stores: collected by the initial actor
        with a key of their own (so from then on every cycle's rollout key is the one it has
        without overlap)."""
        ts = init(key, hp)
        return ts.replace(pending=collect(ts, hp, True))

    return Program(init=init_overlap if cfg.overlap else init, cycle=cycle, epoch=epoch,
                   evaluate=evaluate, hparams=hparams_from_config(cfg), ddpg=agent,
                   relabeller=relabeller, collect=collect, learn=learn, finish=finish,
                   init_state=init)
