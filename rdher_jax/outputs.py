"""Everything a plan writes, and what the loop knows of its runs between epochs.

- :class:`Progress`: every run's best and recent test successes, which runs diverged, and the
  wall clock, kept on every process; the latest checkpoint's metadata is its :meth:`meta`.
  The best-epoch rule (ties go to the later epoch, as baselines saves its best policy) is
  written once, in :meth:`Progress.observe`.
- :class:`RunOutputs`: one run's files (config.yaml, run_info.json, metrics.csv, success.png,
  the best policy, TensorBoard scalars) and its summary record, kept in memory.
- :class:`Outputs`: the plan's files, written by process 0: each run's, the latest state, and
  for a sweep its spec and summary (from the records in memory, never read back from disk).
- The metrics row of an epoch (:func:`epoch_row`) and the run's ``run_info.json``
  (:func:`run_info`).

Where each file goes is :mod:`rdher_jax.plan`'s to say.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np

from . import distributed, summary
from .checkpoint import SELECT_FILE, Checkpointer
from .config import SUCCESS_TOLERANCE, Config, ConfigError, to_yaml
from .executor import resolve_backend
from .plan import BASE_CONFIG_FILE, SPEC_FILE, Plan, TrainingDiverged, latest_slot
from .program import EpochMetrics
from .runlog import (
    MetricsCSV,
    TBWriter,
    make_dir,
    metric_fields,
    package_versions,
    plot_success,
    write_json_atomic,
    write_text_atomic,
)

# success.png is redrawn at most this often while a run trains, and always when it ends: a
# plot costs about 0.2 s (and matplotlib's import 0.4 s the first time), a fifth of a FetchReach
# epoch, and a sweep draws one per run.
PLOT_EVERY_S = 30.0
VERSIONED = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "mjbatch", "gymnasium-robotics", "flax",
             "optax", "brax", "orbax-checkpoint")


# ------------------------------------------------------------------ metrics rows

def csv_fields() -> tuple[str, ...]:
    """The columns of metrics.csv: the loop's epoch and wall_time plus every EpochMetrics field."""
    return metric_fields(f.name for f in dataclasses.fields(EpochMetrics))


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


def run_of(tree: Any, i: int) -> Any:
    """Run ``i`` of a tree with a leading run axis."""
    return jax.tree.map(lambda x: x[i], tree)


# ------------------------------------------------------------------ what the loop knows

@dataclass
class Progress:
    """Every run's best and recent test successes, the runs that diverged (name -> epoch) and
    the wall clock so far; the same on every process."""

    names: tuple[str, ...]
    best: list[float]
    recent: list[list[float]]
    diverged: dict[str, int] = field(default_factory=dict)
    wall: float = 0.0
    # select_top > 1: the test successes of each run's kept candidate policies
    kept: list[list[float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.kept:
            self.kept = [[] for _ in self.names]

    @classmethod
    def fresh(cls, names: Sequence[str]) -> Progress:
        return cls(tuple(names), [-1.0] * len(names), [[] for _ in names])

    @classmethod
    def from_meta(cls, meta: Mapping[str, Any], names: Sequence[str], epoch: int,
                  directory: Path) -> Progress:
        """The progress saved with the latest checkpoint after ``epoch``. Reads the metadata
        of every layout and version: a run's own before runs and sweeps shared one format
        kept scalars (``best_success: 0.9``) where a sweep keeps lists."""
        names = tuple(names)
        saved_names = meta.get("runs")
        if saved_names is not None and list(saved_names) != list(names):
            raise ConfigError(f"cannot resume {directory}: its checkpoint holds runs "
                              f"{saved_names}, not {list(names)}")
        try:
            best = meta["best_success"]
            recent = meta.get("recent_success")  # absent before stop_success existed
            if not isinstance(best, list):  # a run's own, saved as scalars and one list
                best, recent = [best], None if recent is None else [recent]
            if recent is None:
                recent = [[] for _ in names]
            best = [float(b) for b in best]
            recent = [[float(x) for x in r] for r in recent]
            diverged = {k: int(v) for k, v in meta.get("diverged", {}).items()
                        if int(v) <= epoch}
            wall = float(meta["wall_time"])
            kept = meta.get("kept_success")  # absent before select_top existed
            kept = ([[] for _ in names] if kept is None
                    else [[float(x) for x in k] for k in kept])
            if len(best) != len(names) or len(recent) != len(names) or len(kept) != len(names):
                raise ValueError(f"{len(best)} runs' bests for {len(names)} runs")
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
            raise ConfigError(f"cannot resume {directory}: its checkpoint's metadata is "
                              f"damaged ({type(e).__name__}: {e})") from None
        return cls(names, best, recent, diverged, wall, kept)

    def meta(self, wall: float) -> dict[str, Any]:
        """The latest checkpoint's metadata (one format for a run and a sweep)."""
        return {"best_success": list(self.best), "wall_time": round(wall, 3),
                "diverged": dict(self.diverged), "runs": list(self.names),
                "recent_success": [list(r) for r in self.recent],
                "kept_success": [list(k) for k in self.kept]}

    def live(self) -> list[int]:
        return [i for i, name in enumerate(self.names) if name not in self.diverged]

    def take(self, epoch: int, metrics: Any, wall: float, latest: Checkpointer,
             log: Callable[[str], Any]) -> dict[int, dict]:
        """The metrics rows of the live runs after ``epoch``. A run whose losses became
        non-finite is marked diverged and gets no row; when none is left, TrainingDiverged."""
        rows: dict[int, dict] = {}
        for i in self.live():
            row = epoch_row(epoch, run_of(metrics, i), wall)
            bad = nonfinite_losses(row)
            if not bad:
                rows[i] = row
                continue
            self.diverged[self.names[i]] = epoch
            if len(self.names) == 1:
                raise TrainingDiverged(f"{', '.join(bad)} became non-finite in epoch {epoch}; "
                                       f"stopped. {last_good_checkpoint(latest)}")
            if distributed.is_main():
                log(f"{self.names[i]}: {', '.join(bad)} became non-finite in epoch {epoch}; "
                    f"its outputs stop at epoch {epoch - 1}, the other runs go on")
        if not self.live():
            raise TrainingDiverged(
                f"the losses of every run became non-finite (the last in epoch {epoch}); "
                f"stopped. {last_good_checkpoint(latest)}")
        return rows

    def observe(self, rows: Mapping[int, Mapping[str, Any]], window: int,
                top: int = 1) -> tuple[list[int], list[int]]:
        """Take the epoch's test successes; returns the runs with a new best policy and, with
        ``top`` > 1, the runs whose policy joins their ``top`` kept candidates (a new best
        always does). Ties go to the later epoch, as baselines saves its best policy: an
        epoch as good as the worst kept candidate replaces it."""
        new_best, new_kept = [], []
        for i, row in rows.items():
            success = float(row["test_success"])
            if success >= self.best[i]:
                new_best.append(i)
                self.best[i] = success
            if top > 1:
                kept = self.kept[i]
                if len(kept) < top or success >= min(kept):
                    new_kept.append(i)
                    kept.append(success)
                    if len(kept) > top:
                        kept.remove(min(kept))
            self.recent[i] = (self.recent[i] + [success])[-window:]
        return new_best, new_kept

    def stop_met(self, cfg: Config) -> bool:
        """Whether ``stop_success`` is met on every live run (:func:`reached_stop`)."""
        return reached_stop(cfg, self.recent, self.live())


def reached_stop(cfg: Config, recent: Sequence[Sequence[float]], live: Iterable[int]) -> bool:
    """Whether ``stop_success`` is met: every live run's last ``stop_window`` test successes
    (``recent[i]``, oldest first) are all there and average at least ``stop_success`` (to
    within ``config.SUCCESS_TOLERANCE``)."""
    if cfg.stop_success is None:
        return False
    live = list(live)
    return bool(live) and all(
        len(recent[i]) >= cfg.stop_window
        and float(np.mean(recent[i][-cfg.stop_window:])) >= cfg.stop_success - SUCCESS_TOLERANCE
        for i in live)


def last_good_checkpoint(ckpt: Checkpointer) -> str:
    """The sentence a diverged run ends with: where its last good checkpoint is."""
    last = ckpt.latest_epoch()
    if last is None:
        return "No checkpoint was written yet."
    return f"The last good checkpoint (epoch {last}) is kept in {ckpt.directory}"


# ------------------------------------------------------------------ one run's files

def plot_title(cfg: Config) -> str:
    lam = "" if (cfg.lambda_r, cfg.lambda_h) == (1.0, 1.0) else (
        f" lambda_r={cfg.lambda_r:g} lambda_h={cfg.lambda_h:g}")
    return f"{cfg.env} {cfg.algo} seed {cfg.seed}{lam}"


class RunOutputs:
    """The files of one run in ``cfg.run_dir`` and what every epoch adds to them.

    config.yaml and run_info.json (:meth:`start`), metrics.csv (a row per epoch), success.png
    (redrawn every ``PLOT_EVERY_S`` seconds of training and by :meth:`flush`), the best-policy
    checkpoint and TensorBoard scalars; :attr:`record` is the run's summary row, kept in memory.
    """

    def __init__(self, cfg: Config, name: str = "") -> None:
        self.cfg = cfg
        self.run_dir = Path(cfg.run_dir)
        self.ckpt = Checkpointer(self.run_dir, latest=False, select=cfg.select_top > 1)
        try:
            self.csv = MetricsCSV(self.run_dir / "metrics.csv", csv_fields(), extend=True)
        except ValueError as e:
            raise ConfigError(f"cannot continue {self.run_dir}: {e}") from None
        self.tb = TBWriter(self.run_dir) if cfg.tensorboard else None
        self.record = summary.RunRecord.of(name, cfg)
        self.last_row: Mapping[str, Any] = {}  # the newest row of metrics.csv
        self._plot_due = time.monotonic() + PLOT_EVERY_S
        self._unplotted = False

    def start(self, info: Mapping[str, Any]) -> None:
        """Begin the run from epoch 0: write config.yaml and run_info.json, and drop any rows
        and best policy a run killed before its first checkpoint left."""
        self.rewind(0)
        write_text_atomic(self.run_dir / "config.yaml", to_yaml(self.cfg))
        write_json_atomic(self.run_dir / "run_info.json", info)

    def rewind(self, epoch: int) -> None:
        """Continue after ``epoch`` (a resume): later rows and best policies are abandoned;
        the summary record is taken from what is kept (read once, here)."""
        self.ckpt.discard_after(epoch)
        if self.cfg.select_top > 1:  # chosen again when this run ends
            self.ckpt.clear_selected()
            (self.run_dir / SELECT_FILE).unlink(missing_ok=True)
        self.csv.truncate_after(epoch)
        rows = self.csv.rows() if epoch > 0 else []
        self.last_row = rows[-1] if rows else {}
        self.record.resume(self.last_row or None, self.ckpt.best_meta() if epoch > 0 else None)

    def write(self, row: Mapping[str, Any], policy: Any | None, best: bool = True) -> None:
        """Append ``row``; save ``policy`` when given: as the best one (``best``, a new best
        epoch) and, with ``select_top`` > 1, among the candidates."""
        self.csv.append(row)
        if self.tb is not None:
            self.tb.scalars(row, step=int(row["env_steps"]))
        epoch, success = int(row["epoch"]), float(row["test_success"])
        meta = {"test_success": success, "epoch": epoch}
        new_best = policy is not None and best
        if new_best:
            self.ckpt.save_best(epoch, policy, meta)
        if policy is not None and self.cfg.select_top > 1:
            self.keep_candidate(epoch, policy, meta)
        self.record.add(row, new_best=new_best)
        self.last_row = row
        self._unplotted = True

    def keep_candidate(self, epoch: int, policy: Any, meta: Mapping[str, Any]) -> None:
        """Save ``policy`` among the candidates, then drop the worst while more than
        ``select_top`` are kept (the lowest test success; of equals, the earliest epoch)."""
        self.ckpt.save_candidate(epoch, policy, meta)
        kept = self.ckpt.candidates()
        while len(kept) > self.cfg.select_top:
            worst = min(kept, key=lambda e: (float(kept[e]["test_success"]), e))
            self.ckpt.drop_candidate(worst)
            del kept[worst]

    def plot_if_due(self) -> None:
        """Redraw success.png if ``PLOT_EVERY_S`` passed since it was last drawn."""
        if time.monotonic() >= self._plot_due:
            self.flush()

    def flush(self) -> None:
        """Redraw success.png if rows came since it was last drawn."""
        if self._unplotted:
            plot_success(self.run_dir / "metrics.csv", self.run_dir / "success.png",
                         plot_title(self.cfg))
            self._unplotted = False
        self._plot_due = time.monotonic() + PLOT_EVERY_S

    def close(self) -> None:
        self.flush()
        self.ckpt.close()
        if self.tb is not None:
            self.tb.close()


# ------------------------------------------------------------------ the plan's files

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


def usable_cpus() -> int | None:
    """The CPU cores this process may run on (its affinity: 1 under ``taskset -c N``)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count()


def host_info() -> dict[str, Any]:
    """This machine and the package versions (also what the benchmarks record)."""
    versions = package_versions(VERSIONED)
    return {"jax_backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
            "cpu_count": os.cpu_count(), "cpu_affinity": usable_cpus(),
            "machine": platform.machine(),
            "processor": platform.processor() or _cpu_model(),
            "python": platform.python_version(), "versions": versions}


def run_info(cfg: Config, argv: Sequence[str], prog: str) -> dict:
    """Command line, backend, hardware and package versions, for ``run_info.json``."""
    backend, scene = resolve_backend(cfg)
    info = host_info()
    return {"command": " ".join([prog, *argv]), "backend": backend, "scene": scene,
            **{k: info[k] for k in ("jax_backend", "devices", "cpu_count", "cpu_affinity",
                                    "machine", "processor", "python", "versions")}}


class Outputs:
    """What a plan writes. Process 0 writes every run's files (metrics, plots, best policies:
    orbax writes host data from process 0 only); the latest state is saved by every process
    (its own shards, with several)."""

    def __init__(self, plan: Plan, processes: int, info: Mapping[str, Any],
                 log: Callable[[str], Any] = print) -> None:
        self.plan, self.info, self.log = plan, dict(info), log
        self.main = distributed.is_main()
        self.runs = ({i: RunOutputs(c, name) for i, (c, name)
                      in enumerate(zip(plan.runs, plan.names, strict=True))}
                     if self.main else {})
        self.latest = Checkpointer(plan.out_dir, best=False, latest_name=latest_slot(processes),
                                   collective=processes > 1)

    def open(self, restore: Callable[[Any], Any], template: Any) -> tuple[int, Any, Progress]:
        """Resume from the latest checkpoint, or begin: returns (the epoch to continue after,
        the restored state or None, the progress). ``template`` is a thunk for the restore
        template, ``restore`` places the restored state."""
        plan = self.plan
        if plan.resume and self.latest.latest_epoch() is not None:
            start, state, meta = restore_or_refuse(self.latest, template(), plan.out_dir)
            progress = Progress.from_meta(meta, plan.names, start, plan.out_dir)
            for o in self.runs.values():
                o.rewind(start)
            self.log(f"resuming {plan.out_dir} after epoch {start}")
            return start, restore(state), progress
        if plan.resume and self.main:  # killed before its first checkpoint: start over
            self.log(f"{plan.out_dir} has no checkpoint yet; starting it over")
        if plan.sweep and self.main:
            # The spec file goes last of the two: it is what marks a directory as a sweep's.
            write_text_atomic(plan.out_dir / BASE_CONFIG_FILE, to_yaml(plan.base))
            write_text_atomic(plan.out_dir / SPEC_FILE, summary.spec_yaml(plan.varies,
                                                                         plan.names))
            write_json_atomic(plan.out_dir / "run_info.json", self.info)
        for i, o in self.runs.items():
            o.start({**self.info, "sweep_dir": str(plan.out_dir), "run": plan.names[i]}
                    if plan.sweep else self.info)
        return 0, None, Progress.fresh(plan.names)

    def write(self, rows: Mapping[int, Mapping[str, Any]], new_best: Sequence[int],
              policies: Callable[[], Any], new_kept: Sequence[int] = ()) -> None:
        """Each run's row, and the policies of the runs with a new best or a new candidate.
        ``policies`` fetches every run's learner state (once, only when some policy is
        saved)."""
        saved = set(new_best) | set(new_kept)
        pol = policies() if saved else None
        for i, row in rows.items():
            if i in self.runs:
                self.runs[i].write(row, run_of(pol, i) if i in saved else None,
                                   best=i in new_best)

    def select(self, progress: Progress, log: Callable[[str], Any]) -> None:
        """With ``select_top`` > 1, each live run's policy is chosen among its candidates
        (:func:`rdher_jax.policy_test.select`) once training has ended."""
        if not self.runs or self.plan.base.select_top <= 1:
            return
        from .policy_test import select  # builds an evaluation program: only when asked

        for i, o in self.runs.items():
            if self.plan.names[i] not in progress.diverged:
                line = select(o.run_dir, o.ckpt)
                log(f"{self.plan.names[i]}: {line}" if self.plan.sweep else line)

    def save_latest(self, epoch: int, state: Any, meta: Mapping[str, Any]) -> None:
        self.latest.save_latest(epoch, state, meta)

    def between_epochs(self, progress: Progress) -> None:
        """What may wait while the next epoch runs: plots, and a sweep's summary."""
        for o in self.runs.values():
            o.plot_if_due()
        self.write_summary(progress)

    def write_summary(self, progress: Progress) -> None:
        if self.plan.sweep and self.main:
            summary.write(self.plan.out_dir, self.plan.base, self.records(progress),
                          summary.grid_keys(self.plan.varies))

    def records(self, progress: Progress) -> list[summary.RunRecord]:
        return [dataclasses.replace(o.record, status=summary.status(o.record.run,
                                                                    progress.diverged))
                for o in self.runs.values()]

    def summary(self, progress: Progress) -> tuple[list[dict], list[dict]]:
        """A sweep's summary rows and per-setting aggregates (process 0; elsewhere empty)."""
        keys = summary.grid_keys(self.plan.varies)
        rows = [r.row(keys) for r in self.records(progress)]
        return rows, summary.settings_of(rows, keys) if rows else []

    def last_rows(self) -> list[Mapping[str, Any]]:
        """Each run's newest metrics row ({} where none, or on processes that write none)."""
        return [self.runs[i].last_row if i in self.runs else {}
                for i in range(len(self.plan.runs))]

    def flush(self) -> None:
        for o in self.runs.values():
            o.flush()

    def close(self) -> None:
        for o in self.runs.values():
            o.close()
        self.latest.close()


def make_out_dir(plan: Plan) -> None:
    """Create a fresh plan's output directory (process 0; resumed plans have theirs)."""
    if not plan.resume and distributed.is_main():
        make_dir(plan.out_dir, plan.kind)


def restore_or_refuse(ckpt: Checkpointer, template: Any, directory: Path) -> tuple[int, Any, dict]:
    """``ckpt.restore_latest(template)``; any failure to read it is a one-line ConfigError (a
    resume of a directory whose checkpoint is damaged or from another configuration)."""
    try:
        return ckpt.restore_latest(template)
    except Exception as e:  # orbax, tensorstore and our own template checks raise many kinds
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"cannot resume {directory}: its latest checkpoint is unusable: "
                          f"{msg[:300]}") from None
