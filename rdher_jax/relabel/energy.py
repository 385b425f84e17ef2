"""Energy-based episode prioritisation for 'future' relabelling (Zhao & Tresp, CoRL 2018).

HER draws the episode of each training row uniformly. Energy-based prioritisation (EBP) draws
it with probability proportional to its *trajectory energy*: how much work the episode did on
the object. On the object tasks most early episodes never touch the object, and their rows
(and every 'future' goal relabelled from them) teach nothing about moving it; EBP replays the
episodes that did.

Following the authors' code (``ruizhaogit/EnergyBasedPrioritization``, ``replay_buffer.py``,
Fetch branch, ``rank_method='none'``), for an episode's achieved goals ``ag_0 .. ag_T`` (the
object's position on the object tasks) with ``g = 9.81``, ``m = 1`` and ``dt = 0.04`` s:

- potential energy ``P_t = g m (z_t - z_0)`` and kinetic energy
  ``K_t = m/2 |(ag_t - ag_{t-1}) / dt|^2`` for ``t = 1 .. T``, ``E_t = P_t + K_t``;
- transition energy ``e_1 = E_1``, ``e_t = E_t - E_{t-1}``, each clipped to ``[0, clip]``;
- trajectory energy ``sum_t e_t``; an episode's sampling weight is its trajectory energy.

An episode that never moves the object weighs 0 and is not replayed while any other weighs
more; while every stored episode weighs 0 (nothing touched yet) episodes are drawn uniformly,
as HER does (the authors' code has no such case: its normalisation divides by zero). The rows
of a drawn episode are relabelled exactly as HER's (``her.draw_her``'s step, future step and
mask), so only the episode draw differs.

The weights live in the strategy's state, one float per buffer slot, written for the new
episodes once per cycle; their running sum is kept with them, so a batch's episode draw is a
``searchsorted`` of uniforms into it (O(batch * log slots)), not a pass over the buffer.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from rdher_jax.buffer import BufferState
from rdher_jax.relabel.base import Relabeller, RewardFn
from rdher_jax.relabel.her import draw_her, gather_her

# The authors' constants (Fetch tasks): gravity, object mass and env step in seconds.
GRAVITY, MASS, DT = 9.81, 1.0, 0.04


def trajectory_energy(ag: jax.Array, clip: float | jax.Array) -> jax.Array:
    """Trajectory energy of episodes from their achieved goals.

    Args:
        ag: ``(..., T+1, 3)`` achieved goals (positions in metres, z up).
        clip: upper clip of each transition's energy (the authors' ``clip_energy``).

    Returns:
        ``(...,)`` float32 trajectory energies, ``>= 0``.
    """
    ag = ag.astype(jnp.float32)
    height = ag[..., 1:, 2] - ag[..., :1, 2]
    potential = GRAVITY * MASS * height
    velocity = (ag[..., 1:, :] - ag[..., :-1, :]) / DT
    kinetic = 0.5 * MASS * jnp.sum(velocity**2, axis=-1)
    total = potential + kinetic  # (..., T)
    trans = jnp.concatenate([total[..., :1], total[..., 1:] - total[..., :-1]], axis=-1)
    return jnp.sum(jnp.clip(trans, 0.0, clip), axis=-1)


@struct.dataclass
class EnergyState:
    """Per-slot trajectory energies and their running sum.

    Attributes:
        energy: ``(capacity_episodes,)`` float32 weight of each slot (0 for unwritten ones).
        cumulative: ``(capacity_episodes,)`` float32 inclusive running sum of ``energy``.
    """

    energy: jax.Array
    cumulative: jax.Array


def draw_episodes(bits: jax.Array, cumulative: jax.Array, num_episodes: jax.Array) -> jax.Array:
    """Episode slots drawn with probability proportional to their weight.

    Args:
        bits: ``(batch,)`` uint32 random bits.
        cumulative: ``(capacity,)`` inclusive running sum of the slots' weights (0 beyond the
            written slots, which fill from 0).
        num_episodes: int32 scalar, the slots written.

    Returns:
        ``(batch,)`` int32 slots in ``[0, num_episodes)``: slot ``i`` with probability
        ``w_i / sum(w)``, or uniformly while every weight is 0.
    """
    u = (bits >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)  # [0, 1)
    total = cumulative[-1]
    # The first slot whose running sum exceeds u * total: weight-0 slots are never chosen.
    weighted = jnp.searchsorted(cumulative, u * total, side="right").astype(jnp.int32)
    n = jnp.maximum(num_episodes, 1)
    uniform = (bits % n.astype(jnp.uint32)).astype(jnp.int32)
    return jnp.where(total > 0, jnp.minimum(weighted, n - 1), uniform)


def make_her_energy(compute_reward: RewardFn, batch_size: int, capacity_episodes: int,
                    num_new: int, clip: float) -> Relabeller:
    """'future' relabelling with energy-prioritised episodes, as a ``Relabeller``.

    Args:
        compute_reward: the env's ``(achieved, desired) -> reward``.
        batch_size: rows per sample.
        capacity_episodes: buffer slots.
        num_new: episodes added per cycle (``num_envs``).
        clip: the transition energy's upper clip.
    """
    cap = capacity_episodes

    def init() -> EnergyState:
        z = jnp.zeros((cap,), jnp.float32)
        return EnergyState(energy=z, cumulative=z)

    def update(state: EnergyState, buffer: BufferState, params) -> EnergyState:
        del params
        slots = (buffer.insert_pos - num_new + jnp.arange(num_new, dtype=jnp.int32)) % cap
        energy = state.energy.at[slots].set(trajectory_energy(buffer.ag[slots], clip))
        return EnergyState(energy=energy, cumulative=jnp.cumsum(energy))

    def sample(key, state: EnergyState, buffer: BufferState, params, step):
        del step
        k_her, k_ep = jax.random.split(key)
        # HER's draws of step, future step and mask; only the episode is drawn anew.
        _, t, future_t, mask = draw_her(k_her, buffer.num_episodes, buffer.horizon, batch_size,
                                        params.relabel_prob)
        bits = jax.random.bits(k_ep, (batch_size,), jnp.uint32)
        ep_idx = draw_episodes(bits, state.cumulative, buffer.num_episodes)
        return gather_her(buffer, ep_idx, t, future_t, mask, compute_reward)

    return Relabeller("her_energy", init=init, update=update, sample=sample)
