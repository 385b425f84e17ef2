"""Actor and critic networks for goal-conditioned DDPG (baselines HER architecture)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

# Baselines builds its layers with tf's xavier (glorot-uniform) kernels and zero biases; matching
# that costs nothing and keeps the reproduction's starting point the same.
_KERNEL_INIT = nn.initializers.glorot_uniform()


class MLP(nn.Module):
    """ReLU MLP with a linear output layer.

    Attributes:
        hidden: widths of the hidden layers.
        out_dim: width of the output layer.
    """

    hidden: Sequence[int]
    out_dim: int
    layer_norm: bool = False
    # The hidden layers' computation dtype (None: the inputs', float32). bfloat16: inputs and
    # kernels are cast to it for the matmuls; parameters stay float32, and the output layer
    # computes in float32 from the last hidden layer's values.
    dtype: Any = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Args: x (..., in_dim). Returns: (..., out_dim)."""
        for i, width in enumerate(self.hidden):
            x = nn.Dense(width, kernel_init=_KERNEL_INIT, dtype=self.dtype, name=f"hidden_{i}")(x)
            if self.layer_norm:
                x = nn.LayerNorm(name=f"norm_{i}")(x)
            x = nn.relu(x)
        if self.dtype is not None:
            x = x.astype(jnp.float32)
        return nn.Dense(self.out_dim, kernel_init=_KERNEL_INIT, name="out")(x)


class Actor(nn.Module):
    """Deterministic policy pi(o, g) = max_u * tanh(MLP([o, g])).

    Attributes:
        act_dim: action dimension.
        hidden: hidden layer widths.
        max_u: action bound.
    """

    act_dim: int
    hidden: Sequence[int] = (256, 256, 256)
    max_u: float = 1.0
    dtype: Any = None  # hidden layers' computation dtype (MLP.dtype)

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array) -> jax.Array:
        """Maps normalised observations and goals to actions.

        Args:
            obs: normalised observations, (..., obs_dim).
            goal: normalised goals, (..., goal_dim).

        Returns:
            Actions in [-max_u, max_u], (..., act_dim).
        """
        x = jnp.concatenate([obs, goal], axis=-1)
        return self.max_u * jnp.tanh(
            MLP(self.hidden, self.act_dim, dtype=self.dtype, name="mlp")(x))


class Critic(nn.Module):
    """Action-value Q(o, g, u) = MLP([o, g, u / max_u]).

    Attributes:
        hidden: hidden layer widths.
        max_u: action bound (actions enter the network rescaled to [-1, 1]).
        layer_norm: LayerNorm after every hidden Dense layer (off in baselines).
    """

    hidden: Sequence[int] = (256, 256, 256)
    max_u: float = 1.0
    layer_norm: bool = False
    dtype: Any = None  # hidden layers' computation dtype (MLP.dtype)

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array, action: jax.Array) -> jax.Array:
        """Scores normalised observation/goal pairs and raw actions.

        Args:
            obs: normalised observations, (..., obs_dim).
            goal: normalised goals, (..., goal_dim).
            action: actions in [-max_u, max_u], (..., act_dim).

        Returns:
            Q values, (...,).
        """
        x = jnp.concatenate([obs, goal, action / self.max_u], axis=-1)
        return MLP(self.hidden, 1, self.layer_norm, self.dtype, name="mlp")(x)[..., 0]


class CriticEnsemble(nn.Module):
    """``n`` independent critics evaluated as one (flax's lifted vmap over `Critic`).

    Their parameters carry a leading axis of size ``n`` (each critic initialised from its own
    key); the output stacks their Q values, ``(n, ...)``.

    Attributes:
        n: number of critics.
        hidden, max_u, layer_norm, dtype: as `Critic`'s.
    """

    n: int
    hidden: Sequence[int] = (256, 256, 256)
    max_u: float = 1.0
    layer_norm: bool = False
    dtype: Any = None

    @nn.compact
    def __call__(self, obs: jax.Array, goal: jax.Array, action: jax.Array) -> jax.Array:
        """Args as `Critic`'s. Returns: Q values, (n, ...)."""
        critics = nn.vmap(
            Critic, variable_axes={"params": 0}, split_rngs={"params": True},
            in_axes=None, out_axes=0, axis_size=self.n,
        )
        return critics(self.hidden, self.max_u, self.layer_norm, self.dtype, name="ensemble")(
            obs, goal, action)
