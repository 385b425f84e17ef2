"""Goal relabelling strategies behind one interface, and the targets built from their batches.

- ``base``: the ``Transition`` batch and its source ids, the ``Relabeller`` interface
  (init / update / sample) and ``RelabelParams``, the traced hyperparameters.
- ``her``, ``cher``, ``dher``: the strategies ('future', CHER's curriculum, DHER's matching),
  each with its ``make_*`` returning a ``Relabeller``; ``energy``: 'future' relabelling with
  energy-prioritised episodes (``replay_priority=energy``).
- ``targets``: n-step returns and terminal rules over a sampled batch, and the observed return
  of the hindsight-bias diagnostic.

:func:`make_relabeller` builds the strategy a config asks for.
"""

from __future__ import annotations

from rdher_jax.relabel.base import (
    DHER,
    HER,
    REAL,
    SOURCE_NAMES,
    Relabeller,
    RelabelParams,
    RewardFn,
    Transition,
    params_from_config,
    relabel_prob_from_k,
)
from rdher_jax.relabel.cher import make_cher
from rdher_jax.relabel.dher import make_dher
from rdher_jax.relabel.energy import make_her_energy, trajectory_energy
from rdher_jax.relabel.her import make_her, sample_episodes, sample_her
from rdher_jax.relabel.targets import mark_terminal, n_step_returns, observed_return, row_goals

# algo -> strategy. ARCHER and RDHER differ from HER and DHER only in their reward weights.
STRATEGIES: dict[str, str] = {
    "ddpg": "her", "her": "her", "archer": "her", "cher": "cher", "dher": "dher", "rdher": "dher",
}


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
    if kind == "her" and cfg.replay_priority == "energy":
        return make_her_energy(compute_reward, cfg.batch_size, capacity_episodes,
                               num_new=cfg.num_envs, clip=cfg.energy_clip)
    if kind == "her":
        return make_her(compute_reward, cfg.batch_size)
    if kind == "dher":
        return make_dher(compute_reward, cfg.batch_size, capacity_episodes, T, goal_dim,
                         num_new=cfg.num_envs, records=cfg.dher_records,
                         partners=cfg.dher_partners)
    return make_cher(compute_reward, cfg.batch_size, cfg.cher_candidates or 2 * cfg.batch_size,
                     cfg.cher_sample)


__all__ = ["DHER", "HER", "REAL", "SOURCE_NAMES", "STRATEGIES", "RelabelParams", "Relabeller",
           "RewardFn", "Transition", "make_cher", "make_dher", "make_her", "make_her_energy",
           "make_relabeller", "mark_terminal", "n_step_returns", "observed_return",
           "params_from_config", "relabel_prob_from_k", "row_goals", "sample_episodes",
           "sample_her", "trajectory_energy"]
