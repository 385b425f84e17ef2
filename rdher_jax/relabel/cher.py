"""CHER: curriculum-guided selection of hindsight goals (Fang et al., NeurIPS 2019).

A batch is chosen from ``candidates`` 'future'-relabelled transitions by greedily maximising

    F(S) = sum_v max_{c in S} sim(v, c)  -  lam * sum_{c in S} ||g_c - ag_c||

a facility-location term for diversity over goal similarity
``sim = exp(-d^2 / mean(d)^2)`` (``d``: distances between candidate goals), minus a proximity
penalty that grows with ``lam = cher_growth ** step`` (``step``: gradient steps since the epoch
began; CHER's ``1.0001 ** step``, reset each epoch). The greedy is CHER's "lazier than lazy"
(stochastic greedy): each pick scores ``sample`` candidates drawn uniformly from those not yet
chosen and keeps the best marginal gain.

Two choices differ from the authors' code, for fixed shapes on device: the similarity is dense
over all candidates (their facility location uses a 1-nearest-neighbour graph, which on device
is no cheaper than the dense ``C x C`` matrix and makes the objective nearly modular), and each
pick's uniform draw without replacement among the remaining candidates is a partial
Fisher-Yates shuffle of a permutation that keeps the remaining candidates in its first places:
``sample`` uniforms per pick (the numpy reference in the tests is fed the same uniforms), not
one per candidate, and fewer than ``sample`` are scored when fewer remain, so no candidate is
chosen twice even at ``candidates == batch_size``.

At ``batch_size`` 256 the default is 512 candidates, the authors' ratio (64 of 128).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from rdher_jax.buffer import BufferState
from rdher_jax.relabel import her
from rdher_jax.relabel.base import Relabeller, RewardFn


class CHERFns(NamedTuple):
    """CHER's ``sample``, and its parts split into draws and a deterministic selection."""

    sample: Callable
    draw: Callable
    select: Callable


def similarity(goals: jax.Array) -> jax.Array:
    """``exp(-d^2 / mean(d)^2)`` over pairs of ``(C, d)`` goals, mean over distinct pairs."""
    # A sum over the few goal coordinates as whole (C, C) planes: reducing a (C, C, d) array
    # over its minor axis of 3 vectorises poorly on a CPU (twice as slow).
    d2 = sum(jnp.square(goals[:, None, k] - goals[None, :, k]) for k in range(goals.shape[1]))
    d = jnp.sqrt(d2)
    C = goals.shape[0]
    mean_d = jnp.sum(d) / max(C * (C - 1), 1)
    return jnp.exp(-d2 / jnp.maximum(jnp.square(mean_d), 1e-12))


def _swap(perm: jax.Array, i, j) -> jax.Array:
    a, b = perm[i], perm[j]
    return perm.at[i].set(b).at[j].set(a)


def select(goals: jax.Array, proximity: jax.Array, lam: jax.Array, noise: jax.Array,
           sample: int) -> jax.Array:
    """Stochastic-greedy facility location with a proximity penalty.

    A permutation of the candidates keeps the ``n = C - k`` not yet chosen in its first ``n``
    places before pick ``k``. The pick draws its ``sample`` candidates by a partial
    Fisher-Yates shuffle of those places (place ``j`` swaps with place
    ``j + floor(noise[k, j] * (n - j))``), scores the first ``min(sample, n)`` places, and
    swaps the chosen one to place ``n - 1``, out of the remaining.

    Args:
        goals: ``(C, d)`` candidate goals.
        proximity: ``(C,)`` ``||g - ag||`` of each candidate.
        lam: proximity weight.
        noise: ``(K, sample)`` uniforms in ``[0, 1)``, one row per pick (``K <= C``).
        sample: candidates scored per pick.

    Returns:
        ``(K,)`` int32 indices of the chosen candidates, in pick order, each at most once.
    """
    sim = similarity(goals)
    C = goals.shape[0]

    def pick(carry, x):
        cover, perm = carry
        u, k = x
        n = C - k
        for j in range(sample):
            span = jnp.maximum(n - j, 1)
            off = jnp.floor(u[j] * span.astype(u.dtype)).astype(jnp.int32)
            perm = _swap(perm, j, jnp.where(j < n, j + jnp.minimum(off, span - 1), j))
        cand = perm[:sample]
        # ``sim`` is exactly symmetric (each entry is a function of squared coordinate
        # differences), so a candidate's column is read as its row: a contiguous slice rather
        # than a strided gather, twice as fast on a CPU (experiments/bench_relabel.py).
        gain = jnp.sum(jnp.maximum(sim[cand] - cover[None, :], 0.0), axis=1)
        gain = jnp.where(jnp.arange(sample) < n, gain - lam * proximity[cand], -jnp.inf)
        p = jnp.argmax(gain)
        best = cand[p]
        return (jnp.maximum(cover, sim[best]), _swap(perm, p, n - 1)), best

    K = noise.shape[0]
    init = (jnp.zeros((C,), sim.dtype), jnp.arange(C, dtype=jnp.int32))
    _, idx = jax.lax.scan(pick, init, (noise, jnp.arange(K, dtype=jnp.int32)))
    return idx


def build_cher(compute_reward: RewardFn, batch_size: int, candidates: int,
               sample_size: int = 3) -> CHERFns:
    """CHER for batches of ``batch_size`` chosen from ``candidates``.

    Raises:
        ValueError: if ``candidates < batch_size`` or ``sample_size`` is out of range.
    """
    if candidates < batch_size:
        raise ValueError(f"cher_candidates ({candidates}) must be >= batch_size ({batch_size})")
    if not 1 <= sample_size <= candidates:
        raise ValueError(f"cher_sample must be in [1, {candidates}], got {sample_size}")

    def draw(key: jax.Array, buffer: BufferState, relabel_prob):
        """The candidates' HER draws and the selection noise."""
        k_her, k_sel = jax.random.split(key)
        draws = her.draw_her(k_her, buffer.num_episodes, buffer.horizon, candidates,
                             relabel_prob)
        noise = jax.random.uniform(k_sel, (batch_size, sample_size))
        return draws, noise

    def sample(key, state, buffer: BufferState, params, step):
        del state
        draws, noise = draw(key, buffer, params.relabel_prob)
        cand = her.gather_her(buffer, *draws, compute_reward)
        prox = jnp.linalg.norm(cand.goal - buffer.ag[cand.ep, cand.t], axis=-1)
        lam = params.cher_growth ** step.astype(jnp.float32)
        idx = select(cand.goal, prox, lam, noise, sample_size)
        return jax.tree.map(lambda x: x[idx], cand)

    return CHERFns(sample=sample, draw=draw, select=select)


def make_cher(compute_reward: RewardFn, batch_size: int, candidates: int,
              sample_size: int = 3) -> Relabeller:
    """CHER as a ``Relabeller`` (stateless)."""
    f = build_cher(compute_reward, batch_size, candidates, sample_size)
    return Relabeller("cher", init=lambda: (), update=lambda s, b, p: s, sample=f.sample)


__all__ = ["build_cher", "make_cher", "select", "similarity"]
