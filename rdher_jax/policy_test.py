"""A run's policy on new test episodes: ``evaluate`` (what ``python -m rdher_jax.evaluate``
prints, and the experiments' best-policy retest), ``retest`` (the end of a training run with
``retest=N``) and ``select`` (the end of a training run with ``select_top`` > 1: the policy chosen
among the best test epochs' on episodes of its own). A library module: the command lines import
it, not each other.

A run's policy is its selected one where a choice was made, else its best test epoch's
(:meth:`rdher_jax.checkpoint.Checkpointer.restore_policy`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

from . import render
from .checkpoint import SELECT_FILE, Checkpointer
from .config import ConfigError, from_yaml
from .render import DEFAULT_SIZE
from .runlog import write_text_atomic

# Keys of a run's config that do not change the evaluation program: the runs of one sweep (seeds,
# λ pairs) share one build and one compilation (experiments test every run of a sweep).
_PER_RUN_KEYS = ("seed", "lambda_r", "lambda_h", "epochs", "run_dir", "resume",
                 "checkpoint_every", "tensorboard", "progress", "stop_success", "stop_window",
                 "retest", "select_top", "select_episodes")
_PROGRAMS: dict[str, tuple] = {}


def _program(cfg):
    """(env, trainer, policy template, jitted evaluate) for ``cfg``, built once per process for
    configs that differ only in :data:`_PER_RUN_KEYS`."""
    from .executor import build  # loads mujoco: after start-up has chosen its GL backend

    key = repr(dataclasses.replace(cfg, **{k: None for k in _PER_RUN_KEYS}))
    if key not in _PROGRAMS:
        env, trainer = build(cfg)
        template = jax.jit(trainer.ddpg.init)(jax.random.PRNGKey(0), trainer.hparams.ddpg)
        _PROGRAMS.clear()  # one at a time: a program holds its env's native handles
        _PROGRAMS[key] = (env, trainer, template, jax.jit(trainer.evaluate))
    return _PROGRAMS[key]


def evaluate(run_dir: Path, episodes: int = 100, seed: int = 0, backend: str | None = None,
             scene: str | None = None, video: str | Path | None = None,
             video_episodes: int = 3, width: int = DEFAULT_SIZE,
             height: int = DEFAULT_SIZE) -> dict:
    """Test success of the policy of ``run_dir`` over ``episodes`` episodes; with
    ``video``, also ``video_episodes`` deterministic episodes rendered to that .gif or .mp4
    (raises ``render.RenderError`` if MuJoCo cannot render or the file cannot be written)."""
    if video is not None:
        video = render.check_video_path(video, width, height)
        gl = render.select_gl()  # before anything imports mujoco
    from .program import hparams_from_config
    cfg = from_yaml(run_dir / "config.yaml")
    if backend is not None or scene is not None:
        cfg = dataclasses.replace(cfg, backend=backend or cfg.backend,
                                  scene=scene or ("auto" if backend else cfg.scene))
    cfg = dataclasses.replace(cfg, n_test_rollouts=episodes)
    env, trainer, template, run_episodes = _program(cfg)
    ckpt = Checkpointer(run_dir, read_only=True)
    if ckpt.policy_epoch() is None:
        raise ConfigError(f"{run_dir} has no best-policy checkpoint yet")
    epoch, policy, meta = ckpt.restore_policy(template)
    with contextlib.ExitStack() as stack:
        if video is not None:  # a GL context first: an unusable one fails before the episodes
            renderer = stack.enter_context(render.FrameRenderer(env, width, height))
        success = run_episodes(jax.random.PRNGKey(seed), policy, hparams_from_config(cfg))
        out = {"success": float(success), "epoch": epoch, "episodes": episodes,
               "backend": env.backend.name, "scene": env.setup.variant,
               "train_test_success": meta.get("test_success"),
               "selected": "selection_success" in meta}
        if video is not None:
            rollout = jax.jit(render.make_rollout(env, trainer.ddpg.act, video_episodes))
            # Its own key: the video episodes do not depend on how many were evaluated.
            snaps, goals, ok = rollout(jax.random.fold_in(jax.random.PRNGKey(seed), 1), policy)
            frames = render.write_video(
                video, render.render_frames(renderer, snaps, goals, ok), 1.0 / env.dt)
            out.update(video=str(video), video_episodes=video_episodes, frames=frames,
                       video_success=float(np.mean(np.asarray(ok)[:, -1])), gl=gl)
    return out


RETEST_FILE = "retest.json"


def retest(run_dir: Path, episodes: int) -> str:
    """Retests the best policy of ``run_dir`` on ``episodes`` new episodes (seed 0, as
    ``python -m rdher_jax.evaluate``), writes ``retest.json`` and returns the line to print."""
    r = evaluate(run_dir, episodes)
    write_text_atomic(run_dir / RETEST_FILE, json.dumps(r, indent=1) + "\n")
    won = round(r["success"] * episodes)
    which = "selected" if r["selected"] else "best"
    return (f"retest: the {which} policy (epoch {r['epoch']}) succeeds on {won} of {episodes} "
            f"new episodes ({100 * r['success']:.0f}%)")


# The selection episodes' root keys: SELECT_SEED + the run's seed, which no training run
# (seeds 0, 1, ...), retest (seed 0) or benchmark evaluation (1,000,000 + seed) starts from.
SELECT_SEED = 2_000_000


def select(run_dir: Path, ckpt: Checkpointer) -> str:
    """Chooses the run's policy among its kept candidates (the ``select_top`` best test
    epochs'): each is tested on the same ``select_episodes`` episodes (root key SELECT_SEED +
    the run's seed), and the best of them (ties: the later epoch) is saved as the selected
    policy, which :func:`evaluate` and :func:`retest` then test on episodes of their own.
    Returns the line to print."""
    from .program import hparams_from_config
    cfg = from_yaml(run_dir / "config.yaml")
    episodes = cfg.select_episodes
    kept = ckpt.candidates()
    if not kept:
        raise ConfigError(f"{run_dir} has no candidate policies to select from")
    env, trainer, template, run_episodes = _program(
        dataclasses.replace(cfg, n_test_rollouts=episodes))
    key, hp = jax.random.PRNGKey(SELECT_SEED + cfg.seed), hparams_from_config(cfg)
    scores, chosen, policy = {}, None, None
    for epoch in sorted(kept):  # ascending: a later epoch wins a tie
        _, candidate, _ = ckpt.restore_candidate(epoch, template)
        scores[epoch] = float(run_episodes(key, candidate, hp))
        if chosen is None or scores[epoch] >= scores[chosen]:
            chosen, policy = epoch, candidate
    meta = {"epoch": chosen, "test_success": kept[chosen]["test_success"],
            "selection_success": scores[chosen], "selection_episodes": episodes,
            "selection_seed": SELECT_SEED + cfg.seed,
            "candidates": {str(e): {"test_success": kept[e]["test_success"],
                                    "selection_success": scores[e]} for e in sorted(kept)}}
    ckpt.save_selected(chosen, policy, meta)
    write_text_atomic(run_dir / SELECT_FILE, json.dumps(meta, indent=1) + "\n")
    tried = ", ".join(f"{e}: {round(scores[e] * episodes)}" for e in sorted(kept))
    return (f"selected: the policy of epoch {chosen}, the best of the {len(kept)} best test "
            f"epochs on {episodes} selection episodes (successes by epoch: {tried})")
