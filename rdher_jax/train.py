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
)
from .plan import DriveResult, Plan, TrainingDiverged
from .runlog import check_resume_dir
from .startup import for_config, setup

PROG = "python -m rdher_jax.train"


def train(cfg: Config, argv: Sequence[str] | None = None, log=print) -> DriveResult:
    """Run (or continue, with ``cfg.resume``) one training run, the process set up for it
    first; returns the driver's result (``rows[0]``: its last metrics row, ``best[0]``: its
    best test success)."""
    setup(for_config(cfg))
    from .driver import drive  # JAX loads after start-up (rdher_jax.startup)

    return drive(Plan.single(cfg), argv or [], prog=PROG, log=log)


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


def parse_train_args(argv: Sequence[str]) -> Config:
    """The resolved config a command line asks for (a resume: the run's own, continued);
    ``--help`` prints every key and exits 0. Imports no JAX."""
    cfg = parse_args(argv, prog=PROG)
    return load_resume_config(cfg, argv) if cfg.resume is not None else resolve(cfg)


@main_guard
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse_train_args(argv)
    try:
        out = train(cfg, argv)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    row = out.rows[0]
    print(
        f"{cfg.env} {cfg.algo} seed {cfg.seed}: test success {float(row['test_success']):.3f} "
        f"after {int(float(row['env_steps']))} env steps "
        f"({float(row['wall_time']):.0f} s), best {out.best[0]:.3f}"
    )
    if cfg.retest:
        from .policy_test import retest  # JAX is loaded by now

        print(retest(Path(out.out_dir), cfg.retest))
    print(f"results in {out.out_dir}/: metrics.csv, success.png, config.yaml, checkpoints/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
