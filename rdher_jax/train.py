"""Command line: ``python -m rdher_jax.train env=FetchPush algo=her seed=0 ...``.

The epoch function (``trainer.make_trainer``) is jitted once; this thin loop over epochs only
logs, plots and checkpoints. ``python -m rdher_jax.train --help`` lists every option.

The per-epoch bookkeeping of a run (its metrics row, CSV, TensorBoard scalars, best-policy
checkpoint and plot) lives in :class:`RunOutputs`, which ``rdher_jax.sweep`` keeps one of per run.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .checkpoint import Checkpointer
from .config import Config, ConfigError, main_guard, parse_args, resolve, resume_config, to_yaml
from .runlog import (
    MetricsCSV,
    TBWriter,
    check_resume_dir,
    check_run_dir,
    make_run_dir,
    metric_fields,
    plot_success,
    write_json_atomic,
    write_text_atomic,
)

PROG = "python -m rdher_jax.train"


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


def _cpu_model() -> str:
    """The CPU's model name on Linux (platform.processor() is often empty there)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def run_info(cfg: Config, argv: Sequence[str], prog: str = PROG) -> dict:
    """Command line, backend, hardware and package versions, for ``run_info.json``."""
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
        "command": " ".join([prog, *argv]),
        "backend": backend,
        "scene": scene,
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "processor": platform.processor() or _cpu_model(),
        "python": platform.python_version(),
        "versions": versions,
    }


# ------------------------------------------------------------------ metrics rows

def epoch_metric_names() -> tuple[str, ...]:
    """The fields of the trainer's ``EpochMetrics``, in declaration order."""
    from .trainer import EpochMetrics

    return tuple(f.name for f in dataclasses.fields(EpochMetrics))


def csv_fields() -> tuple[str, ...]:
    """The columns of metrics.csv: the loop's epoch and wall_time plus every EpochMetrics field."""
    return metric_fields(epoch_metric_names())


def loss_fields(fields: Iterable[str]) -> tuple[str, ...]:
    """The columns a NaN or inf stops a run on: the losses and the critic's mean Q. Other
    diagnostics may be NaN by design (e.g. a mean over no samples)."""
    return tuple(f for f in fields if f.endswith("_loss") or f == "q_mean")


def epoch_row(epoch: int, metrics: Any, wall_time: float) -> dict[str, int | float]:
    """The metrics.csv row of one run after ``epoch``: every field of ``metrics`` (an
    ``EpochMetrics`` of host scalars) plus epoch and wall time, in :func:`csv_fields` order."""
    values = {f.name: np.asarray(getattr(metrics, f.name)) for f in dataclasses.fields(metrics)}
    row: dict[str, int | float] = {"epoch": epoch, "wall_time": round(wall_time, 3)}
    for k, v in values.items():
        if v.shape != ():
            raise ValueError(f"EpochMetrics.{k} has shape {v.shape}; one run's are scalars")
        row[k] = int(v) if v.dtype.kind in "iub" else float(v)
    return {k: row[k] for k in metric_fields(values)}


def nonfinite_losses(row: Mapping[str, Any]) -> list[str]:
    """The loss columns of ``row`` that are NaN or inf."""
    return [k for k in loss_fields(row) if not math.isfinite(row[k])]


def last_good_checkpoint(ckpt: Checkpointer) -> str:
    """The sentence a diverged run ends with: where its last good checkpoint is."""
    last = ckpt.latest_epoch()
    if last is None:
        return "No checkpoint was written yet."
    return f"The last good checkpoint (epoch {last}) is kept in {ckpt.directory}"


def is_checkpoint_epoch(cfg: Config, epoch: int) -> bool:
    """Whether the latest state is saved after ``epoch`` (1-based): every ``checkpoint_every``
    epochs and after the last one."""
    return epoch % cfg.checkpoint_every == 0 or epoch == cfg.epochs


def plot_title(cfg: Config) -> str:
    lam = "" if (cfg.lambda_r, cfg.lambda_h) == (1.0, 1.0) else (
        f" lambda_r={cfg.lambda_r:g} lambda_h={cfg.lambda_h:g}")
    return f"{cfg.env} {cfg.algo} seed {cfg.seed}{lam}"


class RunOutputs:
    """The files of one run in ``run_dir`` and what every epoch adds to them.

    config.yaml and run_info.json (:meth:`start`), metrics.csv (a row per epoch), success.png,
    the best-policy checkpoint (ties go to the later epoch, as in baselines) and TensorBoard
    scalars. The latest full training state is the caller's: ``train`` saves it per run, a
    sweep saves all runs' stacked states together.
    """

    def __init__(self, cfg: Config, run_dir: str | Path, latest: bool = True) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        # latest=False: no checkpoints/latest here (a sweep's runs share the sweep's).
        self.ckpt = Checkpointer(self.run_dir, latest=latest)
        try:
            self.csv = MetricsCSV(self.run_dir / "metrics.csv", csv_fields(), extend=True)
        except ValueError as e:
            raise ConfigError(f"cannot continue {self.run_dir}: {e}") from None
        self.tb = TBWriter(self.run_dir) if cfg.tensorboard else None
        self.best = -1.0

    def start(self, info: Mapping[str, Any]) -> None:
        """Begin the run from epoch 0: write config.yaml and run_info.json, and drop any rows
        and best policy a run killed before its first checkpoint left."""
        self.rewind(0, -1.0)
        write_text_atomic(self.run_dir / "config.yaml", to_yaml(self.cfg))
        write_json_atomic(self.run_dir / "run_info.json", info)

    def rewind(self, epoch: int, best: float) -> None:
        """Continue after ``epoch`` (a resume): later rows and best policies are abandoned."""
        self.ckpt.discard_after(epoch)
        self.csv.truncate_after(epoch)
        self.best = best

    def record(self, row: Mapping[str, Any], policy: Callable[[], Any]) -> bool:
        """Append ``row``; save ``policy()`` when its test success is the best so far; replot.
        Returns whether it was a new best."""
        self.csv.append(row)
        if self.tb is not None:
            self.tb.scalars(row, step=int(row["env_steps"]))
        new_best = row["test_success"] >= self.best  # baselines saves on >= (ties keep the latest)
        if new_best:
            self.best = float(row["test_success"])
            self.ckpt.save_best(int(row["epoch"]), policy(),
                                {"test_success": self.best, "epoch": int(row["epoch"])})
        plot_success(self.run_dir / "metrics.csv", self.run_dir / "success.png",
                     plot_title(self.cfg))
        return new_best

    def close(self) -> None:
        self.ckpt.close()
        if self.tb is not None:
            self.tb.close()


def restore_or_refuse(ckpt: Checkpointer, template: Any, directory: Path) -> tuple[int, Any, dict]:
    """``ckpt.restore_latest(template)``; any failure to read it is a one-line ConfigError (a
    resume of a directory whose checkpoint is damaged or from another configuration)."""
    try:
        return ckpt.restore_latest(template)
    except Exception as e:  # orbax, tensorstore and our own template checks raise many kinds
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"cannot resume {directory}: its latest checkpoint is unusable: "
                          f"{msg[:300]}") from None


# ------------------------------------------------------------------ one run

def train(cfg: Config, argv: list[str] | None = None, log=print) -> dict:
    """Run (or continue) a training run; returns the final metrics row and paths."""
    argv = argv or []
    check_run_dir(cfg)  # before building anything, and without creating anything
    env, trainer = build(cfg)
    run_dir = make_run_dir(cfg)
    hp = trainer.hparams
    out = RunOutputs(cfg, run_dir)
    ckpt = out.ckpt
    init = jax.jit(trainer.init)
    ts = init(jax.random.PRNGKey(cfg.seed), hp)
    start, wall0 = 0, 0.0
    if cfg.resume is not None and ckpt.latest_epoch() is not None:
        start, ts, meta = restore_or_refuse(ckpt, ts, run_dir)
        wall0 = float(meta["wall_time"])
        out.rewind(start, float(meta["best_success"]))
        log(f"resuming {run_dir} after epoch {start}")
    else:
        if cfg.resume is not None:  # killed before its first checkpoint: start over
            log(f"{run_dir} has no checkpoint yet; starting it over")
        out.start(run_info(cfg, argv))

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
        row = epoch_row(epoch + 1, m, time.perf_counter() - t_start)
        bad = nonfinite_losses(row)
        if bad:
            raise TrainingDiverged(f"{', '.join(bad)} became non-finite in epoch {epoch + 1}; "
                                   f"stopped. {last_good_checkpoint(ckpt)}")
        out.record(row, lambda ts=ts: ts.ddpg)
        if is_checkpoint_epoch(cfg, epoch + 1):
            ckpt.save_latest(epoch + 1, ts, {"best_success": out.best,
                                             "wall_time": row["wall_time"]})
        if bar is not None:
            bar.set_postfix(env_steps=row["env_steps"], sps=f"{steps_per_epoch / dt:.0f}",
                            test=f"{row['test_success']:.2f}")
            bar.update(1)
    if bar is not None:
        bar.close()
    out.close()
    if row is None:
        rows = out.csv.rows()
        row = rows[-1] if rows else {}
    return {"row": row, "best_success": out.best, "run_dir": str(run_dir)}


def load_resume_config(cfg: Config, argv: Sequence[str]) -> Config:
    """:func:`config.resume_config` after checking the directory; a config.yaml that is not a
    run's config is a one-line ConfigError whatever the way it is broken."""
    check_resume_dir(cfg.resume)
    try:
        return resume_config(cfg, argv)
    except ConfigError:
        raise
    except Exception as e:  # e.g. a YAML list where a mapping belongs
        raise ConfigError(f"cannot resume {cfg.resume}: its config.yaml is not a run config "
                          f"({type(e).__name__}: {e})") from None


@main_guard
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse_args(argv, prog=PROG)
    cfg = load_resume_config(cfg, argv) if cfg.resume is not None else resolve(cfg)
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
