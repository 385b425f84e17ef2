"""Episodes of a batch of envs under a policy: the one rollout that training, evaluation, videos
and the benchmarks collect with.

``rollout(env, policy, reset_keys, step_keys, record)`` resets one env per reset key, then
steps all of them ``len(step_keys)`` times under ``jax.lax.scan``. Callers choose their keys
(so each keeps the random numbers it always drew) and what each step records; the loop is
written once. Pure and jittable; imports JAX only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax


def rollout(env: Any, policy: Callable[[Any, Any], jax.Array], reset_keys: jax.Array,
            step_keys: jax.Array | None = None, record: Callable[..., Any] | None = None,
            steps: int | None = None) -> tuple[Any, Any, Any]:
    """Reset a batch of envs and step it.

    Args:
      env: an env with pure ``reset(key)`` and ``step(state, action)`` (``FetchEnv``).
      policy: ``policy(k, state) -> actions`` for the whole batch; ``k`` is the step's entry
        of ``step_keys`` (None without step keys: a deterministic policy).
      reset_keys: one key per env, ``(n, ...)``.
      step_keys: one entry per step (anything ``lax.scan`` can slice along its leading axis),
        or None with ``steps``.
      record: ``record(state, action, next_state) -> pytree`` kept per step; default the
        next state's reward.
      steps: the number of steps when ``step_keys`` is None (default: the env's episode
        length).
    Returns:
      ``(first_state, last_state, records)``, records stacked along a leading step axis.
    """
    record = record or (lambda s, a, nxt: nxt.reward)
    worlds = getattr(env.backend, "worlds", None)
    if worlds is not None and reset_keys.shape[0] > worlds:
        raise ValueError(f"{env.backend.name} backend built for {worlds} envs, asked to step "
                         f"{reset_keys.shape[0]}: make_env(..., worlds={reset_keys.shape[0]})")
    v_step = jax.vmap(env.step)
    first = jax.vmap(env.reset)(reset_keys)

    def step(state, k):
        a = policy(k, state)
        nxt = v_step(state, a)
        return nxt, record(state, a, nxt)

    if step_keys is None:
        steps = env.episode_length if steps is None else steps
    last, ys = jax.lax.scan(step, first, step_keys, length=steps if step_keys is None else None)
    check = getattr(env.backend, "check", None)
    if check is not None:  # the warp backend: its buffers' overflow is an error
        check(last.data)
    return first, last, ys
