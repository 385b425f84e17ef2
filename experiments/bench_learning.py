"""Env steps and wall clock to a test success, for a training setting over seeds.

Runs ``python -m rdher_jax.train`` once per seed (one process each, so every run includes its own
cold start and compilation) with the given ``key=value`` settings, then reads each run's
``metrics.csv`` and records, for each threshold, the first epoch whose test success reaches it
and the first epoch whose mean over the last ``--window`` epochs does (10 test episodes per epoch
make single epochs noisy). Writes a table (markdown and JSON) and the curves under
``experiments/results/``. Runs already finished in ``--runs-dir`` are read, not rerun, so a
benchmark can be completed over several sittings (an unfinished run is resumed).

    python experiments/bench_learning.py --name push-default --seeds 0 1 2 -- \
        env=FetchPush epochs=40
"""

from __future__ import annotations

import csv
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import harness

from rdher_jax.config import RESUMABLE_KEYS, SUCCESS_TOLERANCE

THRESHOLDS = (0.5, 0.9)




def first_hit(rows: list[dict], threshold: float, window: int) -> dict | None:
    """The first epoch at or above ``threshold``, alone and as a trailing mean of ``window``
    (to within the trainer's stop_success tolerance: a float32 7/10 is a hair under 0.7)."""
    out: dict = {}
    succ = [float(r["test_success"]) for r in rows]
    level = threshold - SUCCESS_TOLERANCE
    for i, r in enumerate(rows):
        if "single" not in out and succ[i] >= level:
            out["single"] = {"epoch": int(r["epoch"]), "env_steps": int(r["env_steps"]),
                             "wall_s": float(r["wall_time"])}
        if "window" not in out and i + 1 >= window and \
                statistics.mean(succ[i + 1 - window: i + 1]) >= level:
            out["window"] = {"epoch": int(r["epoch"]), "env_steps": int(r["env_steps"]),
                             "wall_s": float(r["wall_time"])}
    return out or None


STARTUP_FILE = "bench_startup_s.txt"  # written beside a run started fresh by this script


def run_seed(run_dir: Path, seed: int, settings: list[str], train: bool = True,
             retest: int = 0) -> list[dict]:
    """Train (or resume, or just read) one seed; returns its metrics rows.

    A run this script starts fresh also gets its start-up time, from starting the process to
    the start of the training clock (imports, env build, init; the trainer writes run_info.json
    just before its clock starts), kept in ``<run_dir>/bench_startup_s.txt``. ``retest`` > 0:
    the run ends by retesting its best policy on that many new episodes (``retest.json``)."""
    if not train:
        if not (run_dir / "metrics.csv").exists():
            return []
        with open(run_dir / "metrics.csv", newline="") as f:
            return list(csv.DictReader(f))
    argv = [sys.executable, "-m", "rdher_jax.train"]
    fresh = not (run_dir / "config.yaml").exists()
    if not fresh:  # a resume takes the settings a run may change on its way (e.g. epochs=)
        argv += [f"resume={run_dir}"] + [s for s in settings
                                         if s.split("=", 1)[0] in RESUMABLE_KEYS]
    else:
        argv += [*settings, f"seed={seed}", f"run_dir={run_dir}"]
    t_start = time.time()
    subprocess.run(argv + ["progress=false"] + ([f"retest={retest}"] if retest else []),
                   check=True)
    if fresh:
        startup = (run_dir / "run_info.json").stat().st_mtime - t_start
        (run_dir / STARTUP_FILE).write_text(f"{startup:.3f}\n")
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def read_retest(run_dir: Path) -> dict | None:
    """The run's end-of-training retest (``retest.json``): success, epoch and episodes."""
    try:
        r = json.loads((run_dir / "retest.json").read_text())
    except (OSError, ValueError):
        return None
    return {k: r[k] for k in ("success", "epoch", "episodes")}


def read_selection(run_dir: Path) -> dict | None:
    """The run's choice of policy (``select_top`` > 1: ``selection.json``): the chosen epoch,
    the selection episodes and each candidate epoch's test and selection successes."""
    try:
        r = json.loads((run_dir / "selection.json").read_text())
    except (OSError, ValueError):
        return None
    return {k: r[k] for k in ("epoch", "selection_episodes", "candidates")}


def retest_cell(r: dict) -> str:
    t, sel = r.get("retest"), r.get("selection")
    if not t:
        return "-"
    how = f", selected of {len(sel['candidates'])}" if sel else ""
    return f"{100 * t['success']:.0f}% of {t['episodes']} (epoch {t['epoch']}{how})"


def startup_s(run_dir: Path) -> float | None:
    try:
        return float((run_dir / STARTUP_FILE).read_text())
    except (OSError, ValueError):
        return None


def fmt(hit: dict | None, key: str) -> str:
    if not hit or key not in hit:
        return "not reached"
    h = hit[key]
    return f"{h['env_steps']:,} steps, {h['wall_s'] / 60:.1f} min"


def curve_rows(r: dict) -> list[dict]:
    """A seed's recorded curve as metrics rows (what :func:`first_hit` reads)."""
    return [{"epoch": i + 1, "env_steps": st, "wall_time": w, "test_success": sc}
            for i, (st, w, sc) in enumerate(r["curve"])]


def summary(out: Path, window: int) -> str:
    """One table over every setting benchmarked in ``out`` (``<name>.json`` files): what each
    changes from the defaults, and per seed the env steps and minutes to 0.5 and 0.9, and to
    Slide's goal threshold of 0.8 as a trailing mean (found on the curve)."""
    lines = [
        "# Learning speed: every setting measured",
        "",
        "Rows are written by `python experiments/bench_learning.py --summary` from the "
        "`<name>.json` files beside this one; each setting's own `<name>.md`, CSVs and curves "
        f"are there too. 'mean of {window}': the first epoch whose trailing mean of {window} "
        "test evaluations (10 episodes each) reaches the threshold. Minutes are wall clock from "
        "the start of training, compilation included.",
        "",
        "| setting | keys | seed | env steps run | best | to 0.5 | to 0.9 | "
        f"to 0.9, mean of {window} | to 0.8, mean of {window} | retest of the best policy |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for path in sorted(out.glob("*.json")):
        d = json.loads(path.read_text())
        keys = " ".join(k for k in d["settings"] if not k.startswith(("env=", "epochs=")))
        for seed, r in sorted(d["results"].items(), key=lambda kv: int(kv[0])):
            h5, h9 = r["hits"]["0.5"], r["hits"]["0.9"]
            h8 = first_hit(curve_rows(r), 0.8, window)
            lines.append(
                f"| {path.stem} | `{keys}` | {seed} | {r['env_steps']:,} | {r['best']:.2f} | "
                f"{fmt(h5, 'single')} | {fmt(h9, 'single')} | {fmt(h9, 'window')} | "
                f"{fmt(h8, 'window')} | {retest_cell(r)} |")
    text = "\n".join(lines) + "\n"
    (out / "summary.md").write_text(text)
    return text


def write_tables(out: Path, name: str, data: dict, window: int) -> str:
    """``<name>.md`` and ``<name>.json`` from a setting's data (its settings, seeds, note,
    machine limits and per-seed results); returns the markdown."""
    results, limits = data["results"], data.get("machine_limits")
    paragraph = (
        f"`python experiments/bench_learning.py --name {name} --seeds "
        f"{' '.join(map(str, data['seeds']))} -- {' '.join(data['settings'])}` on "
        f"{platform.machine()} ({platform.processor() or 'CPU'}); wall clock from the start "
        "of training (the first epoch's compilation included, imports and env build not; "
        "'start-up': from starting the process to that clock's start, for runs this script "
        "started fresh). "
        f"'mean of {window}': the first epoch whose trailing mean of {window} epochs "
        "reaches the threshold." + (f" {data['note']}" if data.get("note") else ""))
    head = ["seed", "epochs", "env steps", "minutes", "best",
            *(c for t in THRESHOLDS for c in (f"to {t}", f"to {t}, mean of {window}")),
            "start-up (s)", f"to {THRESHOLDS[-1]}, mean of {window}, from process start",
            "retest of the best policy"]
    rows = []
    for seed, r in results.items():
        cells = []
        for t in THRESHOLDS:
            cells += [fmt(r["hits"][str(t)], "single"), fmt(r["hits"][str(t)], "window")]
        up = r.get("startup_s")
        last = (r["hits"][str(THRESHOLDS[-1])] or {}).get("window")
        cells += ["-" if up is None else f"{up:.1f}",
                  "-" if up is None or last is None
                  else f"{(up + last['wall_s']) / 60:.1f} min", retest_cell(r)]
        rows.append([seed, r["epochs"], f"{r['env_steps']:,}", f"{r['wall_s'] / 60:.1f}",
                     f"{r['best']:.2f}", *cells])
    blocks: list = [paragraph, harness.table(head, rows)]
    if limits is not None:
        blocks += [f"The machine's ceilings, measured just before the runs (`python "
                   f"{limits['script']}`):", ["```", limits["table"], "```"]]
    return harness.write_results(out / name, f"Learning speed: {name}", blocks, data,
                                 echo=False)


def retabulate(out: Path, window: int) -> list[str]:
    """Recompute every setting's hits in ``out`` from the curves its JSON holds, and rewrite
    its tables (after a change to how hits are found); returns the names that changed."""
    changed = []
    for path in sorted(out.glob("*.json")):
        data = json.loads(path.read_text())
        for r in data["results"].values():
            r["hits"] = {str(t): first_hit(curve_rows(r), t, window) for t in THRESHOLDS}
        before = (out / f"{path.stem}.md").read_text(), path.read_text()
        write_tables(out, path.stem, data, window)
        if ((out / f"{path.stem}.md").read_text(), path.read_text()) != before:
            changed.append(path.stem)
    return changed


def main() -> None:
    ap = harness.parser("bench_learning.py", __doc__.splitlines()[0], limits=True,
                        out=harness.RESULTS / "bench_learning",
                        out_help="results folder: <name>.md, .json, .png, per-seed CSVs and "
                        "summary.md")
    ap.add_argument("--name", help="name of this setting (file names)")
    ap.add_argument("--summary", action="store_true",
                    help="write summary.md over every setting in --out, train nothing")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--window", type=int, default=3)
    ap.add_argument("--runs-dir", default="runs/bench_learning")
    ap.add_argument("--retabulate", action="store_true",
                    help="recompute the hits of every setting in --out from the curves in its "
                    "JSON and rewrite its tables (and summary.md), train nothing")
    ap.add_argument("--report-only", action="store_true",
                    help="tabulate the runs as they stand (e.g. stopped early), train nothing")
    ap.add_argument("--note", default="", help="a sentence on how the runs were made, kept in "
                    "the .md and .json (e.g. how many ran at once)")
    ap.add_argument("--retest", type=int, default=100, metavar="N",
                    help="each run ends by retesting its best policy on N new episodes "
                    "(the trainer's retest=N; 0: none); its result goes into the tables")
    ap.add_argument("settings", nargs="*", help="key=value training settings")
    args = ap.parse_args()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.retabulate:
        print("changed:", " ".join(retabulate(out, args.window)) or "nothing")
    if args.summary or args.retabulate:
        print(summary(out, args.window))
        return
    if not args.name:
        ap.error("--name is required (or --summary)")
    limits = None if args.report_only else harness.machine_limits(args.limits_script)
    if args.report_only and (out / f"{args.name}.json").is_file():  # keep what the runs had
        before = json.loads((out / f"{args.name}.json").read_text())
        limits, args.note = before.get("machine_limits"), args.note or before.get("note", "")
        args.settings = args.settings or before["settings"]
    results = {}
    for seed in args.seeds:
        run_dir = Path(args.runs_dir) / f"{args.name}-s{seed}"
        rows = run_seed(run_dir, seed, args.settings, train=not args.report_only,
                        retest=args.retest)
        if not rows:
            continue
        (out / f"{args.name}-s{seed}.csv").write_bytes((run_dir / "metrics.csv").read_bytes())
        results[seed] = {
            "epochs": len(rows),
            "env_steps": int(rows[-1]["env_steps"]) if rows else 0,
            "wall_s": float(rows[-1]["wall_time"]) if rows else 0.0,
            "best": max((float(r["test_success"]) for r in rows), default=0.0),
            "startup_s": startup_s(run_dir),
            "retest": read_retest(run_dir),
            "selection": read_selection(run_dir),
            "hits": {str(t): first_hit(rows, t, args.window) for t in THRESHOLDS},
            "curve": [(int(r["env_steps"]), float(r["wall_time"]), float(r["test_success"]))
                      for r in rows],
        }

    text = write_tables(out, args.name, {
        "settings": args.settings, "seeds": args.seeds, "note": args.note,
        "machine_limits": limits, "results": results}, args.window)
    print(text)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for seed, r in results.items():
        steps, wall, succ = zip(*r["curve"], strict=True) if r["curve"] else ((), (), ())
        axes[0].plot(steps, succ, label=f"seed {seed}")
        axes[1].plot([w / 60 for w in wall], succ, label=f"seed {seed}")
    axes[0].set_xlabel("env steps")
    axes[1].set_xlabel("minutes (wall clock)")
    for ax in axes:
        ax.set_ylabel("test success")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        for t in THRESHOLDS:
            ax.axhline(t, color="grey", lw=0.6, ls="--")
    axes[0].legend()
    fig.suptitle(args.name)
    fig.tight_layout()
    fig.savefig(out / f"{args.name}.png", dpi=100)


if __name__ == "__main__":
    main()
