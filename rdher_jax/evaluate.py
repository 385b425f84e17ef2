"""``python -m rdher_jax.evaluate <run dir> [episodes=N] [backend=mujoco|mjx|warp] [scene=...]
[video=out.gif|out.mp4 [video_episodes=K] [width=W] [height=H]]``.

Loads the run's best policy and prints its test success over N deterministic episodes, on the
backend and scene the run trained on unless told otherwise (a policy trained on one backend can
be evaluated on the other). With ``video=``, K more deterministic episodes are rendered
offscreen by MuJoCo (``rdher_jax.render``) and written as a GIF or an MP4.
"""

from __future__ import annotations

import sys
from pathlib import Path

from . import render
from .config import ConfigError, main_guard, split_args
from .policy_test import evaluate
from .render import DEFAULT_SIZE, RenderError
from .startup import Startup, setup

__all__ = ["evaluate", "main", "parse"]

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
