"""Command line: ``python -m rdher_jax.sweep env=FetchPush 'lambdas=[[1,1],[1,2]]' seeds=5``.

Every setting x seed is one run, and all runs are one compiled program (``rdher_jax.driver``):
``jax.jit(jax.vmap(trainer.epoch))`` over their stacked TrainStates and stacked hyperparameters,
sharded over the devices when there are several. What may vary is what the program only traces
(``config.TRACED_KEYS``): ``lambdas=`` (pairs of lambda_r, lambda_h), ``seeds=`` and a grid
over any traced key, ``grid.<key>=[v1,v2,...]`` (several ``grid.`` keys make their product), e.g.

    python -m rdher_jax.sweep env=FetchPush algo=rdher preset=fast \\
        'grid.dher_fraction=[0.2,0.4,0.8]' 'lambdas=[[4,0.5],[2,1]]' seeds=3

Outputs, under ``sweep_dir`` (default ``runs/sweep-<env>-<algo>-<YYYYmmdd-HHMMSS>``):

- ``<run>/`` for each run, named by what varies
  (``[<key><value>_...]lr<lambda_r>_lh<lambda_h>_s<seed>``): what a ``train`` run writes except
  the latest full state, which is the sweep's; ``python -m rdher_jax.evaluate
  <sweep_dir>/<run>`` works on it, and ``resume=`` belongs to the sweep;
- ``checkpoints/latest/<epoch>``: the stacked TrainState of all runs, which
  ``resume=<sweep_dir>`` continues from;
- ``summary.csv``, ``summary.md``, ``summary.json`` (``rdher_jax.summary``), rewritten after
  every epoch; ``sweep.yaml`` (what varies), ``base_config.yaml`` and ``run_info.json``.
"""

from __future__ import annotations

import dataclasses
import datetime
import itertools
import math
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from . import distributed
from .config import (
    FIELD_NAMES,
    RESUMABLE_KEYS,
    TRACED_KEYS,
    Config,
    ConfigError,
    config_from_fields,
    continue_config,
    from_yaml,
    help_text,
    main_guard,
    resolve,
    split_args,
    unknown_key,
    validate,
)
from .distributed import PROCESS_KEYS, ProcessSpec, supervise, wanted
from .distributed import parse as parse_process_keys
from .plan import BASE_CONFIG_FILE, SPEC_FILE, DriveResult, Plan, TrainingDiverged
from .runlog import check_fresh_dir, check_resume_dir
from .startup import for_config, setup
from .summary import grid_keys, num, settings_markdown

PROG = "python -m rdher_jax.sweep"
SWEEP_KEYS: dict[str, str] = {
    "lambdas": "list of [lambda_r, lambda_h] pairs, e.g. 'lambdas=[[1,1],[1,2],[2,1]]' (weights "
               ">= 0); default: the single pair of lambda_r and lambda_h",
    "seeds": "number of seeds N (seeds seed, seed+1, ..., seed+N-1) or an explicit list, "
             "e.g. seeds=5 or 'seeds=[0,3,7]'; default 1",
    "grid.<key>": "list of values of a traced key, e.g. 'grid.dher_fraction=[0.2,0.4,0.8]'; "
                  "several grid keys make their product. Traced keys: " + ", ".join(TRACED_KEYS),
    "sweep_dir": "output directory; default runs/sweep-<env>-<algo>-<YYYYmmdd-HHMMSS>",
    "resume": "sweep directory to continue from its latest checkpoint; other keys may only "
              "change " + ", ".join(sorted(RESUMABLE_KEYS - {"run_dir", "resume"})),
    **PROCESS_KEYS,
}
GRID = "grid."


# ------------------------------------------------------------------ what varies

def _yaml_value(key: str, raw: str) -> Any:
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ConfigError(f"cannot parse {key}={raw!r}: {first}") from None


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def parse_lambdas(raw: str) -> tuple[tuple[float, float], ...]:
    """``'[[1,1],[1,2]]'`` -> ``((1.0, 1.0), (1.0, 2.0))``; anything else is a ConfigError."""
    v = _yaml_value("lambdas", raw)
    usage = "lambdas must be a list of [lambda_r, lambda_h] pairs, e.g. 'lambdas=[[1,1],[1,2]]'"
    if not isinstance(v, list) or not v:
        raise ConfigError(f"{usage}; got {raw!r}")
    if len(v) == 2 and all(_is_number(x) for x in v):
        raise ConfigError(f"{usage}; got one pair {raw!r}: write lambdas=[{raw.strip()}]")
    pairs = []
    for p in v:
        if not isinstance(p, list) or len(p) != 2 or not all(_is_number(x) for x in p):
            raise ConfigError(f"{usage}; {p!r} in {raw!r} is not a pair of numbers")
        if not all(math.isfinite(x) and x >= 0 for x in p):
            raise ConfigError(f"lambda weights must be finite and >= 0, got {p!r} in lambdas")
        pair = (float(p[0]), float(p[1]))
        if pair in pairs:
            raise ConfigError(f"duplicate runs: the pair {p!r} appears twice in lambdas")
        pairs.append(pair)
    return tuple(pairs)


def parse_seeds(raw: str, first: int) -> tuple[int, ...]:
    """``'3'`` -> ``(first, first+1, first+2)``; ``'[0,5]'`` -> ``(0, 5)``."""
    v = _yaml_value("seeds", raw)
    usage = "seeds must be a positive count (seeds=5) or a list of seeds ('seeds=[0,3,7]')"
    if isinstance(v, int) and not isinstance(v, bool):
        if v < 1:
            raise ConfigError(f"{usage}; got {raw!r}")
        seeds = list(range(first, first + v))
    elif isinstance(v, list) and v and all(isinstance(s, int) and not isinstance(s, bool)
                                           for s in v):
        seeds = v
    else:
        raise ConfigError(f"{usage}; got {raw!r}")
    bad = [s for s in seeds if not 0 <= s < 2**32]
    if bad:
        raise ConfigError(f"seeds must be in [0, 2**32), got {bad[0]}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"duplicate runs: seeds {raw!r} repeat a seed")
    return tuple(seeds)


def parse_grid(other: Mapping[str, str], base: Config) -> dict[str, tuple]:
    """``{"grid.<key>": "[v1,...]"}`` -> ``{key: (typed v1, ...)}``, each value checked as a
    value of ``key`` on ``base``."""
    grid: dict[str, tuple] = {}
    for k, raw in other.items():
        if not k.startswith(GRID):
            continue
        key = k[len(GRID):]
        if key == "seed":
            raise ConfigError("grid.seed: sweep seeds with seeds=N or 'seeds=[...]'")
        if key not in FIELD_NAMES:
            raise unknown_key(k, [GRID + f for f in TRACED_KEYS])
        if key not in TRACED_KEYS:
            raise ConfigError(f"{key} fixes the compiled program (a shape, the algorithm or the "
                              f"loop), so a sweep over it is separate runs, one per value; "
                              f"grid keys: {', '.join(TRACED_KEYS)}")
        v = _yaml_value(k, raw)
        if not isinstance(v, list) or not v:
            raise ConfigError(f"{k} must be a non-empty list, e.g. '{k}=[1,2]'; got {raw!r}")
        values = []
        for x in v:
            if isinstance(x, (list, dict)) or x is None:
                raise ConfigError(f"{k}: {x!r} is not a value of {key}")
            try:
                typed = getattr(config_from_fields({key: str(x)}, base=base), key)
            except ConfigError as e:
                raise ConfigError(f"{k}: {e}") from None
            if typed in values:
                raise ConfigError(f"duplicate runs: {key}={x!r} appears twice in {k}")
            values.append(typed)
        grid[key] = tuple(values)
    return grid


def run_name(cfg: Config, grid_keys: Sequence[str] = ()) -> str:
    """A run's directory name: ``[<key><value>_...]lr<lambda_r>_lh<lambda_h>_s<seed>``."""
    head = "".join(f"{k}{num(getattr(cfg, k))}_" for k in grid_keys
                   if k not in ("lambda_r", "lambda_h"))
    return f"{head}lr{num(cfg.lambda_r)}_lh{num(cfg.lambda_h)}_s{cfg.seed}"


def make_plan(base: Config, lambdas: Sequence[tuple[float, float]], seeds: Sequence[int],
              grid: Mapping[str, Sequence[Any]], sweep_dir: Path, resume: bool = False) -> Plan:
    """One run per grid point x lambda pair x seed (that order, seed minor)."""
    runs, names = [], []
    keys = tuple(grid)
    for point in itertools.product(*grid.values()):
        for lr, lh in lambdas:
            for s in seeds:
                c = dataclasses.replace(base, lambda_r=float(lr), lambda_h=float(lh), seed=s,
                                        resume=None, **dict(zip(keys, point, strict=True)))
                name = run_name(c, keys)
                runs.append(validate(dataclasses.replace(c, run_dir=str(sweep_dir / name))))
                names.append(name)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"duplicate runs: {', '.join(dup)} appear more than once")
    varies = {"lambdas": tuple(lambdas), "seeds": tuple(seeds), "grid": dict(grid)}
    return Plan(tuple(runs), sweep_dir, base, sweep=True, resume=resume, varies=varies,
                names=tuple(names))


def default_sweep_dir(cfg: Config, now: datetime.datetime | None = None) -> Path:
    stamp = (now or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sweep-{cfg.env}-{cfg.algo}-{stamp}"


def help_text_sweep() -> str:
    lines = [
        f"usage: {PROG} [key=value ...]",
        "",
        f"example: {PROG} env=FetchPush algo=rdher 'grid.dher_fraction=[0.2,0.8]' "
        "'lambdas=[[1,1],[2,1]]' seeds=5",
        "Every setting x seed is one run; all runs are one compiled program. Sweep keys:",
        "",
    ]
    for k, doc in SWEEP_KEYS.items():
        lines.append(f"  {k}")
        lines.extend(textwrap.wrap(doc, 96, initial_indent=" " * 6, subsequent_indent=" " * 6))
    lines += ["", "Every key of the training config, shared by all runs (seed: the first seed; "
              "run_dir: use sweep_dir):", ""]
    body = help_text(PROG)
    lines.append(body.split("Fields:\n", 1)[-1].strip("\n"))
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class SweepCommand:
    """What a sweep command line asks for: the plan, and how this process joins the others
    (all None: one process, unless SLURM or Open MPI started several)."""

    plan: Plan
    processes: ProcessSpec


def parse_sweep_args(argv: Sequence[str]) -> SweepCommand:
    """The sweep a command line asks for (parsed once, without JAX); ``--help`` prints the keys
    and exits 0.

    Every error is a one-line ConfigError, raised before anything is built or written.
    """
    if any(a in ("-h", "--help") for a in argv):
        sys.stdout.write(help_text_sweep())
        sys.stdout.flush()
        raise SystemExit(0)
    fields, other = split_args(argv, extra=[k for k in SWEEP_KEYS if k != "grid.<key>"],
                               prefixes=(GRID,))
    processes = parse_process_keys(other)
    # Every process must write into the same directory, so a multi-process sweep names it
    # (sweep_dir= or resume=) rather than taking the time-stamped default.
    if wanted(processes) and "sweep_dir" not in other and "resume" not in other:
        raise ConfigError("a multi-process sweep needs sweep_dir= (or resume=): every process "
                          "must name the same directory")
    return SweepCommand(_plan(fields, other), processes)


def _plan(fields: Mapping[str, str], other: Mapping[str, str]) -> Plan:
    if "run_dir" in fields:
        raise ConfigError("a sweep writes each run into <sweep_dir>/<run>; pass sweep_dir= "
                          "instead of run_dir=")
    for key in ("sweep_dir", "resume"):
        if key in other and not other[key].strip():
            raise ConfigError(f"{key} must be a non-empty path")
    if "resume" in other:
        return _resume_plan(Path(other["resume"]), fields, other)
    base = resolve(config_from_fields(fields))
    grid = parse_grid(other, base)
    both = [k for k in grid if k in fields]
    if both:
        raise ConfigError(f"pass either {both[0]}= or grid.{both[0]}=, not both")
    if "lambdas" in other:
        both = [k for k in ("lambda_r", "lambda_h") if k in fields or k in grid]
        if both:
            raise ConfigError(f"pass either lambdas= or {'/'.join(both)}=, not both")
        lambdas = parse_lambdas(other["lambdas"])
    else:  # the resolved config's pair (per task for the weighted algorithms)
        lambdas = ((float(base.lambda_r), float(base.lambda_h)),)
    if "seeds" in other:
        seeds = parse_seeds(other["seeds"], base.seed)
        if "seed" in fields and isinstance(_yaml_value("seeds", other["seeds"]), list):
            raise ConfigError("pass either seed= (the first of seeds=N) or a list of seeds, "
                              "not both")
    else:
        seeds = (base.seed,)
    sweep_dir = Path(other.get("sweep_dir") or default_sweep_dir(base))
    plan = make_plan(dataclasses.replace(base, run_dir=str(sweep_dir)), lambdas, seeds, grid,
                     sweep_dir)
    check_fresh_dir(sweep_dir, "sweep_dir")
    return plan


def _resume_plan(path: Path, fields: Mapping[str, str], other: Mapping[str, str]) -> Plan:
    check_resume_dir(path, marker=SPEC_FILE)
    try:
        saved = yaml.safe_load((path / SPEC_FILE).read_text(encoding="utf-8"))
        lambdas = tuple((float(a), float(b)) for a, b in saved["lambdas"])
        seeds = tuple(int(s) for s in saved["seeds"])
        saved_grid = {str(k): tuple(v) for k, v in (saved.get("grid") or {}).items()}
    except Exception as e:  # unreadable, not YAML, or not the mapping we write
        raise ConfigError(f"cannot resume: {path / SPEC_FILE} is not a sweep spec "
                          f"({type(e).__name__}: {e})") from None
    base_saved = from_yaml(path / BASE_CONFIG_FILE)
    if "lambdas" in other and (asked := parse_lambdas(other["lambdas"])) != lambdas:
        raise ConfigError(f"cannot change lambdas when resuming {path}: it holds "
                          f"{list(lambdas)}, asked for {list(asked)}")
    if "seeds" in other and (asked := parse_seeds(other["seeds"], base_saved.seed)) != seeds:
        raise ConfigError(f"cannot change seeds when resuming {path}: it holds seeds "
                          f"{list(seeds)}, asked for {list(asked)} (move it away to start "
                          "these seeds afresh)")
    grid = parse_grid(other, base_saved)
    if grid and grid != saved_grid:
        raise ConfigError(f"cannot change the grid when resuming {path}")
    if "sweep_dir" in other and Path(other["sweep_dir"]).resolve() != path.resolve():
        raise ConfigError(f"sweep_dir={other['sweep_dir']} differs from resume={path}; a "
                          "resumed sweep writes into the directory it resumes, so pass resume only")
    base = dataclasses.replace(continue_config(base_saved, fields, path), resume=None)
    return make_plan(base, lambdas, seeds, saved_grid, path, resume=True)


def sweep(plan: Plan, argv: Sequence[str] | None = None, log=print,
          devices: Sequence[Any] | None = None,
          processes: ProcessSpec | None = None) -> DriveResult:
    """Run (or continue) every run of ``plan``, the process set up for it first (and joined
    to the others of a multi-process sweep); returns the driver's result, whose ``summary``
    holds the per-run rows and per-setting aggregates."""
    setup(for_config(plan.base, processes))
    from .driver import drive  # JAX loads after start-up (rdher_jax.startup)

    return drive(plan, argv or [], prog=PROG, log=log, devices=devices)


@main_guard
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cmd = parse_sweep_args(argv)
    # One of several processes: the work runs in a supervised child (rdher_jax.distributed).
    rc = supervise(cmd.processes, [sys.executable, "-m", "rdher_jax.sweep", *argv])
    if rc is not None:
        return rc
    plan = cmd.plan
    try:
        out = sweep(plan, argv, processes=cmd.processes)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if distributed.count() > 1:
        mine = [out.names[i] for i in out.local]
        print(f"process {distributed.index()} of {distributed.count()}: runs "
              f"{', '.join(mine) or '(none)'} done; results in {plan.out_dir}/")
        if not distributed.is_main():
            return 0
    print(settings_markdown(plan.base, out.summary[1], grid_keys(plan.varies)).rstrip())
    print(f"\n{len(out.names)} runs ({out.program}); results in {plan.out_dir}/: "
          "summary.md, summary.csv, <run>/metrics.csv, <run>/success.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
