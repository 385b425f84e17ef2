"""Time from process start to a success rate: the README's main job, cold and warm.

    python experiments/bench_start.py                         # FetchReach, 5 + 5 runs a setting
    python experiments/bench_start.py --repeats 3 --variants "" "overlap=true"

Each measured run is a fresh ``python -m rdher_jax.train`` process (the README's main job, plus
the variant's ``key=value`` settings). The clock starts just before the process is started and
stops when its ``metrics.csv`` first holds an epoch whose test success reaches ``--threshold``
(polled every 20 ms, ``bench_train.cold_start_to``); the process's whole wall clock is
reported too.

- **cold**: a machine that never ran it: an empty compilation cache (``RDHER_JAX_CACHE_DIR``
  pointed at a new directory for each run).
- **warm**: the second run: one cache directory, filled by an unmeasured first run, then
  each measured run reads it.

Imports are warm in both (the OS's file cache holds the packages after the first run): only the
compilation cache differs. Variants and modes are interleaved (A cold, A warm, B cold, B warm,
A cold, ...) and medians reported, since this machine's speed drifts. Writes
``experiments/results/bench_start.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import tempfile
from pathlib import Path

from bench_train import cold_start_to

HERE = Path(__file__).resolve().parent


def one_run(settings: list[str], cache: Path, threshold: float) -> dict:
    r = cold_start_to(threshold, None, None, settings, cache_dir=cache, to_end=True)
    hit = r["hit"] or {}
    return {"to_threshold_s": hit.get("seconds"), "epoch": hit.get("epoch"),
            "env_steps": hit.get("env_steps"), "process_s": r["process_s"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--settings", nargs="*", default=[],
                    help="key=value settings of every run (default: none, the main job)")
    ap.add_argument("--variants", nargs="+", default=["", "overlap=true"],
                    help="each a space-separated key=value list added to --settings "
                    "('' : none)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threshold", type=float, default=0.95)
    ap.add_argument("--out", default=str(HERE / "results" / "bench_start.md"))
    args = ap.parse_args()

    results: dict[tuple[str, str], list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_start-") as tmp:
        work = Path(tmp)
        warm_cache = {}
        for v in args.variants:  # the warm caches, filled by an unmeasured run each
            warm_cache[v] = Path(tempfile.mkdtemp(prefix="warm-", dir=work))
            one_run([*args.settings, *v.split()], warm_cache[v], args.threshold)
        for r in range(args.repeats):
            for v in args.variants:
                for mode in ("cold", "warm"):
                    cache = (warm_cache[v] if mode == "warm"
                             else Path(tempfile.mkdtemp(prefix="cold-", dir=work)))
                    res = one_run([*args.settings, *v.split()], cache, args.threshold)
                    results.setdefault((v, mode), []).append(res)
                    print(f"[{r + 1}/{args.repeats}] {v or '(main job)'} {mode}: "
                          f"{res['to_threshold_s']} s to {args.threshold}, "
                          f"process {res['process_s']:.1f} s", flush=True)

    def med(xs):
        xs = [x for x in xs if x is not None]
        return statistics.median(xs) if xs else None

    cmd = "python experiments/bench_start.py " + " ".join(
        [*(["--settings", *args.settings] if args.settings else []), "--variants",
         *(shlex.quote(v) for v in args.variants), "--repeats", str(args.repeats),
         "--threshold", str(args.threshold)])
    lines = [
        "# From process start to test success: the main job, cold and warm",
        "",
        f"`{cmd}` on {platform.machine()} ({platform.processor() or 'CPU'}), "
        f"{os.cpu_count()} CPUs. `python -m rdher_jax.train {' '.join(args.settings)}` plus "
        "the variant; seconds from starting the process to the first metrics.csv row with "
        f"test success >= {args.threshold}, median of {args.repeats} (min-max). cold: an empty "
        "compilation cache; warm: the cache a previous run filled.",
        "",
        "| variant | cache | to threshold (s) | min-max | reached at epoch | process (s) |",
        "|---|---|---|---|---|---|",
    ]
    rows = []
    for (v, mode), rs in results.items():
        t = [x["to_threshold_s"] for x in rs]
        ok = [x for x in t if x is not None]
        row = {"variant": v, "cache": mode, "to_threshold_s": med(t),
               "min_s": min(ok) if ok else None, "max_s": max(ok) if ok else None,
               "reached": sum(x is not None for x in t), "runs": len(rs),
               "epochs": [x["epoch"] for x in rs], "process_s": med([x["process_s"] for x in rs]),
               "all": rs}
        rows.append(row)
        fmt = (lambda x: "not reached" if x is None else f"{x:.1f}")
        lines.append(f"| {v or '(main job)'} | {mode} | {fmt(row['to_threshold_s'])} | "
                     f"{fmt(row['min_s'])}-{fmt(row['max_s'])} | "
                     f"{', '.join(str(e) for e in row['epochs'])} | {row['process_s']:.1f} |")
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
