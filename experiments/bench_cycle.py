"""Where a training cycle's time goes, for the default settings and for a preset, side by side.

    python experiments/bench_cycle.py                       # FetchPush, default vs preset=fast
    python experiments/bench_cycle.py --env FetchPush --repeats 30
    python experiments/bench_cycle.py --overlap-cycles 0        # without the overlap rows
    python experiments/bench_cycle.py --variants fast+bf16:preset=fast,compute_dtype=bfloat16

A cycle is a rollout of ``num_envs`` episodes (host physics through one callback per step),
``n_batches`` sampled gradient steps and the target update. Timing the jitted cycle at the
setting's ``n_batches`` and at ``n_batches=1`` separates the two: the one-batch cycle is almost
all rollout (and store), and the difference divided by ``n_batches - 1`` is one sampled update.
The rollout's share is what overlapping host physics with the learner could save at most.
Beside them, a plain XLA learner of the same widths (an actor and a critic MLP on random
batches: the critic's TD loss, the actor through the critic, two Adam steps, the target
average; no replay, sampling or relabelling) times the update's arithmetic alone, the ceiling
the trainer's update is read against.
Settings are timed interleaved (A, B, B, A, ...: the order rotated every repeat) and medians
reported, since this machine's speed drifts. Writes ``experiments/results/bench_cycle.md`` and
``.json``.
"""

from __future__ import annotations

import harness
import jax
import jax.numpy as jnp
import optax

from rdher_jax import executor, startup
from rdher_jax.config import parse_args, resolve


def cycle_fn(settings: list[str]):
    """A jitted cycle and a filled-in TrainState for the given ``key=value`` settings."""
    cfg = resolve(parse_args([*settings, "run_dir=/tmp/bench_cycle_unused", "progress=false"]))
    _, trainer = executor.build(cfg)
    hp = trainer.hparams
    # Donated, as inside the trainer's epoch scan, where the state is carried in place: without
    # it every call would copy the whole replay buffer.
    cycle = jax.jit(trainer.cycle, donate_argnums=0)
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0), hp)
    for _ in range(3):  # compile, and put a few episodes in the buffer
        ts, m = cycle(ts, hp)
    jax.block_until_ready((ts, m))
    return cfg, cycle, ts, hp


def epoch_fn(settings: list[str], n_cycles: int):
    """A single run's epoch (``n_cycles`` cycles, one test episode) as the trainer runs it,
    compiled and warmed up: the jitted epoch, or executor.OverlapEpoch with overlap=true."""
    from rdher_jax.program import hparams_from_config

    cfg = resolve(parse_args([*settings, f"n_cycles={n_cycles}", "n_test_rollouts=1",
                              "run_dir=/tmp/bench_cycle_unused", "progress=false"]))
    _, _, batch = executor.executor_for([cfg], vmapped=False)
    hp = batch.put(jax.tree.map(lambda x: x[None], hparams_from_config(cfg)))
    ts = batch.init(batch.put(jax.random.PRNGKey(0)[None]), hp)
    for _ in range(2):
        ts, m = batch.epoch(ts, hp)
    jax.block_until_ready((ts, m))
    return cfg, batch.epoch, ts, hp


def plain_learner(n_batches: int, hidden: int, layers: int, dtype=None,
                  obs: int = 25, goal: int = 3, act: int = 4, batch: int = 256):
    """``n_batches`` plain DDPG updates in one scan (see the module doc), jitted, and its
    state."""
    opt = optax.adam(1e-3)

    def mlp_init(key, sizes):
        keys = jax.random.split(key, len(sizes) - 1)
        return [(jax.random.normal(k, (a, b)) / jnp.sqrt(a), jnp.zeros(b))
                for k, a, b in zip(keys, sizes[:-1], sizes[1:], strict=True)]

    def mlp(params, x):
        for i, (w, b) in enumerate(params):
            last = i == len(params) - 1
            cd = jnp.float32 if (last or dtype is None) else dtype
            x = jnp.dot(x.astype(cd), w.astype(cd)).astype(jnp.float32) + b
            x = x if last else jax.nn.relu(x)
        return x

    widths = [hidden] * layers
    ka, kc = jax.random.split(jax.random.PRNGKey(0))
    actor = mlp_init(ka, [obs + goal, *widths, act])
    critic = mlp_init(kc, [obs + goal + act, *widths, 1])
    copy = lambda t: jax.tree.map(jnp.array, t)  # noqa: E731  (distinct buffers: donated)
    state = (actor, critic, copy(actor), copy(critic), opt.init(actor), opt.init(critic))

    def step(s, k):
        actor, critic, t_actor, t_critic, oa, oc = s
        k1, k2, k3 = jax.random.split(k, 3)
        og = jax.random.normal(k1, (batch, obs + goal))
        nog = jax.random.normal(k2, (batch, obs + goal))
        a = jax.random.uniform(k3, (batch, act), minval=-1.0, maxval=1.0)
        q_next = mlp(t_critic, jnp.concatenate([nog, jnp.tanh(mlp(t_actor, nog))], -1))
        y = jax.lax.stop_gradient(-1.0 + 0.98 * q_next)

        def c_loss(c):
            return jnp.mean((mlp(c, jnp.concatenate([og, a], -1)) - y) ** 2)

        def a_loss(p):
            return -jnp.mean(mlp(critic, jnp.concatenate([og, jnp.tanh(mlp(p, og))], -1)))

        uc, oc = opt.update(jax.grad(c_loss)(critic), oc, critic)
        ua, oa = opt.update(jax.grad(a_loss)(actor), oa, actor)
        critic, actor = optax.apply_updates(critic, uc), optax.apply_updates(actor, ua)
        avg = lambda t, o: jax.tree.map(lambda x, y: 0.95 * x + 0.05 * y, t, o)  # noqa: E731
        return (actor, critic, avg(t_actor, actor), avg(t_critic, critic), oa, oc), None

    def run(s, _hp):
        s, _ = jax.lax.scan(step, s, jax.random.split(jax.random.PRNGKey(1), n_batches))
        return s, jnp.zeros(())

    fn = jax.jit(run, donate_argnums=0)
    state, m = fn(state, None)
    jax.block_until_ready((state, m))
    return fn, state, None


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_cycle.py", __doc__.splitlines()[0], repeats=20)
    ap.add_argument("--env", default="FetchPush")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--overlap-cycles", type=int, default=10,
                    help="cycles per timed epoch for the overlap rows (0: skip them)")
    ap.add_argument("--variants", nargs="*", default=[], metavar="NAME:K=V,K=V",
                    help="further settings to time beside the two, e.g. "
                    "fast+bf16:preset=fast,compute_dtype=bfloat16")
    args = ap.parse_args(argv)
    # A second host device, for the overlap=true rows (the others run on the first only).
    startup.setup(startup.Startup(host_devices=2))

    setups = {"default": [f"env={args.env}"], args.preset: [f"env={args.env}",
                                                             f"preset={args.preset}"]}
    for v in args.variants:
        name, _, kvs = v.partition(":")
        if not name or not kvs:
            raise SystemExit(f"error: --variants takes NAME:key=value,key=value, got {v!r}")
        setups[name] = [f"env={args.env}", *kvs.split(",")]
    bench, cfgs = harness.Bench(), {}  # one call per measurement, all in one rotated group
    for name, settings in setups.items():
        cfg, cycle, ts, hp = cycle_fn(settings)
        cfgs[name] = cfg
        bench.add(f"{name}/full", harness.donated(cycle, ts, hp))
        _, cycle1, ts1, hp1 = cycle_fn([*settings, "n_batches=1"])
        bench.add(f"{name}/one", harness.donated(cycle1, ts1, hp1))
    plain = {}  # the plain learner at each setting's widths and dtype, timed alongside
    for name, cfg in cfgs.items():
        shape = f"plain/{cfg.n_batches}x{cfg.layers}x{cfg.hidden}/{cfg.compute_dtype}"
        if shape not in plain.values():
            dt = None if cfg.compute_dtype == "float32" else jnp.bfloat16
            bench.add(shape, harness.donated(*plain_learner(cfg.n_batches, cfg.hidden,
                                                             cfg.layers, dt)))
        plain[name] = shape
    if args.overlap_cycles:
        for name, settings in setups.items():
            for ov in ("false", "true"):
                _, ep, ts, hp = epoch_fn([*settings, f"overlap={ov}"], args.overlap_cycles)
                bench.add(f"{name}/epoch-overlap-{ov}", harness.donated(ep, ts, hp))
    bench.run(args.repeats)
    rows = []
    for name, cfg in cfgs.items():
        full = bench.med(f"{name}/full")
        one = bench.med(f"{name}/one")
        upd = (full - one) / max(cfg.n_batches - 1, 1)
        steps = cfg.num_envs * 50
        plain_upd = bench.med(plain[name]) / cfg.n_batches
        rows.append({
            "setting": name, "settings": setups[name], "num_envs": cfg.num_envs,
            "n_batches": cfg.n_batches, "net": f"{cfg.layers}x{cfg.hidden}",
            "compute_dtype": cfg.compute_dtype,
            "cycle_ms": 1e3 * full, "rollout_ms": 1e3 * one, "update_ms": 1e3 * upd,
            "rollout_share": one / full, "env_steps_per_s": steps / full,
            "updates_per_s": cfg.n_batches / full, "plain_update_ms": 1e3 * plain_upd,
            "plain_updates_per_s": 1 / plain_upd,
        })
    cmd = harness.command("bench_cycle.py", argv)
    h = harness.host()
    cells = []
    for r in rows:
        net = r["net"] + (" bf16" if r["compute_dtype"] == "bfloat16" else "")
        cells.append((r["setting"], f"{r['num_envs']} x 50", r["n_batches"], net,
                      f"{r['cycle_ms']:.0f}",
                      f"{r['rollout_ms']:.0f} ({100 * r['rollout_share']:.0f}%)",
                      f"{r['update_ms']:.2f}", f"{r['plain_update_ms']:.2f}",
                      f"{r['env_steps_per_s']:.0f}", f"{r['updates_per_s']:.0f}"))
    blocks = [
        f"`{cmd}` on {harness.machine(h)}, {jax.device_count()} JAX device(s); medians of "
        f"{args.repeats} interleaved repeats (order rotated every repeat). "
        "'rollout' is the cycle at n_batches=1 (rollout, store, normaliser, one update); "
        "'update' is (cycle - rollout) / (n_batches - 1), one sampled gradient step; "
        "'plain update' is the plain XLA learner's (same widths and dtype, no replay), timed "
        "in the same rounds.",
        harness.table(["setting", "envs x steps", "updates", "net", "cycle ms",
                       "rollout ms (share)", "update ms", "plain update ms", "env-steps/s",
                       "updates/s"], cells),
    ]
    if args.overlap_cycles:
        cells = []
        for r in rows:
            name = r["setting"]
            seq = bench.med(f"{name}/epoch-overlap-false") / args.overlap_cycles
            ovl = bench.med(f"{name}/epoch-overlap-true") / args.overlap_cycles
            bound = max(r["rollout_ms"], r["cycle_ms"] - r["rollout_ms"])
            r.update(overlap_cycles=args.overlap_cycles, seq_epoch_cycle_ms=1e3 * seq,
                     overlap_epoch_cycle_ms=1e3 * ovl)
            cells.append((name, f"{1e3 * seq:.0f}", f"{1e3 * ovl:.0f}", f"{seq / ovl:.2f}x",
                          f"{bound:.0f}"))
        blocks += [
            f"**Overlap** (`overlap=true`): an epoch of {args.overlap_cycles} cycles and one test "
            "episode as the trainer runs it, per cycle, sequential against overlapped (the "
            "rollout on a second host device while the learner trains; "
            "`rdher_jax.executor.OverlapEpoch`), timed in the same interleaved rounds.",
            harness.table(["setting", "sequential ms / cycle", "overlap ms / cycle", "speed-up",
                           "bound: max(rollout, updates) ms"], cells),
        ]
    harness.write_results(args.out, f"Where a {args.env} training cycle's time goes", blocks,
                          {"repeats": args.repeats, "rows": rows}, command=cmd, host=h)


if __name__ == "__main__":
    main()
