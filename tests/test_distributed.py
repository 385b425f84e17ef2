"""Multi-process sweeps (rdher_jax.distributed): processes on localhost, one CPU device each.

The slow tests start real processes through JAX's multi-controller runtime (gloo collectives)
and compare every run's metrics.csv with the same sweep in one process over 2 host devices.
"""

import csv
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rdher_jax import distributed
from rdher_jax.config import ConfigError

SWEEP = [sys.executable, "-m", "rdher_jax.sweep"]
TINY = ["env=FetchReach", "algo=rdher", "lambdas=[[1,1],[2,1]]", "seeds=2", "n_cycles=2",
        "n_batches=4", "batch_size=32", "buffer_size=2000", "n_test_rollouts=2", "hidden=32",
        "progress=false"]
RUNS = ["lr1_lh1_s0", "lr1_lh1_s1", "lr2_lh1_s0", "lr2_lh1_s1"]


def env(devices: int = 1) -> dict:
    # JAX_NUM_CPU_DEVICES is the option rdher_jax.startup sets (jax_num_cpu_devices).
    return {**os.environ, "JAX_PLATFORMS": "cpu", "JAX_NUM_CPU_DEVICES": str(devices)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args: list[str], n: int = 2, heartbeat: int = 100) -> list[subprocess.Popen]:
    port = free_port()
    return [subprocess.Popen(
        [*SWEEP, *args, f"coordinator=127.0.0.1:{port}", f"num_processes={n}",
         f"process_id={i}", f"heartbeat_timeout={heartbeat}", "init_timeout=120"],
        env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(n)]


def finish(procs: list[subprocess.Popen], timeout: float = 600) -> list[str]:
    outs = []
    for p in procs:
        out, _ = p.communicate(timeout=timeout)
        outs.append(out)
        assert p.returncode == 0, out[-3000:]
    return outs


def rows(d: Path, run: str) -> list[dict]:
    with open(d / run / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def reference(tmp: Path, epochs: int) -> Path:
    ref = tmp / "ref"
    subprocess.run([*SWEEP, *TINY, f"epochs={epochs}", f"sweep_dir={ref}"], env=env(2),
                   check=True, capture_output=True, timeout=600)
    return ref


# ------------------------------------------------------------------ no processes started

@pytest.mark.parametrize("keys, fragment", [
    ({"coordinator": "h:1", "num_processes": "2"}, "missing process_id"),
    ({"coordinator": "h", "num_processes": "2", "process_id": "0"}, "must be HOST:PORT"),
    ({"coordinator": "h:70000", "num_processes": "2", "process_id": "0"}, "must be HOST:PORT"),
    ({"coordinator": "h:1", "num_processes": "2", "process_id": "2"},
     "process_id must be < num_processes (2)"),
    ({"coordinator": "h:1", "num_processes": "0", "process_id": "0"},
     "num_processes must be >= 1"),
    ({"init_timeout": "0"}, "init_timeout must be >= 1"),
])
def test_process_keys_are_checked(keys, fragment):
    with pytest.raises(ConfigError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        distributed.parse(keys)


def test_one_process_and_no_cluster_is_not_distributed(monkeypatch):
    for k in ("OMPI_COMM_WORLD_SIZE", "SLURM_JOB_ID", "SLURM_NTASKS", "SLURM_STEP_NUM_TASKS"):
        monkeypatch.delenv(k, raising=False)
    assert not distributed.cluster_detected()
    assert not distributed.initialize(distributed.parse({}))
    assert not distributed.initialize(distributed.parse(
        {"coordinator": "h:1", "num_processes": "1", "process_id": "0"}))
    # A batch script's own python in a 4-task allocation is one process; srun's tasks are not.
    monkeypatch.setenv("SLURM_JOB_ID", "7")
    monkeypatch.setenv("SLURM_NTASKS", "4")
    assert not distributed.cluster_detected()
    monkeypatch.setenv("SLURM_STEP_NUM_TASKS", "4")
    assert distributed.cluster_detected()
    monkeypatch.setenv("SLURM_STEP_NUM_TASKS", "1")
    assert not distributed.cluster_detected()
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")
    assert distributed.cluster_detected()


def test_unreachable_coordinator_is_a_one_line_error(tmp_path):
    port = free_port()  # nothing listens there
    proc = subprocess.run(
        [*SWEEP, "env=FetchReach", f"sweep_dir={tmp_path / 's'}",
         f"coordinator=127.0.0.1:{port}", "num_processes=2", "process_id=1", "init_timeout=2"],
        env=env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "could not reach the coordinator" in lines[0], proc.stderr


def test_a_multi_process_sweep_names_its_directory(tmp_path):
    from rdher_jax import sweep

    with pytest.raises(ConfigError, match="needs sweep_dir="):
        sweep.parse_sweep_args(["env=FetchReach", "coordinator=h:1", "num_processes=2",
                                "process_id=0"])
    cmd = sweep.parse_sweep_args(["env=FetchReach", "coordinator=h:1", "num_processes=2",
                                  "process_id=1", f"sweep_dir={tmp_path / 's'}"])
    assert (cmd.processes.coordinator, cmd.processes.num_processes,
            cmd.processes.process_id) == ("h:1", 2, 1)


# ------------------------------------------------------------------ real processes

@pytest.mark.slow
def test_two_processes_equal_one_process_over_two_devices(tmp_path):
    """2 processes x 1 device: every run's rows equal the one-process sweep over 2 host
    devices, after a 2-process resume too; the files are a one-process sweep's, and a run's
    best policy loads in a plain one-process evaluate."""
    d = tmp_path / "multi"
    outs = finish(start([*TINY, "epochs=2", f"sweep_dir={d}"]))
    assert "process 1 of 2: runs lr2_lh1_s0, lr2_lh1_s1 done" in outs[1]
    assert "in 2 processes" in outs[0]
    finish(start([f"resume={d}", "epochs=3", "progress=false"]))
    ref = reference(tmp_path, 3)
    for run in RUNS:
        assert len(rows(d, run)) == 3
        assert rows(d, run) == rows(ref, run), run
    assert sorted(p.name for p in (d / "checkpoints").iterdir()) == ["latest-2-processes"]
    for f in ("summary.md", "summary.json", "sweep.yaml", "base_config.yaml", "run_info.json"):
        assert (d / f).is_file(), f
    # Resuming with another number of processes is refused, naming the number.
    one = subprocess.run([*SWEEP, f"resume={d}", "epochs=4"], env=env(), capture_output=True,
                         text=True, timeout=300)
    assert one.returncode == 2
    assert "resume it with num_processes=2, not with 1" in one.stderr
    ev = subprocess.run([sys.executable, "-m", "rdher_jax.evaluate", str(d / "lr2_lh1_s1"),
                         "episodes=2"], env=env(), capture_output=True, text=True, timeout=300)
    assert ev.returncode == 0, ev.stderr[-2000:]


@pytest.mark.slow
def test_a_killed_process_stops_the_sweep_and_resume_loses_nothing(tmp_path):
    d = tmp_path / "multi"
    procs = start([*TINY, "epochs=4", f"sweep_dir={d}"], heartbeat=5)
    csv_path = d / "lr1_lh1_s0" / "metrics.csv"
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        if csv_path.is_file() and len(csv_path.read_text().splitlines()) >= 3:  # 2 epochs
            break
        time.sleep(0.2)
    else:
        pytest.fail("the sweep never reached epoch 2")
    procs[1].send_signal(signal.SIGKILL)  # the supervisor: its child dies with it
    out, _ = procs[0].communicate(timeout=300)  # the heartbeat takes the survivor down
    assert procs[0].returncode == 1, out[-2000:]
    assert out.strip().splitlines()[-1].startswith(
        "error: the multi-process sweep stopped (coordinator 127.0.0.1:"), out[-2000:]
    procs[1].wait(timeout=60)
    finish(start([f"resume={d}", "progress=false"]))
    ref = reference(tmp_path, 4)
    for run in RUNS:
        assert rows(d, run) == rows(ref, run), run


@pytest.mark.slow
@pytest.mark.parametrize("ids, counts, codes, fragment", [
    # process_id 1 twice: the runtime aborts the duplicate (never joined) and the two it had
    # joined; one line each, exit 2 and 1
    ([0, 1, 1], [2, 2, 2], {2, 1}, None),
    # num_processes=3 but only two start: neither joins within init_timeout
    ([0, 1], [3, 3], {2}, "could not join the multi-process sweep (coordinator"),
    # the processes disagree on num_processes: the runtime lets them join with process 0's
    ([0, 1], [2, 3], {2}, "the processes disagree on num_processes: process 0 says 2, "
                          "process 1 says 3"),
])
def test_wrong_process_id_or_count_is_a_one_line_error(tmp_path, ids, counts, codes, fragment):
    port = free_port()
    procs = []
    for i, n in zip(ids, counts, strict=True):
        procs.append(subprocess.Popen(
            [*SWEEP, *TINY, f"sweep_dir={tmp_path / 's'}", f"coordinator=127.0.0.1:{port}",
             f"num_processes={n}", f"process_id={i}", "init_timeout=8", "heartbeat_timeout=5"],
            env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        time.sleep(1.0)  # process 0 first; the duplicate after the first process 1
    got = set()
    for p in procs:
        _, err = p.communicate(timeout=300)
        last = err.strip().splitlines()[-1]
        assert p.returncode in (1, 2) and last.startswith("error: ") and \
            "Traceback" not in last, err[-3000:]
        if fragment is not None:
            assert fragment in last, err[-3000:]
        if p.returncode == 2:
            assert "could not join" in last or "disagree" in last, last
        else:
            assert "the multi-process sweep stopped" in last, last
        got.add(p.returncode)
    assert got == codes


def test_a_process_zero_policy_save_restores_in_one_process(tmp_path, monkeypatch):
    """Process 0 of several saves a run's best policy as orbax's plain nested dicts and lists
    (``checkpoint._host_tree``); a one-process reader (evaluate) restores it into the learner's
    own classes: optax states with empty nodes, brax's UInt64 counters."""
    import jax
    import numpy as np

    from rdher_jax import checkpoint
    from rdher_jax.config import parse_args, resolve
    from rdher_jax.executor import build
    from rdher_jax.program import hparams_from_config

    cfg = resolve(parse_args(["hidden=8", "layers=1", "buffer_size=100", "batch_size=8"]))
    _, program = build(cfg)
    state = program.init(jax.random.PRNGKey(0), hparams_from_config(cfg))
    policy = jax.tree.map(np.asarray, jax.device_get(state.ddpg))
    with monkeypatch.context() as m:
        m.setattr(jax, "process_count", lambda: 2)
        plain = checkpoint._host_tree(policy)
    assert isinstance(plain, dict)
    ck = checkpoint.Checkpointer(tmp_path, latest=False)
    ck.save_best(1, plain, {"test_success": 0.5})
    epoch, back, meta = checkpoint.Checkpointer(tmp_path, read_only=True,
                                                latest=False).restore_best(policy)
    assert epoch == 1 and meta["test_success"] == 0.5
    assert jax.tree.structure(back) == jax.tree.structure(policy)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(policy), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_benchmark_script_over_two_processes(tmp_path):
    """experiments/benchmark.py takes the process flags: its sweeps run over both processes
    and process 0 alone collects the results and writes the report."""
    exp = Path(__file__).resolve().parents[1] / "experiments"
    port = free_port()
    out, runs = tmp_path / "out", tmp_path / "runs"
    procs = [subprocess.Popen(
        [sys.executable, str(exp / "benchmark.py"), "--profile", "tiny", "--algos", "her",
         "--out", str(out), "--runs-dir", str(runs), "--no-progress",
         "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
        env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)]
    outs = finish(procs)
    assert "wrote" in outs[0] and "wrote" not in outs[1]
    d = out / "benchmark" / "tiny" / "FetchReach" / "her"
    assert sorted(p.name for p in d.glob("s*.csv")) == ["s0.csv", "s1.csv"]
    assert (out / "benchmark" / "tiny" / "summary.md").is_file()
    sweep_dir = runs / "benchmark" / "tiny" / "FetchReach" / "her"
    assert (sweep_dir / "checkpoints" / "latest-2-processes").is_dir()
