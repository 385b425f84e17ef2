"""The device envs as a ``gymnasium.vector.VectorEnv``, for code written against gymnasium.

``make_vector_env(name, num_envs)`` wraps ``num_envs`` copies of a Fetch task in one batched,
jitted env that follows gymnasium's vector API: numpy in, numpy out, spaces and dtypes as
gymnasium-robotics' ``Fetch*-v4`` (float64 observations, a float32 [-1, 1]^4 action box),
``truncated`` at step 50, ``terminated`` never, ``info["is_success"]`` per env, and a vectorised
``compute_reward(achieved_goal, desired_goal, info)`` for hindsight relabelling. ``to_sb3``
adapts it to Stable-Baselines3's ``VecEnv`` (for SB3's ``HerReplayBuffer``).

Autoreset is ``AutoresetMode.SAME_STEP``: the step that ends an episode returns the first
observation of the next one, and the last observation of the ended one in ``info["final_obs"]``.
That is what the envs already do on device (a fresh goal is drawn inside ``step``), and it is
the convention HER users need: the final transition is whole in one step, and no step is spent
on a reset whose action is ignored (``NEXT_STEP``).

Each ``step`` is one call of ``jax.jit(jax.vmap(env.step))``; the physics state stays on the
device between calls and only the observation, reward, flags and success come back to the host.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

OBS_KEYS = ("achieved_goal", "desired_goal", "observation")  # the order spaces.Dict keeps


def _key_from_seed(seed: int) -> jax.Array:
    """A PRNG key from any non-negative int seed. ``jax.random.PRNGKey`` alone would keep only
    the low 32 bits without x64 (2**32 and 0 would give the same key), so the seed is hashed to
    64 bits by numpy's ``SeedSequence`` first."""
    w = np.random.SeedSequence(seed).generate_state(2, np.uint32)
    return jax.random.fold_in(jax.random.PRNGKey(w[0]), w[1])


def _where_batch(mask: jax.Array, new, old):
    """Per env: ``new`` where ``mask``, else ``old`` (pytrees with a leading env axis)."""
    return jax.vmap(lambda m, a, b: jax.tree.map(lambda x, y: jnp.where(m, x, y), a, b))(
        mask, new, old
    )


class FetchVectorEnv(VectorEnv):
    """``num_envs`` copies of a Fetch task as one gymnasium ``VectorEnv``.

    Build it with ``rdher_jax.make_vector_env``. Spaces, dtypes and episode ends are those of
    gymnasium-robotics' ``Fetch*-v4`` under gymnasium's ``TimeLimit`` (50 steps):

    - ``single_observation_space``: ``Dict`` of float64 ``Box(-inf, inf)`` for
      ``observation`` (10 for Reach, 25 otherwise), ``achieved_goal`` and ``desired_goal`` (3);
      ``observation_space`` is its batch, ``(num_envs, ...)``. The values are computed in
      float32 on the device and returned as float64, so float64 code written for the gymnasium
      envs runs unchanged.
    - ``single_action_space``: float32 ``Box(-1, 1, (4,))``; ``action_space``: ``(num_envs, 4)``.
    - ``step`` returns float64 rewards -(d > threshold), ``terminated`` always False,
      ``truncated`` True on every 50th step of an episode, and ``info["is_success"]``, float32
      (num_envs,), the success of the step just taken (with ``info["_is_success"]``, gymnasium's
      mask, all True).
    - Autoreset ``SAME_STEP`` (``metadata["autoreset_mode"]``): where an episode ended, the
      returned observation starts the next one (new object position and goal), and
      ``info["final_obs"]`` (an object array holding that env's last observation dict, None for
      the others), ``info["final_info"]`` (``{"is_success": ...}``) and their masks
      ``info["_final_obs"]``, ``info["_final_info"]`` are set as gymnasium's ``SyncVectorEnv``
      sets them. Keys absent when no episode ended on that step.
    - ``reset(seed=s)`` draws every env's start from one PRNG key derived from ``s``; a later
      ``reset()`` continues that key's stream, so a seed fixes all episodes that follow.
      ``options={"reset_mask": mask}`` resets only the envs where ``mask`` (bool, (num_envs,))
      is True, as gymnasium's vector envs do.

    Attributes:
      env: the device env (``rdher_jax.envs.FetchEnv``), with its pure ``reset`` / ``step``.
      episode_length, distance_threshold: the task's (50; 0.05, 0.01 for the moving tasks).
    """

    def __init__(self, env, num_envs: int, seed: int | None = None):
        if not env.auto_reset:
            raise ValueError("FetchVectorEnv needs an env built with auto_reset=True")
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.env = env
        self.num_envs = int(num_envs)
        self.episode_length = env.episode_length
        self.distance_threshold = float(env.distance_threshold)
        self.metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

        def box(n):
            return spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64)

        self.single_observation_space = spaces.Dict(
            {"observation": box(env.obs_size), "achieved_goal": box(env.goal_size),
             "desired_goal": box(env.goal_size)}
        )
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(env.action_size,),
                                              dtype=np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

        self._reset_fn = jax.jit(jax.vmap(env.reset))
        self._step_fn = jax.jit(jax.vmap(env.step))
        self._select_fn = jax.jit(_where_batch)
        self._state = None
        self._key = None
        self._first_seed = seed

    def __repr__(self) -> str:
        return (f"FetchVectorEnv({self.env.name}, num_envs={self.num_envs}, "
                f"backend={self.env.backend.name})")

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        """Start new episodes in all envs (or in ``options["reset_mask"]``'s). Returns the batch
        of observations and an empty info, as gymnasium-robotics' reset."""
        if seed is None and self._key is None:
            seed = self._first_seed  # make_vector_env(..., seed=) seeds the first reset
        super().reset(seed=seed)  # validates the seed and seeds self.np_random
        if seed is not None:
            self._key = _key_from_seed(seed)
        elif self._key is None:
            self._key = _key_from_seed(int(self.np_random.integers(2**63 - 1)))
        mask = self._reset_mask(options)
        self._key, sub = jax.random.split(self._key)
        fresh = self._reset_fn(jax.random.split(sub, self.num_envs))
        if mask is None:
            self._state = fresh
        else:
            self._state = self._select_fn(jnp.asarray(mask), fresh, self._state)
        return self._host_obs(jax.device_get(self._state.obs)), {}

    def step(self, actions) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One step of every env; see the class docstring for what comes back."""
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = np.asarray(actions, np.float32)
        if a.shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {a.shape}")
        self._state = self._step_fn(self._state, jnp.asarray(a))
        st = self._state
        out = jax.device_get({"obs": st.obs, "reward": st.reward, "done": st.done,
                              "is_success": st.info["is_success"],
                              "final_obs": st.info["final_obs"]})
        truncated = np.asarray(out["done"], np.bool_).copy()
        terminated = np.zeros(self.num_envs, np.bool_)
        success = np.asarray(out["is_success"], np.float32).copy()
        info = {"is_success": success, "_is_success": np.ones(self.num_envs, np.bool_)}
        if truncated.any():
            final = self._host_obs(out["final_obs"])
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(truncated):
                final_obs[i] = {k: final[k][i].copy() for k in OBS_KEYS}
            info["final_obs"] = final_obs
            info["_final_obs"] = truncated.copy()
            final_success = np.where(truncated, success, 0.0).astype(np.float32)
            info["final_info"] = {"is_success": final_success, "_is_success": truncated.copy()}
            info["_final_info"] = truncated.copy()
        reward = np.asarray(out["reward"], np.float64)
        return self._host_obs(out["obs"]), reward, terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self._state = None

    # ------------------------------------------------------------------ goals and rewards
    def compute_reward(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """Sparse reward -(||achieved - desired|| > threshold) over any leading shape, in numpy,
        as gymnasium-robotics' ``compute_reward`` (float32; ``info`` is unused)."""
        d = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
        return -(d > self.distance_threshold).astype(np.float32)

    # ------------------------------------------------------------------ helpers
    def _reset_mask(self, options) -> np.ndarray | None:
        if not options or "reset_mask" not in options:
            return None
        mask = options["reset_mask"]
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ \
                or mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask'] must be a bool numpy array of shape "
                             f"({self.num_envs},), got {mask!r}")
        if self._state is None:
            raise gymnasium.error.ResetNeeded("a reset_mask needs an earlier full reset()")
        return mask

    @staticmethod
    def _host_obs(obs: dict) -> dict:
        """Float64 numpy copies (new arrays on every call, so callers may keep them)."""
        return {k: np.array(obs[k], dtype=np.float64) for k in OBS_KEYS}


def make_vector_env(name: str, num_envs: int, backend: str | None = None,
                    seed: int | None = None, **env_kwargs) -> FetchVectorEnv:
    """``num_envs`` copies of a Fetch task as a ``gymnasium.vector.VectorEnv``.

    Args:
      name: as ``rdher_jax.make_env`` (FetchReach, FetchPush, FetchSlide, FetchPickAndPlace,
        with or without ``-v4``, or a moving-goal task).
      num_envs: envs stepped together (one batched, jitted step).
      backend: ``"mujoco"``, ``"mjx"``, ``"warp"`` or None for the default (as ``make_env``).
      seed: seed of the first ``reset()`` called without one (a ``reset(seed=...)`` overrides
        it); None draws one at random.
      **env_kwargs: ``scene``, ``num_threads``, ``goal_speed``, passed to ``make_env``.
    Returns:
      A ``FetchVectorEnv``; see its docstring for spaces, dtypes and autoreset.
    """
    from .envs import make_env

    if "auto_reset" in env_kwargs:
        raise ValueError("make_vector_env always auto-resets (SAME_STEP); drop auto_reset")
    env_kwargs.setdefault("worlds", num_envs)  # the warp backend's buffers (others ignore it)
    return FetchVectorEnv(make_env(name, backend, **env_kwargs), num_envs, seed=seed)


# ---------------------------------------------------------------------- Stable-Baselines3
def to_sb3(env: FetchVectorEnv):
    """Adapt a ``FetchVectorEnv`` to Stable-Baselines3's ``VecEnv`` API (needs the ``sb3``
    extra: ``pip install 'rdher-jax[sb3]'``).

    Steps return ``(obs, rewards, dones, infos)`` with one info dict per env holding
    ``is_success``, ``TimeLimit.truncated`` and, where an episode ended, ``terminal_observation``,
    as SB3's ``DummyVecEnv`` gives them; ``env_method("compute_reward", ...)``, which SB3's
    ``HerReplayBuffer`` calls, runs the batched ``compute_reward`` once and returns its result
    for each index asked for. ``seed(s)`` then ``reset()`` resets the batch with seed ``s``.
    """
    return _sb3_class()(env)


@functools.cache
def _sb3_class():
    from stable_baselines3.common.vec_env import VecEnv

    class SB3VecEnv(VecEnv):
        """A ``FetchVectorEnv`` behind SB3's ``VecEnv`` interface (see ``to_sb3``)."""

        def __init__(self, venv: FetchVectorEnv):
            self.venv = venv
            self._actions = None
            super().__init__(venv.num_envs, venv.single_observation_space,
                             venv.single_action_space)

        def reset(self):
            obs, _ = self.venv.reset(seed=self._seeds[0])
            self.reset_infos = [{} for _ in range(self.num_envs)]
            self._reset_seeds()
            self._reset_options()
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = actions

        def step_wait(self):
            obs, reward, terminated, truncated, info = self.venv.step(self._actions)
            dones = terminated | truncated
            infos = []
            for i in range(self.num_envs):
                d = {"is_success": info["is_success"][i],
                     "TimeLimit.truncated": bool(truncated[i] and not terminated[i])}
                if dones[i]:
                    d["terminal_observation"] = info["final_obs"][i]
                infos.append(d)
            return obs, reward.astype(np.float32), dones, infos

        def close(self) -> None:
            self.venv.close()

        def get_attr(self, attr_name: str, indices=None) -> list:
            value = getattr(self.venv, attr_name)
            return [value for _ in self._get_indices(indices)]

        def set_attr(self, attr_name: str, value, indices=None) -> None:
            setattr(self.venv, attr_name, value)

        def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs):
            result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
            return [result for _ in self._get_indices(indices)]

        def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
            return [False for _ in self._get_indices(indices)]

    return SB3VecEnv


__all__ = ["FetchVectorEnv", "make_vector_env", "to_sb3"]
