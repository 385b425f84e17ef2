"""From a sampled batch to what the critic's target needs, and the return a row really received.

A relabeller's ``sample`` gives one-step rows. The trainer then either folds ``n`` steps into
each row (:func:`n_step_returns`) or marks the rows that must not bootstrap
(:func:`mark_terminal`). :func:`observed_return` is the discounted return a row's goal received
in its stored episode, which the hindsight-bias diagnostic compares with Q. All three follow a
row's goal through its episode with :func:`row_goals`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rdher_jax.buffer import BufferState
from rdher_jax.config import TERMINAL_RULES
from rdher_jax.relabel.base import HER, RewardFn, Transition


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


def n_step_returns(buffer: BufferState, batch: Transition, n: int, gamma: jax.Array,
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


def mark_terminal(buffer: BufferState, batch: Transition, rule: str,
                  gamma: jax.Array) -> Transition:
    """Marks rows that do not bootstrap by giving them ``discount = 0``.

    ``rule``: ``"none"`` (Fetch episodes end by time limit only: every row bootstraps),
    ``"success"`` (a row whose reward is 0, i.e. whose goal was reached), or ``"exact"`` (a row
    whose goal at ``t+1`` equals the achieved goal at ``t+1`` exactly: the HER rows relabelled
    with the very next achieved goal, DRLib's rule, and, where the achieved goal rests between
    steps (an untouched object), every HER row relabelled with a later one; never a real goal
    in practice). Applies to one-step rows; :func:`n_step_returns` handles ``"success"`` itself.
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
