"""Goal relabelling strategies behind one interface.

Every strategy is three pure functions built by :func:`make_relabeller` from the config, in the
shape flashbax and Brax use for extension points:

- ``init() -> state``: the strategy's own state (``()`` for HER and CHER, match indices for
  DHER). It lives in ``TrainState.relabel``, so it is checkpointed, resumed and vmapped with
  everything else.
- ``update(state, buffer, params) -> state``: called once per cycle, after the cycle's
  ``num_envs`` new episodes were added to ``buffer``.
- ``sample(key, state, buffer, params, step) -> (state, Transition)``: one training batch.
  ``step`` counts gradient steps since the start of the epoch (CHER's proximity weight grows
  with it).

Rows carry where they came from (``Transition.source``: real, HER-relabelled, DHER-combined),
so reward weights and diagnostics can tell them apart. Hyperparameters of relabelling are a
pytree of their own (:class:`RelabelParams`), traced like ``ddpg.HParams``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from rdher_jax.buffer import BufferState
from rdher_jax.config import TERMINAL_RULES
from rdher_jax.relabel.her import (
    DHER,
    HER,
    REAL,
    SOURCE_NAMES,
    RewardFn,
    Transition,
    relabel_prob_from_k,
    sample_episodes,
    sample_her,
)

# algo -> strategy. ARCHER and RDHER differ from HER and DHER only in their reward weights.
STRATEGIES: dict[str, str] = {
    "ddpg": "her", "her": "her", "archer": "her", "cher": "cher", "dher": "dher", "rdher": "dher",
}


@struct.dataclass
class RelabelParams:
    """Traced hyperparameters of relabelling; every field is a float32 scalar array.

    Attributes:
        relabel_prob: probability that a plain sample gets a 'future' goal (0 for DDPG).
        dher_fraction: DHER fills ``dher_fraction * (1 - recent success rate)`` of a batch with
            combined transitions (0.8 in the DHER authors' code).
        dher_tol: cell size of DHER goal matching, in metres (the authors key positions on a
            1 cm grid).
        cher_growth: CHER's proximity weight is ``cher_growth ** step`` (1.0001 in CHER).
    """

    relabel_prob: jax.Array
    dher_fraction: jax.Array
    dher_tol: jax.Array
    cher_growth: jax.Array

    @classmethod
    def default(cls, **overrides: float) -> RelabelParams:
        values = dict(relabel_prob=0.8, dher_fraction=0.8, dher_tol=0.01, cher_growth=1.0001)
        unknown = set(overrides) - set(values)
        if unknown:
            raise TypeError(f"unknown RelabelParams fields: {sorted(unknown)}")
        values.update(overrides)
        return cls(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})


class Relabeller(NamedTuple):
    """A relabelling strategy as pure functions (see the module docstring)."""

    name: str
    init: Callable[[], Any]
    update: Callable[[Any, BufferState, RelabelParams], Any]
    sample: Callable[[jax.Array, Any, BufferState, RelabelParams, jax.Array],
                     tuple[Any, Transition]]


def params_from_config(cfg) -> RelabelParams:
    """The traced relabelling parameters of a resolved config."""
    prob = relabel_prob_from_k(cfg.replay_k) if cfg.algo != "ddpg" else 0.0
    return RelabelParams.default(relabel_prob=prob, dher_fraction=cfg.dher_fraction,
                                 dher_tol=cfg.dher_tol, cher_growth=cfg.cher_growth)


def make_her(compute_reward: RewardFn, batch_size: int) -> Relabeller:
    """'future' relabelling (baselines' her_sampler); stateless."""

    def sample(key, state, buffer, params, step):
        del step
        return state, sample_her(key, buffer, batch_size, params.relabel_prob, compute_reward)

    return Relabeller("her", init=lambda: (), update=lambda s, b, p: s, sample=sample)


def make_relabeller(cfg, compute_reward: RewardFn, capacity_episodes: int, T: int,
                    goal_dim: int) -> Relabeller:
    """The strategy ``cfg.algo`` asks for, with shapes fixed by the config.

    Args:
        cfg: a resolved ``Config``.
        compute_reward: the env's ``(achieved, desired) -> reward``.
        capacity_episodes: episode slots of the replay buffer.
        T: episode horizon.
        goal_dim: goal size.

    Returns:
        A :class:`Relabeller`.
    """
    kind = STRATEGIES[cfg.algo]
    if kind == "her":
        return make_her(compute_reward, cfg.batch_size)
    if kind == "dher":
        from rdher_jax.relabel.dher import make_dher

        return make_dher(compute_reward, cfg.batch_size, capacity_episodes, T, goal_dim,
                         num_new=cfg.num_envs, records=cfg.dher_records,
                         partners=cfg.dher_partners)
    from rdher_jax.relabel.cher import make_cher

    return make_cher(compute_reward, cfg.batch_size, cfg.cher_candidates or 2 * cfg.batch_size,
                     cfg.cher_sample)


def row_goals(buffer: BufferState, batch: Transition, steps: jax.Array) -> jax.Array:
    """The goal in force for each row at ``steps`` of its episode, ``(B, n) -> (B, n, d)``.

    Fixed for HER rows; ``g[goal_ep, step + goal_shift]`` (held at the episode's ends) for real
    rows (``goal_ep = ep``, no shift) and DHER rows (the goal-providing episode's goals).
    """
    idx = jnp.clip(steps + batch.goal_shift[:, None], 0, buffer.horizon)
    traj = buffer.g[batch.goal_ep[:, None], idx]
    return jnp.where((batch.source == HER)[:, None, None], batch.goal[:, None, :], traj)


def observed_return(buffer: BufferState, batch: Transition, compute_reward: RewardFn,
                    gamma: jax.Array) -> jax.Array:
    """Discounted return each row's goal actually received in its stored episode.

    ``sum_{k=t}^{T-1} gamma^(k-t) r(ag[ep, k+1], goal_{k+1})``, unweighted, where the goal
    follows the row: the stored goals for real rows, the fixed relabelled goal for HER rows, and
    the goal-providing episode's desired goals (``g[goal_ep, k + goal_shift]``, held at its
    ends) for DHER rows. The return is truncated at the episode's end, as the episode was.

    Returns:
        ``(batch,)`` float32.
    """
    T = buffer.horizon
    k = jnp.arange(T, dtype=jnp.int32)[None, :]  # (1, T)
    r = compute_reward(buffer.ag[batch.ep[:, None], k + 1], row_goals(buffer, batch, k + 1))
    live = k >= batch.t[:, None]
    disc = gamma ** jnp.maximum(k - batch.t[:, None], 0).astype(jnp.float32)
    return jnp.sum(jnp.where(live, disc * r, 0.0), axis=-1)


def n_step(buffer: BufferState, batch: Transition, n: int, gamma: jax.Array,
           compute_reward: RewardFn, stop_at_success: bool = False) -> Transition:
    """The n-step version of each row: ``n`` rewards summed, then one bootstrap.

    Row (ep, t) with its goal becomes ``R = sum_{k<m} gamma^k r(ag[ep, t+k+1], goal_{t+k+1})``,
    ``next_obs = o[ep, t+m]``, ``next_goal = goal_{t+m}`` and ``discount = gamma^m``, where
    ``m = min(n, T - t)`` (no step past the episode's end). The goal follows the row as in
    :func:`observed_return`: fixed for HER rows, the stored goals for real rows and the
    goal-providing episode's (held at its ends) for DHER rows. The actions after ``t`` are the
    behaviour policy's: the return is not corrected for being off-policy. ``n = 1`` gives the
    one-step row back (with ``discount = gamma``).

    With ``stop_at_success`` (for ``terminal=success``) a row ends at the first step whose
    reward is 0: the sum stops there and ``discount`` is 0, so it does not bootstrap.

    Returns:
        The batch with reward, next_obs, next_goal and discount replaced.
    """
    T = buffer.horizon
    k = jnp.arange(n, dtype=jnp.int32)[None, :]  # (1, n)
    step = batch.t[:, None] + k  # (B, n): the transition t+k
    live = step < T
    m = jnp.sum(live, axis=-1).astype(jnp.int32)  # min(n, T - t) >= 1
    s1 = jnp.minimum(step + 1, T)
    goal = row_goals(buffer, batch, s1)
    r = compute_reward(buffer.ag[batch.ep[:, None], s1], goal).astype(jnp.float32)
    discount = gamma ** m.astype(jnp.float32)
    if stop_at_success:
        success = live & (r > -0.5)
        # Live up to and including the first success.
        before = jnp.cumsum(success, axis=-1) - success
        live = live & (before == 0)
        m = jnp.sum(live, axis=-1).astype(jnp.int32)
        discount = jnp.where(jnp.any(success & live, axis=-1), 0.0, gamma ** m.astype(jnp.float32))
    disc = gamma ** k.astype(jnp.float32)
    rows = jnp.arange(batch.t.shape[0])
    return batch.replace(
        reward=jnp.sum(jnp.where(live, disc * r, 0.0), axis=-1),
        next_obs=buffer.obs[batch.ep, batch.t + m],
        next_goal=goal[rows, m - 1],
        discount=discount.astype(jnp.float32),
    )


def with_terminal(buffer: BufferState, batch: Transition, rule: str,
                  gamma: jax.Array) -> Transition:
    """Marks rows that do not bootstrap by giving them ``discount = 0``.

    ``rule``: ``"none"`` (Fetch episodes end by time limit only: every row bootstraps),
    ``"success"`` (a row whose reward is 0, i.e. whose goal was reached), or ``"exact"`` (a row
    whose goal at ``t+1`` equals the achieved goal at ``t+1`` exactly: the HER rows relabelled
    with the very next achieved goal, DRLib's rule, and, where the achieved goal rests between
    steps (an untouched object), every HER row relabelled with a later one; never a real goal
    in practice). Applies to one-step rows; ``n_step`` handles ``"success"`` itself.
    """
    if rule == "none":
        return batch
    if rule == "success":
        term = batch.reward > -0.5  # rewards are -1 (not reached) or 0 (reached)
    elif rule == "exact":
        term = jnp.all(batch.next_goal == buffer.ag[batch.ep, batch.t + 1], axis=-1)
    else:
        raise ValueError(f"unknown terminal rule {rule!r}; valid: {', '.join(TERMINAL_RULES)}")
    discount = gamma if batch.discount is None else batch.discount
    return batch.replace(discount=jnp.where(term, 0.0, discount).astype(jnp.float32))


__all__ = ["DHER", "HER", "REAL", "SOURCE_NAMES", "STRATEGIES", "RelabelParams", "Relabeller",
           "Transition", "make_relabeller", "n_step", "observed_return", "params_from_config",
           "relabel_prob_from_k", "sample_episodes", "sample_her", "with_terminal"]
