"""What a training command runs, where it writes and what it gives back: :class:`Plan`, the
directory layout and :class:`DriveResult`.

A plan is N >= 1 runs that differ only in traced keys and seeds. ``python -m rdher_jax.train``
makes a plan of one run in its own directory; ``python -m rdher_jax.sweep`` one of many under a
sweep directory. Everything that differs between the two layouts is decided here, once:

- a run (``train``): ``run_dir/`` holds config.yaml, run_info.json, metrics.csv, success.png,
  ``checkpoints/latest`` (the run's TrainState, no run axis) and ``checkpoints/best`` (its best
  policy);
- a sweep: ``sweep_dir/<run>/`` holds what a run holds except the latest state, which is the
  sweep's: ``sweep_dir/checkpoints/latest`` (every run's TrainState, stacked along a run axis),
  beside ``sweep.yaml`` (what varies, written last: it marks the directory as a sweep's),
  ``base_config.yaml``, ``run_info.json`` and the summary files (``rdher_jax.summary``).

Imports no JAX: the command lines build and check their plan before JAX starts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import Config, ConfigError
from .runlog import check_fresh_dir, check_resume_dir

SPEC_FILE = "sweep.yaml"
BASE_CONFIG_FILE = "base_config.yaml"
RUN_CONFIG_FILE = "config.yaml"


@dataclass(frozen=True)
class Plan:
    """What :func:`rdher_jax.driver.drive` runs and where it writes.

    Attributes:
      runs: one resolved Config per run, each with its own ``run_dir`` and seed; they may
        differ only in traced keys (``config.TRACED_KEYS``) and seeds.
      out_dir: the run directory (one run) or the sweep directory.
      base: the config the runs are made from (a sweep's ``base_config.yaml``, its run_dir the
        sweep directory); a single run's own.
      sweep: the sweep layout (a spec, a summary and one stacked latest checkpoint, the runs
        vmapped even when there is one) rather than a run's own.
      resume: continue ``out_dir`` from its latest checkpoint.
      varies: the sweep's varying keys as written to ``sweep.yaml``: ``lambdas`` (pairs),
        ``seeds`` and ``grid`` (``{field: values}``).
      names: each run's directory name under a sweep directory ("" for a run of its own).
    """

    runs: tuple[Config, ...]
    out_dir: Path
    base: Config
    sweep: bool = False
    resume: bool = False
    varies: Mapping[str, Any] = field(default_factory=dict)
    names: tuple[str, ...] = ()

    @classmethod
    def single(cls, cfg: Config) -> Plan:
        """One run in its own directory (``cfg`` resolved; ``resume`` set to continue it)."""
        out = Path(cfg.resume if cfg.resume is not None else cfg.run_dir)
        return cls((cfg,), out, cfg, sweep=False, resume=cfg.resume is not None, names=("",))

    # ---------------------------------------------------------------- the layout
    @property
    def kind(self) -> str:
        """What the output directory is called in messages and checks."""
        return "sweep_dir" if self.sweep else "run_dir"

    @property
    def marker(self) -> str:
        """The file whose presence makes ``out_dir`` a directory of this layout."""
        return SPEC_FILE if self.sweep else RUN_CONFIG_FILE

    @property
    def vmapped(self) -> bool:
        """Whether the program is ``vmap`` over runs. A run of its own is the unvmapped epoch
        (the numbers it gave before sweeps existed); a sweep is vmapped even over one run."""
        return self.sweep

    @property
    def stacked_latest(self) -> bool:
        """Whether the latest checkpoint holds the runs stacked along a run axis (a sweep's)
        rather than one run's state (a run's own, which evaluate and resume read as is)."""
        return self.sweep


class TrainingDiverged(RuntimeError):
    """Every run's losses became NaN or inf; the last good checkpoint is kept."""


@dataclass(frozen=True)
class DriveResult:
    """What :func:`drive` leaves: where, which runs, how each ended.

    Attributes:
      out_dir: the run or sweep directory.
      names: the runs' names ("" for a run of its own).
      rows: each run's last metrics row of this invocation ({} if it logged none).
      best: each run's best test success.
      diverged: the runs whose losses became non-finite, with the epoch.
      program: how the runs were executed (devices, sharding).
      local: the runs this process stepped.
      summary: the sweep's per-run summary rows and per-setting aggregates (process 0).
      stopped: the epoch after which ``stop_success`` was met, or None.
    """

    out_dir: str
    names: list[str]
    rows: list[dict]
    best: list[float]
    diverged: dict[str, int]
    program: str
    local: list[int]
    summary: tuple[list[dict], list[dict]] = field(default_factory=lambda: ([], []))
    stopped: int | None = None


def check_out_dir(plan: Plan) -> None:
    """The output directory is usable for the plan (before anything is built or written)."""
    if plan.resume:
        check_resume_dir(plan.out_dir, marker=plan.marker)
    else:
        check_fresh_dir(plan.out_dir, plan.kind)


def latest_slot(processes: int) -> str:
    """The name of the latest-state checkpoint slot: ``latest`` with one process,
    ``latest-<N>-processes`` when N processes save it together."""
    return "latest" if processes == 1 else f"latest-{processes}-processes"


def check_process_count(out_dir: Path, processes: int) -> None:
    """A directory checkpointed by N processes resumes only with N: a one-line ConfigError
    naming the number it needs otherwise."""
    ck = Path(out_dir) / "checkpoints"
    if not ck.is_dir():
        return
    found = set()
    for p in ck.iterdir():
        if p.name == "latest" and any(q.name.isdigit() for q in p.iterdir()):
            found.add(1)
        elif p.name.startswith("latest-") and p.name.endswith("-processes"):
            try:
                found.add(int(p.name.split("-")[1]))
            except ValueError:
                continue
    if found and processes not in found:
        need = max(found)
        how = "in one process" if need == 1 else f"with num_processes={need}"
        raise ConfigError(f"{out_dir} was checkpointed by {need} process"
                          f"{'es' if need > 1 else ''}; resume it {how}, not with {processes}")
