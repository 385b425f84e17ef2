"""Goal-conditioned DDPG as pure functions (OpenAI baselines HER's DDPG, with RDHER reward weights).

Every hyperparameter that a sweep may vary lives in `DDPGParams` as a float32 scalar array, so the
whole training function can be `jax.vmap`-ed over a stack of them. Architecture and
preprocessing constants are static and fixed by `make_ddpg`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import optax
from flax import struct

from rdher_jax import _quiet
from rdher_jax.config import TARGET_CLIPS  # the critic target's clip ranges
from rdher_jax.envs.notices import quiet_mjx
from rdher_jax.networks import Actor, Critic, CriticEnsemble

# brax's normaliser. After start-up it imports without MJX (rdher_jax._quiet); a plain import
# of brax imports MJX, whose Warp notices are dropped there, as everywhere MJX is imported.
if not _quiet.brax_deferred():
    quiet_mjx()
from brax.training.acme import running_statistics  # noqa: E402

Params = Any


class Batch(Protocol):
    """Fields of a training batch (`rdher_jax.relabel.Transition` provides them)."""

    obs: jax.Array  # (B, obs_dim)
    goal: jax.Array  # (B, goal_dim)
    action: jax.Array  # (B, act_dim)
    reward: jax.Array  # (B,)
    next_obs: jax.Array  # (B, obs_dim)
    next_goal: jax.Array  # (B, goal_dim)
    hindsight: jax.Array  # (B,) bool: goal is not the stored one (HER or DHER row)
    discount: jax.Array | None  # (B,) bootstrap factor of n-step rows; None: gamma


@struct.dataclass
class DDPGParams:
    """Sweepable learner hyperparameters; every field is a float32 scalar array.

    Relabelling has its own (``rdher_jax.relabel.RelabelParams``).
    """

    actor_lr: jax.Array
    critic_lr: jax.Array
    polyak: jax.Array  # target <- polyak * target + (1 - polyak) * online
    action_l2: jax.Array
    noise_eps: jax.Array  # Gaussian exploration std, as a fraction of max_u
    random_eps: jax.Array  # probability of a uniform random action (per row)
    lambda_r: jax.Array  # reward weight of real transitions (RDHER)
    lambda_h: jax.Array  # reward weight of hindsight transitions (RDHER)
    gamma: jax.Array

    @classmethod
    def default(cls, T: int = 50, **overrides: float) -> DDPGParams:
        """The defaults of ``config.Config`` (baselines' HER settings), unweighted rewards.

        Args:
            T: episode length; sets gamma = 1 - 1/T as in baselines.
            **overrides: field values replacing the defaults.

        Returns:
            DDPGParams with float32 scalar fields.
        """
        from rdher_jax.config import Config

        cfg = Config()
        values: dict[str, float] = {
            k: getattr(cfg, k)
            for k in ("actor_lr", "critic_lr", "polyak", "action_l2", "noise_eps", "random_eps")
        }
        values.update(lambda_r=1.0, lambda_h=1.0, gamma=1.0 - 1.0 / T)
        unknown = set(overrides) - set(values)
        if unknown:
            raise TypeError(f"unknown DDPGParams fields: {sorted(unknown)}")
        values.update(overrides)
        return cls(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})


@struct.dataclass
class DDPGState:
    """Learner state: online and target networks, optimisers and input normalisers."""

    actor_params: Params
    critic_params: Params
    target_actor_params: Params
    target_critic_params: Params
    actor_opt_state: optax.OptState
    critic_opt_state: optax.OptState
    obs_norm: running_statistics.RunningStatisticsState
    goal_norm: running_statistics.RunningStatisticsState


class DDPG(NamedTuple):
    """Pure DDPG functions produced by `make_ddpg` (see there for signatures)."""

    actor: Actor
    critic: Critic | CriticEnsemble
    init: Callable[[jax.Array, DDPGParams], DDPGState]
    q_value: Callable[[Params, jax.Array, jax.Array, jax.Array], jax.Array]
    normalise: Callable[[DDPGState, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
    update_normaliser: Callable[[DDPGState, jax.Array, jax.Array], DDPGState]
    act: Callable[[DDPGState, jax.Array, jax.Array], jax.Array]
    explore: Callable[[jax.Array, DDPGState, jax.Array, jax.Array, DDPGParams], jax.Array]
    critic_target: Callable[[jax.Array, jax.Array, jax.Array, DDPGParams], jax.Array]
    critic_loss: Callable[..., tuple[jax.Array, jax.Array]]
    actor_loss: Callable[[Params, DDPGState, Batch, DDPGParams], jax.Array]
    update: Callable[..., tuple[DDPGState, dict[str, jax.Array]]]
    target_update: Callable[..., DDPGState]


def critic_target(
    reward: jax.Array,
    q_next: jax.Array,
    hindsight: jax.Array,
    hparams: DDPGParams,
    discount: jax.Array | None = None,
    clip: str = "weighted",
) -> jax.Array:
    """Clipped, reward-weighted TD target y = clip(lam * r + gamma * q_next, -lam / (1 - gamma), 0).

    lam is lambda_h on hindsight rows and lambda_r on real rows. With rewards in {-1, 0} the
    weighted return lies in [-lam / (1 - gamma), 0], so by default (``clip="weighted"``) the clip
    range follows each row's weight. ``clip="unweighted"`` clips every row to
    [-1 / (1 - gamma), 0] whatever its weight: baselines' ``clip_return``, which weighting the
    sampled rewards inside baselines-based code (as the paper's Algorithm 1 does) would keep.
    There is no done mask: Fetch episodes end by time limit, which is not termination.

    Args:
        reward: raw rewards, (B,).
        q_next: target-network Q of the next state, (B,).
        hindsight: whether each row's goal was relabelled, (B,) bool.
        hparams: supplies lambda_r, lambda_h, gamma.
        discount: optional (B,) factor on q_next in place of gamma: gamma^m for n-step rows,
            whose reward is already the discounted sum of m rewards, and 0 for rows that do not
            bootstrap (``relabel.mark_terminal``); the clip range keeps gamma's bound.
        clip: "weighted" or "unweighted" (see above).

    Returns:
        Targets (B,), with gradients stopped.
    """
    if clip not in TARGET_CLIPS:
        raise ValueError(f"clip must be one of {TARGET_CLIPS}, got {clip!r}")
    lam = jnp.where(hindsight, hparams.lambda_h, hparams.lambda_r)
    y = lam * reward + (hparams.gamma if discount is None else discount) * q_next
    bound = lam if clip == "weighted" else jnp.ones_like(lam)
    y = jnp.clip(y, -bound / (1.0 - hparams.gamma), 0.0)
    return jax.lax.stop_gradient(y)


def target_subset(key: jax.Array, n_critics: int, size: int) -> jax.Array:
    """The ``size`` of ``n_critics`` target critics whose minimum is a step's TD target (REDQ's
    in-target minimisation): distinct indices drawn uniformly with ``key``, ``(size,)``."""
    return jax.random.choice(key, n_critics, (size,), replace=False)


def _adam(learning_rate: jax.Array) -> optax.GradientTransformation:
    # inject_hyperparams keeps the learning rate in the optimiser state as an array, so a traced
    # (vmapped) learning rate is fine where plain optax.adam would need a Python float.
    return optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)


def _adam_step(
    params: Params, grads: Params, opt_state: optax.OptState, learning_rate: jax.Array
) -> tuple[Params, optax.OptState]:
    # inject_hyperparams reads the rate from its state; overwrite it so the DDPGParams passed to
    # update are authoritative rather than the ones seen at init.
    opt_state = opt_state._replace(
        hyperparams={**opt_state.hyperparams, "learning_rate": learning_rate}
    )
    updates, opt_state = _adam(learning_rate).update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def make_ddpg(
    obs_dim: int,
    goal_dim: int,
    act_dim: int,
    hidden: tuple[int, ...] = (256, 256, 256),
    max_u: float = 1.0,
    clip_obs: float = 200.0,
    norm_eps: float = 0.01,
    norm_clip: float = 5.0,
    target_noise: float = 0.0,
    noise_clip: float = 0.5,
    policy_delay: int = 1,
    layer_norm: bool = False,
    compute_dtype: str = "float32",
    target_clip: str = "weighted",
    n_critics: int = 1,
    target_critics: int | None = None,
) -> DDPG:
    """Builds the DDPG functions for fixed dimensions and architecture.

    Args:
        obs_dim: observation size.
        goal_dim: goal size.
        act_dim: action size.
        hidden: hidden layer widths of actor and critic.
        max_u: action bound.
        clip_obs: raw observations and goals are clipped to +-clip_obs before anything else.
        norm_eps: minimum normaliser std.
        norm_clip: normalised inputs are clipped to +-norm_clip.
        target_noise: std (fraction of max_u) of Gaussian noise on the target policy's action,
            TD3's target smoothing; 0 (baselines) is none.
        noise_clip: that noise is clipped to +-noise_clip * max_u.
        policy_delay: the actor is updated on every policy_delay-th gradient step (TD3's
            delayed policy update); 1 (baselines) updates it on every step.
        layer_norm: LayerNorm in the critic's hidden layers.
        compute_dtype: the hidden layers' matmul dtype, "float32" or "bfloat16" (parameters,
            optimiser state, losses and the output layers stay float32).
        target_clip: the critic target's clip range, "weighted" (per row, [-lam/(1-gamma), 0])
            or "unweighted" ([-1/(1-gamma), 0] for every row); see `critic_target`.
        n_critics: critics trained side by side on the same targets (an ensemble; 1: the single
            critic of baselines). Each has its own initialisation and target network; the actor
            ascends their mean Q, and Q diagnostics report that mean.
        target_critics: the TD target bootstraps from the minimum over this many of the
            n_critics target critics, a subset drawn afresh at every gradient step (REDQ's
            in-target minimisation; with n_critics = 2 and 2 here, TD3's clipped double Q).
            None: all n_critics.
    Returns:
        A DDPG of pure, jittable functions.
    """
    if target_clip not in TARGET_CLIPS:
        raise ValueError(f"target_clip must be one of {TARGET_CLIPS}, got {target_clip!r}")
    if compute_dtype not in ("float32", "bfloat16"):
        raise ValueError(f"compute_dtype must be float32 or bfloat16, got {compute_dtype!r}")
    dtype = None if compute_dtype == "float32" else jnp.bfloat16  # None: the float32 path
    actor = Actor(act_dim=act_dim, hidden=tuple(hidden), max_u=max_u, dtype=dtype)
    if n_critics < 1:
        raise ValueError(f"n_critics must be >= 1, got {n_critics}")
    n_target = n_critics if target_critics is None else target_critics
    if not 1 <= n_target <= n_critics:
        raise ValueError(f"target_critics must be in [1, n_critics={n_critics}], got {n_target}")
    if n_critics == 1:  # the single critic's parameters keep their shapes (no ensemble axis)
        critic = Critic(hidden=tuple(hidden), max_u=max_u, layer_norm=layer_norm, dtype=dtype)
    else:
        critic = CriticEnsemble(n_critics, tuple(hidden), max_u, layer_norm, dtype)
    if policy_delay < 1:
        raise ValueError(f"policy_delay must be >= 1, got {policy_delay}")

    def q_value(params: Params, obs: jax.Array, goal: jax.Array, action: jax.Array) -> jax.Array:
        """The critics' mean Q on normalised inputs, (B,): what the actor ascends."""
        q = critic.apply(params, obs, goal, action)
        return q if n_critics == 1 else jnp.mean(q, axis=0)

    def init(key: jax.Array, hparams: DDPGParams) -> DDPGState:
        """Fresh networks (targets equal to online), Adam states and empty normalisers."""
        k_actor, k_critic = jax.random.split(key)
        obs = jnp.zeros((1, obs_dim), jnp.float32)
        goal = jnp.zeros((1, goal_dim), jnp.float32)
        action = jnp.zeros((1, act_dim), jnp.float32)
        actor_params = actor.init(k_actor, obs, goal)
        critic_params = critic.init(k_critic, obs, goal, action)

        def norm_state(dim: int) -> running_statistics.RunningStatisticsState:
            state = running_statistics.init_state(jnp.zeros((dim,), jnp.float32))
            # brax leaves std_eps a Python float; an array leaf keeps the state a uniform
            # pytree of arrays under vmap and scan. Zero so std = max(norm_eps, sqrt(var)).
            return state.replace(std_eps=jnp.zeros((), jnp.float32))

        return DDPGState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_actor_params=actor_params,
            target_critic_params=critic_params,
            actor_opt_state=_adam(hparams.actor_lr).init(actor_params),
            critic_opt_state=_adam(hparams.critic_lr).init(critic_params),
            obs_norm=norm_state(obs_dim),
            goal_norm=norm_state(goal_dim),
        )

    def normalise(state: DDPGState, obs: jax.Array, goal: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Clips raw inputs to +-clip_obs, standardises them, clips to +-norm_clip."""
        obs = running_statistics.normalize(
            jnp.clip(obs, -clip_obs, clip_obs), state.obs_norm, max_abs_value=norm_clip
        )
        goal = running_statistics.normalize(
            jnp.clip(goal, -clip_obs, clip_obs), state.goal_norm, max_abs_value=norm_clip
        )
        return obs, goal

    def update_normaliser(state: DDPGState, obs: jax.Array, goal: jax.Array) -> DDPGState:
        """Adds raw observations (..., obs_dim) and goals (..., goal_dim) to the statistics."""
        obs_norm = running_statistics.update(
            state.obs_norm, jnp.clip(obs, -clip_obs, clip_obs), std_min_value=norm_eps
        )
        goal_norm = running_statistics.update(
            state.goal_norm, jnp.clip(goal, -clip_obs, clip_obs), std_min_value=norm_eps
        )
        return state.replace(obs_norm=obs_norm, goal_norm=goal_norm)

    def act(state: DDPGState, obs: jax.Array, goal: jax.Array) -> jax.Array:
        """Deterministic policy action for raw (..., obs_dim) observations and goals."""
        return actor.apply(state.actor_params, *normalise(state, obs, goal))

    def explore(
        key: jax.Array, state: DDPGState, obs: jax.Array, goal: jax.Array, hparams: DDPGParams
    ) -> jax.Array:
        """Baselines exploration: Gaussian noise, clip, then uniform random rows w.p. random_eps."""
        k_noise, k_coin, k_uniform = jax.random.split(key, 3)
        action = act(state, obs, goal)
        action = action + hparams.noise_eps * max_u * jax.random.normal(k_noise, action.shape)
        action = jnp.clip(action, -max_u, max_u)
        # One coin per row (not per dimension): a random action replaces the whole action.
        coin = jax.random.bernoulli(k_coin, hparams.random_eps, action.shape[:-1])
        uniform = jax.random.uniform(k_uniform, action.shape, minval=-max_u, maxval=max_u)
        return jnp.where(coin[..., None], uniform, action)

    def critic_loss(
        critic_params: Params,
        state: DDPGState,
        batch: Batch,
        hparams: DDPGParams,
        key: jax.Array | None = None,
    ) -> tuple[jax.Array, jax.Array]:
        """Returns (mean squared TD error, mean Q(o, g, a)) for the given critic parameters.

        ``key`` draws the target-smoothing noise and the target critics' subset; it is needed
        only when target_noise > 0 or target_critics < n_critics. With several critics, each
        regresses on the same targets: the loss and Q are means over critics and batch.
        """
        needs_key = target_noise > 0.0 or n_target < n_critics
        if needs_key and key is None:
            raise ValueError("target_noise > 0 or target_critics < n_critics needs a PRNG key "
                             "in critic_loss/update")
        if n_target < n_critics:
            key, k_subset = jax.random.split(key)
        obs, goal = normalise(state, batch.obs, batch.goal)
        next_obs, next_goal = normalise(state, batch.next_obs, batch.next_goal)
        next_action = actor.apply(state.target_actor_params, next_obs, next_goal)
        if target_noise > 0.0:
            eps = target_noise * max_u * jax.random.normal(key, next_action.shape)
            eps = jnp.clip(eps, -noise_clip * max_u, noise_clip * max_u)
            next_action = jnp.clip(next_action + eps, -max_u, max_u)
        q_next = critic.apply(state.target_critic_params, next_obs, next_goal, next_action)
        if n_critics > 1:  # (n_critics, B): the minimum over the target subset
            if n_target < n_critics:
                q_next = q_next[target_subset(k_subset, n_critics, n_target)]
            q_next = jnp.min(q_next, axis=0)
        y = critic_target(batch.reward, q_next, batch.hindsight, hparams, batch.discount,
                          clip=target_clip)
        # With several critics, y broadcasts over them; each critic's parameters see only their
        # own term, so the mean trains each on its own squared error (Adam is blind to the
        # 1/n_critics scale).
        q = critic.apply(critic_params, obs, goal, batch.action)
        return jnp.mean(jnp.square(q - y)), jnp.mean(q)

    def actor_loss(
        actor_params: Params, state: DDPGState, batch: Batch, hparams: DDPGParams
    ) -> jax.Array:
        """Returns -mean Q(o, g, pi(o, g)) + action_l2 * mean((pi / max_u)^2)."""
        obs, goal = normalise(state, batch.obs, batch.goal)
        pi = actor.apply(actor_params, obs, goal)
        q_pi = q_value(state.critic_params, obs, goal, pi)
        return -jnp.mean(q_pi) + hparams.action_l2 * jnp.mean(jnp.square(pi / max_u))

    def update(
        state: DDPGState,
        batch: Batch,
        hparams: DDPGParams,
        key: jax.Array | None = None,
        step: jax.Array | int = 0,
    ) -> tuple[DDPGState, dict[str, jax.Array]]:
        """One gradient step on the critic and (every policy_delay-th step) the actor.

        Targets are untouched. Both gradients come from the pre-update parameters, as in
        baselines, where one session run computes them before either Adam step is applied.

        Args:
            state: learner state.
            batch: transitions with (B, ...) fields.
            hparams: supplies learning rates and loss weights.
            key: PRNG key for target smoothing and the target critics' subset (see critic_loss).
            step: gradient-step counter; the actor steps when step % policy_delay == 0.

        Returns:
            (new state, metrics dict with critic_loss, actor_loss, q_mean).
        """
        (c_loss, q_mean), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(
            state.critic_params, state, batch, hparams, key
        )
        critic_params, critic_opt_state = _adam_step(
            state.critic_params, c_grads, state.critic_opt_state, hparams.critic_lr
        )

        def actor_step(_):
            a_loss, a_grads = jax.value_and_grad(actor_loss)(
                state.actor_params, state, batch, hparams
            )
            params, opt_state = _adam_step(
                state.actor_params, a_grads, state.actor_opt_state, hparams.actor_lr
            )
            return params, opt_state, a_loss

        if policy_delay == 1:
            actor_params, actor_opt_state, a_loss = actor_step(None)
        else:
            # lax.cond runs one branch, so the skipped actor steps cost nothing.
            actor_params, actor_opt_state, a_loss = jax.lax.cond(
                jnp.asarray(step) % policy_delay == 0,
                actor_step,
                lambda _: (state.actor_params, state.actor_opt_state, jnp.float32(jnp.nan)),
                None,
            )
        state = state.replace(
            actor_params=actor_params,
            critic_params=critic_params,
            actor_opt_state=actor_opt_state,
            critic_opt_state=critic_opt_state,
        )
        return state, {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": q_mean}

    def target_update(
        state: DDPGState, hparams: DDPGParams, do: jax.Array | bool = True
    ) -> DDPGState:
        """Polyak averaging: target <- polyak * target + (1 - polyak) * online.

        ``do`` (a traced bool is fine) False leaves the targets as they are.
        """
        p = jnp.where(do, hparams.polyak, 1.0)

        def mix(target: Params, online: Params) -> Params:
            return jax.tree.map(lambda t, o: p * t + (1.0 - p) * o, target, online)

        return state.replace(
            target_actor_params=mix(state.target_actor_params, state.actor_params),
            target_critic_params=mix(state.target_critic_params, state.critic_params),
        )

    return DDPG(
        actor=actor,
        critic=critic,
        q_value=q_value,
        init=init,
        normalise=normalise,
        update_normaliser=update_normaliser,
        act=act,
        explore=explore,
        critic_target=functools.partial(critic_target, clip=target_clip),
        critic_loss=critic_loss,
        actor_loss=actor_loss,
        update=update,
        target_update=target_update,
    )
