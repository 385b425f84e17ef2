"""Helpers the tests share and the package does not need.

pytest puts ``tests/`` on ``sys.path`` (rootdir-relative, no ``__init__.py``), so test files
import this module as ``helpers``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rdher_jax import buffer as rb

# --- buffer: uniform transition indices, on which the buffer's invariants are tested -----------


def sample_indices(
    key: jax.Array, state: rb.BufferState, batch_size: int
) -> tuple[jax.Array, jax.Array]:
    """Sample transition indices uniformly over the stored episodes.

    Args:
        key: PRNG key.
        state: the buffer.
        batch_size: number of transitions (static).

    Returns:
        ``(ep_idx, t)``: int32 ``(batch_size,)`` arrays, ``ep_idx`` in ``[0, num_episodes)``
        and ``t`` in ``[0, T)``; transition ``i`` is ``obs[ep_idx[i], t[i]]`` ->
        ``obs[ep_idx[i], t[i] + 1]`` under ``action[ep_idx[i], t[i]]``.
    """
    bits = jax.random.bits(key, (2, batch_size), jnp.uint32)
    return rb.indices_from_bits(bits, state.num_episodes, state.horizon)


# --- ddpg: several updates in one scan ---------------------------------------------------------


def update_many(agent, state, batches, hparams):
    """Runs ``agent.update`` over the leading axis of ``batches``.

    Args:
        agent: a ``ddpg.DDPG``.
        state: learner state.
        batches: transitions with (n, B, ...) fields.
        hparams: as for ``agent.update``.

    Returns:
        (final state, metrics with a leading (n,) axis).
    """
    return jax.lax.scan(lambda s, b: agent.update(s, b, hparams), state, batches)


# --- envs: scripted policies that push, grasp and hit ------------------------------------------


def _toward(grip, target, gain=10.0):
    return jnp.clip((target - grip) * gain, -1.0, 1.0)


def scripted_action(task: str, obs: dict) -> jnp.ndarray:
    """One action for ``task`` from an (unbatched or batched) observation dict.

    Expert-ish policies in pure JAX that drive contact-rich trajectories for the conformance
    tests; they are not meant to solve the tasks reliably.
    """
    o, goal = obs["observation"], obs["desired_goal"]
    grip = o[..., 0:3]
    if task == "FetchReach":
        return jnp.concatenate([_toward(grip, goal), jnp.zeros_like(grip[..., :1])], -1)
    obj = o[..., 3:6]
    if task == "FetchPickAndPlace":
        d_xy = jnp.linalg.norm(grip[..., :2] - obj[..., :2], axis=-1, keepdims=True)
        d = jnp.linalg.norm(grip - obj, axis=-1, keepdims=True)
        above = obj + jnp.array([0.0, 0.0, 0.08])
        target = jnp.where(d_xy > 0.01, above, jnp.where(d > 0.01, obj, goal))
        close = (d < 0.02) | (d_xy < 0.01) & (grip[..., 2:3] < obj[..., 2:3] + 0.01)
        finger = jnp.where(close, -1.0, 1.0)
        return jnp.concatenate([_toward(grip, target), finger], -1)
    # Push and Slide: get behind the object on the goal line, then drive through it.
    direc = goal[..., :2] - obj[..., :2]
    direc = direc / (jnp.linalg.norm(direc, axis=-1, keepdims=True) + 1e-6)
    pre = obj[..., :2] - 0.06 * direc
    far = jnp.linalg.norm(grip[..., :2] - pre, axis=-1, keepdims=True) > 0.02
    z = obj[..., 2:3]
    hover = jnp.concatenate([pre, z + 0.06], -1)
    low = jnp.concatenate([pre, z], -1)
    gain = 10.0 if task == "FetchPush" else 40.0  # Slide: hit the puck hard
    push = jnp.concatenate([goal[..., :2], z], -1)
    high = grip[..., 2:3] > z + 0.02
    target = jnp.where(far, hover, jnp.where(high, low, push))
    return jnp.concatenate([_toward(grip, target, gain), jnp.zeros_like(z)], -1)


# --- metrics.csv rows of two runs ---------------------------------------------------------------


def assert_same_rows(a, b, exact=False):
    """Rows of two metrics.csv files: equal, or (``exact`` False) equal to the float rounding
    of two programs (a vmapped sweep against a run of its own); counts always exactly, wall
    time aside."""
    assert len(a) == len(b) > 0
    for ra, rb_ in zip(a, b, strict=True):
        assert ra.keys() == rb_.keys()
        for k in ra:
            if k == "wall_time":
                continue
            if exact or k in ("epoch", "env_steps", "updates"):
                assert ra[k] == rb_[k], (k, ra, rb_)
            else:
                np.testing.assert_allclose(float(ra[k]), float(rb_[k]), rtol=1e-3, atol=1e-5,
                                           equal_nan=True, err_msg=k)


# --- CHER: the stochastic greedy by plain loops ------------------------------------------------


def cher_select_np(goals, prox, lam, noise, sample):
    """CHER's stochastic greedy by plain loops (the reference for ``cher.select``).

    Facility location over ``exp(-d^2 / mean(d)^2)`` minus ``lam`` times each candidate's
    proximity. Pick ``k`` draws ``min(sample, n)`` of the ``n`` candidates not yet chosen without
    replacement, by a partial Fisher-Yates shuffle of a list that holds the remaining
    candidates first (uniform ``noise[k, j]`` picks place ``j + floor(u * (n - j))``, in
    float32 as on device), and keeps the best gain; the chosen one moves to place ``n - 1``.
    """
    C = len(goals)
    d = np.sqrt(((goals[:, None] - goals[None]) ** 2).sum(-1))
    sim = np.exp(-(d**2) / (d.sum() / (C * (C - 1))) ** 2)
    cover, perm, chosen = np.zeros(C), list(range(C)), []
    for k, u in enumerate(np.asarray(noise, np.float32)):
        n = C - k
        m = min(sample, n)
        for j in range(m):
            r = j + min(int(np.floor(u[j] * np.float32(n - j))), n - j - 1)
            perm[j], perm[r] = perm[r], perm[j]
        gains = [np.maximum(sim[:, c] - cover, 0).sum() - lam * prox[c] for c in perm[:m]]
        p = int(np.argmax(gains))
        best = perm[p]
        perm[p], perm[n - 1] = perm[n - 1], perm[p]
        chosen.append(best)
        cover = np.maximum(cover, sim[:, best])
    return np.array(chosen)
