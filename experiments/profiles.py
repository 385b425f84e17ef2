"""Budget profiles of the paper's experiments, and the sweep driver of ablation.py and benchmark.py.

A profile gives each task a :class:`Budget`: how many seeds, and the ``key=value`` training
settings every sweep of that task gets (the algorithm, the λ pairs and the seeds come from the
experiment). The profile's name, doc and the task's budget are written into every setting's
``run_info.json`` under ``experiments/results/``, so each table says what budget produced it.

- ``tiny``: FetchReach only, 2 epochs of 2 cycles, 4 updates of batch 32, 32-unit networks, 2
  seeds. A smoke test of the whole pipeline (the tests run it); learns nothing.
- ``cpu``: what a 2-core CPU finishes. FetchReach at the paper's learner settings (Table 1), 5
  seeds, 5 epochs of 10 cycles (5,000 env steps per run, the default of ``python -m
  rdher_jax.train`` for Reach, where HER and RDHER reach 0.9-1.0 test success). FetchPush
  (``--tasks FetchPush``): :data:`PUSH_CPU`, ``preset=fast`` for 500,000 env steps, 3 seeds.
- ``solve``: the recipe that solves FetchPush, FetchPickAndPlace and FetchSlide (:data:`SOLVE`):
  ``preset=fast`` with each task's own values and budget, 5 seeds.
- ``paper``: the paper's budget: every task, Table 1's settings, 5 seeds, 50 epochs (10 cycles
  each for Reach, 50 for the others). A CPU runs it: a 5-seed sweep is 13-26 min (Reach; CHER
  the most) and 1 h 36 min to 1 h 48 min (Slide and PickAndPlace, HER, DHER and RDHER) of one
  core beside another sweep (``run_info.json`` under ``experiments/results/benchmark/paper/``),
  on an Intel Xeon; a 3-seed Slide sweep 55-64 min there, 1 h 54 min on a slower AMD EPYC
  (beside another sweep and a test-suite run), where one seed alone, a piece of its own beside
  another on the second core, is about 42 min (about 50 s per epoch): use ``--first-seed`` to
  split a setting that does not fit in a sitting. FetchPush HER as five one-seed pieces on the
  AMD EPYC: 22 min 13 s per run; its RDHER as one 5-seed sweep there: 28 min 16 s per run
  (vmapping saves nothing with this learner on a CPU). Every task and algorithm's time per run
  is in RESULTS.md's Table 3, and what each experiment has cost in ``results/cost.md``.
  The paper does not state its epoch counts; 50 is ``n_epochs``'s default in the code it builds on
  (openai/baselines ``her/experiment/train.py``, mengf1/DHER ``train_dyreach.py``) and fits
  Table 3's wall clock (HER on Push: 3 h 30 min on one CPU core, i.e. 4.2 min per 50-cycle
  epoch; on Reach 46 min, 56 s per 10-cycle epoch).

Sweep directories (with checkpoints) live under ``<runs-dir>/<kind>/<profile>/<task>/<sweep>``
and are what makes a long experiment resumable: :func:`run_job` continues an unfinished sweep
(``resume=``), skips a finished one, and starts a missing one. A setting too long for one
sitting can be run in pieces of its seeds: ``--seeds 3`` for seeds 0-2, then ``--seeds 5
--first-seed 3`` for seeds 3-4 in ``<sweep>.s3-4``; collecting merges the pieces. A seed
trained already as a run of its own, of the same settings, becomes its piece with ``--seeds
K+1 --first-seed K --adopt RUN_DIR`` (:func:`adopt_job`, ``rdher_jax/adopt.py``: the configs
are compared key by key, and the piece is written as its sweep would be after the run's
epochs); the next call without ``--adopt`` resumes it.

On a many-core CPU the fastest layout is one run per core, each process pinned to its own
(:func:`run_pool`, ``--cores``): every seed of every sweep named becomes a one-seed piece
(``<sweep>`` for seed 0, ``<sweep>.s<K>-<K>`` for seed K), run in its own process pinned to a
free core of those listed, the next starting as one ends; each setting is collected as its
last piece ends. RESULTS.md (section 2) has the minutes of runs so pinned against one run
alone on both cores; a seed's rows do not depend on the layout (``tests/test_train.py``).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import os
import re
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rdher_jax.config import Config, ConfigError
from rdher_jax.runlog import write_text_atomic
from rdher_jax.startup import Startup, setup
from rdher_jax.summary import grid_keys, num, settings_markdown
from rdher_jax.tasks import MOVING_TASKS, PAPER_TASKS, TASK_NAMES
from rdher_jax.tasks import TASKS as TASK_TABLE

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "results"
DEFAULT_RUNS = HERE.parent / "runs" / "experiments"

TASKS: tuple[str, ...] = PAPER_TASKS
BENCHMARK_ALGOS: tuple[str, ...] = ("ddpg", "her", "cher", "dher", "rdher")
# Section 5.2: the pairs {1, 2}, {1, 4}, {0.5, 4} in both orders, as (lambda_r, lambda_h).
ABLATION_PAIRS: tuple[tuple[float, float], ...] = (
    (1.0, 2.0), (2.0, 1.0), (1.0, 4.0), (4.0, 1.0), (0.5, 4.0), (4.0, 0.5),
)
ALGO_LABELS: dict[str, str] = {"ddpg": "DDPG", "her": "HER", "cher": "CHER", "dher": "DHER",
                               "rdher": "RDHER", "archer": "ARCHER"}


@dataclass(frozen=True)
class Budget:
    """Seeds and shared ``key=value`` settings of every sweep of one task."""

    seeds: int
    settings: Mapping[str, Any]  # epochs None: not decided yet (a placeholder)
    note: str = ""
    placeholder: bool = False

    def resolved(self, epochs: int | None = None) -> dict[str, Any]:
        """The settings with ``epochs`` overridden; a ConfigError while it is still unset."""
        out = dict(self.settings)
        if epochs is not None:
            out["epochs"] = epochs
        if out.get("epochs") is None:
            raise ConfigError(f"this budget has no epoch count yet ({self.note}); set it in "
                              "experiments/profiles.py or pass --epochs N")
        return out


@dataclass(frozen=True)
class Profile:
    doc: str
    budgets: Mapping[str, Budget]
    default_tasks: tuple[str, ...]


# Table 1 of the paper (baselines' HER settings at one MPI worker) is the trainer's defaults; the
# keys that size a run are passed explicitly, so that every run's json records them.
PAPER_LEARNER: dict[str, Any] = {
    k: getattr(Config(), k)
    for k in ("num_envs", "n_batches", "batch_size", "buffer_size", "n_test_rollouts", "hidden",
              "layers")
}
TINY = Budget(2, {"epochs": 2, "n_cycles": 2, "n_batches": 4, "batch_size": 32,
                  "buffer_size": 2000, "n_test_rollouts": 2, "hidden": 32},
              "smoke test of the pipeline; learns nothing")
REACH_CPU = Budget(5, {"epochs": 5, "n_cycles": 10, **PAPER_LEARNER},
                   "the paper's learner; 5 epochs (5,000 env steps per run) in place of its 50")
# FetchPush on a 2-core CPU: preset=fast (see docs/performance.md, 'preset=fast'), 3 seeds, 200
# epochs of 50 one-episode cycles = 500,000 env steps per run, where preset=fast has reached test
# success 0.9 (experiments/results/bench_learning/summary.md). A setting of 3 seeds as one vmapped
# sweep took 1 h 41 min (HER) and about 2 h 10 min (RDHER, whose matching grows with the buffer)
# of one core, beside another sweep on the other core; on another day the same budget as
# one-seed pieces took 80-87 min per seed (beyond/cpu: rdher_f0.2, dher_f0.2), which is mostly
# this machine's day-to-day drift (the moving-goal sweeps below, vmapped, ran at that pace too);
# rdher_plain's seed 0 took 60 min; since then a sweep's delayed actor step stays a cond under
# vmap (1.24x faster epochs, docs/design.md) and DHER's merge takes one prefix sum (RDHER's
# epochs a further 1.38x). The
# committed reduced set is HER against RDHER at the paper's pair (--algos her rdher); the other
# three algorithms are about 2 hours each and the ablation's six weighted settings about 10 hours,
# and every sweep resumes where it stopped, so they can be finished over several sittings.
# dher_fraction=0.8 written out: the committed FetchPush rows were run when preset=fast kept the
# authors' share (it now takes 0.2), so that these sweeps resume and rerun as they ran.
# overlap=false likewise: preset=fast took overlap=true after these rows (and the moving-goal
# ones below) were run, sequentially; and n_critics=1: it took twin critics on Push after them.
PUSH_CPU = Budget(3, {"preset": "fast", "dher_fraction": 0.8, "overlap": False, "n_critics": 1,
                      "epochs": 200},
                  "preset=fast with the authors' dher_fraction=0.8, sequential (overlap=false), "
                  "200 epochs of 50 one-episode cycles (500,000 env steps per run)")
# The moving-goal tasks (experiments/moving_goals.py). FetchReachMoving: the paper's learner,
# where HER and DHER both reach 1.0 within 10 epochs. FetchPushMoving: preset=fast for 250,000
# env steps; a setting of 3 seeds took 1 h 44 min (HER) and 2 h 7 min (DHER, share 0.2) of one
# core (run_info.json in experiments/results/moving/cpu/).
REACH_MOVING_CPU = Budget(3, {"epochs": 8, "n_cycles": 10, **PAPER_LEARNER},
                          "the paper's learner; 8 epochs of 10 cycles (8,000 env steps per run)")
PUSH_MOVING_CPU = Budget(3, {"preset": "fast", "overlap": False, "epochs": 100},
                         "preset=fast, sequential (overlap=false), 100 epochs of 50 one-episode "
                         "cycles (250,000 env steps per run)")

# The recipe that solves the manipulation tasks (issue: Push and PickAndPlace to 97%, Slide to
# 80%, best policy retested on 100 episodes): preset=fast with each task's own values and budget
# (rdher_jax/tasks.py, Task.preset_values), 5 seeds, sequential (overlap=false) so that two runs
# share the two cores.
SOLVE_TASKS: tuple[str, ...] = ("FetchPush", "FetchPickAndPlace", "FetchSlide")
SOLVE = {t: Budget(5, {"preset": "fast", "overlap": False, **TASK_TABLE[t].preset_values["fast"]},
                   "preset=fast with the task's own values and budget (rdher_jax/tasks.py), "
                   "sequential (overlap=false)")
         for t in SOLVE_TASKS}

PROFILES: dict[str, Profile] = {
    "tiny": Profile("FetchReach smoke test: 2 epochs of 2 cycles, tiny networks, 2 seeds",
                    {"FetchReach": TINY}, ("FetchReach",)),
    "cpu": Profile("what a 2-core CPU finishes: FetchReach at the paper's settings for 5 epochs, "
                   "5 seeds; FetchPush (--tasks FetchPush) preset=fast for 200 epochs, 3 seeds; "
                   "the moving tasks: FetchReachMoving at the paper's settings for 8 epochs, "
                   "FetchPushMoving preset=fast for 100 epochs, 3 seeds",
                   {"FetchReach": REACH_CPU, "FetchPush": PUSH_CPU,
                    "FetchReachMoving": REACH_MOVING_CPU, "FetchPushMoving": PUSH_MOVING_CPU},
                   ("FetchReach",)),
    "paper": Profile(
        "the paper's budget, which a CPU can run (one run on one core of a 2-core CPU beside "
        "another, by the algorithm: Reach 2.6-5.2 min, Push 21-33, Slide 20-34, PickAndPlace "
        "19-27; each in RESULTS.md, Table 3, and cost.md): Table 1's settings, 50 epochs "
        "(Reach 10 cycles each, others 50), 5 seeds, every task",
        {**{t: Budget(5, {"epochs": 50, "n_cycles": TASK_TABLE[t].n_cycles, **PAPER_LEARNER},
                      "the paper's settings (epochs: see profiles.py)")
            for t in TASKS},
         # The moving tasks at the same learner and budget (250,000 env steps for Push), 3 seeds.
         **{t: Budget(3, {"epochs": 50, "n_cycles": TASK_TABLE[t].n_cycles, **PAPER_LEARNER},
                      "the paper's settings on a moving-goal task, 3 seeds")
            for t in MOVING_TASKS}},
        TASKS),
    "solve": Profile("the recipe that solves Push, PickAndPlace and Slide: preset=fast with each "
                     "task's own values and budget (Push 500,000 env steps, PickAndPlace "
                     "600,000, Slide 2,000,000), 5 seeds", SOLVE, SOLVE_TASKS),
}


def budget_for(profile: str, task: str) -> Budget:
    prof = PROFILES[profile]
    if task not in prof.budgets:
        raise ConfigError(f"profile {profile} has no budget for {task}; it has "
                          f"{', '.join(prof.budgets)}")
    return prof.budgets[task]


# ------------------------------------------------------------------ sweeps

@dataclass(frozen=True)
class Setting:
    """One curve: the runs of a sweep with one λ pair (or all of them when ``lambdas`` is None)."""

    name: str  # its results directory
    label: str
    algo: str
    lambdas: tuple[float, float] | None
    order: int  # position in tables and legends


@dataclass(frozen=True)
class Job:
    """One vmapped sweep: a task, an algorithm, its λ pairs x seeds, and the settings it feeds."""

    kind: str  # ablation | benchmark
    profile: str
    task: str
    name: str  # the sweep's directory name
    algo: str
    lambdas: tuple[tuple[float, float], ...] | None  # None: the config's default pair
    seeds: int
    settings: Mapping[str, Any]
    outputs: tuple[Setting, ...]
    runs_dir: Path
    budget: Budget
    extra: tuple[str, ...] = ()  # key=value tokens of this sweep alone (after the budget's)
    # Another experiment's sweep that this one's setting is read from (e.g. the ablation's HER
    # curve from the benchmark's HER sweep: the same program, seeds and budget). Such a sweep
    # is collected here, never run: its own script runs it.
    sweep_kind: str | None = None
    # > 0: this call runs only seeds first_seed..seeds-1, as a sweep of their own (a piece).
    first_seed: int = 0

    @property
    def _task_dir(self) -> Path:
        return self.runs_dir / (self.sweep_kind or self.kind) / self.profile / self.task

    @property
    def sweep_dir(self) -> Path:
        """The directory this call runs in: ``<name>``, or for a piece of the seeds
        ``<name>.s<first>-<last>``."""
        if self.first_seed:
            return self._task_dir / f"{self.name}.s{self.first_seed}-{self.seeds - 1}"
        return self._task_dir / self.name

    def piece_dirs(self) -> list[Path]:
        """Every existing sweep directory of this setting, whichever call ran it: the whole
        sweep's (``<name>``) first, then its pieces (``<name>.s<first>-<last>``) by first seed."""
        d = self._task_dir
        piece = re.compile(rf"{re.escape(self.name)}\.s(\d+)-(\d+)")
        found = sorted((int(m.group(1)), p) for p in (d.iterdir() if d.is_dir() else ())
                       if (m := piece.fullmatch(p.name)) and p.is_dir())
        return [p for p in [d / self.name, *(p for _, p in found)] if p.is_dir()]

    @property
    def borrowed(self) -> bool:
        return self.sweep_kind is not None and self.sweep_kind != self.kind

    @property
    def epochs(self) -> int:
        return int(self.settings["epochs"])

    def argv(self, progress: bool) -> list[str]:
        """The sweep's key=value arguments, without sweep_dir= / resume=."""
        out = [f"env={self.task}", f"algo={self.algo}"]
        # A key of the sweep's own replaces the budget's value in place (one value per key).
        own = dict(t.split("=", 1) for t in self.extra)
        out += [f"{k}={own.pop(k, v)}" for k, v in self.settings.items()]
        out += [t for t in self.extra if t.split("=", 1)[0] in own]
        if self.lambdas is not None:
            out.append("lambdas=[" + ",".join(f"[{num(a)},{num(b)}]" for a, b in self.lambdas)
                       + "]")
        if self.first_seed:
            out.append("seeds=[" + ",".join(map(str, range(self.first_seed, self.seeds))) + "]")
        else:
            out.append(f"seeds={self.seeds}")
        out.append(f"progress={str(progress).lower()}")
        return out


def make_jobs(kind: str, profile: str, tasks: Sequence[str], runs_dir: Path,
              seeds: int | None, epochs: int | None,
              sweeps: Callable[[str], list[tuple]], first_seed: int = 0) -> list[Job]:
    """One Job per (task, sweep) given by ``sweeps(task)`` -> [(name, algo, lambdas, outputs)],
    or ``(name, algo, lambdas, outputs, extra)`` with ``extra`` the sweep's own key=value
    tokens, or ``(..., extra, borrow)`` with ``borrow`` the kind of another experiment whose
    sweep of that name is read (at the budget's own seed count, as that experiment runs it).
    ``first_seed`` > 0 makes each sweep run here a piece: seeds first_seed..N-1 only."""
    jobs = []
    for task in tasks:
        b = budget_for(profile, task)
        settings = b.resolved(epochs)
        for name, algo, lambdas, outputs, *more in sweeps(task):
            extra = tuple(more[0]) if more else ()
            borrow = more[1] if len(more) > 1 else None
            n = b.seeds if borrow else (seeds or b.seeds)
            if first_seed and not borrow and first_seed >= n:
                raise ConfigError(f"--first-seed {first_seed} leaves no seed of {task}'s {n} "
                                  f"(seeds 0..{n - 1}); raise --seeds")
            jobs.append(Job(kind, profile, task, name, algo, lambdas, n, settings, outputs,
                            runs_dir, b, extra, borrow, 0 if borrow else first_seed))
    return jobs


# A named setting of a one-sweep-per-setting experiment (moving_goals.py, beyond.py): its
# label ("{pair}" in it stands for the task's paper pair, e.g. "(4, 0.5)"), algorithm, λ pairs
# (None: the task's paper pair), the sweep's own key=value tokens, and the experiment whose
# sweep of the algorithm's name it is read from (None: run here).
NamedSetting = tuple[str, str, tuple[tuple[float, float], ...] | None, tuple[str, ...],
                     str | None]

# DHER, and RDHER at the task's paper pair, at the authors' share of combined rows written out,
# for a profile whose budget takes another (solve: preset=fast's 0.2): rows of the benchmark's
# table (benchmark.py --settings) and settings of beyond.py.
AUTHORS_SHARE: dict[str, NamedSetting] = {
    "dher_f0.8": ("DHER, share 0.8 (the authors')", "dher", None, ("dher_fraction=0.8",), None),
    "rdher_f0.8": ("RDHER {pair}, share 0.8 (the authors')", "rdher", None,
                   ("dher_fraction=0.8",), None),
}


def pair_label(lambda_r: float, lambda_h: float) -> str:
    """A (λ_r, λ_h) pair as labels write it, e.g. "(4, 0.5)"."""
    return f"({num(lambda_r)}, {num(lambda_h)})"


def paper_pair(task: str) -> str:
    """The task's paper pair (λ_r, λ_h) as labels write it."""
    return pair_label(*TASK_TABLE[task].paper_lambdas)


def named_sweeps(table: Mapping[str, NamedSetting],
                 names: Sequence[str]) -> Callable[[str], list[tuple]]:
    """``sweeps(task)`` for :func:`make_jobs`: one sweep per name of ``table``, in the order
    given, named by the setting (a borrowed one by its algorithm, as the lending experiment
    names it), ordered in tables as ``table`` lists them."""
    def sweeps(task: str) -> list[tuple]:
        out = []
        for name in dict.fromkeys(names):
            label, algo, lambdas, extra, borrow = table[name]
            label = label.replace("{pair}", paper_pair(task))
            setting = Setting(name, label, algo, lambdas[0] if lambdas else None,
                              list(table).index(name))
            out.append((algo if borrow else name, algo, lambdas, (setting,), extra, borrow))
        return out

    return sweeps


def _run_seeds(sweep_dir: Path, epochs: int) -> tuple[set[int], set[int]]:
    """(every seed the sweep's summary lists, those with ``epochs`` epochs logged or
    diverged); both empty where it has no summary yet."""
    try:
        rows = json.loads((sweep_dir / "summary.json").read_text(encoding="utf-8"))["runs"]
    except (OSError, ValueError, KeyError):
        return set(), set()
    return ({int(r["seed"]) for r in rows},
            {int(r["seed"]) for r in rows
             if int(r.get("epochs", 0)) >= epochs or r.get("status", "ok") != "ok"})


def _finished(sweep_dir: Path, epochs: int) -> bool:
    """Every run of the sweep has ``epochs`` epochs logged, or has diverged."""
    seeds, done = _run_seeds(sweep_dir, epochs)
    return bool(seeds) and seeds == done


def sweep_args(job: Job, progress: bool) -> tuple[list[str], str]:
    """The sweep's arguments for this call and what it will do: start, resume or skip."""
    d = job.sweep_dir
    argv = job.argv(progress)
    if (d / "sweep.yaml").is_file():
        if _finished(d, job.epochs):
            return argv + [f"resume={d}"], "skip"
        return argv + [f"resume={d}"], "resume"
    if d.is_dir() and any(d.iterdir()):
        raise ConfigError(f"{d} exists but holds no sweep.yaml (a sweep stopped while it was "
                          "starting); remove it to start that sweep again")
    return argv + [f"sweep_dir={d}"], "start"


def run_job(job: Job, progress: bool, dry_run: bool = False, log=print) -> str:
    """Start, resume or skip one sweep; returns what it did. Bad arguments are ConfigErrors."""
    import shlex

    from rdher_jax import sweep as sw

    argv, action = sweep_args(job, progress)
    cmd = shlex.join(["python", "-m", "rdher_jax.sweep", *argv])
    if action == "skip":
        log(f"[{job.task} {job.name}] finished ({job.epochs} epochs): {job.sweep_dir}")
        return action
    spec = sw.parse_sweep_args(argv).plan  # validates everything before anything runs
    log(f"[{job.task} {job.name}] {action}{' (dry run)' if dry_run else ''}: {cmd}")
    if dry_run:
        return action
    try:
        out = sw.sweep(spec, argv, log=log)
    except sw.TrainingDiverged as e:  # every run diverged: its files keep the good epochs
        log(f"[{job.task} {job.name}] {e}")
        return "diverged"
    log(settings_markdown(spec.base, out.summary[1], grid_keys(spec.varies)).rstrip())
    return action


def _seeds_done(job: Job) -> set[int]:
    """The seeds some sweep directory of ``job``'s setting holds finished (or diverged)."""
    return set().union(*(_run_seeds(d, job.epochs)[1] for d in job.piece_dirs()))


def collected_seeds(job: Job, out_root: Path) -> set[int]:
    """The seeds ``job`` has collected, finished, into every setting it feeds under
    ``out_root``: each with its CSV and a ``run_info.json`` entry of all its epochs (or
    diverged). They are done even where no sweep directory holds them any more (checkpoints
    are never committed, so a study resumed on another machine has only these)."""
    done: set[int] | None = None
    for s in job.outputs:
        dest = out_root / job.kind / job.profile / job.task / s.name
        try:
            runs = json.loads((dest / "run_info.json").read_text(encoding="utf-8"))["runs"]
        except (OSError, ValueError, KeyError):
            return set()
        mine = {int(n[1:]) for n, r in runs.items()
                if re.fullmatch(r"s\d+", n) and (dest / f"{n}.csv").is_file()
                and (int(r.get("epochs", 0)) >= job.epochs or r.get("status", "ok") != "ok")}
        done = mine if done is None else done & mine
    return done or set()


def seed_pieces(job: Job, out_root: Path | None = None) -> list[Job]:
    """``job``'s seeds (first_seed..seeds-1) as one-seed pieces, but those finished already in
    any of the setting's sweep directories (a whole sweep's or a piece's) and, given
    ``out_root`` (``--keep-collected``), those collected there (:func:`collected_seeds`)."""
    import dataclasses

    done = _seeds_done(job) | (collected_seeds(job, out_root) if out_root else set())
    out = [dataclasses.replace(job, first_seed=k, seeds=k + 1)
           for k in range(job.first_seed, job.seeds) if k not in done]
    for p in out:  # seed 0's piece is the whole sweep's directory: it must hold seed 0 alone
        try:
            held = yaml_seeds(p.sweep_dir / "sweep.yaml")
        except OSError:
            continue
        if held != [p.first_seed]:
            raise ConfigError(f"{p.sweep_dir} is an unfinished sweep of seeds "
                              f"{', '.join(map(str, held))}, not a one-seed piece: finish it "
                              "without --cores")
    return out


def yaml_seeds(path: Path) -> list[int]:
    """The seeds a sweep directory's ``sweep.yaml`` runs."""
    import yaml

    return [int(k) for k in yaml.safe_load(path.read_text(encoding="utf-8"))["seeds"]]


# A pool piece's process: pinned to its core before JAX or the physics start their threads
# (both size their pools from the affinity), then one run_job.
_PIECE_MAIN = """
import os, pickle, sys
os.sched_setaffinity(0, {int(sys.argv[1])})
sys.path.insert(0, sys.argv[2])
import profiles
job = pickle.loads(sys.stdin.buffer.read())
profiles.setup(profiles.Startup())
profiles.run_job(job, False)
"""


def check_cores(cores: Sequence[int]) -> list[int]:
    """``--cores`` as given, or a ConfigError: each once, each one this process may run on."""
    allowed = sorted(os.sched_getaffinity(0))
    if len(set(cores)) != len(cores):
        raise ConfigError(f"--cores names a core twice: {' '.join(map(str, cores))}")
    bad = [c for c in cores if c not in allowed]
    if bad:
        raise ConfigError(f"--cores {' '.join(map(str, bad))}: this process may run on cores "
                          f"{', '.join(map(str, allowed))}")
    return list(cores)


def run_pool(jobs: Sequence[Job], cores: Sequence[int], dry_run: bool = False, log=print,
             poll_s: float = 2.0, finished: Callable[[Job], None] | None = None,
             out_root: Path | None = None) -> int:
    """Run every seed of ``jobs`` as a one-seed piece (:func:`seed_pieces`; given ``out_root``,
    not the seeds collected there, finished), each in a process
    of its own pinned to one of ``cores``, as many at once as there are cores, the next piece
    starting on the core the last one freed. Pieces go lowest seed first across the settings
    (every setting's seed 0, then every setting's seed 1, ...): a study cut short holds the same
    seeds of each setting, the unit of its paired comparisons, and settings compared by seed
    run side by side, under the same load. Each piece's output goes to ``<sweep dir>.log``.
    ``finished(job)`` is called as the last piece of a job ends (e.g. to collect it while the
    others run). A piece killed with the pool resumes from its checkpoint when the same command
    runs again (finished seeds are not run twice). Returns how many pieces failed."""
    import pickle
    import subprocess
    import sys
    import time

    pieces = {(j.task, j.name): (j, seed_pieces(j, out_root)) for j in jobs if not j.borrowed}
    if out_root is not None:
        for j in jobs:
            kept = sorted(k for k in collected_seeds(j, out_root) - _seeds_done(j)
                          if j.first_seed <= k < j.seeds) if not j.borrowed else []
            if kept:
                log(f"[{j.task} {j.name}] seed(s) {', '.join(map(str, kept))} collected in "
                    f"{out_root}, finished, no sweep directory: not run again")
    queue = sorted((p for _, ps in pieces.values() for p in ps), key=lambda p: p.first_seed)
    left = {key: len(ps) for key, (_, ps) in pieces.items()}
    log(f"pool: {len(queue)} one-seed piece(s) on core(s) {', '.join(map(str, cores))}"
        + (" (dry run)" if dry_run else ""))
    if dry_run:
        for p in queue:
            log(f"[{p.task} {p.name} s{p.first_seed}] {sweep_args(p, False)[1]}: {p.sweep_dir}")
        return 0
    here = str(Path(__file__).resolve().parent)
    running: dict[int, tuple[Any, Job, Any, float]] = {}
    failed = 0
    try:
        while queue or running:
            for c in cores:
                if c in running or not queue:
                    continue
                p = queue.pop(0)
                logf = p.sweep_dir.with_name(p.sweep_dir.name + ".log")
                logf.parent.mkdir(parents=True, exist_ok=True)
                out = open(logf, "ab")
                proc = subprocess.Popen([sys.executable, "-c", _PIECE_MAIN, str(c), here],
                                        stdin=subprocess.PIPE, stdout=out,
                                        stderr=subprocess.STDOUT)
                proc.stdin.write(pickle.dumps(p))
                proc.stdin.close()
                running[c] = (proc, p, out, time.monotonic())
                log(f"[{p.task} {p.name} s{p.first_seed}] core {c}: started, log {_rel(logf)}")
            time.sleep(poll_s if running else 0)
            for c, (proc, p, out, t0) in list(running.items()):
                rc = proc.poll()
                if rc is None:
                    continue
                out.close()
                del running[c]
                took = _duration(time.monotonic() - t0)
                if rc == 0:
                    log(f"[{p.task} {p.name} s{p.first_seed}] core {c}: done in {took}")
                else:
                    failed += 1
                    log(f"[{p.task} {p.name} s{p.first_seed}] core {c}: failed (exit {rc}) "
                        f"after {took}; see {_rel(p.sweep_dir)}.log")
                left[(p.task, p.name)] -= 1
                if finished is not None and not left[(p.task, p.name)]:
                    try:
                        finished(pieces[(p.task, p.name)][0])
                    except Exception as e:  # the other pieces train on; the end collects again
                        log(f"[{p.task} {p.name}] collecting failed ({type(e).__name__}: {e}); "
                            "the pieces go on")
    finally:
        for proc, _, out, _ in running.values():  # interrupted: the pieces stop with the pool
            proc.terminate()
            proc.wait()
            out.close()
    return failed


def adopt_job(job: Job, source: Path, dry_run: bool = False, log=print) -> Path:
    """Make ``source``, a run of its own (``python -m rdher_jax.train``), the sweep ``job``
    would run for its one seed (``--seeds K+1 --first-seed K``), as that sweep would be after
    the run's epochs; the next call without ``--adopt`` resumes it to the job's epochs and
    collects it as any piece (:mod:`rdher_jax.adopt`). Refused (a ConfigError, nothing written)
    unless the run is the same learning problem as the sweep's run, stopped at a checkpoint,
    and the sweep directory does not exist yet."""
    import dataclasses
    import shlex

    from rdher_jax import sweep as sw

    if job.borrowed:
        raise ConfigError(f"--adopt: {job.name} of {job.task} is the {job.sweep_kind} "
                          f"experiment's sweep; adopt it there")
    n = job.seeds - job.first_seed
    if n != 1:
        raise ConfigError(f"--adopt fills the sweep of one seed; this call's has {n} (seeds "
                          f"{job.first_seed}..{job.seeds - 1}): pass --seeds K+1 --first-seed K")
    from rdher_jax import adopt

    d = job.sweep_dir
    src = adopt.Source.read(source)
    adopt.refuse_existing(src, d)  # before the sweep's own check, which suggests resume=
    full = sw.parse_sweep_args([*job.argv(False), f"sweep_dir={d}"]).plan
    if len(full.runs) != 1:
        raise ConfigError(f"--adopt fills a sweep of one run; {job.name} of {job.task} has "
                          f"{len(full.runs)} per seed")
    adopt.check(src, d, full.runs[0])  # at the job's epochs: the run may not have more
    # The sweep this call would have run with --epochs <the run's>, after the run's epochs.
    at = dataclasses.replace(job, settings={**job.settings, "epochs": src.config.epochs})
    argv = [*at.argv(False), f"sweep_dir={d}"]
    plan = sw.parse_sweep_args(argv).plan
    log(f"[{job.task} {job.name}] adopt{' (dry run)' if dry_run else ''}: {source} "
        f"({src.epoch} of {job.epochs} epochs) as {d / plan.names[0]}, as if by: "
        f"{shlex.join(['python', '-m', 'rdher_jax.sweep', *argv])}")
    if dry_run:
        return d
    return adopt.adopt(src, plan, argv, sw.PROG, log=log)


# ------------------------------------------------------------------ results

HARDWARE_KEYS = ("backend", "scene", "jax_backend", "devices", "cpu_count", "cpu_affinity",
                 "machine", "processor", "python")


def _last_row(text: str) -> dict[str, str] | None:
    rows = list(csv.DictReader(io.StringIO(text)))
    return rows[-1] if rows else None


def _rel(p: Path) -> str:
    try:
        return os.path.relpath(p.resolve(), Path.cwd())
    except ValueError:  # another drive
        return str(p)


# The best policy of each finished run is tested on this many episodes, seeded with
# EVAL_SEED + the run's seed: root keys that no training run (seeds 0, 1, ...) starts from.
EVAL_EPISODES = 100
EVAL_SEED = 1_000_000
# --precise-episodes: the same policy tested once more on many episodes, seeded with
# PRECISE_SEED + the run's seed (apart from training, from the retest above and from the
# selection's 2,000,000 + seed), where a 100-episode retest's binomial noise (about 2 points of
# standard error near 95%) hides whether a seed plateaus or was unlucky.
PRECISE_SEED = 3_000_000


def best_policy_eval(run_dir: Path, seed: int, episodes: int,
                     cached: dict[str, Any] | None = None,
                     base: int = EVAL_SEED) -> dict[str, Any] | None:
    """Test success of ``run_dir``'s best-policy checkpoint over ``episodes`` episodes seeded
    with ``base`` + the run's seed ``seed`` (``rdher_jax.evaluate``); ``cached`` is returned as
    it is when it was made for the same checkpoint epoch, episodes and seed. None without a
    best-policy checkpoint."""
    from rdher_jax.checkpoint import Checkpointer
    from rdher_jax.evaluate import evaluate

    best = Checkpointer(run_dir, read_only=True).policy_epoch()
    if best is None:
        return None
    key = {"epoch": best, "episodes": episodes, "seed": base + seed}
    if cached and all(cached.get(k) == v for k, v in key.items()):
        return cached
    r = evaluate(run_dir, episodes=episodes, seed=base + seed)
    return {**key, "success": r["success"], "train_test_success": r["train_test_success"]}


def _adopted(info: Mapping[str, Any]) -> dict[str, Any]:
    """A sweep directory's record of the run it adopted (``--adopt``), if it adopted one."""
    return {"adopted": info["adopted"]} if "adopted" in info else {}


def _collected_pieces(meta: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The sweep directories a collected setting's runs came from (its run_info.json), each
    with the seeds it gave: a record written before pieces named their seeds gives them by its
    directory's name (``<name>.s<first>-<last>``, or seeds 0.. for the whole sweep's)."""
    seeds = set(meta.get("seeds") or ())
    pieces = meta.get("pieces")
    if pieces is None:  # one sweep directory
        sw = meta.get("sweep") or {}
        pieces = [{"dir": sw.get("dir"), "command": sw.get("command"), "runs": sw.get("runs"),
                   "wall_clock_s": meta.get("wall_clock_s"), "hardware": meta.get("hardware"),
                   "seeds": sorted(seeds)}]
    out = []
    for p in pieces:
        if "seeds" not in p:
            m = re.search(r"\.s(\d+)-(\d+)$", str(p.get("dir")))
            span = range(int(m[1]), int(m[2]) + 1) if m else range(int(p.get("runs") or 0))
            p = {**p, "seeds": sorted(seeds.intersection(span))}
        out.append(dict(p))
    return out


def collect(job: Job, out_root: Path, command: str, log=print,
            eval_episodes: int = EVAL_EPISODES, keep_collected: bool = False,
            precise_episodes: int = 0) -> list[Path]:
    """Copy each run's metrics.csv and a trimmed run_info.json into
    ``<out_root>/<kind>/<profile>/<task>/<setting>/`` (``s<seed>.csv``, ``run_info.json``).

    A run that has finished its epochs (or diverged) also gets its best policy tested on
    ``eval_episodes`` fresh episodes (:func:`best_policy_eval`; 0: not tested), recorded in
    run_info.json beside the best 10-episode epoch of its metrics. Only in a one-process run:
    the checkpoints of a multi-process sweep are tested by ``--collect-only`` afterwards.
    ``precise_episodes`` > 0: the same policy is also tested on that many episodes of a seed
    stream of their own (:data:`PRECISE_SEED`), recorded as ``best_policy_precise``; a test
    made before is kept while its run is unchanged, whatever this call's value.

    A setting run in pieces (``--first-seed``) is collected from all of them: each seed below
    ``job.seeds`` (a later piece, perhaps still running, waits for a collect that names it) from
    the first directory that holds it (the whole sweep's, then the pieces'), the wall clock
    summed over the pieces, each piece recorded under ``pieces`` with its seeds.

    ``keep_collected``: a seed (< the job's seeds) already collected into the setting's
    directory whose sweep directory is gone (a study run in pieces on machines that do not
    share a runs directory) is kept as it was, CSV, best-policy test and piece record; without
    it, a collected seed no sweep directory holds is removed. A kept piece whose other seeds
    are read again now keeps its share of the wall clock and runs, so none is counted twice.

    Small text files only; checkpoints stay in the sweep directory. Returns the setting dirs.
    """
    from rdher_jax import distributed

    loaded = []  # (sweep dir, its runs, its run_info) of the whole sweep and of each piece
    for p in job.piece_dirs():
        try:
            loaded.append((p, json.loads((p / "summary.json").read_text(encoding="utf-8"))["runs"],
                           json.loads((p / "run_info.json").read_text(encoding="utf-8"))))
        except (OSError, ValueError, KeyError):
            continue
    if job.borrowed and not loaded:
        return collect_borrowed_results(job, out_root, log)
    if not loaded:
        log(f"[{job.task} {job.name}] nothing to collect yet in {job.sweep_dir}")
        return []
    d, _, info = loaded[0]
    # Each seed from the directory where it has run the most epochs, the first of them on a tie
    # (the whole sweep before its pieces): a seed started again as a piece of its own, beside an
    # abandoned whole sweep that holds it too, is read from the piece.
    best: dict[tuple, dict[str, Any]] = {}
    for p, runs_p, _ in loaded:
        for r in runs_p:
            key = (r["lambda_r"], r["lambda_h"], r["seed"])
            if key in best:
                old = best[key]
                use = r if int(r.get("epochs", 0)) > int(old.get("epochs", 0)) else old
                log(f"[{job.task} {job.name}] seed {r['seed']} is in {_rel(old['_dir'])} "
                    f"({old.get('epochs', 0)} epochs) and {_rel(p)} ({r.get('epochs', 0)}): "
                    f"reading {_rel(use['_dir'] if use is old else p)}")
                if use is old:
                    continue
            best[key] = {**r, "_dir": p}
    # Only the seeds this collect names (0..seeds-1): a piece still running for a later seed
    # is not mixed into a summary of fewer.
    rows = [r for r in best.values() if int(r["seed"]) < job.seeds]
    later = sorted({int(r["seed"]) for r in best.values()} - {int(r["seed"]) for r in rows})
    if later:
        log(f"[{job.task} {job.name}] not collected: seed(s) {', '.join(map(str, later))}, "
            f"beyond --seeds {job.seeds}")
    written = []
    for s in job.outputs:
        mine = [r for r in rows
                if s.lambdas is None or (r["lambda_r"], r["lambda_h"]) == tuple(s.lambdas)]
        dest = out_root / job.kind / job.profile / job.task / s.name
        dest.mkdir(parents=True, exist_ok=True)
        runs: dict[str, Any] = {}
        walls: dict[Path, float] = {}
        try:
            before_meta = json.loads((dest / "run_info.json").read_text(encoding="utf-8"))
            before = before_meta["runs"]
        except (OSError, ValueError, KeyError):
            before_meta, before = {}, {}
        for r in mine:
            src = r["_dir"] / r["run"] / "metrics.csv"
            if not src.is_file():
                continue
            text = src.read_text(encoding="utf-8")
            last = _last_row(text)
            if last is None:
                continue
            write_text_atomic(dest / f"s{r['seed']}.csv", text)
            walls[r["_dir"]] = max(walls.get(r["_dir"], 0.0), float(last["wall_time"]))
            name = f"s{r['seed']}"
            runs[name] = {"epochs": int(last["epoch"]),
                          "env_steps": int(float(last["env_steps"])),
                          "status": r["status"],
                          "wall_clock_s": float(last["wall_time"])}
            done = int(last["epoch"]) >= job.epochs or r["status"] != "ok"
            if not done:
                log(f"[{job.task} {s.name} {name}] collected while under way: "
                    f"{last['epoch']} of {job.epochs} epochs (quoted.py leaves it out of "
                    "its figures until it finishes)")
            # The retest, and the longer test of the same policy (each kept from before while
            # the run has not changed, whatever this call asks for).
            for key, episodes, base, what in (
                    ("best_policy", eval_episodes, EVAL_SEED, "test"),
                    ("best_policy_precise", precise_episodes, PRECISE_SEED, "more")):
                cached = before.get(name, {}).get(key)
                if done and episodes > 0 and distributed.count() == 1:
                    ev = best_policy_eval(r["_dir"] / r["run"], int(r["seed"]), episodes,
                                          cached, base=base)
                    if ev is not None:
                        if ev is not cached:
                            log(f"[{job.task} {s.name} {name}] best policy (epoch "
                                f"{ev['epoch']}) on {episodes} {what} episodes: "
                                f"{ev['success']:.3f}")
                        runs[name][key] = ev
                elif cached is not None and done and \
                        before.get(name, {}).get("epochs") == runs[name]["epochs"]:
                    runs[name][key] = cached  # not tested now; the run has not changed
        kept: list[dict[str, Any]] = []  # pieces collected before whose directories are gone
        if keep_collected and before_meta:
            for piece in _collected_pieces(before_meta):
                names = [f"s{k}" for k in piece["seeds"]
                         if f"s{k}" not in runs and k < job.seeds and f"s{k}" in before
                         and (dest / f"s{k}.csv").is_file()]
                if not names:
                    continue
                if len(names) < len(piece["seeds"]):  # its other seeds are read again now
                    share = len(names) / len(piece["seeds"])
                    piece = {**piece, "seeds": [int(n[1:]) for n in names],
                             "runs": round(int(piece.get("runs") or 0) * share),
                             "wall_clock_s": float(piece.get("wall_clock_s") or 0.0) * share}
                for n in names:
                    runs[n] = before[n]
                kept.append(piece)
                log(f"[{job.task} {s.name}] kept {', '.join(names)}, collected before from "
                    f"{piece['dir']}, whose sweep directory is gone")
        for stale in dest.glob("s*.csv"):
            if stale.stem not in runs:
                stale.unlink()
        pair = (mine[0]["lambda_r"], mine[0]["lambda_h"]) if mine else (
            (before_meta.get("lambda_r"), before_meta.get("lambda_h")) if kept else (None, None))
        # Runs of one sweep are one program: they share its wall clock (first epoch's
        # compilation included, process start and env build not). Pieces add up.
        wall = sum(walls.values()) + sum(float(p.get("wall_clock_s") or 0.0) for p in kept)
        n_runs = sum(i.get("n_runs") or 0 for p, _, i in loaded if p in walls) \
            + sum(int(p.get("runs") or 0) for p in kept)
        meta = {
            "kind": job.kind, "profile": job.profile, "task": job.task, "setting": s.name,
            "label": s.label, "algo": s.algo, "order": s.order,
            "lambda_r": pair[0], "lambda_h": pair[1],
            "seeds": sorted(int(k[1:]) for k in runs),
            "budget": {"profile": job.profile, "profile_doc": PROFILES[job.profile].doc,
                       "seeds": job.seeds, "settings": dict(job.settings),
                       "note": job.budget.note, "placeholder": job.budget.placeholder},
            "command": command,
            "extra": list(job.extra),
            "sweep": {"name": job.name, "dir": _rel(d), "command": info.get("command"),
                      "runs": n_runs or info.get("n_runs"),
                      "program": info.get("program"),
                      "state_bytes_per_run": info.get("state_bytes_per_run"),
                      **_adopted(info)},
            "hardware": {k: info.get(k) for k in HARDWARE_KEYS},
            "versions": info.get("versions"),
            "runs": runs,
            "wall_clock_s": wall,
            "wall_clock_per_run_s": wall / n_runs if n_runs else None,
        }
        if len(walls) + len(kept) > 1:  # run in pieces (--first-seed): each piece's record
            meta["pieces"] = kept + [
                {"dir": _rel(p), "command": i.get("command"), "runs": i.get("n_runs"),
                 "wall_clock_s": walls[p], "hardware": {k: i.get(k) for k in HARDWARE_KEYS},
                 "seeds": sorted({int(r["seed"]) for r in mine if r["_dir"] == p
                                  and f"s{r['seed']}" in runs}), **_adopted(i)}
                for p, _, i in loaded if p in walls]
        write_text_atomic(dest / "run_info.json", json.dumps(meta, indent=1, sort_keys=True) + "\n")
        written.append(dest)
    log(f"[{job.task} {job.name}] collected {len(job.outputs)} setting(s) into "
        f"{out_root / job.kind / job.profile / job.task}")
    return written


def collect_borrowed_results(job: Job, out_root: Path, log=print) -> list[Path]:
    """A borrowed setting whose sweep directory is gone (its checkpoints are never committed):
    copy the other experiment's collected results instead, i.e. ``<out_root>/<sweep_kind>/
    <profile>/<task>/<sweep name>/`` (``s<seed>.csv`` and ``run_info.json``: the same runs
    :func:`collect` copied from that sweep), with run_info.json's kind, setting, label and
    order made this experiment's and the source named under ``borrowed_from``. The CSVs are
    copied byte for byte. Nothing is written when the source has no results either."""
    (s,) = job.outputs  # a borrowed sweep gives one setting
    src = out_root / job.sweep_kind / job.profile / job.task / job.name
    try:
        meta = json.loads((src / "run_info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        log(f"[{job.task} {job.name}] nothing to collect: neither the {job.sweep_kind} sweep "
            f"{job.sweep_dir} nor its results {src} exist (run {job.sweep_kind}.py first)")
        return []
    dest = out_root / job.kind / job.profile / job.task / s.name
    dest.mkdir(parents=True, exist_ok=True)
    csvs = {p.name: p.read_text(encoding="utf-8") for p in sorted(src.glob("s*.csv"))}
    for stale in dest.glob("s*.csv"):
        if stale.name not in csvs:
            stale.unlink()
    for name, text in csvs.items():
        write_text_atomic(dest / name, text)
    meta.update({"kind": job.kind, "setting": s.name, "label": s.label, "order": s.order,
                 "borrowed_from": {"results": _rel(src), "kind": job.sweep_kind,
                                   "setting": meta.get("setting"),
                                   "command": meta.get("command")}})
    write_text_atomic(dest / "run_info.json", json.dumps(meta, indent=1, sort_keys=True) + "\n")
    log(f"[{job.task} {job.name}] copied the {job.sweep_kind} results {_rel(src)} "
        f"({len(csvs)} runs; its sweep directory is gone) into {_rel(dest)}")
    return [dest]


# ------------------------------------------------------------------ the command line

def add_common_args(ap: Any) -> None:
    """The arguments ablation.py and benchmark.py share."""
    import argparse

    ap.add_argument("--profile", choices=tuple(PROFILES), required=True,
                    help="budget profile (see experiments/profiles.py): "
                    + "; ".join(f"{k}: {p.doc}" for k, p in PROFILES.items()))
    ap.add_argument("--tasks", nargs="+", choices=TASK_NAMES, default=None, metavar="TASK",
                    help=f"tasks to run, of {', '.join(TASK_NAMES)}; default: the profile's "
                    "(tiny, cpu: FetchReach; paper: all four)")
    ap.add_argument("--seeds", type=int, default=None,
                    help="seeds 0..N-1; default: the profile's for the task")
    ap.add_argument("--first-seed", type=int, default=0, metavar="K",
                    help="run only seeds K..N-1 of the N (--seeds, or the profile's), as a sweep "
                    "of their own (<sweep>.s<K>-<N-1>), to split a setting that does not fit "
                    "in one sitting; collecting merges every piece of a setting (default 0: "
                    "all N in one sweep)")
    ap.add_argument("--adopt", type=Path, default=None, metavar="RUN_DIR",
                    help="train nothing: make RUN_DIR, a run of its own (python -m "
                    "rdher_jax.train) of the same settings and seed, the sweep of seed K "
                    "(--seeds K+1 --first-seed K, one task and one sweep), as that sweep would "
                    "be after the run's epochs; the same command without --adopt then resumes "
                    "it to the profile's epochs and collects it. Refused, writing nothing, "
                    "unless the settings match key by key (rdher_jax/adopt.py) and the sweep "
                    "directory does not exist")
    ap.add_argument("--epochs", type=int, default=None,
                    help="override the profile's epoch count (an unfinished or finished sweep "
                    "is continued to it)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help="results root; per-run CSVs, jsons and the report go under "
                    "<out>/<kind>/<profile>/ (default: experiments/results)")
    ap.add_argument("--runs-dir", type=Path, default=DEFAULT_RUNS,
                    help="root of the sweep directories (checkpoints), "
                    "<runs-dir>/<kind>/<profile>/<task>/<sweep> (default: runs/experiments)")
    ap.add_argument("--dry-run", action="store_true",
                    help="validate and print each sweep's command and whether it would start, "
                    "resume or be skipped; train and write nothing")
    ap.add_argument("--status", action="store_true",
                    help="train and write nothing: print, per setting, each seed's epochs so "
                    "far and the sweep directory (whole sweep or piece) that holds them, or "
                    "that it is missing; an unfinished run's time left at its recent pace")
    ap.add_argument("--collect-only", action="store_true",
                    help="train nothing: copy what the sweep directories hold now (e.g. while "
                    "the sweeps run in another process) and write the report")
    ap.add_argument("--keep-collected", action="store_true",
                    help="when collecting, keep the seeds already in --out whose sweep "
                    "directories are gone (a setting run in pieces on machines that do not "
                    "share --runs-dir), and with --cores do not run them again; without it "
                    "such seeds are removed")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bars (default: when stderr is a terminal)")
    ap.add_argument("--eval-episodes", type=int, default=EVAL_EPISODES, metavar="N",
                    help="test each finished run's best policy on N episodes with seeds no "
                    f"training run uses (default {EVAL_EPISODES}; 0: do not)")
    ap.add_argument("--precise-episodes", type=int, default=0, metavar="N",
                    help="also test each finished run's best policy on N more episodes of a "
                    "seed stream of their own (e.g. 1000: a 100-episode retest's noise is "
                    "about 2 points near 95%%), kept in run_info.json and reported beside the "
                    "retest (default 0: not; a test made before is kept)")
    ap.add_argument("--cores", type=int, nargs="+", default=None, metavar="CORE",
                    help="run every seed named as a one-seed piece in a process of its own "
                    "pinned to one of these CPU cores, one piece per core at a time, lowest "
                    "seed first across the settings, each setting collected as its last "
                    "piece ends (each piece's output in <sweep dir>.log; the same command "
                    "again resumes what was cut short and skips finished seeds)")
    ap.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="multi-process: process 0's coordination address; with "
                    "--num-processes and --process-id, each process started with the same "
                    "command (not needed under SLURM or Open MPI; see README, 'Sweeps over "
                    "several machines')")
    ap.add_argument("--num-processes", type=int, default=None, help="multi-process: N")
    ap.add_argument("--process-id", type=int, default=None, help="multi-process: this one's index")


_RUN_NAME = re.compile(r"lr(?P<lr>[^_]+)_lh(?P<lh>[^_]+)_s(?P<seed>\d+)")


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def seconds_per_epoch(rows: Sequence[Mapping[str, str]], last: int = 10) -> float | None:
    """The median wall-clock seconds of the run's last ``last`` epochs, from the ``wall_time``
    column of its metrics rows (cumulative over resumes; a step back or a gap of several
    epochs is skipped); the first epoch alone (compile included) when it is all there is."""
    pts = [(int(r["epoch"]), float(r["wall_time"])) for r in rows
           if r.get("epoch") and r.get("wall_time")]
    steps = [(t1 - t0) / (e1 - e0) for (e0, t0), (e1, t1) in itertools.pairwise(pts)
             if e1 == e0 + 1 and t1 > t0][-last:]
    if steps:
        return float(statistics.median(steps))
    return pts[0][1] / pts[0][0] if len(pts) == 1 and pts[0][0] > 0 else None


def _left(epochs_left: int, per_epoch: float | None) -> str:
    if per_epoch is None:
        return ""
    return f"; about {_duration(epochs_left * per_epoch)} left at {per_epoch:.1f} s/epoch"


def status_lines(job: Job, now: float | None = None) -> list[str]:
    """Where each seed of ``job``'s setting stands: its epochs so far (the last row of its
    metrics.csv) and the sweep directory holding it, over the whole sweep and every piece;
    a seed held by several directories is listed with each, the one collecting reads first.
    An unfinished run also says how long its remaining epochs take at the pace of its last
    ones (:func:`seconds_per_epoch`)."""
    import time

    now = time.time() if now is None else now
    found: dict[tuple[str, str], dict[int, list[tuple[int, Path, float]]]] = {}
    for d in job.piece_dirs():
        for run in sorted(p for p in d.iterdir() if p.is_dir()):
            m = _RUN_NAME.fullmatch(run.name)
            f = run / "metrics.csv"
            if m is None or not f.is_file():
                continue
            rows = list(csv.DictReader(io.StringIO(f.read_text(encoding="utf-8"))))
            epochs = int(rows[-1]["epoch"]) if rows else 0
            found.setdefault((m["lr"], m["lh"]), {}).setdefault(int(m["seed"]), []).append(
                (epochs, d, f.stat().st_mtime, seconds_per_epoch(rows)))
    head = (f"[{job.task} {job.name}] {job.seeds} seeds x {job.epochs} epochs"
            + (f", read from the {job.sweep_kind} experiment's sweep" if job.borrowed else ""))
    if not found:
        return [head, f"  no run in {_rel(job.sweep_dir)}"
                + ("; collecting copies that experiment's results, if any" if job.borrowed
                   else "")]
    out = [head]
    for (lr, lh), seeds in sorted(found.items()):
        if len(found) > 1 or job.lambdas is not None:
            out.append(f"  λ_r {lr}, λ_h {lh}:")
        for seed in sorted(set(range(job.seeds)) | set(seeds)):
            held = sorted(seeds.get(seed, []), key=lambda h: -h[0])  # most epochs first
            if not held:
                out.append(f"  {'s' + str(seed) + ':':<5} missing")
                continue
            for i, (epochs, d, mtime, per_epoch) in enumerate(held):
                done = epochs >= job.epochs
                state = "done" if done else f"{epochs}/{job.epochs} epochs"
                label = f"s{seed}:" if i == 0 else ""
                eta = "" if done else _left(job.epochs - epochs, per_epoch)
                out.append(f"  {label:<5} {state:<15} {_rel(d)} "
                           f"(updated {_duration(max(now - mtime, 0.0))} ago{eta})")
    return out


def adopt_command(kind: str, args: Any, sweeps: Callable[[str], list[tuple]]) -> int:
    """``--adopt RUN_DIR``: :func:`adopt_job` for the one sweep the arguments name."""
    asked = [f for f, on in (("--status", args.status), ("--collect-only", args.collect_only),
                             ("--coordinator", args.coordinator is not None),
                             ("--num-processes", args.num_processes is not None),
                             ("--process-id", args.process_id is not None)) if on]
    if asked:
        raise ConfigError(f"--adopt trains and collects nothing, in one process; drop "
                          f"{', '.join(asked)}")
    if args.first_seed < 0:
        raise ConfigError(f"--first-seed must be >= 0, got {args.first_seed}")
    tasks = list(dict.fromkeys(args.tasks or PROFILES[args.profile].default_tasks))
    jobs = make_jobs(kind, args.profile, tasks, args.runs_dir, args.seeds, args.epochs, sweeps,
                     args.first_seed)
    if len(jobs) != 1:
        raise ConfigError(f"--adopt fills one sweep; these arguments name {len(jobs)} ("
                          + ", ".join(f"{j.task} {j.name}" for j in jobs) + ")")
    setup(Startup(ffi=False))
    adopt_job(jobs[0], args.adopt, dry_run=args.dry_run)
    return 0


def run_experiment(kind: str, script: str, args: Any, argv: Sequence[str],
                   sweeps: Callable[[str], list[tuple]]) -> int:
    """Plan, run (or resume, or skip) and collect every sweep, then write the report.

    Returns the exit status: 0, or 2 after a one-line ``error:`` for a bad setting.
    """
    import shlex
    import sys

    from rdher_jax import distributed

    try:
        for name in ("seeds", "epochs"):
            v = getattr(args, name)
            if v is not None and v < 1:
                raise ConfigError(f"--{name} must be >= 1, got {v}")
        for name in ("eval_episodes", "precise_episodes"):
            if getattr(args, name) < 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be >= 0, got "
                                  f"{getattr(args, name)}")
        keys = {"coordinator": args.coordinator, "num_processes": args.num_processes,
                "process_id": args.process_id}
        if args.cores is not None:
            check_cores(args.cores)
            if any(v is not None for v in keys.values()) or args.collect_only or \
                    args.status or args.adopt is not None:
                raise ConfigError("--cores runs its pieces as processes of its own: not with "
                                  "--adopt, --status, --collect-only, --coordinator, "
                                  "--num-processes or --process-id")
        if args.adopt is not None:
            return adopt_command(kind, args, sweeps)
        if args.status:
            tasks = list(dict.fromkeys(args.tasks or PROFILES[args.profile].default_tasks))
            for job in make_jobs(kind, args.profile, tasks, args.runs_dir, args.seeds,
                                 args.epochs, sweeps, 0):
                print("\n".join(status_lines(job)))
            return 0
        # Every sweep of the experiment runs over all the processes; process 0 collects and
        # writes the results and the report.
        if not args.dry_run:
            spec = distributed.parse({k: str(v) for k, v in keys.items() if v is not None})
            # One of several processes: the work runs in a supervised child.
            script_path = str(Path(__file__).resolve().parent / script)
            rc = distributed.supervise(spec, [sys.executable, script_path, *argv])
            if rc is not None:
                return rc
            setup(Startup(processes=spec))
        main = distributed.is_main()
        tasks = list(dict.fromkeys(args.tasks or PROFILES[args.profile].default_tasks))
        if args.first_seed < 0:
            raise ConfigError(f"--first-seed must be >= 0, got {args.first_seed}")
        jobs = make_jobs(kind, args.profile, tasks, args.runs_dir, args.seeds, args.epochs,
                         sweeps, args.first_seed)
        progress = sys.stderr.isatty() if args.progress is None else args.progress
        command = shlex.join(["python", f"experiments/{script}", *argv])
        failed = 0

        def collect_now(job: Job) -> None:  # a setting whose pieces have all ended
            import report

            collect(job, args.out, command, eval_episodes=args.eval_episodes,
                    keep_collected=args.keep_collected, precise_episodes=args.precise_episodes)
            for p in report.write_reports(args.out, only={(kind, args.profile)}):
                print(f"wrote {p}")

        if args.cores is not None:  # every piece, each setting collected as it ends; then all
            failed = run_pool(jobs, args.cores, dry_run=args.dry_run, finished=collect_now,
                              out_root=args.out if args.keep_collected else None)
        for task in tasks:
            mine = [j for j in jobs if j.task == task]
            for job in mine:
                if job.borrowed and main:
                    print(f"[{job.task} {job.name}] read from the {job.sweep_kind} sweep "
                          f"{job.sweep_dir} (run by {job.sweep_kind}.py, not here)")
                elif not args.collect_only and args.cores is None:
                    run_job(job, progress and main, dry_run=args.dry_run,
                            log=print if main else (lambda *a, **k: None))
                if not args.dry_run and main:
                    collect(job, args.out, command, eval_episodes=args.eval_episodes,
                            keep_collected=args.keep_collected,
                            precise_episodes=args.precise_episodes)
            if not args.dry_run and main:
                import report

                for p in report.write_reports(args.out, only={(kind, args.profile)}):
                    print(f"wrote {p}")
    except ConfigError as e:
        sys.stdout.flush()
        print(f"error: {e}", file=sys.stderr)
        return 2
    if failed:
        print(f"error: {failed} piece(s) failed; their logs are named above", file=sys.stderr)
        return 1
    return 0
