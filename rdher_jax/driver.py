"""The run driver: N >= 1 runs as one compiled program, epoch after epoch.

``python -m rdher_jax.train`` (one run) and ``python -m rdher_jax.sweep`` (many) are thin
command lines over :func:`drive`, which takes a :class:`~rdher_jax.plan.Plan` (the runs'
resolved configs and where they write) and runs its epoch loop. Its rooms:

- :mod:`rdher_jax.plan`: what runs and the layout of a run's and a sweep's directories;
- :mod:`rdher_jax.executor`: the compiled program over the run axis (one device, sharded,
  several processes, overlapped, compiled ahead);
- :mod:`rdher_jax.outputs`: metrics rows, files, checkpoints and the sweep summary, and what
  the loop knows of its runs (:class:`~rdher_jax.outputs.Progress`).

A run whose losses become NaN or inf stops being logged (its files keep its last good epoch);
the others go on. The program stops only when every run has diverged (TrainingDiverged).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from . import distributed
from .config import Config, ConfigError
from .executor import Executor, executor_for, stack, tree_bytes
from .outputs import Outputs, make_out_dir, reached_stop, run_info
from .plan import DriveResult, Plan, TrainingDiverged, check_out_dir, check_process_count
from .program import hparams_from_config
from .runlog import DirLock

__all__ = ["DriveResult", "Plan", "TrainingDiverged", "drive", "reached_stop"]


def is_checkpoint_epoch(cfg: Config, epoch: int) -> bool:
    """Whether the latest state is saved after ``epoch`` (1-based): every ``checkpoint_every``
    epochs and after the last one."""
    return epoch % cfg.checkpoint_every == 0 or epoch == cfg.epochs


def _refuse(plan: Plan, processes: int) -> None:
    """What no plan may ask of this process, as one-line ConfigErrors, before anything runs."""
    if processes > 1 and not plan.sweep:
        raise ConfigError("a run of its own is one process; start a multi-process sweep with "
                          "python -m rdher_jax.sweep")
    if processes > 1 and plan.base.overlap:
        raise ConfigError("overlap=true runs in one process (two host devices of one machine)")
    if distributed.is_main():
        check_out_dir(plan)
    if plan.resume:
        check_process_count(plan.out_dir, processes)


def _info(plan: Plan, ex: Executor, ts: Any, argv: Sequence[str], prog: str,
          processes: int) -> dict:
    info = run_info(plan.base, argv, prog)
    if plan.sweep:
        per_run = tree_bytes(ts) // ex.n_padded
        info.update(runs=list(plan.names), n_runs=len(plan.runs), n_padded=ex.n_padded,
                    program=ex.describe(), state_bytes_per_run=per_run,
                    state_bytes=per_run * ex.n_padded)
    if processes > 1:
        info.update(processes=processes, hosts=distributed.hosts(),
                    process_of_run={plan.names[i]: ex.owner(i) for i in range(len(plan.runs))})
    return info


class _Bar:
    """The progress bar (process 0, ``progress=true``): epochs, env steps per second and the
    mean test success of the epoch."""

    def __init__(self, plan: Plan, start: int, steps_per_epoch: int) -> None:
        cfg, n = plan.base, len(plan.runs)
        self.steps, self.many, self.bar = steps_per_epoch, n > 1, None
        if cfg.progress and distributed.is_main():
            from tqdm.auto import tqdm

            desc = f"{cfg.env} {cfg.algo}" + (f" x{n} runs" if plan.sweep else "")
            self.bar = tqdm(total=cfg.epochs, initial=start, desc=desc, unit="epoch",
                            dynamic_ncols=True, file=sys.stderr)

    def tick(self, rows: dict[int, dict], env_steps: int, dt: float) -> None:
        if self.bar is None:
            return
        tests = [r["test_success"] for r in rows.values()]
        if tests:
            post = {"env_steps": env_steps, "sps": f"{self.steps / dt:.0f}",
                    "test": f"{np.mean(tests):.2f}"}
            if self.many:
                post["best"] = f"{max(tests):.2f}"
            self.bar.set_postfix(post)
        self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def drive(plan: Plan, argv: Sequence[str] = (), prog: str = "",
          log: Callable[[str], Any] = print,
          devices: Sequence[Any] | None = None) -> DriveResult:
    """Run (or continue) every run of ``plan`` as one program (the process set up first:
    :func:`rdher_jax.startup.setup`). The output directory is locked while it runs (process
    0 holds :class:`rdher_jax.runlog.DirLock`): a second process on it is refused."""
    lock = DirLock()
    try:
        return _drive(plan, argv, prog, log, devices, lock)
    finally:
        lock.release()


def _drive(plan: Plan, argv: Sequence[str], prog: str, log: Callable[[str], Any],
           devices: Sequence[Any] | None, lock: DirLock) -> DriveResult:
    processes, cfg, n = distributed.count(), plan.base, len(plan.runs)
    _refuse(plan, processes)
    main = distributed.is_main()
    if plan.resume and main:  # before compiling: a second process is refused at once
        lock.hold(plan.out_dir, plan.kind)
    env, _, ex = executor_for(plan.runs, devices, vmapped=plan.vmapped)
    hps = ex.put(stack([hparams_from_config(c) for c in plan.runs]))
    keys = ex.put(stack([jax.random.PRNGKey(c.seed) for c in plan.runs]))
    ex.compile_ahead(keys, hps)
    ts = ex.init(keys, hps)
    make_out_dir(plan)
    if main:
        lock.hold(plan.out_dir, plan.kind)
    distributed.barrier("rdher_jax.drive.out_dir")
    out = Outputs(plan, processes, _info(plan, ex, ts, argv, prog, processes), log)
    start, restored, progress = out.open(
        lambda state: ex.place_restored(state, plan.stacked_latest),
        lambda: ex.restore_template(ts, plan.stacked_latest))
    ts = ts if restored is None else restored
    del restored
    distributed.barrier("rdher_jax.drive.started")
    out.write_summary(progress)

    bar = _Bar(plan, start, cfg.n_cycles * cfg.num_envs * env.episode_length * n)
    t_start = time.perf_counter() - progress.wall
    # A resumed run that had already met stop_success stops at once.
    stopped = start if start < cfg.epochs and progress.stop_met(cfg) else None
    pending = ex.epoch(ts, hps) if start < cfg.epochs and stopped is None else None
    t_prev = time.perf_counter()
    # Each epoch's files are written in this order: metrics rows and best policies, then the
    # latest state (so that a run killed in between resumes consistent); then the next epoch is
    # dispatched (it donates the state), and plots, summary and progress bar are written while
    # it runs.
    try:
        for epoch in range(start + 1, cfg.epochs + 1):
            if pending is None:
                break
            (ts, m), pending = pending, None
            m = ex.host(m)  # every run's, on every process
            now = time.perf_counter()
            dt, t_prev = now - t_prev, now
            rows = progress.take(epoch, m, now - t_start, out.latest, log)
            new_best, new_kept = progress.observe(rows, cfg.stop_window, cfg.select_top)
            stop = progress.stop_met(cfg)
            out.write(rows, new_best, lambda ts=ts: ex.host(ts.ddpg), new_kept)
            if stop or is_checkpoint_epoch(cfg, epoch):
                out.save_latest(epoch, ex.latest_state(ts, plan.stacked_latest),
                                progress.meta(now - t_start))
            if not stop and epoch < cfg.epochs:
                pending = ex.epoch(ts, hps)
            out.between_epochs(progress)
            bar.tick(rows, int(np.max(m.env_steps)), dt)
            if stop:
                stopped = epoch
                break
    finally:
        out.flush()
    bar.close()
    out.select(progress, log)
    if stopped is not None and distributed.is_main():
        log(f"stopped after epoch {stopped}: the mean test success of the last "
            f"{cfg.stop_window} epochs reached stop_success={cfg.stop_success:g}"
            + (" on every run" if n > 1 else "")
            + ("; resume with stop_success=null to train on" if stopped == start else ""))
    summary = out.summary(progress) if plan.sweep else ([], [])
    rows = [dict(r) for r in out.last_rows()]
    out.close()
    distributed.barrier("rdher_jax.drive.done")
    return DriveResult(str(plan.out_dir), list(plan.names), rows, list(progress.best),
                       dict(progress.diverged), ex.describe(), ex.local_runs(), summary, stopped)
