"""Pure, fixed-shape, episode-major replay buffer.

The buffer stores whole episodes in a ring of ``capacity // T`` slots. Its state is a pytree of
fixed-shape arrays with no Python-side counters, so ``init``, ``add`` and the samplers built on
``indices_from_bits`` (``rdher_jax.relabel``) can be jitted, scanned and vmapped (a sweep vmaps
the whole train function over seeds, giving every leaf a leading seed axis).

Each ``add`` writes whole episodes in one functional update, so a sampled transition
``(o_t, a_t, o_{t+1})`` always comes from a single episode.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Episode:
    """A batch of ``B`` whole episodes of horizon ``T``.

    Attributes:
        obs: ``(B, T+1, obs_dim)`` observations, including the final one.
        ag: ``(B, T+1, goal_dim)`` achieved goal at each step.
        g: ``(B, T+1, goal_dim)`` desired goal at each step (per step, so goals may move).
        action: ``(B, T, act_dim)`` actions.
    """

    obs: jax.Array
    ag: jax.Array
    g: jax.Array
    action: jax.Array


@struct.dataclass
class BufferState:
    """Ring buffer of whole episodes.

    Attributes:
        obs: ``(capacity_episodes, T+1, obs_dim)``.
        ag: ``(capacity_episodes, T+1, goal_dim)``.
        g: ``(capacity_episodes, T+1, goal_dim)``.
        action: ``(capacity_episodes, T, act_dim)``.
        insert_pos: int32 scalar, the next slot to write.
        num_episodes: int32 scalar, the number of episodes stored (``<= capacity_episodes``).
    """

    obs: jax.Array
    ag: jax.Array
    g: jax.Array
    action: jax.Array
    insert_pos: jax.Array
    num_episodes: jax.Array

    @property
    def capacity_episodes(self) -> int:
        """Number of episode slots (static; read inside a vmap it is the per-seed value)."""
        return self.action.shape[-3]

    @property
    def horizon(self) -> int:
        """Episode length ``T`` (static)."""
        return self.action.shape[-2]


def _as_int(name: str, value: int | float) -> int:
    # Configs often carry sizes as floats (``1e6``); accept them only when integral.
    if isinstance(value, bool):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if isinstance(value, float):
        if not value.is_integer():
            raise ValueError(f"{name} must be an integer, got {value!r}")
        value = int(value)
    return int(value)


def init(
    capacity: int,
    T: int,
    obs_dim: int,
    goal_dim: int,
    act_dim: int,
    dtype: jnp.dtype = jnp.float32,
) -> BufferState:
    """Create an empty buffer.

    Args:
        capacity: capacity in transitions; the buffer holds ``capacity // T`` whole episodes.
        T: episode horizon (number of actions per episode).
        obs_dim: observation size.
        goal_dim: goal size.
        act_dim: action size.
        dtype: storage dtype of the four data arrays.

    Returns:
        A zero-filled ``BufferState`` with ``insert_pos == num_episodes == 0``.

    Raises:
        ValueError: if a size is not a positive integer or ``capacity < T``.
    """
    capacity = _as_int("capacity", capacity)
    T = _as_int("T", T)
    for name, dim in (("obs_dim", obs_dim), ("goal_dim", goal_dim), ("act_dim", act_dim)):
        if _as_int(name, dim) < 1:
            raise ValueError(f"{name} must be >= 1, got {dim}")
    if T < 1:
        raise ValueError(f"T must be >= 1, got {T}")
    capacity_episodes = capacity // T
    if capacity_episodes < 1:
        raise ValueError(
            f"capacity ({capacity} transitions) must hold at least one episode of T={T} steps"
        )
    n = capacity_episodes
    return BufferState(
        obs=jnp.zeros((n, T + 1, int(obs_dim)), dtype),
        ag=jnp.zeros((n, T + 1, int(goal_dim)), dtype),
        g=jnp.zeros((n, T + 1, int(goal_dim)), dtype),
        action=jnp.zeros((n, T, int(act_dim)), dtype),
        insert_pos=jnp.zeros((), jnp.int32),
        num_episodes=jnp.zeros((), jnp.int32),
    )


def add(state: BufferState, ep: Episode) -> BufferState:
    """Write ``B`` episodes at slots ``insert_pos, insert_pos+1, ...`` modulo capacity.

    Args:
        state: the buffer.
        ep: ``B`` whole episodes; ``B`` is static and must be ``<= capacity_episodes``.

    Returns:
        The updated buffer; the oldest episodes are overwritten once it is full.

    Raises:
        ValueError: if ``B > capacity_episodes`` or an episode field has the wrong shape.
    """
    cap = state.capacity_episodes
    b = ep.action.shape[0]
    if b > cap:
        # With B > capacity the scatter indices would repeat and the winner is unspecified.
        raise ValueError(f"cannot add {b} episodes to a buffer of {cap} episode slots")
    for name in ("obs", "ag", "g", "action"):
        got, want = getattr(ep, name).shape, getattr(state, name).shape
        if got != (b,) + want[1:]:
            raise ValueError(f"Episode.{name} has shape {got}, expected {(b,) + want[1:]}")
    slots = (state.insert_pos + jnp.arange(b, dtype=jnp.int32)) % cap

    def write(buf: jax.Array, new: jax.Array) -> jax.Array:
        # B <= capacity, so the slots are distinct and the scatter is well defined.
        return buf.at[slots].set(new.astype(buf.dtype), unique_indices=True)

    return state.replace(
        obs=write(state.obs, ep.obs),
        ag=write(state.ag, ep.ag),
        g=write(state.g, ep.g),
        action=write(state.action, ep.action),
        insert_pos=((state.insert_pos + b) % cap).astype(jnp.int32),
        num_episodes=jnp.minimum(state.num_episodes + b, cap).astype(jnp.int32),
    )


def indices_from_bits(
    bits: jax.Array, num_episodes: jax.Array, T: int
) -> tuple[jax.Array, jax.Array]:
    """Turn two rows of random uint32 bits into uniform episode slots and steps.

    Slots fill in order from 0 and only wrap once full, so ``[0, num_episodes)`` is exactly the
    set of written slots. With ``num_episodes == 0`` every slot is 0 (an unwritten one).

    Args:
        bits: ``(2, batch)`` uint32 random bits.
        num_episodes: int32 scalar (may be traced).
        T: episode horizon (static).

    Returns:
        ``(ep_idx, t)``: int32 ``(batch,)`` arrays in ``[0, num_episodes)`` and ``[0, T)``.
    """
    # A modulo of 32 random bits: the bias, below num_episodes / 2**32, is negligible, and one
    # bits draw is cheaper to compile and run than jax.random.randint's two per array.
    n = jnp.maximum(num_episodes, 1).astype(jnp.uint32)
    ep_idx = (bits[0] % n).astype(jnp.int32)
    t = (bits[1] % jnp.uint32(T)).astype(jnp.int32)
    return ep_idx, t


def bytes_per_transition(
    T: int, obs_dim: int, goal_dim: int, act_dim: int, itemsize: int = 4
) -> float:
    """Storage cost of one transition, amortised over its episode.

    An episode stores ``T+1`` observations, achieved and desired goals and ``T`` actions; the
    two int32 counters are ignored.

    Args:
        T: episode horizon.
        obs_dim: observation size.
        goal_dim: goal size.
        act_dim: action size.
        itemsize: bytes per stored element (4 for float32).

    Returns:
        Bytes per transition.
    """
    per_episode = (T + 1) * (obs_dim + 2 * goal_dim) + T * act_dim
    return per_episode * itemsize / T
