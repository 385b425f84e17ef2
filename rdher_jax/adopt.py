"""A run of its own adopted as the one run of a sweep, so that the sweep resumes it.

A long ``python -m rdher_jax.train`` run may be the very run that one seed of a sweep would
make (e.g. one seed of a benchmark profile, ``experiments/benchmark.py --adopt``). Adopting it
writes the sweep directory that ``python -m rdher_jax.sweep`` would have left after the run's
epochs (:mod:`rdher_jax.plan` says what it holds), so ``resume=`` continues it:

- ``checkpoints/latest/<epoch>``: the run's latest state with a leading run axis of length 1
  (a sweep's latest state is its real runs stacked on the host, padding dropped), its metadata
  the run's progress under the sweep's run name;
- ``<run>/``: the run's metrics.csv, success.png, best policy, candidates and selected policy
  (select_top > 1), selection.json and TensorBoard scalars; config.yaml and run_info.json as
  the sweep writes them. Not ``retest.json``: a sweep does not retest;
- ``sweep.yaml``, ``base_config.yaml``, ``run_info.json`` (whose ``adopted`` names the source)
  and the summary files.

Only the same learning problem is adopted (:func:`differences`). The programs are not the
same, though: a sweep's epoch is vmapped, over one run too, and a run's own is not, and XLA
rounds the two differently (their metrics agree to about 1e-6 relative, not bit for bit:
tests/test_adopt.py). An adopted run's later epochs are therefore what a sweep computes from
its state, within rounding of what the run would have computed by itself.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import shutil
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from . import summary
from .checkpoint import SELECT_FILE, Checkpointer
from .config import DHER_ALGOS, FIELD_NAMES, Config, ConfigError, from_yaml, to_yaml
from .executor import resolve_backend
from .outputs import Progress
from .plan import BASE_CONFIG_FILE, RUN_CONFIG_FILE, SPEC_FILE, Plan
from .runlog import write_json_atomic, write_text_atomic

# The files of a run's directory that a sweep's run directory holds as they are (with its
# checkpoints and TensorBoard scalars).
_RUN_FILES = ("metrics.csv", "success.png", SELECT_FILE)
# What may differ between the run and the sweep's run (besides fewer epochs and the unused
# keys, see differences): where the outputs go, which is not what is computed;
_DIRECTORIES = ("run_dir", "resume")
# and whether a progress bar is drawn on stderr.
_OUTPUT_ONLY = ("progress",)


def unused_keys(cfg: Config) -> set[str]:
    """The keys that the learning of ``cfg`` never reads (tests/test_adopt.py trains two runs
    that differ only in each, and finds the same metrics)."""
    # Read only when a command line is parsed, to fill in the preset's values, which are
    # compared key by key.
    out = {"preset"}
    if cfg.algo not in DHER_ALGOS:
        out.add("dher_fraction")  # read only by DHER's goal combination (relabel/dher.py)
    return out


def differences(run: Config, target: Config) -> list[str]:
    """Each key in which ``run`` (a run's resolved config) differs from ``target`` (the
    sweep's run it is to become) beyond what adopting allows, as ``key: run -> target``.

    Allowed: the directories, the progress bar, the keys neither learner reads
    (:func:`unused_keys`), and fewer epochs than ``target`` (the sweep trains on); more are
    not, for the run has trained past what the sweep is to be."""
    skip = {*_DIRECTORIES, *_OUTPUT_ONLY, *(unused_keys(run) & unused_keys(target))}
    out = []
    for k in FIELD_NAMES:
        a, b = getattr(run, k), getattr(target, k)
        # Fewer epochs: the sweep trains on from where the run stopped.
        if k in skip or a == b or (k == "epochs" and a < b):
            continue
        out.append(f"{k}: {a!r} -> {b!r}")
    return out


@dataclass(frozen=True)
class Source:
    """A run of its own, read and checked: its config, its run_info.json, the epoch of its
    latest checkpoint (which every row of metrics.csv reaches, and none passes)."""

    dir: Path
    config: Config
    info: dict
    epoch: int

    @classmethod
    def read(cls, run_dir: Path) -> Source:
        d = Path(run_dir)
        if not d.is_dir():
            raise ConfigError(f"cannot adopt {d}: no such directory")
        if not (d / RUN_CONFIG_FILE).is_file():
            raise ConfigError(f"cannot adopt {d}: it holds no {RUN_CONFIG_FILE}, so it is no "
                              "run directory")
        cfg = from_yaml(d / RUN_CONFIG_FILE)
        try:
            info = json.loads((d / "run_info.json").read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise ConfigError(f"cannot adopt {d}: its run_info.json is unreadable "
                              f"({type(e).__name__})") from None
        if "sweep_dir" in info:
            raise ConfigError(f"cannot adopt {d}: it is a run of the sweep {info['sweep_dir']}, "
                              "not a run of its own")
        return cls(d, cfg, info, _checked_epoch(d))


def _last_epoch(metrics: Path) -> int:
    rows = list(csv.DictReader(io.StringIO(metrics.read_text(encoding="utf-8"))))
    return int(rows[-1]["epoch"]) if rows else 0


def _checked_epoch(d: Path) -> int:
    """The epoch of the run's latest checkpoint, once metrics.csv is seen to end there."""
    with Checkpointer(d, read_only=True) as ck:
        epoch = ck.latest_epoch()
    if epoch is None:
        raise ConfigError(f"cannot adopt {d}: it has no latest checkpoint")
    rows = _last_epoch(d / "metrics.csv") if (d / "metrics.csv").is_file() else 0
    if rows != epoch:
        raise ConfigError(
            f"cannot adopt {d}: its metrics.csv ends at epoch {rows} and its latest checkpoint "
            f"at {epoch}; it is still training, or stopped between the two (python -m "
            f"rdher_jax.train resume={d} epochs={epoch} makes them agree)")
    return epoch


def refuse_existing(src: Source, dest: Path) -> None:
    """A one-line ConfigError if the sweep directory ``dest`` exists and is not empty."""
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise ConfigError(f"cannot adopt {src.dir}: {dest} exists; adopting never overwrites "
                          "(move it away first)")


def check(src: Source, dest: Path, target: Config) -> None:
    """A one-line ConfigError unless ``src`` may become ``target``, the run of a sweep in
    ``dest``: the sweep directory does not exist (or is empty), and the configs differ in
    nothing but what :func:`differences` allows (naming each key that differs)."""
    refuse_existing(src, dest)
    diff = differences(src.config, target)
    if diff:
        raise ConfigError(f"cannot adopt {src.dir} as seed {target.seed} of {dest}: not the "
                          f"same program ({'; '.join(diff)})")
    # backend=auto is decided on the machine: the run's and the sweep's must be the same.
    want = "/".join(resolve_backend(target))
    have = f"{src.info.get('backend')}/{src.info.get('scene')}"
    if have != want:
        raise ConfigError(f"cannot adopt {src.dir}: it ran on backend/scene {have}, and the "
                          f"sweep would run on {want} here")


def _snapshot(d: Path) -> tuple:
    """What must not change while a run is adopted: its metrics and its checkpoints' steps."""
    ck = d / "checkpoints"
    return ((d / "metrics.csv").read_bytes(),
            sorted(str(p.relative_to(ck)) for p in ck.glob("*/*") if p.name.isdigit()))


def adopt(src: Source, plan: Plan, argv: Sequence[str], prog: str,
          log: Callable[[str], Any] = print) -> Path:
    """Write ``plan``'s directory (a fresh sweep of one run, ``argv`` its command line after
    ``prog``) holding ``src`` as its run after ``src.epoch`` epochs; returns it.

    The checks first (:func:`differences`, the physics backend), then everything is written
    into a temporary directory beside it, renamed into place at the end: a failure leaves
    nothing, and an existing sweep directory is never overwritten (a one-line ConfigError)."""
    if not plan.sweep or len(plan.runs) != 1 or plan.resume:
        raise ConfigError(f"adopting fills a fresh sweep of one run; {plan.out_dir} would have "
                          f"{len(plan.runs)}")
    dest, (cfg,), (name,) = plan.out_dir, plan.runs, plan.names
    check(src, dest, cfg)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.adopting-{uuid.uuid4().hex[:8]}")
    try:
        before = _snapshot(src.dir)
        _write(src, plan, argv, prog, tmp)
        if _snapshot(src.dir) != before:
            raise ConfigError(f"cannot adopt {src.dir}: it changed while it was read (is it "
                              "still training?); nothing was written")
        tmp.rename(dest)  # atomic; replaces nothing but an empty directory
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log(f"adopted {src.dir} ({src.epoch} epochs) as {dest / name}")
    return dest


def _write(src: Source, plan: Plan, argv: Sequence[str], prog: str, tmp: Path) -> None:
    """Everything :func:`adopt` writes, into ``tmp`` (named ``plan.out_dir`` in the files)."""
    (cfg,), (name,), dest = plan.runs, plan.names, plan.out_dir
    run = tmp / name
    with Checkpointer(src.dir, read_only=True) as reader:
        # Restored as saved (nested dicts of host arrays), then saved as a sweep saves its
        # state: its real runs stacked on the host along a leading run axis, here of length 1.
        epoch, state, meta = reader.restore_latest(None)
        if epoch != src.epoch:
            raise ConfigError(f"cannot adopt {src.dir}: its latest checkpoint moved from epoch "
                              f"{src.epoch} to {epoch} (is it still training?)")
        stacked = jax.tree.map(lambda x: np.asarray(x)[None], state)
        del state
        progress = dataclasses.replace(Progress.from_meta(meta, ("",), epoch, src.dir),
                                       names=(name,))
        with Checkpointer(tmp, best=False) as latest:
            latest.save_latest(epoch, stacked, progress.meta(progress.wall))
        state_bytes = int(sum(x.nbytes for x in jax.tree.leaves(stacked)))
        del stacked
        # The policies, as the run's own checkpointer in a sweep keeps them.
        best_meta = reader.best_meta()
        with Checkpointer(run, latest=False, select=cfg.select_top > 1) as ck:
            if best_meta is not None:
                ck.save_best(*reader.restore_best(None))
            for e in reader.candidates():
                ck.save_candidate(*reader.restore_candidate(e, None))
            if reader.selected_epoch() is not None:
                ck.save_selected(*reader.restore_policy(None))
    for f in _RUN_FILES:
        if (src.dir / f).is_file():
            shutil.copy2(src.dir / f, run / f)
    if (src.dir / "tb").is_dir():
        shutil.copytree(src.dir / "tb", run / "tb")

    adopted = {"from": str(src.dir.resolve()), "command": src.info.get("command"),
               # python -m rdher_jax.train records no commit; a source that names one keeps it.
               "commit": src.info.get("commit"), "epochs": epoch}
    # The sweep's record, its host and versions the run's (where the adopted epochs ran).
    info = {**src.info, "command": " ".join([prog, *argv]), "runs": [name], "n_runs": 1,
            "n_padded": 1, "program": "a run of its own (not vmapped) for the adopted epochs",
            "state_bytes_per_run": state_bytes, "state_bytes": state_bytes, "adopted": adopted}
    write_text_atomic(run / RUN_CONFIG_FILE, to_yaml(cfg))
    write_json_atomic(run / "run_info.json", {**info, "sweep_dir": str(dest), "run": name})
    write_text_atomic(tmp / BASE_CONFIG_FILE, to_yaml(plan.base))
    write_text_atomic(tmp / SPEC_FILE, summary.spec_yaml(plan.varies, plan.names))
    write_json_atomic(tmp / "run_info.json", info)
    record = summary.RunRecord.of(name, cfg)
    rows = list(csv.DictReader(io.StringIO((run / "metrics.csv").read_text(encoding="utf-8"))))
    record.resume(rows[-1], best_meta)  # as the sweep's resume takes it up
    record.status = summary.status(name, progress.diverged)
    summary.write(tmp, plan.base, [record], summary.grid_keys(plan.varies))
