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
then A warm, B cold, B warm, A cold, ...: the order rotated every repeat) and medians reported,
since this machine's speed drifts. Writes
``experiments/results/bench_start.md`` and ``.json``.
"""

from __future__ import annotations

import shlex
import statistics
import tempfile
from pathlib import Path

import harness
from bench_train import cold_start_to


def one_run(settings: list[str], cache: Path, threshold: float) -> dict:
    r = cold_start_to(threshold, None, None, settings, cache_dir=cache, to_end=True)
    hit = r["hit"] or {}
    return {"to_threshold_s": hit.get("seconds"), "epoch": hit.get("epoch"),
            "env_steps": hit.get("env_steps"), "process_s": r["process_s"]}


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_start.py", __doc__.splitlines()[0], repeats=5)
    ap.add_argument("--settings", nargs="*", default=[],
                    help="key=value settings of every run (default: none, the main job)")
    ap.add_argument("--variants", nargs="+", default=["", "overlap=true"],
                    help="each a space-separated key=value list added to --settings "
                    "('' : none)")
    ap.add_argument("--threshold", type=float, default=0.95)
    args = ap.parse_args(argv)
    from rdher_jax import startup

    # This process only starts and watches the runs (and reads the host): nothing to build.
    startup.setup(startup.Startup(ffi=False, compile_cache=False))

    with tempfile.TemporaryDirectory(prefix="bench_start-") as tmp:
        work = Path(tmp)
        warm_cache = {}
        for v in args.variants:  # the warm caches, filled by an unmeasured run each
            warm_cache[v] = Path(tempfile.mkdtemp(prefix="warm-", dir=work))
            one_run([*args.settings, *v.split()], warm_cache[v], args.threshold)

        def measure(case: tuple[str, str]) -> dict:
            v, mode = case
            cache = (warm_cache[v] if mode == "warm"
                     else Path(tempfile.mkdtemp(prefix="cold-", dir=work)))
            res = one_run([*args.settings, *v.split()], cache, args.threshold)
            print(f"{v or '(main job)'} {mode}: {res['to_threshold_s']} s to "
                  f"{args.threshold}, process {res['process_s']:.1f} s", flush=True)
            return res

        cases = [(v, mode) for v in args.variants for mode in ("cold", "warm")]
        results = harness.interleave(cases, args.repeats, measure, lambda r: print(
            f"repeat {r + 1}/{args.repeats} done", flush=True))

    def med(xs):
        xs = [x for x in xs if x is not None]
        return statistics.median(xs) if xs else None

    cmd = "python experiments/bench_start.py " + " ".join(
        [*(["--settings", *args.settings] if args.settings else []), "--variants",
         *(shlex.quote(v) for v in args.variants), "--repeats", str(args.repeats),
         "--threshold", str(args.threshold)])
    rows, cells = [], []
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
        cells.append((v or "(main job)", mode, fmt(row["to_threshold_s"]),
                      f"{fmt(row['min_s'])}-{fmt(row['max_s'])}",
                      ", ".join(str(e) for e in row["epochs"]), f"{row['process_s']:.1f}"))
    h = harness.host()
    harness.write_results(args.out, "From process start to test success: the main job, cold "
                          "and warm", [
        f"`{cmd}` on {harness.machine(h)}. `python -m rdher_jax.train "
        f"{' '.join(args.settings)}` plus the variant; seconds from starting the process to the "
        f"first metrics.csv row with test success >= {args.threshold}, median of {args.repeats} "
        "(min-max), the cases interleaved (order rotated every repeat). cold: an empty "
        "compilation cache; warm: the cache a previous run filled.",
        harness.table(["variant", "cache", "to threshold (s)", "min-max", "reached at epoch",
                       "process (s)"], cells),
    ], {"rows": rows}, command=cmd, host=h)


if __name__ == "__main__":
    main()
