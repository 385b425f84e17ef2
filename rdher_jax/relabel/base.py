"""What every relabelling strategy shares: the batch it returns, its interface and its parameters.

Every strategy is three pure functions, in the shape flashbax and Brax use for extension points:

- ``init() -> state``: the strategy's own state (``()`` for HER and CHER, match indices for
  DHER). It lives in ``TrainState.relabel``, so it is checkpointed, resumed and vmapped with
  everything else.
- ``update(state, buffer, params) -> state``: called once per cycle, after the cycle's
  ``num_envs`` new episodes were added to ``buffer``.
- ``sample(key, state, buffer, params, step) -> Transition``: one training batch; it reads the
  state and never changes it. ``step`` counts gradient steps since the start of the epoch
  (CHER's proximity weight grows with it).

Rows carry where they came from (``Transition.source``: real, HER-relabelled, DHER-combined),
so reward weights and diagnostics can tell them apart. Hyperparameters of relabelling are a
pytree of their own (:class:`RelabelParams`), traced like ``ddpg.DDPGParams``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from rdher_jax.buffer import BufferState

RewardFn = Callable[[jax.Array, jax.Array], jax.Array]

# Where a sampled row's goal came from (``Transition.source``).
REAL, HER, DHER = 0, 1, 2
SOURCE_NAMES = ("real", "her", "dher")


@struct.dataclass
class Transition:
    """A training batch; every field has leading dimension ``batch_size``.

    Attributes:
        obs: ``o_t``.
        goal: goal the actor and critic are conditioned on at ``t``.
        action: ``a_t``.
        reward: ``(batch,)`` float32, recomputed with ``compute_reward``.
        next_obs: ``o_{t+1}``.
        next_goal: goal at ``t+1`` (equal to ``goal`` for HER-relabelled samples).
        source: ``(batch,)`` int32, where the row came from: ``REAL`` (the stored goal),
            ``HER`` ('future' relabelled) or ``DHER`` (combined with another episode's goals).
        ep: ``(batch,)`` int32 episode slot of ``(o_t, a_t, o_{t+1})``.
        t: ``(batch,)`` int32 step of that transition in its episode.
        goal_ep: ``(batch,)`` int32 slot whose desired-goal trajectory the row follows (``ep``
            for real rows, the goal-providing episode for DHER rows; unused for HER rows).
        goal_shift: ``(batch,)`` int32: at step ``k`` of episode ``ep`` the row's goal is
            ``g[goal_ep, k + goal_shift]`` (0 for real rows; unused for HER rows).

        discount: ``(batch,)`` float32 factor on the bootstrapped value, or ``None`` for
            ``gamma`` (one-step rows); set by ``targets.n_step_returns`` and
            ``targets.mark_terminal``.

    The four index fields let diagnostics follow a row's goal through its stored episode
    (``targets.observed_return``); the learner reads the first seven and discount.
    """

    obs: jax.Array
    goal: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    next_goal: jax.Array
    source: jax.Array
    ep: jax.Array
    t: jax.Array
    goal_ep: jax.Array
    goal_shift: jax.Array
    discount: jax.Array | None = None

    @property
    def hindsight(self) -> jax.Array:
        """``(batch,)`` bool: the goal is not the stored one (HER or DHER row)."""
        return self.source != REAL


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
        """The defaults of ``config.Config`` (relabel_prob from its replay_k)."""
        from rdher_jax.config import Config

        cfg = Config()
        values = dict(relabel_prob=relabel_prob_from_k(cfg.replay_k),
                      dher_fraction=cfg.dher_fraction, dher_tol=cfg.dher_tol,
                      cher_growth=cfg.cher_growth)
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
    sample: Callable[[jax.Array, Any, BufferState, RelabelParams, jax.Array], Transition]


def relabel_prob_from_k(k: float) -> float:
    """Relabel probability for ``k`` relabelled goals per real goal (baselines' ``replay_k``).

    Args:
        k: ratio of relabelled to original goals (4 in baselines).

    Returns:
        ``1 - 1 / (1 + k)`` (0.8 for ``k = 4``).
    """
    return 1.0 - 1.0 / (1.0 + k)


def params_from_config(cfg) -> RelabelParams:
    """The traced relabelling parameters of a resolved config."""
    prob = relabel_prob_from_k(cfg.replay_k) if cfg.algo != "ddpg" else 0.0
    return RelabelParams.default(relabel_prob=prob, dher_fraction=cfg.dher_fraction,
                                 dher_tol=cfg.dher_tol, cher_growth=cfg.cher_growth)
