"""Whether an XLA:CPU flag makes the learner cheaper: the `preset=fast` update under each flag.

    python experiments/bench_xla_flags.py                     # the default flag sets, 3 rounds
    python experiments/bench_xla_flags.py --rounds 5 --variants xnn:--xla_cpu_use_xnnpack=true

``XLA_FLAGS`` is read once, when JAX starts its CPU backend, so every variant runs in a fresh
process (this script with ``--child``), in rounds (A, B, C, A, B, C, ...) since this machine's
speed drifts. Each child times, medians of ``--repeats`` calls after a warm-up:

- the trainer's ``preset=fast`` cycle on FetchPush at 40 updates and at 1 (``bench_cycle``'s
  ``cycle_fn``, sequential), so that their difference over 39 is one sampled update, sampling,
  relabelling and the delayed actor included;
- the plain XLA learner of the same widths (``bench_cycle.plain_learner``, 2 x 256, batch 256:
  the arithmetic alone).

The table gives each variant's median over rounds and its ratio to the first variant (no
flags). Writes ``experiments/results/bench_xla_flags.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# name: flags. XLA:CPU's library back ends for dots (XNNPACK, YNNPACK, oneDNN), 512-bit vectors
# (this CPU has AVX-512; XLA prefers 256-bit by default) and fast math.
DEFAULT_VARIANTS = (
    "none:",
    "xnnpack:--xla_cpu_use_xnnpack=true",
    "xnn-dot:--xla_cpu_experimental_xnn_fusion_type=LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
    "ynn-dot:--xla_cpu_experimental_ynn_fusion_type=LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
    "onednn-dot:--xla_cpu_experimental_onednn_fusion_type=LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
    "vector512:--xla_cpu_prefer_vector_width=512",
    "fast-math:--xla_cpu_enable_fast_math=true",
)


def child(repeats: int) -> dict:
    """Time the cycle at 40 and 1 updates and the plain learner in this process."""
    sys.path.insert(0, str(HERE))
    import jax
    from bench_cycle import cycle_fn, plain_learner, time_once

    base = ["env=FetchPush", "preset=fast", "overlap=false"]
    fns = {
        "cycle40": cycle_fn([*base, "n_batches=40"])[1:],
        "cycle1": cycle_fn([*base, "n_batches=1"])[1:],
        "plain40": plain_learner(40, 256, 2),
    }
    for k in fns:  # warm-up
        time_once(fns, k)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k in fns:
            times[k].append(time_once(fns, k))
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "cycle_ms": 1e3 * med["cycle40"],
        "update_ms": 1e3 * (med["cycle40"] - med["cycle1"]) / 39,
        "plain_updates_per_s": 40 / med["plain40"],
        "jax": jax.__version__,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS),
                    metavar="NAME:FLAGS", help="the first is the baseline the ratios are to")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=15, help="timed calls per child")
    ap.add_argument("--out", default=str(HERE / "results" / "bench_xla_flags.md"))
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.repeats)))
        return

    variants = []
    for v in args.variants:
        name, sep, flags = v.partition(":")
        if not sep or not name:
            ap.error(f"variant {v!r} is not NAME:FLAGS")
        variants.append((name, flags))
    rows: dict[str, list[dict]] = {name: [] for name, _ in variants}
    t0 = time.time()
    for r in range(args.rounds):
        for name, flags in variants:
            env = dict(os.environ)
            env["XLA_FLAGS"] = " ".join(x for x in (env.get("XLA_FLAGS", ""), flags) if x)
            p = subprocess.run([sys.executable, __file__, "--child", "--repeats",
                                str(args.repeats)], env=env, capture_output=True, text=True)
            if p.returncode != 0:
                raise SystemExit(f"variant {name} failed: {p.stderr.strip().splitlines()[-1]}")
            res = json.loads(p.stdout.strip().splitlines()[-1])
            rows[name].append(res)
            print(f"[{r + 1}/{args.rounds}] {name}: cycle {res['cycle_ms']:.1f} ms, update "
                  f"{res['update_ms']:.2f} ms, plain {res['plain_updates_per_s']:.0f}/s",
                  flush=True)

    def med(name, key):
        return statistics.median(x[key] for x in rows[name])

    base = variants[0][0]
    given = ("" if args.variants == list(DEFAULT_VARIANTS)
             else " --variants " + " ".join(shlex.quote(v) for v in args.variants))
    lines = [
        "# XLA:CPU flags against the learner's cost",
        "",
        f"`python experiments/bench_xla_flags.py --rounds {args.rounds} --repeats "
        f"{args.repeats}{given}` on {platform.machine()} ({os.cpu_count()} cores), JAX "
        f"{rows[base][0]['jax']}, {time.time() - t0:.0f} s. Each variant a fresh process per "
        "round, rounds interleaved; medians over rounds of each process's median. 'update': one "
        "sampled `preset=fast` update (the 40-update cycle less the 1-update cycle, over 39); "
        "'plain': the plain XLA learner of the same widths (2 x 256, batch 256). Ratios: the "
        f"variant's time over `{base}`'s (below 1: faster).",
        "",
        "| variant | XLA_FLAGS | cycle (ms) | update (ms) | update ratio | plain updates/s | "
        "plain ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    u0, p0 = med(base, "update_ms"), med(base, "plain_updates_per_s")
    for name, flags in variants:
        u, p = med(name, "update_ms"), med(name, "plain_updates_per_s")
        lines.append(f"| {name} | `{flags or '(none)'}` | {med(name, 'cycle_ms'):.1f} | "
                     f"{u:.2f} | {u / u0:.2f} | {p:.0f} | {p0 / p:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(
        {"variants": dict(variants), "rounds": rows}, indent=1))


if __name__ == "__main__":
    main()
