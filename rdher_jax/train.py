"""Command line: ``python -m rdher_jax.train env=FetchPush algo=her seed=0 ...``.

One run, in its own directory: a thin parser over ``rdher_jax.driver`` (which also runs
``rdher_jax.sweep``'s many). ``python -m rdher_jax.train --help`` lists every option.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from .config import (
    Config,
    ConfigError,
    main_guard,
    parse_args,
    resolve,
    resume_config,
    wants_overlap,
)
from .runlog import check_resume_dir

PROG = "python -m rdher_jax.train"


def __getattr__(name: str):
    # The driver (and with it JAX) is imported lazily, so ``main`` can start work before it;
    # its names stay reachable from here.
    if name in ("Plan", "TrainingDiverged", "drive", "request_host_devices"):
        from . import driver

        return getattr(driver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def train(cfg: Config, argv: Sequence[str] | None = None, log=print) -> dict:
    """Run (or continue, with ``cfg.resume``) one training run; returns its final metrics row,
    its best test success and its directory."""
    from .driver import Plan, drive

    out = drive(Plan.single(cfg), argv or [], prog=PROG, log=log)
    return {"row": out["rows"][0], "best_success": out["best"][0], "run_dir": out["out_dir"]}


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
    # On a machine that never ran the project, compile the native physics' FFI handlers while
    # JAX is imported (rdher_jax.ffi_build); nothing to do afterwards.
    from . import ffi_build

    ffi_build.start()
    from .driver import TrainingDiverged, request_host_devices

    if wants_overlap(argv):  # before anything starts JAX's backend
        request_host_devices(2)
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
