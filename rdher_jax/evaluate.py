"""``python -m rdher_jax.evaluate <run dir> [episodes=N] [backend=mujoco|mjx|warp] [scene=...]
[video=out.gif|out.mp4 [video_episodes=K] [width=W] [height=H]]``.

Loads the run's best policy and prints its test success over N deterministic episodes, on the
backend and scene the run trained on unless told otherwise (a policy trained on one backend can
be evaluated on the other). With ``video=``, K more deterministic episodes are rendered
offscreen by MuJoCo (``rdher_jax.render``) and written as a GIF or an MP4.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

from . import render
from .checkpoint import Checkpointer
from .config import ConfigError, from_yaml, main_guard, split_args
from .render import DEFAULT_SIZE, RenderError
from .startup import Startup, setup

USAGE = ("usage: python -m rdher_jax.evaluate <run dir> [episodes=100] [seed=0] "
         "[backend=auto|mujoco|mjx|warp] [scene=auto|original|mjx|warp] "
         "[video=out.gif|out.mp4] [video_episodes=3] [width=480] [height=480]")
VIDEO_OPTS = ("video_episodes", "width", "height")
MIN_SIZE, MAX_SIZE = 64, 4096


def parse(argv: list[str]) -> tuple[Path, dict]:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        raise SystemExit(0)
    run_dir = Path(argv[0])
    opts = {"episodes": "100", "seed": "0", "backend": None, "scene": None, "video": None,
            "video_episodes": "3", "width": str(DEFAULT_SIZE), "height": str(DEFAULT_SIZE)}
    _, given_opts = split_args(argv[1:], extra=tuple(opts), config_keys=False)
    opts.update(given_opts)
    given = set(given_opts)
    for key in ("episodes", "seed", *VIDEO_OPTS):
        if not opts[key].isdigit() or (key != "seed" and int(opts[key]) < 1):
            raise ConfigError(f"{key} must be a positive integer, got {opts[key]!r}")
    for key in ("width", "height"):
        if not MIN_SIZE <= int(opts[key]) <= MAX_SIZE:
            raise ConfigError(f"{key} must be {MIN_SIZE} to {MAX_SIZE} pixels, got {opts[key]}")
    if opts["video"] is None and given & set(VIDEO_OPTS):
        raise ConfigError(f"{', '.join(sorted(given & set(VIDEO_OPTS)))} needs video=<file>")
    if not (run_dir / "config.yaml").is_file():
        raise ConfigError(f"{run_dir} is not a run directory (no config.yaml)")
    if opts["video"] is not None:
        try:
            render.check_video_path(opts["video"], int(opts["width"]), int(opts["height"]))
        except RenderError as e:
            raise ConfigError(str(e)) from None
    return run_dir, opts


# Keys of a run's config that do not change the evaluation program: the runs of one sweep (seeds,
# λ pairs) share one build and one compilation (experiments test every run of a sweep).
_PER_RUN_KEYS = ("seed", "lambda_r", "lambda_h", "epochs", "run_dir", "resume",
                 "checkpoint_every", "tensorboard", "progress", "stop_success", "stop_window")
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
    """Test success of the best policy of ``run_dir`` over ``episodes`` episodes; with
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
    if ckpt.best_epoch() is None:
        raise ConfigError(f"{run_dir} has no best-policy checkpoint yet")
    epoch, policy, meta = ckpt.restore_best(template)
    with contextlib.ExitStack() as stack:
        if video is not None:  # a GL context first: an unusable one fails before the episodes
            renderer = stack.enter_context(render.FrameRenderer(env, width, height))
        success = run_episodes(jax.random.PRNGKey(seed), policy, hparams_from_config(cfg))
        out = {"success": float(success), "epoch": epoch, "episodes": episodes,
               "backend": env.backend.name, "scene": env.setup.variant,
               "train_test_success": meta.get("test_success")}
        if video is not None:
            rollout = jax.jit(render.make_rollout(env, trainer.ddpg.act, video_episodes))
            # Its own key: the video episodes do not depend on how many were evaluated.
            snaps, goals, ok = rollout(jax.random.fold_in(jax.random.PRNGKey(seed), 1), policy)
            frames = render.write_video(
                video, render.render_frames(renderer, snaps, goals, ok), 1.0 / env.dt)
            out.update(video=str(video), video_episodes=video_episodes, frames=frames,
                       video_success=float(np.mean(np.asarray(ok)[:, -1])), gl=gl)
    return out


@main_guard
def main(argv: list[str] | None = None) -> int:
    run_dir, o = parse(list(sys.argv[1:] if argv is None else argv))
    try:
        setup(Startup(gl=o["video"] is not None))
        r = evaluate(run_dir, int(o["episodes"]), int(o["seed"]), o["backend"], o["scene"],
                     o["video"], int(o["video_episodes"]), int(o["width"]), int(o["height"]))
    except RenderError as e:
        raise ConfigError(str(e)) from None
    print(f"{run_dir}: best policy (epoch {r['epoch']}) test success {r['success']:.3f} over "
          f"{r['episodes']} episodes on backend={r['backend']} scene={r['scene']}")
    if "video" in r:
        print(f"wrote {r['video']}: {r['video_episodes']} episodes, {r['frames']} frames "
              f"(success {r['video_success']:.2f}), MUJOCO_GL={r['gl']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
