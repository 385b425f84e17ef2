"""Run directory, metrics CSV, plot, atomic JSON and TensorBoard writers."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from rdher_jax.config import Config, ConfigError, default_run_dir
from rdher_jax.runlog import (
    LEADING_FIELDS,
    MetricsCSV,
    TBWriter,
    check_dir_usable,
    check_fresh_dir,
    check_resume_dir,
    make_dir,
    metric_fields,
    plot_success,
    write_json_atomic,
    write_text_atomic,
)

METRIC_FIELDS = LEADING_FIELDS


def _row(epoch: int) -> dict:
    return {
        "epoch": epoch,
        "env_steps": 1000 * epoch,
        "updates": 40 * epoch,
        "wall_time": 1.5 * epoch,
        "test_success": np.float32(epoch / 10),
        "train_success": epoch / 20,
        "critic_loss": 0.1,
        "actor_loss": -0.2,
        "q_mean": float("nan"),
    }


def _leftovers(directory: Path) -> list[str]:
    return [p.name for p in directory.iterdir() if p.name.endswith(".tmp")]


def test_fresh_and_resumed_dirs(tmp_path: Path) -> None:
    run = tmp_path / "a" / "b"
    assert make_dir(run) == run and run.is_dir()
    assert make_dir(run) == run  # existing but empty is fine
    (run / "metrics.csv").write_text("x\n")
    with pytest.raises(ConfigError, match="exists and is not empty; pass resume="):
        make_dir(run)
    with pytest.raises(ConfigError, match="has no config.yaml"):
        check_resume_dir(run)
    (run / "config.yaml").write_text("env: FetchReach\n")
    check_resume_dir(run)
    with pytest.raises(ConfigError, match="does not exist"):
        check_resume_dir(tmp_path / 'missing')
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="not a directory"):
        make_dir(tmp_path / 'file')
    with pytest.raises(ConfigError, match="cannot create run_dir .*file is not a directory"):
        make_dir(tmp_path / 'file' / 'x')
    with pytest.raises(ConfigError, match="has no config.yaml"):
        check_resume_dir(tmp_path / 'a')


def test_unusable_dirs_leave_nothing_behind(tmp_path: Path) -> None:
    before = sorted(tmp_path.rglob("*"))
    check_dir_usable(tmp_path / "new" / "deeper", "run_dir")  # usable: created, then removed
    check_fresh_dir(tmp_path / 'other' / 'run')
    assert sorted(tmp_path.rglob("*")) == before
    for bad in ("/proc/x/y", "/sys/rdher-test"):
        with pytest.raises(ConfigError, match="cannot create run_dir") as info:
            make_dir(bad)
        assert "\n" not in str(info.value)
        assert not Path(bad).exists()


def test_concurrent_checks_of_sibling_dirs(tmp_path: Path, monkeypatch) -> None:
    """Two processes checking sweep directories under one new parent: the other's cleanup
    removes the shared parent between this check's two mkdirs. The check must still pass
    (it did not: 'cannot create sweep_dir ...: No such file or directory')."""
    shared, target = tmp_path / "runs", tmp_path / "runs" / "a"
    real_mkdir, removed = Path.mkdir, []

    def mkdir(self, *args, **kwargs):
        if self == target and not removed:
            shared.rmdir()  # the other process's cleanup, just before this mkdir
            removed.append(shared)
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    check_dir_usable(target, "sweep_dir")
    monkeypatch.undo()
    assert removed and not target.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only directories")
def test_read_only_dirs_are_refused(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    (ro / "config.yaml").write_text("env: FetchReach\n")
    ro.chmod(0o555)
    try:
        with pytest.raises(ConfigError, match="cannot create run_dir .*Permission denied"):
            make_dir(ro / 'a' / 'b')
        with pytest.raises(ConfigError, match="is not writable"):
            check_resume_dir(ro)
        assert sorted(p.name for p in ro.iterdir()) == ["config.yaml"]
    finally:
        ro.chmod(0o755)


def test_unwritable_dirs_are_refused_for_root_too(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The same refusals as above, with the filesystem's answer simulated (root bypasses
    permission bits, and the suite may run as root)."""
    real_mkdir, real_write = Path.mkdir, Path.write_bytes

    def mkdir(self, *a, **kw):
        if self.name == "b":
            raise PermissionError(13, "Permission denied")
        return real_mkdir(self, *a, **kw)

    def write_bytes(self, data):
        if self.name.startswith(".write-probe-"):
            raise OSError(30, "Read-only file system")
        return real_write(self, data)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    with pytest.raises(ConfigError, match="cannot create run_dir .*Permission denied"):
        make_dir(tmp_path / 'a' / 'b' / 'c')
    assert list(tmp_path.iterdir()) == []  # 'a' was created to find out, and removed
    monkeypatch.setattr(Path, "write_bytes", write_bytes)
    with pytest.raises(ConfigError, match="run_dir .* is not writable: Read-only file system"):
        make_dir(tmp_path / 'x' / 'y')
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text("env: FetchReach\n")
    with pytest.raises(ConfigError, match="resume directory .* is not writable"):
        check_resume_dir(tmp_path / 'run')
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["config.yaml"]


def test_metric_fields_keep_the_leading_columns_first() -> None:
    names = ["test_success", "train_success", "critic_loss", "actor_loss", "q_mean",
             "env_steps", "updates", "frac_her", "bias_real"]
    assert metric_fields(names) == (*LEADING_FIELDS, "frac_her", "bias_real")
    assert metric_fields(["updates", "x"]) == ("epoch", "updates", "wall_time", "x")


def test_default_run_dir_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    path = make_dir(default_run_dir(Config(env="FetchSlide", seed=4)))
    assert path.parent == Path("runs") and path.name.startswith("FetchSlide-her-s4-")
    assert (tmp_path / path).is_dir()


def test_metrics_csv_append_reopen_truncate(tmp_path: Path) -> None:
    path = tmp_path / "metrics.csv"
    log = MetricsCSV(path, METRIC_FIELDS)
    assert path.read_text() == ",".join(METRIC_FIELDS) + "\n"
    for e in range(1, 4):
        log.append(_row(e))
    rows = MetricsCSV(path, METRIC_FIELDS).rows()  # reopening continues the same file
    assert [r["epoch"] for r in rows] == ["1", "2", "3"]
    assert rows[1]["test_success"] == "0.2" and rows[0]["q_mean"] == "nan"
    log.append({"epoch": 4, "env_steps": 4000})  # missing columns stay empty
    assert log.rows()[-1]["test_success"] == ""
    with pytest.raises(ValueError):
        log.append({"epoch": 5, "bogus": 1})
    assert len(log.rows()) == 4  # the rejected row wrote nothing
    assert log.truncate_after(2) == 2
    assert [r["epoch"] for r in log.rows()] == ["1", "2"]
    assert log.truncate_after(7) == 0
    log.append(_row(3))
    assert [r["epoch"] for r in log.rows()] == ["1", "2", "3"]
    assert _leftovers(tmp_path) == []


def test_metrics_csv_torn_line_and_header_mismatch(tmp_path: Path) -> None:
    path = tmp_path / "metrics.csv"
    log = MetricsCSV(path, ["epoch", "x"])
    log.append({"epoch": 1, "x": 0.5})
    with open(path, "a") as f:
        f.write("2,0.")  # a row cut short by a crash
    log = MetricsCSV(path, ["epoch", "x"])
    assert log.rows() == [{"epoch": "1", "x": "0.5"}]
    log.append({"epoch": 2, "x": 0.25})
    assert path.read_text() == "epoch,x\n1,0.5\n2,0.25\n"
    with pytest.raises(ValueError, match="has columns"):
        MetricsCSV(path, ["epoch", "y"])
    with pytest.raises(ValueError, match="has columns"):
        MetricsCSV(path, ["epoch", "y"], extend=True)  # x would be lost
    log = MetricsCSV(path, ["epoch", "x", "y"], extend=True)  # a metric was added
    assert path.read_text() == "epoch,x,y\n1,0.5,\n2,0.25,\n"
    log.append({"epoch": 3, "x": 1, "y": 2})
    assert MetricsCSV(path, ["epoch", "x", "y"]).rows()[-1] == {"epoch": "3", "x": "1", "y": "2"}
    path.write_text("epoch,x\n1,0.5\n")
    path.write_text("epo")  # even the header was torn
    assert MetricsCSV(path, ["epoch", "x"]).rows() == []
    assert path.read_text() == "epoch,x\n"


def test_plot_success(tmp_path: Path) -> None:
    # Other test files (the experiment reports) may have imported pyplot already.
    pyplot_before = "matplotlib.pyplot" in sys.modules
    log = MetricsCSV(tmp_path / "metrics.csv", METRIC_FIELDS)
    png = tmp_path / "success.png"
    plot_success(log.path, png, "empty")  # header only: still a valid image
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for e in range(1, 6):
        log.append(_row(e))
    log.append({"epoch": 6, "env_steps": 6000})  # blank success cells are skipped
    plot_success(log.path, png, "FetchReach her s0")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert _leftovers(tmp_path) == []
    assert pyplot_before or "matplotlib.pyplot" not in sys.modules  # plotting needs no pyplot


def test_write_json_atomic(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "summary.json"
    write_json_atomic(path, {"a": np.float32(0.5), "b": np.arange(3), "c": Path("x")})
    assert json.loads(path.read_text()) == {"a": 0.5, "b": [0, 1, 2], "c": "x"}
    with pytest.raises(TypeError):
        write_json_atomic(path, {"bad": object()})
    assert json.loads(path.read_text())["a"] == 0.5  # the old file survived the failure
    assert _leftovers(path.parent) == []
    write_text_atomic(path, "{}")
    assert path.read_text() == "{}"
    assert path.stat().st_mode & 0o044  # readable by others under a usual umask


def test_tensorboard_writer(tmp_path: Path) -> None:
    pytest.importorskip("tensorboardX")
    tb = TBWriter(tmp_path)
    tb.scalars({"test_success": np.float32(0.5), "epoch": 1, "note": "skipped"}, step=1)
    tb.flush()
    tb.close()
    assert tb.backend == "tensorboardX"
    assert any(p.name.startswith("events.out.tfevents") for p in (tmp_path / "tb").iterdir())


def test_tensorboard_missing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for mod in ("tensorboardX", "torch", "torch.utils.tensorboard", "tensorflow"):
        monkeypatch.setitem(sys.modules, mod, None)  # makes the import raise ImportError
    with pytest.raises(ConfigError) as info:
        TBWriter(tmp_path)
    assert "pip install tensorboardX" in str(info.value) and "\n" not in str(info.value)
