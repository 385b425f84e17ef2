"""``overlap=true``: each cycle's episodes collected on a second host device while the learner
trains (executor.OverlapEpoch), against the sequential cycle.

The checks that need two host devices run in a child process started with
``JAX_NUM_CPU_DEVICES=2`` (this process's JAX has one)."""

import csv
import os
import subprocess
import sys
import textwrap

import pytest

from rdher_jax.config import ConfigError, parse_args

TINY = ["env=FetchReach", "hidden=16", "layers=1", "batch_size=16", "n_batches=3",
        "buffer_size=1000", "n_test_rollouts=2", "n_cycles=3", "progress=false"]


def child(code: str, timeout: int = 600) -> str:
    env = {**os.environ, "JAX_NUM_CPU_DEVICES": "2", "JAX_PLATFORMS": "cpu"}
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                       capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-4000:]
    return p.stdout


def test_overlapped_cycles_store_the_sequential_episodes():
    """With an actor that cannot change what is collected (every action uniform random,
    random_eps=1), the overlapped cycles collect exactly the sequential cycles' episodes: the
    same rollout keys in the same order. Stored one cycle later, after one warm-up episode:
    overlap's buffer[1:] plus its pending episodes equal the sequential buffer, and both count
    the same env steps."""
    out = child(f"""
        import jax, numpy as np
        from rdher_jax.config import parse_args, resolve
        from rdher_jax.executor import build, Executor, overlap_devices
        from rdher_jax.program import hparams_from_config
        args = {TINY!r} + ["random_eps=1.0", "run_dir=/tmp/unused-overlap"]
        got = {{}}
        for overlap in (False, True):
            cfg = resolve(parse_args(args + [f"overlap={{str(overlap).lower()}}"]))
            devices, other = overlap_devices(None)
            _, program = build(cfg)
            batch = Executor(program, 1, devices, vmapped=False,
                             overlap=(cfg.n_cycles, other) if overlap else None)
            hp = jax.tree.map(lambda x: x[None], hparams_from_config(cfg))
            ts = batch.init(jax.random.PRNGKey(3)[None], hp)
            for _ in range(2):
                ts, m = batch.epoch(ts, hp)
            got[overlap] = jax.device_get(ts)
        seq, ovl = got[False], got[True]
        n = int(seq.env_steps[0]) // 50
        assert int(ovl.env_steps[0]) == int(seq.env_steps[0]), (ovl.env_steps, seq.env_steps)
        for f in ("obs", "ag", "g", "action"):
            a = np.asarray(getattr(seq.buffer, f))[0, :n]
            stored = np.asarray(getattr(ovl.buffer, f))[0, :n]
            pend = np.asarray(getattr(ovl.pending.episode, f))[0]
            b = np.concatenate([stored[pend.shape[0]:], pend])
            np.testing.assert_array_equal(a, b, err_msg=f)
            assert not np.array_equal(stored[:pend.shape[0]], a[:pend.shape[0]])  # the warm-up
        print("OK", n)
    """)
    assert out.startswith("OK "), out
    assert int(out.split()[1]) == 2 * 3 * 2  # 2 epochs x 3 cycles x 2 envs (the default)


@pytest.mark.slow
def test_overlap_run_resumes_to_the_same_rows(tmp_path):
    """The pending episodes are part of the checkpoint: 2 epochs then a resume to 3 give the
    rows of 3 epochs in one go (every column but wall_time)."""
    def rows(d):
        with open(d / "metrics.csv", newline="") as f:
            return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]

    a, b = tmp_path / "a", tmp_path / "b"
    child(f"""
        import sys
        from rdher_jax import train
        args = {TINY!r} + ["overlap=true"]
        assert train.main(args + ["epochs=3", "run_dir={a}"]) == 0
        assert train.main(args + ["epochs=2", "run_dir={b}"]) == 0
        assert train.main(["resume={b}", "epochs=3", "progress=false"]) == 0
    """)
    assert len(rows(a)) == 3 and rows(a) == rows(b)


@pytest.mark.slow
def test_overlap_cli_sets_up_its_second_device(tmp_path):
    """The CLI asks JAX for the second host device itself (no environment variable), also when
    it resumes an overlap run, and records overlap in config.yaml."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_NUM_CPU_DEVICES"}
    d = tmp_path / "run"
    for extra in (["overlap=true", "epochs=1", f"run_dir={d}"], [f"resume={d}", "epochs=2"]):
        args = [*TINY, *extra] if extra[0] == "overlap=true" else extra
        p = subprocess.run([sys.executable, "-m", "rdher_jax.train", *args], env=env,
                           capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr[-3000:]
    assert "overlap: true" in (d / "config.yaml").read_text()


def test_overlap_needs_two_host_devices():
    import jax

    from rdher_jax.executor import overlap_devices

    if len(jax.devices()) >= 2:
        pytest.skip("this process has two devices")
    with pytest.raises(ConfigError, match="second host device"):
        overlap_devices(None)
    assert parse_args(["overlap=true"]).overlap is True
    assert parse_args([]).overlap is False


# The overlapped cycle itself is checked by test_overlapped_cycles_store_the_sequential_episodes.
@pytest.mark.slow
@pytest.mark.parametrize("vmapped", [False, True])
def test_split_init_is_init_overlap(vmapped):
    """The driver starts an overlapped run as two programs (the state, cacheable, then the first
    episodes by the cycles' own collect program); that is ``program.init`` (init_overlap) in
    one: the same state and the same first episodes, bit for bit."""
    out = child(f"""
        import jax, numpy as np
        from rdher_jax.config import parse_args, resolve
        from rdher_jax.executor import build, OverlapEpoch, overlap_devices
        from rdher_jax.program import hparams_from_config
        cfg = resolve(parse_args({TINY!r} + ["overlap=true", "run_dir=/tmp/unused-overlap"]))
        devices, other = overlap_devices(None)
        _, program = build(cfg)
        hp = jax.tree.map(lambda x: x[None], hparams_from_config(cfg))
        keys = jax.random.PRNGKey(7)[None]
        ref = jax.jit(jax.vmap(program.init))(keys, hp)
        got = OverlapEpoch(program, {vmapped}, devices[0], other, cfg.n_cycles).init(keys, hp)
        a, b = jax.tree.leaves(jax.device_get(ref)), jax.tree.leaves(jax.device_get(got))
        assert jax.tree.structure(ref) == jax.tree.structure(got)
        assert all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))
        assert np.asarray(got.pending.episode.obs).shape[:2] == (1, cfg.num_envs)
        print("ok")
    """)
    assert out.strip().endswith("ok")


def test_a_preset_that_sets_overlap_names_itself_in_the_error(monkeypatch):
    """On devices overlap cannot use (here: one CPU device; on a GPU: not a CPU), a run whose
    preset turned overlap on is told which key to add."""
    import jax

    from rdher_jax import config as config_mod
    from rdher_jax.executor import executor_for

    if len(jax.devices()) >= 2:
        pytest.skip("this process has two devices")
    monkeypatch.setitem(config_mod.PRESETS, "ov", config_mod.Preset("test", {"overlap": True}))
    cfg = config_mod.resolve(parse_args(["preset=ov", "env=FetchReach"]))
    with pytest.raises(ConfigError, match=r"second host device.*preset=ov sets overlap=true.*"
                       r"add overlap=false"):
        executor_for([cfg])


@pytest.mark.parametrize("settings, threads", [
    ([], None), (["overlap=true"], 1), (["overlap=true", "physics_threads=2"], 2),
    (["physics_threads=3"], 3)])
def test_the_physics_takes_one_thread_beside_an_overlapped_learner(settings, threads):
    """overlap=true: the native physics steps on one host thread (its device's core), unless
    physics_threads says otherwise; without overlap it takes every usable core."""
    from rdher_jax.envs.native import _cpu_threads

    from rdher_jax import executor
    from rdher_jax.config import resolve

    cfg = resolve(parse_args(["env=FetchReach", *settings]))
    env, _ = executor.build(cfg)
    assert env.backend.num_threads == (threads or _cpu_threads())


def test_physics_threads_must_be_positive():
    from rdher_jax.config import resolve

    with pytest.raises(ConfigError, match="physics_threads must be >= 1"):
        resolve(parse_args(["physics_threads=0"]))
