"""Run-directory outputs: the metrics CSV, the success plot, atomic JSON and TensorBoard.

Everything here is written so that a run killed at any instant leaves readable files: the CSV
is appended one fsync'd row at a time, and whole-file outputs are replaced atomically.
"""

import contextlib
import csv
import io
import json
import math
import os
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rdher_jax.config import ConfigError

# The first columns of metrics.csv, in this order; any other field of the trainer's
# EpochMetrics follows them in declaration order (see metric_fields).
LEADING_FIELDS: tuple[str, ...] = (
    "epoch",
    "env_steps",
    "updates",
    "wall_time",
    "test_success",
    "train_success",
    "critic_loss",
    "actor_loss",
    "q_mean",
)
# Columns the training loop adds to the trainer's metrics.
LOOP_FIELDS: tuple[str, ...] = ("epoch", "wall_time")



def package_versions(packages: Sequence[str]) -> dict[str, str | None]:
    """The installed version of each package (None where it is not installed), read from the
    installed metadata: importing none of them."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for pkg in packages:
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out

def metric_fields(names: Iterable[str]) -> tuple[str, ...]:
    """The CSV columns for an epoch's metric ``names`` (e.g. the fields of ``EpochMetrics``).

    :data:`LEADING_FIELDS` come first (those that are among ``names`` or :data:`LOOP_FIELDS`),
    then the remaining names in the order given, so that new metrics only ever add columns.
    """
    names = list(names)
    have = set(names) | set(LOOP_FIELDS)
    lead = [f for f in LEADING_FIELDS if f in have]
    return tuple(lead + [n for n in dict.fromkeys(names) if n not in lead])


def _os_reason(e: OSError) -> str:
    return e.strerror or type(e).__name__


def check_dir_usable(path: str | Path, what: str) -> None:
    """Raise a one-line ConfigError unless ``path`` is, or can be created as, a directory this
    process can write files into. Leaves nothing behind: directories it had to create to find
    out are removed again, and so is its probe file.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what} {path} exists and is not a directory")
    missing: list[Path] = []
    p = path.absolute()
    while not p.exists() and not p.is_symlink() and p != p.parent:
        missing.append(p)
        p = p.parent
    if not p.is_dir():
        raise ConfigError(f"cannot create {what} {path}: {p} is not a directory")
    created: list[Path] = []
    try:
        for d in reversed(missing):
            try:
                # parents=True: another process checking a sibling directory at the same time
                # may have removed a parent this loop created (its own check's cleanup).
                d.mkdir(parents=True)
            except FileExistsError:
                continue  # made by another process meanwhile: not ours to remove
            except OSError as e:
                raise ConfigError(f"cannot create {what} {path}: {_os_reason(e)}") from None
            created.append(d)
        probe = path / f".write-probe-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as e:
            raise ConfigError(f"{what} {path} is not writable: {_os_reason(e)}") from None
    finally:
        for d in reversed(created):
            with contextlib.suppress(OSError):
                d.rmdir()


def check_fresh_dir(path: str | Path, what: str = "run_dir") -> None:
    """Raise a one-line ConfigError unless ``path`` can become a new output directory: absent
    or empty, and writable (checked by :func:`check_dir_usable`, which leaves nothing behind)."""
    path = Path(path)
    if path.is_dir() and any(path.iterdir()):
        raise ConfigError(
            f"{what} {path} exists and is not empty; pass resume={path} to continue it "
            f"or choose another {what}"
        )
    check_dir_usable(path, what)


def check_resume_dir(path: str | Path, marker: str = "config.yaml") -> None:
    """Raise a one-line ConfigError unless ``path`` is a writable output directory holding
    ``marker`` (the file that every run or sweep directory starts with)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"cannot resume: {path} does not exist")
    if not path.is_dir():
        raise ConfigError(f"cannot resume: {path} is not a directory")
    if not (path / marker).is_file():
        raise ConfigError(f"cannot resume: {path} has no {marker}, so it is no run directory")
    check_dir_usable(path, "resume directory")


def make_dir(path: str | Path, what: str = "run_dir") -> Path:
    """Create ``path`` (and its parents) after :func:`check_fresh_dir`; a failure is a
    one-line ConfigError that leaves no directory behind."""
    path = Path(path)
    check_fresh_dir(path, what)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # only if something changed since the check
        raise ConfigError(f"cannot create {what} {path}: {_os_reason(e)}") from None
    return path


class DirLock:
    """An exclusive lock on ``<dir>/.lock`` (``fcntl.flock``) while a process writes a run or
    sweep directory: a second process started on the same directory (a resume while the run
    still trains) would rewind the metrics and checkpoints under the first. The kernel drops
    the lock with the process, so a killed run leaves nothing to clean up."""

    def __init__(self) -> None:
        self._file: Any = None

    def hold(self, path: str | Path, what: str = "run_dir") -> None:
        """Take the lock on ``path`` (once; later calls do nothing), or raise a one-line
        ConfigError naming the process that holds it."""
        if self._file is not None:
            return
        try:
            import fcntl
        except ImportError:  # not a POSIX system: no lock
            return
        f = open(Path(path) / ".lock", "a+", encoding="utf-8")  # noqa: SIM115 (held open)
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            pid = f.read().strip() or "unknown"
            f.close()
            raise ConfigError(f"{what} {path} is in use by another process (pid {pid}); two "
                              "processes writing one directory corrupt it: wait for that one "
                              "to end, or stop it, then resume") from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._file = f

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing the file drops the lock
            self._file = None


def _fsync_dir(path: Path) -> None:
    # Makes a rename durable; some filesystems refuse to open directories, which is harmless.
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def _atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    The body must create the temporary file. It is hidden (dot prefix) and in the same
    directory, so that os.replace is a rename within one filesystem.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Not mkstemp: its 0600 mode would survive the rename; open() honours the umask.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` so that readers see the old or the new file, never a part."""
    with _atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_default(x: Any) -> Any:
    """JSON fallback for numpy/jax scalars and arrays (they expose item/tolist)."""
    if hasattr(x, "tolist"):
        return x.tolist()
    if hasattr(x, "item"):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"object of type {type(x).__name__} is not JSON serializable")


def write_json_atomic(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically; numpy/jax values become Python numbers."""
    write_text_atomic(path, json.dumps(obj, indent=2, default=json_default) + "\n")


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if hasattr(v, "dtype"):  # numpy / jax scalars; str() of a jax array is "Array(...)"
        a = np.asarray(v)
        # numpy's str is the shortest text that round-trips *this* precision: a float32 0.2
        # is written as 0.2, not as its float64 widening 0.20000000298023224.
        return str(a[()]) if a.dtype.kind == "f" else a.item()
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return v


class MetricsCSV:
    """Per-epoch metrics appended to a CSV file, durable after every row.

    An existing file is continued; a torn last line left by a crash mid-write is dropped on
    open. Its header must equal ``fieldnames``, except that with ``extend=True`` a file whose
    columns are all among ``fieldnames`` (written before metrics were added) is rewritten with
    the new header, its old rows keeping empty cells in the new columns.
    """

    def __init__(self, path: str | Path, fieldnames: Sequence[str], extend: bool = False) -> None:
        self.path = Path(path)
        self.fieldnames = list(fieldnames)
        if len(set(self.fieldnames)) != len(self.fieldnames):
            raise ValueError(f"duplicate CSV column names: {self.fieldnames}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.path.exists() or self.path.stat().st_size == 0:
            self._rewrite([])
            return
        self._drop_torn_line()
        with open(self.path, newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), None)
        if header == self.fieldnames:
            return
        if extend and header and set(header) <= set(self.fieldnames):
            self._rewrite(self.rows())
            return
        raise ValueError(
            f"{self.path} has columns {header}, expected {self.fieldnames}; "
            "it belongs to a different version of the trainer"
        )

    def _drop_torn_line(self) -> None:
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1
            with open(self.path, "rb+") as f:
                f.truncate(keep)
                os.fsync(f.fileno())
            if keep == 0:  # not even the header survived
                self._rewrite([])

    def _encode(self, rows: Sequence[Mapping[str, Any]], header: bool) -> str:
        buf = io.StringIO()
        w = csv.DictWriter(buf, self.fieldnames, extrasaction="raise", lineterminator="\n")
        if header:
            w.writeheader()
        for row in rows:
            w.writerow({k: _cell(v) for k, v in row.items()})
        return buf.getvalue()

    def _rewrite(self, rows: Sequence[Mapping[str, Any]]) -> None:
        write_text_atomic(self.path, self._encode(rows, header=True))

    def append(self, row: Mapping[str, Any]) -> None:
        """Append one row (missing columns stay empty; unknown columns raise ValueError)."""
        line = self._encode([row], header=False)  # encode first: a bad row writes nothing
        # One write of the whole line: a crash leaves at most a torn last line, dropped on open.
        with open(self.path, "a", newline="", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def rows(self) -> list[dict[str, str]]:
        """All rows as dictionaries of strings."""
        with open(self.path, newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))

    def truncate_after(self, epoch: int) -> int:
        """Drop rows whose epoch is greater than ``epoch`` (a resumed run re-logs them).

        Returns the number of rows dropped. The file is replaced atomically.
        """
        if "epoch" not in self.fieldnames:
            raise ValueError("truncate_after needs an 'epoch' column")
        rows = self.rows()
        keep = [r for r in rows if r["epoch"] != "" and int(float(r["epoch"])) <= epoch]
        if len(keep) != len(rows):
            self._rewrite(keep)
        return len(rows) - len(keep)


def _read_series(csv_path: Path, x: str, ys: Sequence[str]) -> dict[str, tuple[list, list]]:
    """Columns ``ys`` against ``x``, skipping empty or unparsable cells."""
    out: dict[str, tuple[list, list]] = {y: ([], []) for y in ys}
    with open(csv_path, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            try:
                xv = float(row[x])
            except (KeyError, TypeError, ValueError):
                continue
            for y in ys:
                try:
                    yv = float(row[y])
                except (KeyError, TypeError, ValueError):
                    continue
                out[y][0].append(xv)
                out[y][1].append(yv)
    return out


def plot_success(csv_path: str | Path, png_path: str | Path, title: str) -> None:
    """Plot test and train success rate against environment steps into ``png_path``."""
    # Figure + Agg canvas directly, not pyplot: no global backend state, no GUI, thread-safe.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    series = _read_series(Path(csv_path), "env_steps", ("test_success", "train_success"))
    fig = Figure(figsize=(6.4, 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for name, style in (("test_success", "-o"), ("train_success", "--")):
        xs, ys = series[name]
        if xs:
            ax.plot(xs, ys, style, label=name.replace("_", " "), markersize=3)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right")
    fig.tight_layout()
    with _atomic_path(png_path) as tmp:
        fig.savefig(tmp, format="png")


def _summary_writer_cls() -> Any:
    """tensorboardX's or torch's SummaryWriter class, or None when neither imports."""
    try:
        from tensorboardX import SummaryWriter

        return SummaryWriter
    except ImportError:
        pass
    try:
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter
    except ImportError:
        return None


class TBWriter:
    """TensorBoard scalars under ``<run_dir>/tb``.

    Uses tensorboardX, else torch.utils.tensorboard, else tf.summary; with none installed the
    constructor raises a one-line ConfigError.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.logdir = Path(run_dir) / "tb"
        self._tf: Any = None
        cls = _summary_writer_cls()
        if cls is not None:
            # Positional: tensorboardX names the argument logdir, torch log_dir.
            self._writer: Any = cls(str(self.logdir))
            self.backend: str = cls.__module__.split(".")[0]
            return
        try:
            import tensorflow as tf
        except ImportError:
            raise ConfigError(
                "tensorboard=true needs tensorboardX (pip install tensorboardX), "
                "torch or tensorflow; none is installed"
            ) from None
        self._tf = tf
        self._writer = tf.summary.create_file_writer(str(self.logdir))
        self.backend = "tensorflow"

    def scalars(self, values: Mapping[str, Any], step: int) -> None:
        """Write every numeric value of ``values`` at ``step``; other values are skipped."""
        for tag, v in values.items():
            v = _cell(v)
            if isinstance(v, str) and v == "nan":
                v = math.nan
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            if self._tf is not None:
                with self._writer.as_default():
                    self._tf.summary.scalar(tag, float(v), step=step)
            else:
                self._writer.add_scalar(tag, float(v), global_step=step)

    def flush(self) -> None:
        """Push buffered events to disk."""
        self._writer.flush()

    def close(self) -> None:
        """Flush and release the event file."""
        self._writer.close()
