"""``python -m rdher_jax.evaluate <run dir> [episodes=N] [backend=mujoco|mjx] [scene=...]``.

Loads the run's best policy and prints its test success over N deterministic episodes, on the
backend and scene the run trained on unless told otherwise (a policy trained on one backend can
be evaluated on the other).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax

from .checkpoint import Checkpointer
from .config import ConfigError, from_yaml, main_guard

USAGE = ("usage: python -m rdher_jax.evaluate <run dir> [episodes=100] [seed=0] "
         "[backend=auto|mujoco|mjx] [scene=auto|original|mjx]")


def parse(argv: list[str]) -> tuple[Path, dict]:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        raise SystemExit(0)
    run_dir, opts = Path(argv[0]), {"episodes": "100", "seed": "0", "backend": None, "scene": None}
    for tok in argv[1:]:
        key, eq, val = tok.partition("=")
        if not eq or key not in opts:
            raise ConfigError(f"bad argument {tok!r}; {USAGE}")
        opts[key] = val
    for key in ("episodes", "seed"):
        if not opts[key].isdigit() or (key == "episodes" and int(opts[key]) < 1):
            raise ConfigError(f"{key} must be a positive integer, got {opts[key]!r}")
    if not (run_dir / "config.yaml").is_file():
        raise ConfigError(f"{run_dir} is not a run directory (no config.yaml)")
    return run_dir, opts


def evaluate(run_dir: Path, episodes: int = 100, seed: int = 0, backend: str | None = None,
             scene: str | None = None) -> dict:
    """Test success of the best policy of ``run_dir`` over ``episodes`` episodes."""
    from .train import build

    cfg = from_yaml(run_dir / "config.yaml")
    if backend is not None or scene is not None:
        cfg = dataclasses.replace(cfg, backend=backend or cfg.backend,
                                  scene=scene or ("auto" if backend else cfg.scene))
    cfg = dataclasses.replace(cfg, n_test_rollouts=episodes)
    env, trainer = build(cfg)
    template = jax.jit(trainer.ddpg.init)(jax.random.PRNGKey(0), trainer.hparams.ddpg)
    ckpt = Checkpointer(run_dir, read_only=True)
    if ckpt.best_epoch() is None:
        raise ConfigError(f"{run_dir} has no best-policy checkpoint yet")
    epoch, policy, meta = ckpt.restore_best(template)
    success = jax.jit(trainer.evaluate)(jax.random.PRNGKey(seed), policy, trainer.hparams)
    return {"success": float(success), "epoch": epoch, "episodes": episodes,
            "backend": env.backend.name, "scene": env.setup.variant,
            "train_test_success": meta.get("test_success")}


@main_guard
def main(argv: list[str] | None = None) -> int:
    run_dir, o = parse(list(sys.argv[1:] if argv is None else argv))
    r = evaluate(run_dir, int(o["episodes"]), int(o["seed"]), o["backend"], o["scene"])
    print(f"{run_dir}: best policy (epoch {r['epoch']}) test success {r['success']:.3f} over "
          f"{r['episodes']} episodes on backend={r['backend']} scene={r['scene']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
