"""Whether an XLA:CPU flag makes the learner cheaper: the `preset=fast` update under each flag.

    python experiments/bench_xla_flags.py                     # the default flag sets, 3 rounds
    python experiments/bench_xla_flags.py --rounds 5 --variants xnn:--xla_cpu_use_xnnpack=true

``XLA_FLAGS`` is read once, when JAX starts its CPU backend, so every variant runs in a fresh
process (this script with ``--child``), in rounds (A, B, C, B, C, A, ...: the order rotated
every round) since this machine's speed drifts. Each child times, medians of ``--repeats`` calls
after a warm-up:

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
import shlex
import statistics
import subprocess
import sys
import time

import harness

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
    from rdher_jax import startup

    startup.setup(startup.Startup())
    import jax
    from bench_cycle import cycle_fn, plain_learner

    base = ["env=FetchPush", "preset=fast", "overlap=false"]
    bench = harness.Bench(log=None)  # stdout carries the result line only
    bench.add("cycle40", harness.donated(*cycle_fn([*base, "n_batches=40"])[1:]))
    bench.add("cycle1", harness.donated(*cycle_fn([*base, "n_batches=1"])[1:]))
    bench.add("plain40", harness.donated(*plain_learner(40, 256, 2)))
    bench.run(repeats)
    med = {k: bench.med(k) for k in bench.times}
    return {
        "cycle_ms": 1e3 * med["cycle40"],
        "update_ms": 1e3 * (med["cycle40"] - med["cycle1"]) / 39,
        "plain_updates_per_s": 40 / med["plain40"],
        "jax": jax.__version__,
    }


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_xla_flags.py", __doc__.splitlines()[0], repeats=15)
    ap.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS),
                    metavar="NAME:FLAGS", help="the first is the baseline the ratios are to")
    ap.add_argument("--rounds", type=int, default=3,
                    help="fresh processes per variant, interleaved (medians)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.repeats)))
        return
    from rdher_jax import startup

    # This process only starts the children (and reads the host): nothing to build.
    startup.setup(startup.Startup(ffi=False, compile_cache=False))

    variants = []
    for v in args.variants:
        name, sep, flags = v.partition(":")
        if not sep or not name:
            ap.error(f"variant {v!r} is not NAME:FLAGS")
        variants.append((name, flags))
    flags_of = dict(variants)
    t0 = time.time()

    def measure(name: str) -> dict:
        # XLA_FLAGS in the child's environment: read once, when its CPU backend starts.
        env = dict(os.environ)
        env["XLA_FLAGS"] = " ".join(x for x in (env.get("XLA_FLAGS", ""), flags_of[name]) if x)
        p = subprocess.run([sys.executable, __file__, "--child", "--repeats",
                            str(args.repeats)], env=env, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"variant {name} failed: {p.stderr.strip().splitlines()[-1]}")
        res = json.loads(p.stdout.strip().splitlines()[-1])
        print(f"{name}: cycle {res['cycle_ms']:.1f} ms, update {res['update_ms']:.2f} ms, "
              f"plain {res['plain_updates_per_s']:.0f}/s", flush=True)
        return res

    rows = harness.interleave([name for name, _ in variants], args.rounds, measure,
                              lambda r: print(f"round {r + 1}/{args.rounds} done", flush=True))

    def med(name, key):
        return statistics.median(x[key] for x in rows[name])

    base = variants[0][0]
    given = ("" if args.variants == list(DEFAULT_VARIANTS)
             else " --variants " + " ".join(shlex.quote(v) for v in args.variants))
    cmd = harness.command("bench_xla_flags.py", argv)
    h = harness.host()
    u0, p0 = med(base, "update_ms"), med(base, "plain_updates_per_s")
    cells = []
    for name, flags in variants:
        u, p = med(name, "update_ms"), med(name, "plain_updates_per_s")
        cells.append((name, f"`{flags or '(none)'}`", f"{med(name, 'cycle_ms'):.1f}",
                      f"{u:.2f}", f"{u / u0:.2f}", f"{p:.0f}", f"{p0 / p:.2f}"))
    harness.write_results(args.out, "XLA:CPU flags against the learner's cost", [
        f"`python experiments/bench_xla_flags.py --rounds {args.rounds} --repeats "
        f"{args.repeats}{given}` on {harness.machine(h)}, {time.time() - t0:.0f} s. Each "
        "variant a fresh process per round, rounds interleaved (order rotated every round); "
        "medians over rounds of each process's median. 'update': one sampled `preset=fast` "
        "update (the 40-update cycle less the 1-update cycle, over 39); 'plain': the plain XLA "
        "learner of the same widths (2 x 256, batch 256). Ratios: the variant's time over "
        f"`{base}`'s (below 1: faster).",
        harness.table(["variant", "XLA_FLAGS", "cycle (ms)", "update (ms)", "update ratio",
                       "plain updates/s", "plain ratio"], cells),
    ], {"variants": flags_of, "rounds": rows}, command=cmd, host=h)


if __name__ == "__main__":
    main()
