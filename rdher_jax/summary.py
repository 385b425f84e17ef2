"""A sweep's spec and summary files: ``sweep.yaml``, ``summary.csv``, ``summary.md`` and
``summary.json``.

Each run's row is read back from its ``metrics.csv`` (best and final test success, env steps,
status); runs that share every varying value but the seed form a *setting*, summarised as mean
and sample std over seeds. The varying keys are ``lambda_r``/``lambda_h`` (always shown) and any
``grid.<key>`` of the sweep.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

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


def grid_keys(plan: Any) -> tuple[str, ...]:
    return tuple(plan.varies.get("grid", {}))


def _mean_std(xs: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; NaN for a single value)."""
    a = np.asarray(xs, dtype=float)
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else math.nan


def _read(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return [r for r in csv.DictReader(f) if r.get("test_success", "") != ""]


def collect(plan: Any, diverged: Mapping[str, int]) -> tuple[list[dict], list[dict]]:
    """Per-run rows (read back from each run's metrics.csv) and per-setting aggregates."""
    keys = grid_keys(plan)
    rows = []
    for c, name in zip(plan.runs, plan.names, strict=True):
        data = _read(Path(c.run_dir) / "metrics.csv")
        best_i = None
        for i, r in enumerate(data):  # ties go to the later epoch, as the best checkpoint
            if best_i is None or float(r["test_success"]) >= float(data[best_i]["test_success"]):
                best_i = i
        last = data[-1] if data else None
        rows.append({
            "run": name,
            **{k: getattr(c, k) for k in keys},
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
    return rows, settings


def _setting(row: Mapping[str, Any], keys: Sequence[str]) -> tuple:
    return (*(row[k] for k in keys), row["lambda_r"], row["lambda_h"])


def _pm(mean: float, std: float) -> str:
    return f"{mean:.3f}" if math.isnan(std) else f"{mean:.3f} ± {std:.3f}"


def _cell(v: Any) -> str:
    return num(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def markdown(plan: Any, rows: Sequence[dict], settings: Sequence[dict]) -> str:
    keys = (*grid_keys(plan), "lambda_r", "lambda_h")
    n_seeds = max((s["seeds"] for s in settings), default=0)
    base = plan.base
    out = [f"# Sweep: {base.env} {base.algo}, {len(settings)} settings x {n_seeds} seeds", "",
           "Mean ± sample std (ddof=1) over seeds of each run's best and final test success.", "",
           "| " + " | ".join(keys) + " | seeds | best test success | final test success "
           "| env steps | diverged |",
           "|" + "---|" * (len(keys) + 5)]
    for s in settings:
        out.append("| " + " | ".join(_cell(s[k]) for k in keys) + f" | {s['seeds']} | "
                   f"{_pm(s['best_mean'], s['best_std'])} | "
                   f"{_pm(s['final_mean'], s['final_std'])} | {s['env_steps']} | "
                   f"{s['diverged']} |")
    out += ["", "| run | " + " | ".join(keys) + " | seed | epochs | env steps | best test "
            "success (epoch) | final test success | status |",
            "|" + "---|" * (len(keys) + 7)]
    for r in rows:
        out.append(f"| {r['run']} | " + " | ".join(_cell(r[k]) for k in keys)
                   + f" | {r['seed']} | {r['epochs']} | {r['env_steps']} | "
                   f"{r['best_test_success']:.3f} ({r['best_epoch']}) | "
                   f"{r['final_test_success']:.3f} | {r['status']} |")
    return "\n".join(out) + "\n"


def write(plan: Any, diverged: Mapping[str, int]) -> tuple[list[dict], list[dict]]:
    """Write summary.csv (one row per run, with its setting's aggregates), summary.md and
    summary.json under the sweep directory; returns (rows, settings)."""
    rows, settings = collect(plan, diverged)
    keys = (*grid_keys(plan), "lambda_r", "lambda_h")
    by_setting = {tuple(s[k] for k in keys): s for s in settings}
    buf = io.StringIO()
    w = csv.DictWriter(buf, ("run", *keys, "seed", *RUN_FIELDS, *SETTING_FIELDS),
                       lineterminator="\n")
    w.writeheader()
    for r in rows:
        s = by_setting[_setting(r, grid_keys(plan))]
        w.writerow({**r, "setting_seeds": s["seeds"], "setting_best_mean": s["best_mean"],
                    "setting_best_std": s["best_std"], "setting_final_mean": s["final_mean"],
                    "setting_final_std": s["final_std"]})
    out = Path(plan.out_dir)
    write_text_atomic(out / "summary.csv", buf.getvalue())
    write_text_atomic(out / "summary.md", markdown(plan, rows, settings))
    write_json_atomic(out / "summary.json", {"runs": rows, "settings": settings})
    return rows, settings
