"""Orbax checkpoints: round trips, one step per slot, atomicity under SIGKILL, clear errors."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from rdher_jax.checkpoint import Checkpointer, CheckpointError


@struct.dataclass
class Inner:
    w: jax.Array
    b: jax.Array


@struct.dataclass
class State:
    params: Inner
    opt: dict
    buffer: np.ndarray
    key: jax.Array  # raw uint32 key
    typed_key: jax.Array  # new-style typed key
    step: jax.Array
    extras: tuple
    name: str = struct.field(pytree_node=False, default="ddpg")


def make_state(v: float, n: int = 1000) -> State:
    return State(
        params=Inner(w=jnp.full((4, 3), v), b=jnp.arange(3.0) + v),
        opt={"mu": jnp.zeros((4, 3)) + v, "count": jnp.int32(int(v))},
        buffer=np.full((n, 7), v, np.float32),
        key=jax.random.PRNGKey(int(v)),
        typed_key=jax.random.key(int(v) + 1),
        step=jnp.asarray(int(v), jnp.int64 if jax.config.jax_enable_x64 else jnp.int32),
        extras=(jnp.ones(2) * v, np.int64(5)),
    )


def assert_tree_equal(a: object, b: object) -> None:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        if jax.dtypes.issubdtype(getattr(x, "dtype", None), jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def steps(ck: Checkpointer, slot: str) -> list[str]:
    return sorted(p.name for p in (ck.directory / slot).iterdir())


def test_round_trip_and_one_step_per_slot(tmp_path: Path) -> None:
    ck = Checkpointer(tmp_path)
    assert ck.latest_epoch() is None and ck.best_epoch() is None and ck.best_meta() is None
    with pytest.raises(CheckpointError, match="no checkpoint"):
        ck.restore_latest(make_state(0.0))
    ck.save_latest(1, make_state(1.0), {"test_success": np.float32(0.25), "env_steps": 100})
    ck.save_latest(2, make_state(2.0), {"test_success": 0.5, "loss": float("nan")})
    ck.save_best(1, {"actor": make_state(1.0).params}, {"test_success": 0.75})
    assert steps(ck, "latest") == ["2"] and steps(ck, "best") == ["1"]
    assert (ck.latest_epoch(), ck.best_epoch()) == (2, 1)
    assert ck.best_meta() == {"test_success": 0.75}
    ck.close()

    fresh = Checkpointer(tmp_path)  # a new process would see the same
    epoch, state, meta = fresh.restore_latest(make_state(0.0))
    assert epoch == 2 and meta["test_success"] == 0.5 and np.isnan(meta["loss"])
    assert_tree_equal(state, make_state(2.0))
    assert isinstance(state, State) and isinstance(state.buffer, np.ndarray)
    assert isinstance(state.params.w, jax.Array)
    epoch, policy, meta = fresh.restore_best({"actor": make_state(0.0).params})
    assert epoch == 1 and meta == {"test_success": 0.75}
    assert_tree_equal(policy, {"actor": make_state(1.0).params})
    # Abstract templates work too: no need to allocate a buffer just to restore into it.
    abstract = jax.eval_shape(lambda: make_state(0.0))
    # (eval_shape would narrow the int64 scalar to int32 and the buffer is numpy, so those two
    # are spelled out.)
    abstract = abstract.replace(
        buffer=jax.ShapeDtypeStruct((1000, 7), np.float32),
        extras=(abstract.extras[0], np.int64(0)),
    )
    assert fresh.restore_latest(abstract)[0] == 2
    fresh.close()


def test_resume_rewrites_abandoned_epochs(tmp_path: Path) -> None:
    ck = Checkpointer(tmp_path)
    ck.save_latest(5, make_state(5.0), {})
    ck.save_best(6, {"w": jnp.ones(2)}, {"test_success": 1.0})
    ck.save_latest(3, make_state(3.0), {})  # orbax alone would silently skip an older step
    assert ck.latest_epoch() == 3 and steps(ck, "latest") == ["3"]
    ck.save_latest(3, make_state(4.0), {})  # same epoch again replaces it
    assert_tree_equal(ck.restore_latest(make_state(0.0))[1], make_state(4.0))
    ck.discard_after(3)
    assert ck.best_epoch() is None and ck.latest_epoch() == 3
    ck.close()


def test_template_mismatch_is_a_clear_error(tmp_path: Path) -> None:
    ck = Checkpointer(tmp_path)
    ck.save_latest(1, make_state(1.0), {})
    cases = [
        (make_state(0.0, n=999), "buffer has shape (1000, 7) in the checkpoint but (999, 7)"),
        (
            make_state(0.0).replace(params=Inner(w=jnp.zeros((4, 3), jnp.int32), b=jnp.zeros(3))),
            "params.w has dtype float32 in the checkpoint but int32",
        ),
        (
            make_state(0.0).replace(opt={"mu": jnp.zeros((4, 3))}),
            "opt.count in the checkpoint but not in the template",
        ),
        (
            make_state(0.0).replace(opt={"mu": jnp.zeros((4, 3)), "count": 0, "nu": 0.0}),
            "opt.nu missing from the checkpoint",
        ),
    ]
    for template, fragment in cases:
        with pytest.raises(CheckpointError) as info:
            ck.restore_latest(template)
        assert fragment in str(info.value) and "\n" not in str(info.value)
    ck.close()


def test_leftovers_of_interrupted_saves_are_ignored_and_cleaned(tmp_path: Path) -> None:
    ck = Checkpointer(tmp_path)
    ck.save_latest(1, make_state(1.0), {"e": 1})
    ck.save_latest(2, make_state(2.0), {"e": 2})
    ck.close()
    latest = tmp_path / "checkpoints" / "latest"
    # A save killed mid-write (orbax's temporary name), an older step whose deletion was
    # interrupted, and a half-deleted directory of our own.
    (latest / "3.orbax-checkpoint-tmp" / "state.orbax-checkpoint-tmp").mkdir(parents=True)
    (latest / "3.orbax-checkpoint-tmp" / "state.orbax-checkpoint-tmp" / "junk").write_text("x")
    (latest / "1").mkdir(exist_ok=True)
    (latest / ".deleting-7-abcd").mkdir()

    reader = Checkpointer(tmp_path, read_only=True)  # a reader deletes nothing
    epoch, state, meta = reader.restore_latest(make_state(0.0))
    assert (epoch, meta) == (2, {"e": 2})
    assert_tree_equal(state, make_state(2.0))
    assert len(list(latest.iterdir())) == 4
    with pytest.raises(CheckpointError, match="read-only"):
        reader.save_latest(3, make_state(3.0), {})
    reader.close()

    writer = Checkpointer(tmp_path)
    assert sorted(p.name for p in latest.iterdir()) == ["2"]
    writer.save_latest(3, make_state(3.0), {"e": 3})
    assert writer.restore_latest(make_state(0.0))[2] == {"e": 3}
    writer.close()


CHILD = textwrap.dedent(
    """
    import sys
    import numpy as np
    from rdher_jax.checkpoint import Checkpointer

    ck = Checkpointer(sys.argv[1])
    data = np.random.default_rng(0).random(4_000_000, dtype=np.float32)  # 16 MB, incompressible
    epoch = 1
    while True:
        print(f"saving {epoch}", flush=True)
        ck.save_latest(epoch, {"buffer": data + epoch, "epoch": np.int32(epoch)}, {"epoch": epoch})
        print(f"saved {epoch}", flush=True)
        epoch += 1
    """
)


def test_sigkill_during_save_keeps_previous_checkpoint(tmp_path: Path) -> None:
    """Kill a writer at several points of its save loop; every kill leaves a restorable step."""
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    proc = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "run")],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        # Wait until one save has completed and the next one has begun, then kill mid-save.
        line = ""
        while not line.startswith("saving 2"):
            line = proc.stdout.readline()
            assert line, "writer exited early"
        time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    latest = tmp_path / "run" / "checkpoints" / "latest"
    left = sorted(p.name for p in latest.iterdir())
    template = {"buffer": np.zeros(4_000_000, np.float32), "epoch": np.int32(0)}
    base = np.random.default_rng(0).random(4_000_000, dtype=np.float32)
    for read_only in (True, False):  # a reader, then a resuming writer that tidies up
        ck = Checkpointer(tmp_path / "run", read_only=read_only)
        epoch, state, meta = ck.restore_latest(template)
        assert meta == {"epoch": epoch} and int(state["epoch"]) == epoch >= 1, left
        np.testing.assert_array_equal(state["buffer"], base + epoch)
        ck.close()
    assert not [p for p in latest.iterdir() if not p.name.isdigit()], left
