"""Hindsight experience replay with the 'future' strategy, as in OpenAI baselines.

Follows ``baselines/her/her_sampler.py``: a transition ``(e, t)`` is drawn uniformly, and with
probability ``relabel_prob`` its goal is replaced by the achieved goal at a strictly future step
``future_t`` in ``[t+1, T]`` (stable-baselines3 also allows ``future_t == t``). The reward is
recomputed from the achieved goal after the action.

Sampling is split into ``draw_her`` (all random draws) and ``gather_her`` (a deterministic
gather), so a reference implementation can be fed the same draws.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rdher_jax.buffer import BufferState, Episode, indices_from_bits
from rdher_jax.relabel.base import HER, REAL, Relabeller, RewardFn, Transition


def future_step(t: jax.Array, u: jax.Array, T: int) -> jax.Array:
    """Map uniforms ``u`` in ``[0, 1)`` to a strictly future step ``t + 1 + floor(u * (T - t))``.

    Args:
        t: int step indices in ``[0, T)``.
        u: float uniforms in ``[0, 1)``, same shape as ``t``.
        T: episode horizon.

    Returns:
        int32 steps in ``[t+1, T]``.
    """
    offset = jnp.floor(u * (T - t).astype(u.dtype)).astype(jnp.int32)
    # Guard against float rounding pushing u * (T - t) up to T - t, which would index T + 1.
    return jnp.minimum(t + 1 + offset, T).astype(jnp.int32)


def draw_her(
    key: jax.Array,
    num_episodes: jax.Array,
    T: int,
    batch_size: int,
    relabel_prob: jax.Array | float,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Make every random draw of one HER batch.

    Args:
        key: PRNG key.
        num_episodes: int32 scalar, episodes stored (may be traced).
        T: episode horizon (static).
        batch_size: number of samples (static).
        relabel_prob: probability of relabelling each sample (may be traced).

    Returns:
        ``(ep_idx, t, future_t, mask)``: int32 episode slots in ``[0, num_episodes)``, int32
        steps in ``[0, T)``, int32 future steps in ``[t+1, T]`` and the bool relabel mask, all
        of shape ``(batch_size,)``.
    """
    # One bits draw for the whole batch: cheaper to compile and run than one call per array.
    bits = jax.random.bits(key, (4, batch_size), jnp.uint32)
    ep_idx, t = indices_from_bits(bits[:2], num_episodes, T)
    # The top 24 bits give floats exactly, in [0, 1 - 2**-24].
    u = (bits[2:] >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)
    future_t = future_step(t, u[0], T)
    # A per-sample Bernoulli mask as in baselines (not a fixed integer split), so the
    # probability can be a traced value that is scheduled or swept at run time.
    mask = u[1] < relabel_prob
    return ep_idx, t, future_t, mask


def gather_her(
    buffer: BufferState | Episode,
    ep_idx: jax.Array,
    t: jax.Array,
    future_t: jax.Array,
    mask: jax.Array,
    compute_reward: RewardFn,
) -> Transition:
    """Gather a HER batch for given draws.

    Args:
        buffer: the replay buffer, or a batch of whole episodes (same field layout).
        ep_idx: int episode slots, ``(batch,)``.
        t: int steps in ``[0, T)``, ``(batch,)``.
        future_t: int steps in ``[t+1, T]``, ``(batch,)``.
        mask: bool relabel mask, ``(batch,)``.
        compute_reward: ``(achieved, desired) -> reward``, vectorised over leading dims.

    Returns:
        The ``Transition`` batch.
    """
    m = mask[:, None]
    future_ag = buffer.ag[ep_idx, future_t]
    goal = jnp.where(m, future_ag, buffer.g[ep_idx, t])
    next_goal = jnp.where(m, future_ag, buffer.g[ep_idx, t + 1])
    # The reward of (o_t, a_t) is judged on the achieved goal after the action, against the goal
    # in force at t+1 (the relabelled one, or the possibly moving original goal).
    reward = compute_reward(buffer.ag[ep_idx, t + 1], next_goal).astype(jnp.float32)
    return Transition(
        obs=buffer.obs[ep_idx, t],
        goal=goal,
        action=buffer.action[ep_idx, t],
        reward=reward,
        next_obs=buffer.obs[ep_idx, t + 1],
        next_goal=next_goal,
        source=jnp.where(mask, HER, REAL).astype(jnp.int32),
        ep=ep_idx,
        t=t,
        goal_ep=ep_idx,
        goal_shift=jnp.zeros_like(t),
    )


def sample_her(
    key: jax.Array,
    buffer: BufferState,
    batch_size: int,
    relabel_prob: jax.Array | float,
    compute_reward: RewardFn,
) -> Transition:
    """Sample a batch with 'future' hindsight relabelling.

    Args:
        key: PRNG key.
        buffer: the replay buffer (must hold at least one episode).
        batch_size: number of transitions (static).
        relabel_prob: probability of relabelling each sample (may be traced; 0.8 for k=4).
        compute_reward: ``(achieved, desired) -> reward``, vectorised over leading dims.

    Returns:
        A ``Transition`` batch.
    """
    draws = draw_her(key, buffer.num_episodes, buffer.horizon, batch_size, relabel_prob)
    return gather_her(buffer, *draws, compute_reward)


def sample_episodes(
    key: jax.Array,
    episodes: Episode,
    batch_size: int,
    relabel_prob: jax.Array | float,
    compute_reward: RewardFn,
) -> Transition:
    """'future' relabelled transitions drawn from a batch of whole episodes (no buffer).

    The trainer feeds the observation normaliser with these, from the episodes just collected,
    as baselines does.
    """
    n = jnp.asarray(episodes.action.shape[0], jnp.int32)
    draws = draw_her(key, n, episodes.action.shape[1], batch_size, relabel_prob)
    return gather_her(episodes, *draws, compute_reward)


def make_her(compute_reward: RewardFn, batch_size: int) -> Relabeller:
    """'future' relabelling (baselines' her_sampler) as a ``Relabeller``; stateless."""

    def sample(key, state, buffer, params, step):
        del state, step
        return sample_her(key, buffer, batch_size, params.relabel_prob, compute_reward)

    return Relabeller("her", init=lambda: (), update=lambda s, b, p: s, sample=sample)
