"""Command line: ``python -m rdher_jax.sweep env=FetchPush 'lambdas=[[1,1],[1,2]]' seeds=5``.

Every (lambda_r, lambda_h) pair x seed is one run, and all runs are one compiled program:
``jax.jit(jax.vmap(trainer.epoch))`` over their stacked TrainStates and stacked hyperparameters
(each run's from its own Config through ``trainer.hparams_from_config``), called once per epoch
from a Python loop that logs, plots and checkpoints like ``rdher_jax.train``.

With several JAX devices the run axis is split over a 1-D mesh ``"runs"``
(``NamedSharding(mesh, P("runs"))``) and the vmapped epoch runs under ``shard_map``, so each
device steps only its own runs: no collective is needed, and the native backend's
``pure_callback`` is made once per device per env step for that device's runs. (Plain
``jit`` with sharded inputs also works, but XLA's partitioner then pins the callback to device
0 and gathers every run's env batch there and back at each step.) When the number of runs does
not divide the number of devices, the run axis is padded with copies of the first run, computed
and discarded: up to ``devices - 1`` wasted runs, rather than refusing e.g. 35 runs on 2 devices.

Outputs, under ``sweep_dir`` (default ``runs/sweep-<env>-<algo>-<YYYYmmdd-HHMMSS>``):

- ``<run>/`` for each run ``lr<lambda_r>_lh<lambda_h>_s<seed>``: what a ``train`` run writes
  (config.yaml, run_info.json, metrics.csv, success.png, checkpoints/best), except the latest
  full state, which is the sweep's: ``python -m rdher_jax.evaluate <sweep_dir>/<run>`` works on
  it, and ``resume=`` belongs to the sweep;
- ``checkpoints/latest/<epoch>``: the stacked TrainState of all runs (one orbax checkpoint)
  every ``checkpoint_every`` epochs, which ``resume=<sweep_dir>`` continues from;
- ``summary.csv``, ``summary.md``, ``summary.json``: per run best and final test success and
  env steps, and per lambda pair mean and std over seeds; rewritten after every epoch;
- ``sweep.yaml`` (lambdas, seeds, runs), ``base_config.yaml`` (the shared config) and
  ``run_info.json`` (command, devices, hardware, versions, state sizes).

A run whose losses become NaN or inf stops being logged (its files keep its last good epoch and
the summary marks it); the others go on. The sweep stops only when every run has diverged.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import difflib
import io
import math
import sys
import textwrap
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from .checkpoint import Checkpointer
from .config import (
    FIELD_NAMES,
    RESUMABLE_KEYS,
    Config,
    ConfigError,
    from_yaml,
    help_text,
    main_guard,
    parse_args,
    resolve,
    split_token,
    to_yaml,
    validate,
)
from .runlog import (
    check_fresh_dir,
    check_resume_dir,
    make_dir,
    write_json_atomic,
    write_text_atomic,
)
from .train import (
    RunOutputs,
    TrainingDiverged,
    build,
    epoch_row,
    is_checkpoint_epoch,
    last_good_checkpoint,
    nonfinite_losses,
    restore_or_refuse,
    run_info,
)

PROG = "python -m rdher_jax.sweep"
SWEEP_KEYS: dict[str, str] = {
    "lambdas": "list of [lambda_r, lambda_h] pairs, e.g. 'lambdas=[[1,1],[1,2],[2,1]]' (weights "
               ">= 0); default: the single pair of lambda_r and lambda_h",
    "seeds": "number of seeds N (seeds seed, seed+1, ..., seed+N-1) or an explicit list, "
             "e.g. seeds=5 or 'seeds=[0,3,7]'; default 1",
    "sweep_dir": "output directory; default runs/sweep-<env>-<algo>-<YYYYmmdd-HHMMSS>",
    "resume": "sweep directory to continue from its latest checkpoint; other keys may only "
              "change epochs, n_test_rollouts, backend, checkpoint_every, tensorboard, progress",
}
SPEC_FILE = "sweep.yaml"
BASE_CONFIG_FILE = "base_config.yaml"


# ------------------------------------------------------------------ the sweep's runs

def _num(x: float) -> str:
    """1.0 -> '1', 0.5 -> '0.5': the shortest text that gives back the same float."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(float(x))


def run_name(cfg: Config) -> str:
    """The directory name of a run: ``lr<lambda_r>_lh<lambda_h>_s<seed>``."""
    return f"lr{_num(cfg.lambda_r)}_lh{_num(cfg.lambda_h)}_s{cfg.seed}"


@dataclass(frozen=True)
class SweepSpec:
    """What a sweep runs: the shared config, the lambda pairs and the seeds, and where."""

    base: Config  # resolved; run_dir is the sweep directory
    lambdas: tuple[tuple[float, float], ...]
    seeds: tuple[int, ...]
    sweep_dir: Path
    resume: bool = False

    def runs(self) -> list[Config]:
        """One resolved Config per run, lambda pair major, seed minor."""
        out = []
        for lr, lh in self.lambdas:
            for s in self.seeds:
                c = dataclasses.replace(self.base, lambda_r=float(lr), lambda_h=float(lh), seed=s,
                                        resume=None)
                out.append(validate(dataclasses.replace(
                    c, run_dir=str(self.sweep_dir / run_name(c)))))
        names = [run_name(c) for c in out]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"duplicate runs: {', '.join(dup)} appear more than once")
        return out


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


def default_sweep_dir(cfg: Config, now: datetime.datetime | None = None) -> Path:
    stamp = (now or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sweep-{cfg.env}-{cfg.algo}-{stamp}"


def help_text_sweep() -> str:
    lines = [
        f"usage: {PROG} [key=value ...]",
        "",
        f"example: {PROG} env=FetchPush algo=rdher 'lambdas=[[1,1],[1,2],[2,1]]' seeds=5",
        "Every lambda pair x seed is one run; all runs are one compiled program. Sweep keys:",
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


def _split_args(argv: Sequence[str]) -> tuple[dict[str, str], dict[str, str]]:
    """``key=value`` tokens -> (sweep keys, config keys); later tokens win."""
    sweep_args: dict[str, str] = {}
    cfg_args: dict[str, str] = {}
    for tok in argv:
        key, value = split_token(tok)
        if key in SWEEP_KEYS:
            sweep_args[key] = value
        elif key in FIELD_NAMES:
            cfg_args[key] = value
        else:
            close = difflib.get_close_matches(key, [*SWEEP_KEYS, *FIELD_NAMES], n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ConfigError(f"unknown key {key!r}{hint}; run with --help to list the keys")
    if "run_dir" in cfg_args:
        raise ConfigError("a sweep writes each run into <sweep_dir>/<run>; pass sweep_dir= "
                          "instead of run_dir=")
    for key in ("sweep_dir", "resume"):
        if key in sweep_args and not sweep_args[key].strip():
            raise ConfigError(f"{key} must be a non-empty path")
    return sweep_args, cfg_args


def parse_sweep_args(argv: Sequence[str]) -> SweepSpec:
    """The sweep a command line asks for; ``--help`` prints the keys and exits 0.

    Every error is a one-line ConfigError, raised before anything is built or written.
    """
    if any(a in ("-h", "--help") for a in argv):
        sys.stdout.write(help_text_sweep())
        sys.stdout.flush()
        raise SystemExit(0)
    sweep_args, cfg_args = _split_args(argv)
    tokens = [f"{k}={v}" for k, v in cfg_args.items()]
    if "resume" in sweep_args:
        return _resume_spec(Path(sweep_args["resume"]), sweep_args, tokens)
    base = resolve(parse_args(tokens, prog=PROG))
    if "lambdas" in sweep_args:
        both = [k for k in ("lambda_r", "lambda_h") if k in cfg_args]
        if both:
            raise ConfigError(f"pass either lambdas= or {'/'.join(both)}=, not both")
        lambdas = parse_lambdas(sweep_args["lambdas"])
    else:  # the resolved config's pair (per task for the weighted algorithms)
        lambdas = ((float(base.lambda_r), float(base.lambda_h)),)
    if "seeds" in sweep_args:
        seeds = parse_seeds(sweep_args["seeds"], base.seed)
        if "seed" in cfg_args and isinstance(_yaml_value("seeds", sweep_args["seeds"]), list):
            raise ConfigError("pass either seed= (the first of seeds=N) or a list of seeds, "
                              "not both")
    else:
        seeds = (base.seed,)
    sweep_dir = Path(sweep_args.get("sweep_dir") or default_sweep_dir(base))
    spec = SweepSpec(dataclasses.replace(base, run_dir=str(sweep_dir)), lambdas, seeds,
                     sweep_dir)
    spec.runs()  # duplicate names and per-run validation, before anything is written
    check_fresh_dir(sweep_dir, "sweep_dir")
    return spec


def _resume_spec(path: Path, sweep_args: Mapping[str, str], tokens: list[str]) -> SweepSpec:
    check_resume_dir(path, marker=SPEC_FILE)
    try:
        saved = yaml.safe_load((path / SPEC_FILE).read_text(encoding="utf-8"))
        lambdas = tuple((float(a), float(b)) for a, b in saved["lambdas"])
        seeds = tuple(int(s) for s in saved["seeds"])
    except Exception as e:  # unreadable, not YAML, or not the mapping we write
        raise ConfigError(f"cannot resume: {path / SPEC_FILE} is not a sweep spec "
                          f"({type(e).__name__}: {e})") from None
    base_saved = from_yaml(path / BASE_CONFIG_FILE)
    if "lambdas" in sweep_args and parse_lambdas(sweep_args["lambdas"]) != lambdas:
        raise ConfigError(f"cannot change lambdas when resuming {path}")
    if "seeds" in sweep_args and parse_seeds(sweep_args["seeds"], base_saved.seed) != seeds:
        raise ConfigError(f"cannot change seeds when resuming {path}")
    if "sweep_dir" in sweep_args and Path(sweep_args["sweep_dir"]).resolve() != path.resolve():
        raise ConfigError(f"sweep_dir={sweep_args['sweep_dir']} differs from resume={path}; a "
                          "resumed sweep writes into the directory it resumes, so pass resume only")
    new = resolve(parse_args(tokens, base=dataclasses.replace(base_saved, run_dir=None),
                             prog=PROG))
    new = dataclasses.replace(new, run_dir=str(path))
    changed = [k for k in FIELD_NAMES
               if k not in RESUMABLE_KEYS and getattr(new, k) != getattr(base_saved, k)]
    if changed:
        diffs = ", ".join(f"{k}: {getattr(base_saved, k)!r} -> {getattr(new, k)!r}"
                          for k in changed)
        raise ConfigError(f"cannot change {diffs} when resuming {path}")
    spec = SweepSpec(new, lambdas, seeds, path, resume=True)
    spec.runs()
    return spec


# ------------------------------------------------------------------ the program

def stack(trees: Sequence[Any]) -> Any:
    """Stack pytrees of equal structure along a new leading (run) axis."""
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def tree_bytes(tree: Any) -> int:
    """Bytes held by the array leaves of ``tree`` (their global size when sharded)."""
    return int(sum(np.dtype(x.dtype).itemsize * math.prod(x.shape)
                   for x in jax.tree.leaves(tree)))


class SweepProgram:
    """A trainer's ``init`` and ``epoch`` over a leading run axis, each one compiled program.

    One device: ``jax.jit(jax.vmap(f))``. Several: the same vmapped function under ``shard_map``
    over the 1-D mesh ``"runs"``, inputs and outputs split by ``NamedSharding(mesh,
    P("runs"))``; ``n_padded`` (the run count rounded up to a multiple of the device count) is
    the length of the run axis the program sees.
    """

    def __init__(self, trainer: Any, n_runs: int, devices: Sequence[Any] | None = None) -> None:
        self.devices = list(devices or jax.devices())
        d = len(self.devices)
        self.n_runs = n_runs
        self.n_padded = -(-n_runs // d) * d
        if d == 1:
            # Committed to the device, as restored checkpoints are: jit's cache tells committed
            # from uncommitted inputs, and a resume in the same process should not recompile.
            self.mesh = None
            self.sharding = jax.sharding.SingleDeviceSharding(self.devices[0])
            self.init = jax.jit(jax.vmap(trainer.init))
            self.epoch = jax.jit(jax.vmap(trainer.epoch), donate_argnums=0)
            return
        from jax.sharding import Mesh, NamedSharding
        from jax.sharding import PartitionSpec as P

        self.mesh = Mesh(np.array(self.devices), ("runs",))
        self.sharding = NamedSharding(self.mesh, P("runs"))

        def split(f):
            # check_vma=False: pure_callback results (the native physics) carry no
            # varying-manual-axes type, so scans carrying env states through them fail the check.
            # Every output is split over "runs" (nothing is claimed replicated), so the check
            # has nothing to protect here.
            return jax.shard_map(jax.vmap(f), mesh=self.mesh, in_specs=P("runs"),
                                 out_specs=P("runs"), check_vma=False)

        self.init = jax.jit(split(trainer.init))
        self.epoch = jax.jit(split(trainer.epoch), donate_argnums=0)

    def pad(self, tree: Any) -> Any:
        """Extend the run axis to ``n_padded`` with copies of the first run."""
        k = self.n_padded - self.n_runs
        if k == 0:
            return tree
        return jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], k, axis=0)]), tree)

    def unpad(self, tree: Any) -> Any:
        """The real runs of a padded tree, as host arrays.

        On the host on purpose: slicing a run-sharded array on device compiles a program with
        a cross-device collective, and XLA:CPU runs host devices on one thread pool, so with
        more host devices than pool threads two devices can block in the collective's
        rendezvous while the third never gets a thread (seen as a 40 s rendezvous abort).
        Nothing the sweep runs between epochs may need a collective.
        """
        return jax.tree.map(lambda x: np.asarray(x)[: self.n_runs], jax.device_get(tree))

    def put(self, tree: Any) -> Any:
        """Pad and place ``tree`` as the program's inputs are placed."""
        return jax.device_put(self.pad(tree), self.sharding)

    def describe(self) -> str:
        if self.mesh is None:
            return f"one device ({self.devices[0]})"
        pad = (f", padded from {self.n_runs} with copies of the first run"
               if self.n_padded != self.n_runs else "")
        return (f"shard_map over mesh ('runs',) of {len(self.devices)} devices, "
                f"{self.n_padded // len(self.devices)} runs per device{pad}")


# Fields that change neither the compiled program nor what it computes per epoch.
_LOOP_ONLY = ("run_dir", "resume", "epochs", "checkpoint_every", "progress", "tensorboard")
_LAST_PROGRAM: dict[str, Any] = {}


def _program_for(runs: Sequence[Config], devices: Sequence[Any] | None):
    """Env, trainer and :class:`SweepProgram` of a sweep's runs.

    Shapes and the algorithm come from the shared config (built from the first run's);
    everything that differs between runs is in each run's hyperparameters and key. The last
    program is kept for the life of the process, so a sweep resumed in the same process (in a
    notebook, or a test) reuses its compilation instead of compiling it again.
    """
    devices = list(devices or jax.devices())
    first = dataclasses.replace(runs[0], **{k: getattr(Config(), k) for k in _LOOP_ONLY})
    key = (to_yaml(first), len(runs), tuple(str(d) for d in devices))
    if _LAST_PROGRAM.get("key") != key:
        _LAST_PROGRAM.clear()  # one at a time: a program holds its env and compiled code
        env, trainer = build(runs[0])
        _LAST_PROGRAM.update(key=key, value=(env, trainer,
                                             SweepProgram(trainer, len(runs), devices)))
    return _LAST_PROGRAM["value"]


# ------------------------------------------------------------------ summary

def _mean_std(xs: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; NaN for a single value)."""
    a = np.asarray(xs, dtype=float)
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else math.nan


def summarize(runs: Sequence[Config], sweep_dir: Path,
              diverged: Mapping[str, int]) -> tuple[list[dict], list[dict]]:
    """Per-run rows (read back from each run's metrics.csv) and per-lambda-pair aggregates."""
    rows = []
    for c in runs:
        name = run_name(c)
        path = sweep_dir / name / "metrics.csv"
        data = []
        if path.exists():
            with open(path, newline="", encoding="utf-8") as f:
                data = [r for r in csv.DictReader(f) if r.get("test_success", "") != ""]
        best_i = None
        for i, r in enumerate(data):  # ties go to the later epoch, as the best checkpoint
            if best_i is None or float(r["test_success"]) >= float(data[best_i]["test_success"]):
                best_i = i
        last = data[-1] if data else None
        rows.append({
            "run": name,
            "lambda_r": c.lambda_r,
            "lambda_h": c.lambda_h,
            "seed": c.seed,
            "epochs": int(last["epoch"]) if last else 0,
            "env_steps": int(float(last["env_steps"])) if last else 0,
            "best_test_success": float(data[best_i]["test_success"]) if data else math.nan,
            "best_epoch": int(data[best_i]["epoch"]) if data else 0,
            "final_test_success": float(last["test_success"]) if last else math.nan,
            "status": f"diverged in epoch {diverged[name]}" if name in diverged else "ok",
        })
    pairs = []
    for lr, lh in dict.fromkeys((r["lambda_r"], r["lambda_h"]) for r in rows):
        mine = [r for r in rows if (r["lambda_r"], r["lambda_h"]) == (lr, lh)]
        bm, bs = _mean_std([r["best_test_success"] for r in mine])
        fm, fs = _mean_std([r["final_test_success"] for r in mine])
        pairs.append({"lambda_r": lr, "lambda_h": lh, "seeds": len(mine),
                      "best_mean": bm, "best_std": bs, "final_mean": fm, "final_std": fs,
                      "env_steps": max(r["env_steps"] for r in mine),
                      "diverged": sum(r["status"] != "ok" for r in mine)})
    return rows, pairs


SUMMARY_FIELDS = ("run", "lambda_r", "lambda_h", "seed", "epochs", "env_steps",
                  "best_test_success", "best_epoch", "final_test_success", "status",
                  "pair_seeds", "pair_best_mean", "pair_best_std", "pair_final_mean",
                  "pair_final_std")


def _pm(mean: float, std: float) -> str:
    return f"{mean:.3f}" if math.isnan(std) else f"{mean:.3f} ± {std:.3f}"


def summary_markdown(base: Config, rows: Sequence[dict], pairs: Sequence[dict]) -> str:
    n_seeds = max((p["seeds"] for p in pairs), default=0)
    out = [f"# Sweep: {base.env} {base.algo}, {len(pairs)} lambda pairs x {n_seeds} seeds", "",
           "Mean ± sample std (ddof=1) over seeds of each run's best and final test success.", "",
           "| lambda_r | lambda_h | seeds | best test success | final test success | env steps "
           "| diverged |",
           "|---|---|---|---|---|---|---|"]
    for p in pairs:
        out.append(f"| {_num(p['lambda_r'])} | {_num(p['lambda_h'])} | {p['seeds']} | "
                   f"{_pm(p['best_mean'], p['best_std'])} | "
                   f"{_pm(p['final_mean'], p['final_std'])} | {p['env_steps']} | "
                   f"{p['diverged']} |")
    out += ["", "| run | lambda_r | lambda_h | seed | epochs | env steps | best test success "
            "(epoch) | final test success | status |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['run']} | {_num(r['lambda_r'])} | {_num(r['lambda_h'])} | {r['seed']} "
                   f"| {r['epochs']} | {r['env_steps']} | {r['best_test_success']:.3f} "
                   f"({r['best_epoch']}) | {r['final_test_success']:.3f} | {r['status']} |")
    return "\n".join(out) + "\n"


def write_summary(spec: SweepSpec, runs: Sequence[Config],
                  diverged: Mapping[str, int]) -> tuple[list[dict], list[dict]]:
    """Write summary.csv (one row per run, with its lambda pair's aggregates), summary.md and
    summary.json under the sweep directory; returns (rows, pairs)."""
    rows, pairs = summarize(runs, spec.sweep_dir, diverged)
    by_pair = {(p["lambda_r"], p["lambda_h"]): p for p in pairs}
    buf = io.StringIO()
    w = csv.DictWriter(buf, SUMMARY_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        p = by_pair[(r["lambda_r"], r["lambda_h"])]
        w.writerow({**r, "pair_seeds": p["seeds"], "pair_best_mean": p["best_mean"],
                    "pair_best_std": p["best_std"], "pair_final_mean": p["final_mean"],
                    "pair_final_std": p["final_std"]})
    write_text_atomic(spec.sweep_dir / "summary.csv", buf.getvalue())
    write_text_atomic(spec.sweep_dir / "summary.md", summary_markdown(spec.base, rows, pairs))
    write_json_atomic(spec.sweep_dir / "summary.json", {"runs": rows, "pairs": pairs})
    return rows, pairs


# ------------------------------------------------------------------ the loop

def _spec_yaml(spec: SweepSpec, runs: Sequence[Config]) -> str:
    return yaml.safe_dump({"lambdas": [list(p) for p in spec.lambdas],
                           "seeds": list(spec.seeds),
                           "runs": [run_name(c) for c in runs]}, sort_keys=False)


def _row_of(metrics: Any, i: int) -> Any:
    return jax.tree.map(lambda x: x[i], metrics)


def sweep(spec: SweepSpec, argv: Sequence[str] | None = None, log=print,
          devices: Sequence[Any] | None = None) -> dict:
    """Run (or continue) every run of ``spec`` as one program; returns the summary and paths."""
    from .trainer import hparams_from_config

    argv = list(argv or [])
    cfg = spec.base
    runs = spec.runs()
    names = [run_name(c) for c in runs]
    if spec.resume:
        check_resume_dir(spec.sweep_dir, marker=SPEC_FILE)
    else:
        check_fresh_dir(spec.sweep_dir, "sweep_dir")
    env, trainer, program = _program_for(runs, devices)
    hps = program.put(stack([hparams_from_config(c) for c in runs]))
    keys = program.put(stack([jax.random.PRNGKey(c.seed) for c in runs]))
    ts = program.init(keys, hps)

    if not spec.resume:
        make_dir(spec.sweep_dir, "sweep_dir")
    ckpt = Checkpointer(spec.sweep_dir, best=False)
    outs = [RunOutputs(c, Path(c.run_dir), latest=False) for c in runs]
    per_run = tree_bytes(ts) // program.n_padded
    info = {**run_info(cfg, argv, prog=PROG), "runs": names, "n_runs": len(runs),
            "n_padded": program.n_padded, "program": program.describe(),
            "state_bytes_per_run": per_run, "state_bytes": per_run * program.n_padded}
    start, wall0, diverged = 0, 0.0, {}
    if spec.resume and ckpt.latest_epoch() is not None:
        start, state, meta = restore_or_refuse(ckpt, program.unpad(ts), spec.sweep_dir)
        if meta.get("runs") != names:
            raise ConfigError(f"cannot resume {spec.sweep_dir}: its checkpoint holds runs "
                              f"{meta.get('runs')}, not {names}")
        ts = program.put(state)
        del state
        try:
            wall0 = float(meta["wall_time"])
            diverged = {k: int(v) for k, v in meta["diverged"].items() if int(v) <= start}
            bests = [float(b) for b in meta["best_success"]]
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ConfigError(f"cannot resume {spec.sweep_dir}: its checkpoint's metadata is "
                              f"damaged ({type(e).__name__}: {e})") from None
        for o, b in zip(outs, bests, strict=True):
            o.rewind(start, b)
        log(f"resuming {spec.sweep_dir} after epoch {start}")
    else:
        if spec.resume:  # killed before its first checkpoint: start over
            log(f"{spec.sweep_dir} has no checkpoint yet; starting it over")
        # The spec file goes last of the two: it is what marks a directory as a sweep's.
        write_text_atomic(spec.sweep_dir / BASE_CONFIG_FILE, to_yaml(cfg))
        write_text_atomic(spec.sweep_dir / SPEC_FILE, _spec_yaml(spec, runs))
        write_json_atomic(spec.sweep_dir / "run_info.json", info)
        for o, name in zip(outs, names, strict=True):
            o.start({**info, "sweep_dir": str(spec.sweep_dir), "run": name})
    write_summary(spec, runs, diverged)

    steps_per_epoch = cfg.n_cycles * cfg.num_envs * env.episode_length * len(runs)
    bar = None
    if cfg.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.epochs, initial=start, unit="epoch", dynamic_ncols=True,
                   desc=f"{cfg.env} {cfg.algo} x{len(runs)} runs", file=sys.stderr)
    t_start = time.perf_counter() - wall0
    rows: list[dict] = []
    pairs: list[dict] = []
    for epoch in range(start, cfg.epochs):
        t0 = time.perf_counter()
        ts, m = program.epoch(ts, hps)
        m = jax.device_get(m)
        dt = time.perf_counter() - t0
        host: dict[str, Any] = {}

        def policies(ts=ts, host=host):
            # Every run's learner state, fetched once and only when some run has a new best;
            # sliced per run on the host (see SweepProgram.unpad).
            if "ddpg" not in host:
                host["ddpg"] = jax.device_get(ts.ddpg)
            return host["ddpg"]

        wall = time.perf_counter() - t_start
        tests = []
        for i, (o, name) in enumerate(zip(outs, names, strict=True)):
            if name in diverged:
                continue
            row = epoch_row(epoch + 1, _row_of(m, i), wall)
            bad = nonfinite_losses(row)
            if bad:
                diverged[name] = epoch + 1
                log(f"{name}: {', '.join(bad)} became non-finite in epoch {epoch + 1}; its "
                    f"outputs stop at epoch {epoch}, the other runs go on")
                continue
            o.record(row, lambda i=i: _row_of(policies(), i))
            tests.append(row["test_success"])
        if len(diverged) == len(runs):
            raise TrainingDiverged(
                f"the losses of every run became non-finite (the last in epoch {epoch + 1}); "
                f"stopped. {last_good_checkpoint(ckpt)}")
        if is_checkpoint_epoch(cfg, epoch + 1):
            ckpt.save_latest(epoch + 1, program.unpad(ts), {
                "best_success": [o.best for o in outs], "wall_time": round(wall, 3),
                "diverged": diverged, "runs": names})
        rows, pairs = write_summary(spec, runs, diverged)
        if bar is not None:
            bar.set_postfix(sps=f"{steps_per_epoch / dt:.0f}", test=f"{np.mean(tests):.2f}",
                            best=f"{max(tests):.2f}")
            bar.update(1)
    if bar is not None:
        bar.close()
    for o in outs:
        o.close()
    ckpt.close()
    if not rows:
        rows, pairs = summarize(runs, spec.sweep_dir, diverged)
    return {"sweep_dir": str(spec.sweep_dir), "runs": names, "rows": rows, "pairs": pairs,
            "diverged": diverged, "program": program.describe()}


@main_guard
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    spec = parse_sweep_args(argv)
    try:
        out = sweep(spec, argv)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    md = (spec.sweep_dir / "summary.md").read_text(encoding="utf-8")
    print(md.split("\n\n| run |", 1)[0].rstrip())
    print(f"\n{len(out['runs'])} runs ({out['program']}); results in {spec.sweep_dir}/: "
          "summary.md, summary.csv, <run>/metrics.csv, <run>/success.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
