"""Command line: ``python -m rdher_jax.train env=FetchPush algo=her seed=0 ...``.

The epoch function (``trainer.make_trainer``) is jitted once; this thin loop over epochs only
logs, plots and checkpoints. ``python -m rdher_jax.train --help`` lists every option.
"""

from __future__ import annotations

import math
import platform
import sys
import time
from pathlib import Path

import jax

from .checkpoint import Checkpointer
from .config import Config, ConfigError, main_guard, parse_args, resolve, resume_config, to_yaml
from .runlog import (
    MetricsCSV,
    TBWriter,
    make_run_dir,
    plot_success,
    write_json_atomic,
    write_text_atomic,
)

LOSS_KEYS = ("critic_loss", "actor_loss", "q_mean")


class TrainingDiverged(RuntimeError):
    """A loss became NaN or inf; the last good checkpoint is kept."""


def resolve_backend(cfg: Config) -> tuple[str, str]:
    """The physics backend and scene a config asks for, with ``auto`` decided here."""
    from .envs import default_backend

    backend = default_backend() if cfg.backend == "auto" else cfg.backend
    scene = cfg.scene if cfg.scene != "auto" else ("original" if backend == "mujoco" else "mjx")
    if backend == "mjx" and scene != "mjx":
        raise ConfigError("backend=mjx needs scene=mjx (mjx.put_model rejects the original)")
    return backend, scene


def build(cfg: Config):
    """Env, trainer and hyperparameters of a resolved config."""
    from .envs import make_env
    from .trainer import make_trainer

    backend, scene = resolve_backend(cfg)
    env = make_env(cfg.env, backend=backend, scene=scene, auto_reset=False)
    return env, make_trainer(cfg, env)


def run_info(cfg: Config, argv: list[str]) -> dict:
    import importlib.metadata as md

    versions = {}
    for pkg in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "mjbatch", "gymnasium-robotics", "flax",
                "optax", "brax", "orbax-checkpoint"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            versions[pkg] = None
    backend, scene = resolve_backend(cfg)
    return {
        "command": " ".join(["python -m rdher_jax.train", *argv]),
        "backend": backend,
        "scene": scene,
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "machine": platform.machine(),
        "processor": platform.processor(),
        "python": platform.python_version(),
        "versions": versions,
    }


def train(cfg: Config, argv: list[str] | None = None, log=print) -> dict:
    """Run (or continue) a training run; returns the final metrics row and paths."""
    argv = argv or []
    run_dir = make_run_dir(cfg)
    env, trainer = build(cfg)
    hp = trainer.hparams
    ckpt = Checkpointer(run_dir)
    csv = MetricsCSV(run_dir / "metrics.csv")
    tb = TBWriter(run_dir) if cfg.tensorboard else None
    init = jax.jit(trainer.init)
    ts = init(jax.random.PRNGKey(cfg.seed), hp)
    start, best, wall0 = 0, -1.0, 0.0
    if cfg.resume is not None and ckpt.latest_epoch() is not None:
        start, ts, meta = ckpt.restore_latest(ts)
        best, wall0 = float(meta["best_success"]), float(meta["wall_time"])
        ckpt.discard_after(start)
        csv.truncate_after(start)
        log(f"resuming {run_dir} after epoch {start}")
    else:
        if cfg.resume is not None:  # killed before its first checkpoint: start over
            csv.truncate_after(0)
            log(f"{run_dir} has no checkpoint yet; starting it over")
        write_text_atomic(run_dir / "config.yaml", to_yaml(cfg))
        write_json_atomic(run_dir / "run_info.json", run_info(cfg, argv))

    epoch_fn = jax.jit(trainer.epoch, donate_argnums=0)
    steps_per_epoch = cfg.n_cycles * cfg.num_envs * env.episode_length
    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.epochs, initial=start, desc=f"{cfg.env} {cfg.algo}", unit="epoch",
                   dynamic_ncols=True, file=sys.stderr)
    t_start = time.perf_counter() - wall0
    row = None
    for epoch in range(start, cfg.epochs):
        t0 = time.perf_counter()
        ts, m = epoch_fn(ts, hp)
        m = jax.device_get(m)
        dt = time.perf_counter() - t0
        row = {
            "epoch": epoch + 1,
            "env_steps": int(m.env_steps),
            "updates": int(m.updates),
            "wall_time": round(time.perf_counter() - t_start, 3),
            "test_success": float(m.test_success),
            "train_success": float(m.train_success),
            **{k: float(getattr(m, k)) for k in LOSS_KEYS},
        }
        bad = [k for k in LOSS_KEYS if not math.isfinite(row[k])]
        if bad:
            last = ckpt.latest_epoch()
            raise TrainingDiverged(
                f"{', '.join(bad)} became non-finite in epoch {epoch + 1}; stopped. The last good "
                f"checkpoint (epoch {last}) is kept in {ckpt.directory}"
            )
        csv.append(row)
        if tb is not None:
            tb.scalars(row, step=row["env_steps"])
        if row["test_success"] >= best:  # baselines saves on >= (ties keep the latest)
            best = row["test_success"]
            ckpt.save_best(epoch + 1, ts.ddpg, {"test_success": best, "epoch": epoch + 1})
        if (epoch + 1) % cfg.checkpoint_every == 0 or epoch + 1 == cfg.epochs:
            ckpt.save_latest(epoch + 1, ts, {"best_success": best, "wall_time": row["wall_time"]})
        plot_success(run_dir / "metrics.csv", run_dir / "success.png",
                     f"{cfg.env} {cfg.algo} seed {cfg.seed}")
        if bar is not None:
            bar.set_postfix(env_steps=row["env_steps"], sps=f"{steps_per_epoch / dt:.0f}",
                            test=f"{row['test_success']:.2f}")
            bar.update(1)
    if bar is not None:
        bar.close()
    ckpt.close()
    if tb is not None:
        tb.close()
    if row is None:
        rows = csv.rows()
        row = rows[-1] if rows else {}
    return {"row": row, "best_success": best, "run_dir": str(run_dir)}


@main_guard
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse_args(argv, prog="python -m rdher_jax.train")
    cfg = resume_config(cfg, argv) if cfg.resume is not None else resolve(cfg)
    try:
        out = train(cfg, argv)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    row, run_dir = out["row"], Path(out["run_dir"])
    print(
        f"{cfg.env} {cfg.algo} seed {cfg.seed}: test success {float(row['test_success']):.3f} "
        f"after {int(float(row['env_steps']))} env steps "
        f"({float(row['wall_time']):.0f} s), best {out['best_success']:.3f}"
    )
    print(f"results in {run_dir}/: metrics.csv, success.png, config.yaml, checkpoints/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
