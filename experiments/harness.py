"""What every benchmark script shares: its command line, the host, interleaved timing, the files.

A benchmark script parses its arguments with :func:`parser` (``--out``, ``--repeats``,
``--quick`` and ``--limits-script`` where it takes them, plus its own flags), calls
``rdher_jax.startup.setup`` in ``main`` before anything touches a JAX device, times with
:class:`Bench` (or :func:`interleave`, for measurements that are not one jitted call) and
writes ``<out>.md`` and ``<out>.json`` with :func:`write_results`. :func:`seconds` times one
call, and :class:`Stamps` stamps each call of a function called from elsewhere (a host callback
inside a jitted program): the time inside it and the time between two calls.

Timing is interleaved because this machine's speed drifts (other processes, clocks): variants
compared with each other are measured within seconds of each other, in an order rotated every
repeat so that none always runs first (after a pause) or last, and medians are reported.

Importing this module imports neither JAX nor the package: start-up comes first.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


# ---- the command line


def parser(script: str, description: str, *, out: str | Path | None = None,
           repeats: int | None = None, quick: str | None = None,
           limits: bool = False, out_help: str | None = None) -> argparse.ArgumentParser:
    """The common argparse base for ``experiments/<script>.py``.

    Args:
      script: the script's file name (``bench_cycle.py``), for usage lines and default paths.
      description: the first line of the script's docstring.
      out: the default of ``--out`` (a path whose suffix is replaced by ``.md`` and ``.json``;
        default ``experiments/results/<script stem>.md``).
      repeats: if given, ``--repeats`` with this default (interleaved repeats, median).
      quick: if given, ``--quick`` with this help (what the smallest run does).
      limits: add ``--limits-script`` (a machine-ceilings script run first, recorded).
      out_help: ``--out``'s help where it is not one results file (e.g. a folder of them).
    """
    ap = argparse.ArgumentParser(prog=f"python experiments/{script}", description=description)
    ap.add_argument("--out", type=Path,
                    default=Path(out) if out else RESULTS / f"{Path(script).stem}.md",
                    help=out_help or "results file (.md; the .json beside it)")
    if repeats is not None:
        ap.add_argument("--repeats", type=int, default=repeats,
                        help="interleaved repeats (medians)")
    if quick is not None:
        ap.add_argument("--quick", action="store_true", help=quick)
    if limits:
        ap.add_argument("--limits-script", default=None, metavar="PATH",
                        help="a machine-limits script to run first and record (its ceilings)")
    return ap


def command(script: str, argv: Sequence[str] | None = None) -> str:
    """The command line as the results file shows it: absolute paths by their names only (they
    name this machine, not the measurement)."""
    argv = sys.argv[1:] if argv is None else argv
    return " ".join(["python", f"experiments/{script}",
                     *(Path(a).name if a.startswith("/") else shlex.quote(a) for a in argv)])


def say(line: str) -> None:
    """Print a progress line now (stdout is a pipe when a script runs under another)."""
    print(line, flush=True)


# ---- the host


# The packages a benchmark's figures depend on, in the order a results page lists them.
PACKAGES = ("jax", "jaxlib", "numpy", "mujoco", "mujoco-mjx", "mjbatch", "gymnasium",
            "gymnasium-robotics")


def versions(packages: Sequence[str] = PACKAGES) -> dict[str, str | None]:
    """The installed version of each package (None where it is not installed;
    ``rdher_jax.runlog.package_versions``). Imports no JAX: for a process that must not start
    JAX's backend."""
    from rdher_jax.runlog import package_versions

    return package_versions(packages)


def host() -> dict[str, Any]:
    """This machine, its load and the package versions (``rdher_jax.outputs.host_info``, with
    those of :data:`PACKAGES` it lacks), with the cores this process may use and the load
    average: on a shared machine the figures are read against them. Call after start-up (it
    starts JAX's backend)."""
    from rdher_jax.outputs import host_info

    info = host_info()
    affinity = info.pop("cpu_affinity")  # named "affinity" in the benchmarks' files
    return {**info, "versions": {**versions(), **info["versions"]},
            "affinity": affinity, "loadavg": list(os.getloadavg())}


def machine(h: Mapping[str, Any]) -> str:
    """A host in a few words for a results file's first paragraph."""
    jax = h["versions"].get("jax")
    return (f"{h['processor'] or h['machine']} ({h['affinity']} usable of {h['cpu_count']} "
            f"CPUs), JAX {jax}, {h['jax_backend']}")


def machine_limits(script: str | None) -> dict | None:
    """Run a machine-ceilings script (``--limits-script``): its table (stdout) and its figures
    (the JSON it writes to ``--json PATH``), or None without one. A script that fails stops the
    benchmark (``CalledProcessError``) before anything is measured."""
    if not script:
        return None
    t0 = time.perf_counter()
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        p = subprocess.run([sys.executable, script, "--json", f.name], capture_output=True,
                           text=True, timeout=600, check=True)
        figures = json.loads(Path(f.name).read_text() or "{}")
    return {"script": Path(script).name, "table": p.stdout.strip(), "figures": figures,
            "seconds": time.perf_counter() - t0}


# ---- interleaved repeats


def rotated(names: Sequence[Hashable], r: int) -> list:
    """``names`` in the order of repeat ``r``: rotated by ``r``, so each leads once in turn."""
    if not names:
        return []
    k = r % len(names)
    return [*names[k:], *names[:k]]


def interleave(groups: Mapping[str, Sequence[Hashable]] | Sequence[Hashable], repeats: int,
               measure: Callable[[Hashable], Any],
               progress: Callable[[int], Any] | None = None) -> dict[Hashable, list]:
    """Measure every name once per repeat, group after group, each group in the rotated order
    of :func:`rotated`; returns each name's measurements in repeat order. ``measure`` may
    return a time or anything else (a child process's figures)."""
    if not isinstance(groups, Mapping):
        groups = {"main": list(groups)}
    out: dict[Hashable, list] = {n: [] for names in groups.values() for n in names}
    for r in range(repeats):
        for names in groups.values():
            for n in rotated(list(names), r):
                out[n].append(measure(n))
        if progress is not None:
            progress(r)
    return out


def quartiles(xs: Sequence[float]) -> tuple[float, float]:
    """First and third quartiles (both the value itself for one)."""
    if len(xs) < 2:
        return xs[0], xs[0]
    q = statistics.quantiles(xs, n=4, method="inclusive")
    return q[0], q[2]


def spread(xs: Sequence[float]) -> dict[str, float]:
    """Median, fastest (the least disturbed repeat), quartiles and range of a list of times."""
    q1, q3 = quartiles(xs)
    return {"median": statistics.median(xs), "best": min(xs), "q1": q1, "q3": q3,
            "max": max(xs), "n": len(xs)}


def seconds(fn: Callable, *args: Any, clock: Callable[[], float] = time.perf_counter) -> float:
    """Seconds one call of ``fn(*args)`` takes, its device work waited for."""
    t0 = clock()
    _block(fn(*args))
    return clock() - t0


class Stamps:
    """A function wrapped so that each call's start and end are stamped: the time spent inside
    it, and between two calls the time spent elsewhere (wrap a host callback: the time between
    its calls is the compiled program's own work around it).

    Call it as the function; ``clear`` before each measurement. ``clock``: seconds (a test's
    fake).
    """

    def __init__(self, fn: Callable, clock: Callable[[], float] = time.perf_counter):
        self.fn, self.clock = fn, clock
        self.starts: list[float] = []
        self.ends: list[float] = []

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.starts.append(self.clock())
        out = self.fn(*args, **kwargs)
        self.ends.append(self.clock())
        return out

    def clear(self) -> None:
        self.starts, self.ends = [], []

    def durations(self) -> list[float]:
        """Seconds inside each call."""
        return [e - s for s, e in zip(self.starts, self.ends, strict=True)]

    def gaps(self, group: int | None = None) -> list[float]:
        """Seconds from the end of each call to the start of the next. With ``group``, calls
        come in groups of that many consecutive calls (a rollout's steps) and only the gaps
        inside a group count (not those from one group's last call to the next's first)."""
        return [self.starts[i + 1] - self.ends[i] for i in range(len(self.ends) - 1)
                if group is None or i % group != group - 1]

    def mean_call(self) -> float:
        """Mean seconds inside a call (NaN without one)."""
        return _mean(self.durations())

    def mean_gap(self, group: int | None = None) -> float:
        """Mean of :meth:`gaps` (NaN without one)."""
        return _mean(self.gaps(group))


def _mean(xs: Sequence[float]) -> float:
    return statistics.fmean(xs) if xs else math.nan


def donated(fn: Callable, state: Any, *args: Any) -> Callable[[], Any]:
    """A thunk for :class:`Bench` over ``fn(state, *args) -> (state, out)`` whose state is
    donated (a training cycle that updates its replay buffer in place): each call carries the
    new state into the next."""
    box = [state]

    def call():
        res = fn(box[0], *args)
        box[0] = res[0]
        return res

    return call


class Bench:
    """Interleaved timing of jitted functions, with medians.

    Each measurement runs a function ``inner`` times (calibrated to about ``min_time`` seconds;
    once with the default 0) and keeps the time per call divided by ``per``. Functions are
    timed in groups; in each repeat every group runs once, in an order rotated by the repeat,
    so that variants compared with each other (one group) are measured within seconds of each
    other. ``log``: where progress lines go (None: nowhere); ``clock``: seconds (a test's fake).
    """

    def __init__(self, min_time: float = 0.0, log: Callable[[str], Any] | None = say,
                 clock: Callable[[], float] = time.perf_counter):
        self.min_time, self.log, self.clock = min_time, log, clock
        self.fns: dict[str, tuple] = {}
        self.groups: dict[str, list[str]] = {}
        self.inner: dict[str, int] = {}
        self.compile_s: dict[str, float] = {}
        self.times: dict[str, list[float]] = {}

    def add(self, name: str, f: Callable, *args: Any, per: int = 1, group: str = "main") -> None:
        """Compile (the first call, timed: ``compile_s``) and, with a ``min_time``, calibrate
        (a second call) ``f(*args)``. ``per``: calls of the timed unit inside one call of ``f``
        (times are divided by it)."""
        t0 = self.clock()
        _block(f(*args))
        self.compile_s[name] = one = self.clock() - t0
        if self.min_time > 0:  # without one, a call more would only cost time
            t0 = self.clock()
            _block(f(*args))
            one = self.clock() - t0
        self.inner[name] = max(1, math.ceil(self.min_time / max(one, 1e-6)))
        self.fns[name] = (f, args, per)
        self.groups.setdefault(group, []).append(name)
        self.times[name] = []
        if self.log:
            self.log(f"  compiled {name}: {self.compile_s[name]:.1f} s, one call "
                     f"{one * 1e3:.2f} ms")  # with compilation, without a min_time

    def _time(self, name: str) -> float:
        f, args, per = self.fns[name]
        n = self.inner[name]
        t0 = self.clock()
        for _ in range(n):
            _block(f(*args))
        return (self.clock() - t0) / n / per

    def run(self, repeats: int) -> None:
        """``repeats`` interleaved rounds over every group (appends to the times)."""
        done = interleave(self.groups, repeats, self._time,
                          (lambda r: self.log(f"  repeat {r + 1}/{repeats} done"))
                          if self.log else None)
        for name, ts in done.items():
            self.times[name] += ts

    def med(self, name: str) -> float:
        return statistics.median(self.times[name])

    def best(self, name: str) -> float:
        return min(self.times[name])

    def spread(self, name: str) -> dict[str, float]:
        return spread(self.times[name])

    def ratios(self, num: str | list[str], den: str) -> list[float]:
        """Per repeat: sum of the times of ``num`` / time of ``den``."""
        num = [num] if isinstance(num, str) else num
        return [sum(self.times[n][r] for n in num) / self.times[den][r]
                for r in range(len(self.times[den]))]

    def ratio(self, num: str | list[str], den: str) -> float:
        """Median over repeats of the paired ratio."""
        return statistics.median(self.ratios(num, den))

    def ratio_quartiles(self, num: str | list[str], den: str) -> tuple[float, float]:
        """First and third quartiles of the paired ratios over repeats."""
        return quartiles(self.ratios(num, den))


def _block(x: Any) -> Any:
    """Wait for a result's device work (a no-op for host values): a jitted call returns
    before its work is done."""
    if "jax" in sys.modules:
        return sys.modules["jax"].block_until_ready(x)
    return x


# ---- the results files


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A markdown table's lines (cells already formatted)."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(str(c) for c in row) + " |" for row in rows)]


def write_results(out: str | Path, title: str, blocks: Sequence[str | Sequence[str]],
                  data: Mapping[str, Any], *, command: str | None = None,
                  host: Mapping[str, Any] | None = None, echo: bool = True) -> str:
    """Write ``<out>.md`` (``# title``, then the blocks: a paragraph, or a list of lines such
    as a :func:`table`, separated by blank lines) and ``<out>.json`` (``data``, with the
    command and host beside it). Returns the markdown; prints it unless ``echo`` is False.
    Both files come from the same figures, so the table and the JSON cannot disagree."""
    out = Path(out)
    parts = [f"# {title}"]
    for b in blocks:
        parts.append(b if isinstance(b, str) else "\n".join(b))
    text = "\n\n".join(parts) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text, encoding="utf-8")
    doc = {**({"command": command} if command else {}), **({"host": host} if host else {}),
           **data}
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=str) + "\n",
                                        encoding="utf-8")
    if echo:
        print(text)
    return text
