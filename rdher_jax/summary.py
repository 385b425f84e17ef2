"""A sweep's spec and summary files: ``sweep.yaml``, ``summary.csv``, ``summary.md`` and
``summary.json``.

Each run's row is a :class:`RunRecord` the driver keeps in memory (best and final test success,
env steps, status); runs that share every varying value but the seed form a *setting*,
summarised as mean and sample std over seeds. The varying keys are ``lambda_r``/``lambda_h``
(always shown) and any ``grid.<key>`` of the sweep.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .config import TRACED_KEYS
from .runlog import write_json_atomic, write_text_atomic

RUN_FIELDS = ("epochs", "env_steps", "best_test_success", "best_epoch", "final_test_success",
              "status")
SETTING_FIELDS = ("setting_seeds", "setting_best_mean", "setting_best_std",
                  "setting_final_mean", "setting_final_std")


def num(x: float) -> str:
    """1.0 -> '1', 0.5 -> '0.5': the shortest text that gives back the same float."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(float(x))


def spec_yaml(varies: Mapping[str, Any], names: Sequence[str]) -> str:
    """``sweep.yaml``: the lambda pairs, the seeds, the grid and the run names, in order."""
    return yaml.safe_dump({"lambdas": [list(p) for p in varies["lambdas"]],
                           "seeds": list(varies["seeds"]),
                           "grid": {k: list(v) for k, v in varies.get("grid", {}).items()},
                           "runs": list(names)}, sort_keys=False)


def grid_keys(varies: Mapping[str, Any]) -> tuple[str, ...]:
    """The grid keys of a sweep's ``varies`` (``Plan.varies``), in order."""
    return tuple(varies.get("grid", {}))


@dataclass
class RunRecord:
    """One run's summary row: what it varies, how far it got, its best and final success."""

    run: str
    values: Mapping[str, Any]  # every traced key's value (the grid keys are read from it)
    lambda_r: float
    lambda_h: float
    seed: int
    epochs: int = 0
    env_steps: int = 0
    best_test_success: float = math.nan
    best_epoch: int = 0
    final_test_success: float = math.nan
    status: str = "ok"

    @classmethod
    def of(cls, name: str, cfg: Any) -> RunRecord:
        return cls(name, {k: getattr(cfg, k) for k in TRACED_KEYS}, cfg.lambda_r, cfg.lambda_h,
                   cfg.seed)

    def add(self, row: Mapping[str, Any], new_best: bool) -> None:
        """Take the run's next metrics row (``new_best``: the loop's verdict on it)."""
        self.epochs, self.env_steps = int(row["epoch"]), int(row["env_steps"])
        self.final_test_success = float(row["test_success"])
        if new_best:
            self.best_test_success, self.best_epoch = self.final_test_success, self.epochs

    def resume(self, last: Mapping[str, Any] | None, best: Mapping[str, Any] | None) -> None:
        """Start again from a kept last metrics row and best-policy metadata (a resume)."""
        fresh = RunRecord(self.run, self.values, self.lambda_r, self.lambda_h, self.seed)
        self.__dict__.update(dataclasses.asdict(fresh))
        if last is not None:
            self.epochs, self.env_steps = int(last["epoch"]), int(float(last["env_steps"]))
            self.final_test_success = float(last["test_success"])
        if best is not None:
            self.best_test_success = float(best["test_success"])
            self.best_epoch = int(best["epoch"])

    def row(self, keys: Sequence[str]) -> dict[str, Any]:
        """The summary.csv / summary.json row (``keys``: the sweep's grid keys)."""
        return {"run": self.run, **{k: self.values[k] for k in keys},
                "lambda_r": self.lambda_r, "lambda_h": self.lambda_h, "seed": self.seed,
                **{f: getattr(self, f) for f in RUN_FIELDS}}


def status(run: str, diverged: Mapping[str, int]) -> str:
    return f"diverged in epoch {diverged[run]}" if run in diverged else "ok"


def _mean_std(xs: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; NaN for a single value)."""
    a = np.asarray(xs, dtype=float)
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else math.nan


def settings_of(rows: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> list[dict]:
    """Per-setting aggregates of summary rows (``keys``: the grid keys)."""
    settings = []
    for values in dict.fromkeys(_setting(r, keys) for r in rows):
        mine = [r for r in rows if _setting(r, keys) == values]
        bm, bs = _mean_std([r["best_test_success"] for r in mine])
        fm, fs = _mean_std([r["final_test_success"] for r in mine])
        settings.append({**dict(zip((*keys, "lambda_r", "lambda_h"), values, strict=True)),
                         "seeds": len(mine), "best_mean": bm, "best_std": bs,
                         "final_mean": fm, "final_std": fs,
                         "env_steps": max(r["env_steps"] for r in mine),
                         "diverged": sum(r["status"] != "ok" for r in mine)})
    return settings


def _setting(row: Mapping[str, Any], keys: Sequence[str]) -> tuple:
    return (*(row[k] for k in keys), row["lambda_r"], row["lambda_h"])


def _pm(mean: float, std: float) -> str:
    return f"{mean:.3f}" if math.isnan(std) else f"{mean:.3f} ± {std:.3f}"


def _cell(v: Any) -> str:
    return num(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def settings_markdown(base: Any, settings: Sequence[dict], keys: Sequence[str]) -> str:
    """The heading and the per-setting table of summary.md (what the sweep command prints)."""
    cols = (*keys, "lambda_r", "lambda_h")
    n_seeds = max((s["seeds"] for s in settings), default=0)
    out = [f"# Sweep: {base.env} {base.algo}, {len(settings)} settings x {n_seeds} seeds", "",
           "Mean ± sample std (ddof=1) over seeds of each run's best and final test success.", "",
           "| " + " | ".join(cols) + " | seeds | best test success | final test success "
           "| env steps | diverged |",
           "|" + "---|" * (len(cols) + 5)]
    for s in settings:
        out.append("| " + " | ".join(_cell(s[k]) for k in cols) + f" | {s['seeds']} | "
                   f"{_pm(s['best_mean'], s['best_std'])} | "
                   f"{_pm(s['final_mean'], s['final_std'])} | {s['env_steps']} | "
                   f"{s['diverged']} |")
    return "\n".join(out) + "\n"


def markdown(base: Any, rows: Sequence[dict], settings: Sequence[dict],
             keys: Sequence[str]) -> str:
    cols = (*keys, "lambda_r", "lambda_h")
    out = [settings_markdown(base, settings, keys).rstrip("\n"), "",
           "| run | " + " | ".join(cols) + " | seed | epochs | env steps | best test "
           "success (epoch) | final test success | status |",
           "|" + "---|" * (len(cols) + 7)]
    for r in rows:
        out.append(f"| {r['run']} | " + " | ".join(_cell(r[k]) for k in cols)
                   + f" | {r['seed']} | {r['epochs']} | {r['env_steps']} | "
                   f"{r['best_test_success']:.3f} ({r['best_epoch']}) | "
                   f"{r['final_test_success']:.3f} | {r['status']} |")
    return "\n".join(out) + "\n"


def write(out_dir: Path, base: Any, records: Sequence[RunRecord],
          keys: Sequence[str]) -> tuple[list[dict], list[dict]]:
    """Write summary.csv (one row per run, with its setting's aggregates), summary.md and
    summary.json under the sweep directory; returns (rows, settings)."""
    rows = [r.row(keys) for r in records]
    settings = settings_of(rows, keys)
    by_setting = {tuple(s[k] for k in (*keys, "lambda_r", "lambda_h")): s for s in settings}
    buf = io.StringIO()
    w = csv.DictWriter(buf, ("run", *keys, "lambda_r", "lambda_h", "seed", *RUN_FIELDS,
                             *SETTING_FIELDS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        s = by_setting[_setting(r, keys)]
        w.writerow({**r, "setting_seeds": s["seeds"], "setting_best_mean": s["best_mean"],
                    "setting_best_std": s["best_std"], "setting_final_mean": s["final_mean"],
                    "setting_final_std": s["final_std"]})
    out = Path(out_dir)
    write_text_atomic(out / "summary.csv", buf.getvalue())
    write_text_atomic(out / "summary.md", markdown(base, rows, settings, keys))
    write_json_atomic(out / "summary.json", {"runs": rows, "settings": settings})
    return rows, settings
