"""Can host physics and the learner run at the same time on a CPU? Three ways, side by side.

    python experiments/bench_overlap.py                  # FetchPush, 2 host devices
    python experiments/bench_overlap.py --repeats 15

The two halves of a training cycle, built from the real pieces: a *rollout* (one FetchPush
episode, ``num_envs`` envs, 50 native-physics steps through the env's ``pure_callback``, random
actions) and a *learner* (``n_batches`` Adam steps of a 2x256 critic-sized MLP on a batch of
256, no callback; as ``preset=fast``'s update). Each timed alone, then together:

- ``one program``: both in one jitted function, the two scans data-independent;
- ``two programs, one device``: two jitted calls dispatched back to back, learner first;
- ``two programs, two devices``: the same, the learner on host device 0 and the rollout on
  host device 1 (two host devices, which this script asks start-up for).

"Overlapped" is max(alone) / together: 1.0 when the pair costs as much as its slower half,
max/sum when it costs the sum. Calls are interleaved and medians reported (this machine's speed
drifts). Writes ``experiments/results/bench_overlap.md`` and ``.json``.
"""

from __future__ import annotations

import harness
import jax
import jax.numpy as jnp
import optax
from rdher_jax.envs import make_env
from rdher_jax.envs.rollout import rollout as env_rollout

from rdher_jax import startup


def make_rollout(env_name: str, num_envs: int):
    env = make_env(env_name, backend="mujoco", auto_reset=False)

    def rollout(key):
        keys = jax.random.split(key, num_envs + 1)
        policy = lambda k, s: jax.random.uniform(k, (num_envs, 4), minval=-1.0, maxval=1.0)  # noqa: E731
        return env_rollout(env, policy, keys[1:], jax.random.split(keys[0], 50))[2]

    return rollout


def make_learner(n_batches: int, batch: int = 256, hidden: int = 256, obs: int = 31):
    opt = optax.adam(1e-3)

    def init(key):
        k1, k2, k3 = jax.random.split(key, 3)
        params = {"w1": jax.random.normal(k1, (obs + 4, hidden)) * 0.05,
                  "w2": jax.random.normal(k2, (hidden, hidden)) * 0.05,
                  "w3": jax.random.normal(k3, (hidden, 1)) * 0.05}
        return params, opt.init(params)

    def loss(p, x, y):
        h = jax.nn.relu(x @ p["w1"])
        h = jax.nn.relu(h @ p["w2"])
        return jnp.mean((h @ p["w3"] - y) ** 2)

    def learn(carry, key):
        def body(c, k):
            p, s = c
            kx, ky = jax.random.split(k)
            x = jax.random.normal(kx, (batch, obs + 4))
            y = jax.random.normal(ky, (batch, 1))
            g = jax.grad(loss)(p, x, y)
            u, s = opt.update(g, s, p)
            return (optax.apply_updates(p, u), s), None

        return jax.lax.scan(body, carry, jax.random.split(key, n_batches))[0]

    return init, learn


def main(argv: list[str] | None = None) -> None:
    ap = harness.parser("bench_overlap.py", __doc__.splitlines()[0], repeats=11)
    ap.add_argument("--env", default="FetchPush")
    ap.add_argument("--num-envs", type=int, default=1)
    ap.add_argument("--n-batches", type=int, default=40)
    args = ap.parse_args(argv)

    # A second host device for the two-device case: set before anything touches a device.
    startup.setup(startup.Startup(host_devices=2))

    d0, d1 = jax.devices()[:2]
    rollout = jax.jit(make_rollout(args.env, args.num_envs))
    init, learn = make_learner(args.n_batches)
    learn_j = jax.jit(learn)

    rollout_fn = make_rollout(args.env, args.num_envs)

    @jax.jit
    def both(carry, k1, k2):
        return learn(carry, k1), rollout_fn(k2)

    key = jax.random.PRNGKey(0)
    carry0 = jax.device_put(init(key), d0)
    k_learn0, k_roll0 = jax.device_put(key, d0), jax.device_put(key, d0)
    k_roll1 = jax.device_put(key, d1)

    cases = {
        "rollout alone": lambda: rollout(k_roll0),
        "learner alone": lambda: learn_j(carry0, k_learn0),
        "one program": lambda: both(carry0, k_learn0, k_roll0),
        "two programs, one device": lambda: (learn_j(carry0, k_learn0), rollout(k_roll0)),
        "two programs, two devices": lambda: (learn_j(carry0, k_learn0), rollout(k_roll1)),
    }
    bench = harness.Bench()  # one call per measurement
    for name, fn in cases.items():
        bench.add(name, fn)
    bench.run(args.repeats)
    med = {k: bench.med(k) for k in cases}
    slower = max(med["rollout alone"], med["learner alone"])
    total = med["rollout alone"] + med["learner alone"]
    rows = []
    for name, t in med.items():
        together = name not in ("rollout alone", "learner alone")
        rows.append({"case": name, "median_ms": 1000 * t,
                     "overlapped": slower / t if together else None,
                     "of_sum": t / total if together else None})
    h = harness.host()
    cells = [(r["case"], f"{r['median_ms']:.1f}",
              "-" if r["overlapped"] is None else f"{r['overlapped']:.2f}",
              "-" if r["of_sum"] is None else f"{r['of_sum']:.2f}") for r in rows]
    cmd = harness.command("bench_overlap.py", argv)
    harness.write_results(args.out, "Host physics and the learner at the same time?", [
        f"`{cmd}` ({args.env}, rollout: {args.num_envs} env(s) x 50 native steps; learner: "
        f"{args.n_batches} Adam steps, 2x256 MLP, batch 256); {harness.machine(h)}; median of "
        f"{args.repeats}, interleaved (order rotated every repeat).",
        harness.table(["case", "median (ms)", "max(alone) / this", "this / sum(alone)"], cells),
        "1.00 in the third column: the pair costs its slower half (full overlap); "
        "this / sum = 1.00: they ran one after the other.",
    ], {"env": args.env, "num_envs": args.num_envs, "n_batches": args.n_batches,
        "repeats": args.repeats, "rows": rows}, command=cmd, host=h)


if __name__ == "__main__":
    main()
