"""HER against DHER and RDHER on a moving-goal task, a few seeds each, on this CPU.

DHER was made for goals that move. This runs one vmapped sweep per algorithm (seeds as the
run axis) on ``FetchReachMoving`` (or ``--env``), then writes a table of best and final test
success, the batch composition and the hindsight bias per source, a plot of the mean test
success over seeds against env steps, and each run's metrics CSV, under
``experiments/results/moving_goals/``. Run directories (with checkpoints) go under ``runs/``; a
second call resumes them.

    python experiments/moving_goals.py --seeds 3 --epochs 8
"""

from __future__ import annotations

import argparse
import csv
import platform
import statistics
import sys
from pathlib import Path

ALGOS = ("her", "dher", "rdher")


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def mean_sd(xs: list[float]) -> str:
    if len(xs) < 2:
        return f"{xs[0]:.2f}"
    return f"{statistics.mean(xs):.2f} ± {statistics.stdev(xs):.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="FetchReachMoving")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--runs-dir", default="runs/moving_goals")
    ap.add_argument("--out", default="experiments/results/moving_goals")
    args = ap.parse_args()

    from rdher_jax import sweep

    runs = Path(args.runs_dir)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    curves: dict[str, tuple[list[float], list[float]]] = {}
    lines = [
        f"# HER, DHER and RDHER on {args.env}",
        "",
        f"`python experiments/moving_goals.py --env {args.env} --seeds {args.seeds} "
        f"--epochs {args.epochs}` on {platform.machine()}, {platform.processor() or 'CPU'}; "
        "defaults otherwise (2 envs, 40 updates of 256 per cycle, 10 cycles per epoch, 10 test "
        "episodes). Mean ± std over seeds; bias columns: mean over the last epoch and seeds of "
        "Q minus the observed discounted return, weighted as trained, per sample source.",
        "",
        "| algo | λ_r / λ_h | seeds | best test success | final test success | test success, "
        "mean of last 3 epochs | DHER rows in batches (last epoch) | bias real | bias HER | "
        "bias DHER |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for algo in ALGOS:
        d = runs / f"{args.env}-{algo}"
        argv = [f"env={args.env}", f"algo={algo}", f"seeds={args.seeds}",
                f"epochs={args.epochs}", "progress=false"]
        argv += [f"resume={d}"] if (d / "sweep.yaml").exists() else [f"sweep_dir={d}"]
        if sweep.main(argv) not in (0, None):
            sys.exit(f"error: the {algo} sweep failed")
        run_dirs = sorted(p for p in d.iterdir() if (p / "metrics.csv").exists())
        for p in run_dirs:  # the per-run CSVs are small: keep them with the results
            (out / algo).mkdir(exist_ok=True)
            (out / algo / f"{p.name}.csv").write_bytes((p / "metrics.csv").read_bytes())
        rows = [read_rows(p / "metrics.csv") for p in run_dirs]
        best = [max(float(r["test_success"]) for r in rs) for rs in rows]
        final = [float(rs[-1]["test_success"]) for rs in rows]
        last3 = [statistics.mean(float(r["test_success"]) for r in rs[-3:]) for rs in rows]

        def last(col: str, rows=rows) -> str:
            vals = [float(rs[-1][col]) for rs in rows if rs[-1][col] not in ("", "nan")]
            return mean_sd(vals) if vals else "-"

        first = read_rows(d / "summary.csv")[0]
        lam = f"{float(first['lambda_r']):g} / {float(first['lambda_h']):g}"
        lines.append(f"| {algo} | {lam} | {len(rows)} | {mean_sd(best)} | {mean_sd(final)} | "
                     f"{mean_sd(last3)} | {last('frac_dher')} | {last('bias_real')} | "
                     f"{last('bias_her')} | {last('bias_dher')} |")
        steps = [float(r["env_steps"]) for r in rows[0]]
        mean = [statistics.mean(float(rs[i]["test_success"]) for rs in rows)
                for i in range(len(steps))]
        curves[algo] = (steps, mean)
    text = "\n".join(lines) + "\n"
    (out / "summary.md").write_text(text)
    print(text)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for algo, (x, y) in curves.items():
        ax.plot(x, y, marker="o", label=algo)
    ax.set_xlabel("env steps")
    ax.set_ylabel(f"test success (mean of {args.seeds} seeds)")
    ax.set_title(args.env)
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "success.png", dpi=100)
    print(f"wrote {out / 'summary.md'} and {out / 'success.png'}")


if __name__ == "__main__":
    main()
