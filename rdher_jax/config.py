"""Run configuration: a frozen dataclass, ``key=value`` command-line overrides and YAML I/O.

The dataclass is used as an OmegaConf structured config, so overrides are parsed and typed by
OmegaConf; range checks that OmegaConf cannot express live in :func:`validate`. Every user error
is raised as :class:`ConfigError` with a one-line message, which :func:`main_guard` turns into
``error: <msg>`` on stderr and exit status 2.
"""

import dataclasses
import datetime
import difflib
import functools
import math
import sys
import textwrap
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from .tasks import MOVING_TASKS, TASK_NAMES, TASKS, defaults_doc

ENV_NAMES: tuple[str, ...] = TASK_NAMES
ALGO_NAMES: tuple[str, ...] = ("ddpg", "her", "archer", "cher", "dher", "rdher")
# RDHER's reward weights (lambda_r, lambda_h) per task are the paper's (``tasks.TASKS``). ARCHER
# has no published Fetch weights and no public code, so it uses the same.
WEIGHTED_ALGOS: tuple[str, ...] = ("archer", "rdher")
DHER_ALGOS: tuple[str, ...] = ("dher", "rdher")
# The default ring of DHER's recorded matches holds at least this many (the authors keep every
# match of the buffer; 65536 covered every FetchPush run measured at the paper's settings).
MIN_DHER_RECORDS = 65536
BACKENDS: tuple[str, ...] = ("auto", "mujoco", "mjx", "warp")
SCENES: tuple[str, ...] = ("auto", "original", "mjx", "warp")
TERMINAL_RULES: tuple[str, ...] = ("none", "success", "exact")
COMPUTE_DTYPES: tuple[str, ...] = ("float32", "bfloat16")
PHYSICS_CALLS: tuple[str, ...] = ("ffi", "callback")
# The critic target's clip range (ddpg.critic_target): each row's weighted range, or
# baselines' unweighted clip_return for every row.
TARGET_CLIPS: tuple[str, ...] = ("weighted", "unweighted")
REPLAY_PRIORITIES: tuple[str, ...] = ("none", "energy")
# The algorithms whose rows are drawn episode-first by 'future' relabelling (the strategy
# energy-based prioritisation reweights).
HER_FAMILY: tuple[str, ...] = ("ddpg", "her", "archer")

# Fields whose value may differ between a run and its continuation: they change neither the
# learning problem nor the shapes of what the checkpoint holds.
RESUMABLE_KEYS: frozenset[str] = frozenset(
    {
        "epochs",
        "n_test_rollouts",
        "retest",
        "select_top",
        "select_episodes",
        "backend",
        "run_dir",
        "resume",
        "checkpoint_every",
        "tensorboard",
        "progress",
        "compile_cache",
        "physics_call",
        "physics_threads",
        "stop_success",
        "stop_window",
    }
)
# The fields that reach the compiled program only as traced values (``program.Hyper``), so runs
# that differ in them (and in the seed) are one program: what a sweep may vary.
TRACED_KEYS: tuple[str, ...] = (
    "actor_lr", "critic_lr", "polyak", "action_l2", "noise_eps", "random_eps", "lambda_r",
    "lambda_h", "gamma", "replay_k", "dher_fraction", "dher_tol", "cher_growth",
)
PROG = "python -m rdher_jax.train"
# How far under a success threshold a rate may fall and still reach it: a success rate is a
# float32 ratio of counts (7/10 is 0.699999988), so 9/10 or a mean of (7, 10, 10)/10 sits a hair
# either side of 0.9. stop_success (driver.reached_stop) and the benchmarks' reports share it.
SUCCESS_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Preset:
    """A named set of key values; explicit ``key=value`` arguments override them."""

    doc: str
    values: Mapping[str, Any]


# Presets change the learner away from the paper-faithful defaults, which stay as the paper ran
# them. Their values are measured choices: experiments/bench_learning.py and docs/performance.md
# say what each one bought.
PRESETS: dict[str, Preset] = {
    "fast": Preset(
        "learn FetchPush on a 2-core CPU: one episode then 40 gradient steps per cycle (0.8 "
        "per env step) on 2x256 networks, the next episode collected on the second core while "
        "they run (overlap=true: CPU only); TD3's target smoothing and delayed actor, target "
        "networks moved by 1% every 2nd step, no action penalty; a transition whose goal is "
        "exactly the next achieved goal does not bootstrap; dher/rdher combine at most "
        "0.2 (1 - s) of a batch. Changes the algorithm: see docs/performance.md, 'preset=fast'",
        {
            "num_envs": 1,
            "n_batches": 40,
            "layers": 2,
            "action_l2": 0.0,
            "target_every": 2,
            "polyak": 0.99,
            "target_noise": 0.2,
            "policy_delay": 2,
            "terminal": "exact",
            # DHER's combined share (authors: 0.8): at 0.8 the combined rows crowd out HER's
            # relabelled ones; 0.2 matches HER on FetchPushMoving (experiments/results/RESULTS.md,
            # section 5).
            "dher_fraction": 0.2,
            # Physics beside the learner: 1.66x cheaper cycles on 2 cores, and no more steps to
            # success over 3 seeds (docs/performance.md, 'Overlap').
            "overlap": True,
            # The best policy's success on 100 new episodes, the figure the benchmarks report
            # (a 10-episode test epoch at 1.0 retests at 76-83% on PickAndPlace).
            "retest": 100,
            # The run's policy: the best of its 5 best test epochs' on 100 selection episodes,
            # not the luckiest 10-episode test (docs/performance.md, 'select_top').
            "select_top": 5,
        },
    ),
}


class ConfigError(ValueError):
    """A user error in the configuration; its message is always a single line."""

    def __init__(self, msg: str) -> None:
        # Messages may embed library text; keep them on one line so stderr stays greppable.
        super().__init__(" ".join(str(msg).split()))


def _f(default: Any, doc: str) -> Any:
    return field(default=default, metadata={"help": doc})


@dataclass(frozen=True)
class Config:
    """Hyper-parameters and run options of one training run."""

    preset: str | None = _f(
        None, "named set of values applied before the other keys, which override it: "
        + ", ".join(PRESETS) + " (listed below)"
    )
    env: str = _f("FetchReach", "task: one of " + ", ".join(ENV_NAMES))
    algo: str = _f(
        "her",
        "ddpg (no relabelling), her ('future' relabelling), archer (her with reward weights), "
        "cher (curriculum-selected her goals), dher (goal matching and combination across "
        "failed episodes, mixed with her), rdher (dher with reward weights)",
    )
    seed: int = _f(0, "PRNG seed (0 <= seed < 2**32)")
    epochs: int | None = _f(
        None, "training epochs; null: the task's default (epochs x cycles: " + defaults_doc()
        + ")")
    n_cycles: int | None = _f(None, "cycles per epoch; null: the task's default (see epochs)")
    n_batches: int = _f(40, "gradient steps per cycle")
    batch_size: int = _f(256, "transitions per gradient step")
    num_envs: int = _f(
        2, "parallel rollouts per cycle (baselines' rollout_batch_size x MPI workers)"
    )
    n_test_rollouts: int = _f(10, "deterministic test episodes per epoch")
    retest: int = _f(
        0, "after training, the best policy is retested on this many new deterministic "
        "episodes (python -m rdher_jax.evaluate), printed and written to retest.json; 0: none"
    )
    select_top: int = _f(
        1, "the run's policy is chosen when training ends among the policies of its select_top "
        "best test epochs (ties: the later), kept as it trains: each is tested on the same "
        "select_episodes new episodes and the best of them is the run's policy (checkpoints/"
        "selected), the one evaluate and retest then test on episodes of their own. 1: the best "
        "test epoch's policy (baselines)"
    )
    select_episodes: int = _f(100, "select_top > 1: episodes each candidate policy is tested on")
    buffer_size: int = _f(1_000_000, "replay buffer capacity in transitions")
    backend: str = _f(
        "auto", "physics: auto|mujoco|mjx|warp (auto: warp on an NVIDIA GPU with Warp "
        "installed, else mjx on a GPU, else mujoco)"
    )
    scene: str = _f("auto", "scene model: auto|original|mjx|warp")
    overlap: bool = _f(
        False, "backend=mujoco: collect each cycle's episodes on a second host device while the "
        "learner trains on the stored ones, so a cycle costs about the larger of its rollout "
        "and its updates, not their sum. A cycle's updates then see the episodes up to the "
        "previous cycle (the actor that collects is the current one). Changes the algorithm: "
        "docs/performance.md, 'Overlap'"
    )
    hidden: int = _f(256, "units per hidden layer of actor and critic")
    layers: int = _f(3, "hidden layers of actor and critic")
    actor_lr: float = _f(1e-3, "actor Adam learning rate")
    critic_lr: float = _f(1e-3, "critic Adam learning rate")
    polyak: float = _f(0.95, "target-network averaging coefficient, in [0, 1]")
    action_l2: float = _f(1.0, "weight of the squared-action penalty in the actor loss")
    noise_eps: float = _f(0.2, "std of Gaussian exploration noise, as a fraction of max action")
    random_eps: float = _f(0.3, "probability of a uniformly random exploratory action")
    target_every: int = _f(
        0, "gradient steps between target-network updates (each by polyak); 0: one update per "
        "cycle after its n_batches steps (baselines)"
    )
    target_noise: float = _f(
        0.0, "TD3 target smoothing: std of Gaussian noise on the target action, as a fraction of "
        "max action; 0: none (baselines)"
    )
    noise_clip: float = _f(0.5, "target smoothing noise is clipped to +-noise_clip x max action")
    policy_delay: int = _f(
        1, "the actor is updated every policy_delay-th gradient step (TD3); 1: every step"
    )
    layer_norm: bool = _f(False, "LayerNorm in the critic's hidden layers")
    n_critics: int = _f(
        1, "critics trained side by side on the same TD targets, each with its own "
        "initialisation and target network; the actor ascends their mean Q. 1: baselines' "
        "single critic"
    )
    target_critics: int | None = _f(
        None, "the TD target bootstraps from the minimum over this many of the n_critics "
        "target critics, drawn afresh at every gradient step (REDQ); null: all of them "
        "(n_critics=2: TD3's clipped double Q)"
    )
    compute_dtype: str = _f(
        "float32", "dtype of the hidden layers' matmuls: float32|bfloat16 (parameters, "
        "optimiser state, losses and output layers stay float32). Changes the numerics: "
        "docs/performance.md, 'bfloat16'"
    )
    n_step: int = _f(
        1, "n-step returns: each sampled row sums n rewards (its own goal throughout, no "
        "off-policy correction) before bootstrapping; 1: one-step (baselines)"
    )
    terminal: str = _f(
        "none", "which transitions do not bootstrap: none (Fetch episodes end by time limit "
        "only: the paper's setting), success (a transition that reaches its goal, reward 0), "
        "exact (a transition whose goal is exactly the next achieved goal: HER rows relabelled "
        "with the very next step, DRLib's rule)"
    )
    target_clip: str = _f(
        "weighted", "the critic target's clip range: weighted ([-lambda/(1-gamma), 0], the range "
        "of each row's weighted return) or unweighted ([-1/(1-gamma), 0] for every row: "
        "baselines' clip_return, kept by code that weights the sampled rewards as the paper's "
        "Algorithm 1 does); the same for unweighted algorithms"
    )
    replay_k: int = _f(4, "HER ratio: goals are relabelled with probability 1 - 1/(1 + k)")
    replay_priority: str = _f(
        "none", "how ddpg/her/archer draw a row's episode: none (uniformly, baselines) or energy "
        "(in proportion to the work it did on the object, Zhao & Tresp 2018: episodes that "
        "never move it are not replayed once any other has). Changes the algorithm: "
        "docs/algorithms.md, 'Energy-based prioritisation'"
    )
    energy_clip: float = _f(
        0.5, "replay_priority=energy: upper clip of each transition's energy (the EBP authors' "
        "clip_energy, 0.5 on the Fetch tasks)"
    )
    lambda_r: float | None = _f(
        None, "reward weight on real transitions (>= 0); null: the paper's per-task value for "
        "rdher and archer (Reach, PickAndPlace 2; Push, Slide 4), else 1"
    )
    lambda_h: float | None = _f(
        None, "reward weight on hindsight (HER-relabelled or DHER-combined) transitions (>= 0); "
        "null: the paper's per-task value for rdher and archer (Reach, PickAndPlace 1; Push, "
        "Slide 0.5), else 1"
    )
    dher_fraction: float = _f(
        0.8, "dher/rdher: at most this fraction of a batch are combined transitions, scaled by "
        "(1 - success rate of the last 100 episodes), as in the DHER authors' code"
    )
    dher_tol: float = _f(0.01, "dher/rdher: goal-matching grid cell in metres (authors: 1 cm)")
    dher_records: int | None = _f(
        None, "dher/rdher: size of the ring of recorded goal matches; null: the larger of "
        f"{MIN_DHER_RECORDS} and the matches one cycle can record (2 * num_envs * (T+1) * "
        "dher_partners)"
    )
    dher_partners: int = _f(
        8, "dher/rdher: matches recorded per new achieved point and per new desired-goal cell "
        "each cycle"
    )
    cher_candidates: int | None = _f(
        None, "cher: 'future' candidates a batch is selected from; null: 2 x batch_size"
    )
    cher_sample: int = _f(3, "cher: candidates scored per greedy pick (lazier-than-lazy)")
    cher_growth: float = _f(
        1.0001, "cher: proximity weight = cher_growth ** (gradient steps since the epoch began)"
    )
    gamma: float | None = _f(None, "discount in (0, 1); null: 1 - 1/T with T the episode length")
    episode_length: int | None = _f(
        None, "env steps per episode (T); null: the task's, 50 for every task (gymnasium-robotics' "
        "max_episode_steps). The DHER authors' only Dy-Pushing registration uses 200"
    )
    goal_speed: float | None = _f(
        None, "moving tasks only: metres the goal moves per env step (>= 0; 0 keeps it still); "
        "null: the task's, 0.011 for FetchReachMoving and 0.005 for FetchPushMoving (the DHER "
        "authors')"
    )
    run_dir: str | None = _f(
        None, "output directory; null: runs/<env>-<algo>-s<seed>-<YYYYmmdd-HHMMSS>"
    )
    resume: str | None = _f(None, "run directory to continue from its latest checkpoint")
    checkpoint_every: int = _f(1, "epochs between checkpoints")
    stop_success: float | None = _f(
        None, "stop early once the mean test success of the last stop_window epochs reaches "
        "this (a sweep: once every run's does), after saving a checkpoint; null: run every epoch"
    )
    stop_window: int = _f(3, "epochs averaged for stop_success")
    tensorboard: bool = _f(False, "also write TensorBoard scalars (needs tensorboardX)")
    progress: bool = _f(True, "show a progress bar")
    compile_cache: bool = _f(
        True, "keep compiled programs on disk for later processes (JAX's persistent cache, "
        "one directory per CPU kind and JAX version under $RDHER_JAX_CACHE_DIR or "
        "~/.cache/rdher_jax)"
    )
    physics_call: str = _f(
        "ffi", "how jitted code calls the native physics (backend=mujoco): ffi (XLA FFI "
        "handlers, built once per machine with the C++ compiler; programs holding them are "
        "cacheable) or callback (jax.pure_callback, never cached); the same results bit for "
        "bit, and ffi falls back to callback with a warning where it cannot be built"
    )
    physics_threads: int | None = _f(
        None, "host threads stepping the native physics (backend=mujoco); null: every usable "
        "core, or 1 with overlap=true, whose learner runs beside it; the results do not "
        "depend on it"
    )


FIELD_NAMES: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(Config))
_HINTS: dict[str, Any] = typing.get_type_hints(Config)


def _type_name(tp: Any) -> str:
    """``int``, ``float | None`` -> ``int``, ``float|null`` (the spelling used on the CLI)."""
    args = typing.get_args(tp)
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        return "|".join("null" if a is type(None) else a.__name__ for a in args)
    return tp.__name__


def _fmt_value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    return str(v)


def help_text(prog: str = PROG) -> str:
    """The ``--help`` text: every field with its type, default and description."""
    lines = [
        f"usage: {prog} [key=value ...]",
        "",
        f"example: {prog} env=FetchSlide algo=her seed=0 epochs=20",
        "Values are parsed as YAML scalars; write null for None. Fields:",
        "",
    ]
    for f in dataclasses.fields(Config):
        head = f"  {f.name}: {_type_name(_HINTS[f.name])} = {_fmt_value(f.default)}"
        lines.append(head)
        lines.extend(
            textwrap.wrap(f.metadata["help"], 96, initial_indent=" " * 6, subsequent_indent=" " * 6)
        )
    lines += ["", "Presets (preset=<name>; keys given explicitly override a preset's values):", ""]
    for name, preset in PRESETS.items():
        values = " ".join(f"{k}={_fmt_value(v)}" for k, v in preset.values.items())
        lines.extend(textwrap.wrap(f"{name}: {values}", 96, initial_indent="  ",
                                   subsequent_indent=" " * 6))
        lines.extend(
            textwrap.wrap(preset.doc, 96, initial_indent=" " * 6, subsequent_indent=" " * 6)
        )
        per_task = "; ".join(
            f"{t}: " + " ".join(f"{k}={_fmt_value(v)}" for k, v in task.preset_values[name].items())
            for t, task in TASKS.items() if name in task.preset_values)
        if per_task:
            lines.extend(textwrap.wrap(f"per task: {per_task}", 96, initial_indent=" " * 6,
                                       subsequent_indent=" " * 6))
    return "\n".join(lines) + "\n"


def _check(ok: bool, msg: str) -> None:
    if not ok:
        raise ConfigError(msg)


def _one_of(name: str, value: str, allowed: Sequence[str]) -> None:
    if value not in allowed:
        close = difflib.get_close_matches(value, allowed, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ConfigError(f"unknown {name} {value!r}{hint}; valid: {', '.join(allowed)}")


def validate(cfg: Config) -> Config:
    """Range checks OmegaConf's typing cannot express; returns ``cfg`` or raises ConfigError."""
    _one_of("env", cfg.env, ENV_NAMES)
    _one_of("algo", cfg.algo, ALGO_NAMES)
    _one_of("backend", cfg.backend, BACKENDS)
    _one_of("scene", cfg.scene, SCENES)
    _one_of("terminal", cfg.terminal, TERMINAL_RULES)
    _one_of("compute_dtype", cfg.compute_dtype, COMPUTE_DTYPES)
    _one_of("target_clip", cfg.target_clip, TARGET_CLIPS)
    _one_of("physics_call", cfg.physics_call, PHYSICS_CALLS)
    _one_of("replay_priority", cfg.replay_priority, REPLAY_PRIORITIES)
    _check(cfg.replay_priority == "none" or cfg.algo in HER_FAMILY,
           f"replay_priority={cfg.replay_priority} applies to {', '.join(HER_FAMILY)}, not "
           f"{cfg.algo}")
    _check(math.isfinite(cfg.energy_clip) and cfg.energy_clip > 0,
           f"energy_clip must be a finite number > 0, got {cfg.energy_clip}")
    _check(cfg.terminal != "exact" or cfg.n_step == 1, "terminal=exact needs n_step=1")
    if cfg.preset is not None:
        _one_of("preset", cfg.preset, tuple(PRESETS))
    _check(0 <= cfg.seed < 2**32, f"seed must be in [0, 2**32), got {cfg.seed}")
    _check(cfg.physics_threads is None or cfg.physics_threads >= 1,
           f"physics_threads must be >= 1 or null, got {cfg.physics_threads}")
    positive = (
        "epochs",
        "n_cycles",
        "n_batches",
        "batch_size",
        "num_envs",
        "n_test_rollouts",
        "buffer_size",
        "hidden",
        "layers",
        "checkpoint_every",
        "dher_records",
        "dher_partners",
        "cher_candidates",
        "cher_sample",
        "policy_delay",
        "n_critics",
        "target_critics",
        "n_step",
        "episode_length",
        "stop_window",
    )
    for name in positive:
        v = getattr(cfg, name)
        _check(v is None or v >= 1, f"{name} must be a positive integer, got {v}")
    _check(cfg.replay_k >= 0, f"replay_k must be >= 0, got {cfg.replay_k}")
    _check(cfg.retest >= 0, f"retest must be >= 0, got {cfg.retest}")
    _check(cfg.select_top >= 1, f"select_top must be >= 1, got {cfg.select_top}")
    _check(cfg.select_episodes >= 1,
           f"select_episodes must be >= 1, got {cfg.select_episodes}")
    _check(cfg.target_every >= 0, f"target_every must be >= 0, got {cfg.target_every}")
    _check(cfg.target_critics is None or cfg.target_critics <= cfg.n_critics,
           f"target_critics ({cfg.target_critics}) must not exceed n_critics ({cfg.n_critics})")
    T = episode_length(cfg)
    _check(cfg.n_step <= T, f"n_step must be <= the episode length {T}, got {cfg.n_step}")
    _check(
        cfg.batch_size <= cfg.buffer_size,
        f"batch_size ({cfg.batch_size}) must not exceed buffer_size ({cfg.buffer_size})",
    )
    floats = (
        "actor_lr",
        "critic_lr",
        "polyak",
        "action_l2",
        "noise_eps",
        "random_eps",
        "lambda_r",
        "lambda_h",
        "gamma",
        "dher_fraction",
        "dher_tol",
        "cher_growth",
        "target_noise",
        "noise_clip",
        "goal_speed",
    )
    for name in floats:
        v = getattr(cfg, name)
        _check(v is None or math.isfinite(v), f"{name} must be a finite number, got {v}")
    for name in ("actor_lr", "critic_lr"):
        _check(getattr(cfg, name) > 0, f"{name} must be > 0, got {getattr(cfg, name)}")
    for name in ("polyak", "random_eps"):
        v = getattr(cfg, name)
        _check(0.0 <= v <= 1.0, f"{name} must be in [0, 1], got {v}")
    for name in ("action_l2", "noise_eps", "lambda_r", "lambda_h", "target_noise", "noise_clip"):
        v = getattr(cfg, name)
        _check(v is None or v >= 0, f"{name} must be >= 0, got {v}")
    _check(0.0 <= cfg.dher_fraction <= 1.0,
           f"dher_fraction must be in [0, 1], got {cfg.dher_fraction}")
    _check(cfg.dher_tol > 0, f"dher_tol must be > 0, got {cfg.dher_tol}")
    if cfg.goal_speed is not None:
        _check(cfg.env in MOVING_TASKS,
               f"goal_speed applies to the moving tasks ({', '.join(MOVING_TASKS)}), not "
               f"{cfg.env}")
        _check(cfg.goal_speed >= 0, f"goal_speed must be >= 0, got {cfg.goal_speed}")
    if cfg.stop_success is not None:
        _check(math.isfinite(cfg.stop_success) and 0.0 < cfg.stop_success <= 1.0,
               f"stop_success must be in (0, 1] or null, got {cfg.stop_success}")
    _check(cfg.cher_growth >= 1.0, f"cher_growth must be >= 1, got {cfg.cher_growth}")
    if cfg.cher_candidates is not None:
        _check(cfg.cher_candidates >= cfg.batch_size,
               f"cher_candidates ({cfg.cher_candidates}) must be >= batch_size "
               f"({cfg.batch_size})")
        _check(cfg.cher_sample <= cfg.cher_candidates,
               f"cher_sample ({cfg.cher_sample}) must be <= cher_candidates "
               f"({cfg.cher_candidates})")
    if cfg.algo in DHER_ALGOS and cfg.dher_records is not None:
        need = dher_records_needed(cfg)
        _check(cfg.dher_records >= need,
               f"dher_records ({cfg.dher_records}) must be >= 2 * num_envs * (T+1) * "
               f"dher_partners = {need}, the matches one cycle can record")
    _check(cfg.gamma is None or 0.0 < cfg.gamma < 1.0, f"gamma must be in (0, 1), got {cfg.gamma}")
    for name in ("run_dir", "resume"):
        v = getattr(cfg, name)
        _check(v is None or v.strip() != "", f"{name} must be a non-empty path or null")
    return cfg


def _merge(base: Config, overrides: Any, raw: Mapping[str, str]) -> Config:
    """Merge an OmegaConf node onto ``base``, translating OmegaConf errors to ConfigError."""
    try:
        merged = OmegaConf.merge(OmegaConf.structured(base), overrides)
        cfg = OmegaConf.to_object(merged)
    except ConfigKeyError as e:
        raise unknown_key(str(getattr(e, "key", None) or e), FIELD_NAMES) from None
    except OmegaConfBaseException as e:
        key = str(getattr(e, "full_key", None) or getattr(e, "key", None) or "")
        if key in _HINTS:
            shown = raw.get(key, _fmt_value(OmegaConf.select(overrides, key, default=None)))
            raise ConfigError(
                f"invalid value {shown!r} for {key} (expected {_type_name(_HINTS[key])})"
            ) from None
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ConfigError(f"invalid configuration: {first}") from None
    assert isinstance(cfg, Config)
    return validate(cfg)


def unknown_key(key: str, valid: Sequence[str]) -> ConfigError:
    """The one-line error of a key that no command takes, with the closest valid key."""
    close = difflib.get_close_matches(key, list(valid), n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    return ConfigError(f"unknown key {key!r}{hint}; run with --help to list the keys")


def split_args(argv: Sequence[str], extra: Sequence[str] = (), prefixes: Sequence[str] = (),
               config_keys: bool = True) -> tuple[dict[str, str], dict[str, str]]:
    """``key=value`` tokens -> (config fields, other keys); later tokens win.

    The other keys are those in ``extra`` and any starting with one of ``prefixes`` (e.g.
    ``grid.``); ``config_keys=False`` takes no config field. Every other key is a one-line
    ConfigError naming the closest valid key. This is the parser of every command line of the
    project (train, sweep, evaluate).
    """
    fields: dict[str, str] = {}
    other: dict[str, str] = {}
    valid = [*extra, *(FIELD_NAMES if config_keys else ())]
    for tok in argv:
        key, value = split_token(tok)
        if key in extra or any(key.startswith(p) for p in prefixes):
            other[key] = value
        elif config_keys and key in FIELD_NAMES:
            fields[key] = value
        else:
            # Checked before OmegaConf so that dotted or hydra-style keys get the same message.
            raise unknown_key(key, valid)
    return fields, other


def split_token(tok: str) -> tuple[str, str]:
    """``"key=value"`` -> ``(key, value)``; anything else is a ConfigError."""
    key, sep, value = tok.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"malformed argument {tok!r}: expected key=value")
    return key, value


def preset_values(name: str, env: str | None = None) -> dict[str, Any]:
    """The values of preset ``name``, with task ``env``'s own values for it on top
    (``tasks.Task.preset_values``); ``null`` gives none."""
    name = name.strip()
    if name in ("null", "~", ""):
        return {}
    _one_of("preset", name, tuple(PRESETS))
    per_task = TASKS[env].preset_values.get(name, {}) if env in TASKS else {}
    return {**PRESETS[name].values, **per_task}


def preset_tokens(name: str, env: str | None = None) -> dict[str, str]:
    """The ``key -> value`` text of :func:`preset_values`."""
    return {k: _fmt_value(v) for k, v in preset_values(name, env).items()}


def parse_args(argv: Sequence[str], base: Config | None = None, prog: str = PROG) -> Config:
    """Apply ``key=value`` tokens onto ``base`` (default: ``Config()``) and validate.

    ``-h``/``--help`` anywhere prints :func:`help_text` and exits 0. Later tokens win over
    earlier ones for the same key.
    """
    if any(a in ("-h", "--help") for a in argv):
        sys.stdout.write(help_text(prog))
        sys.stdout.flush()
        raise SystemExit(0)
    raw, _ = split_args(argv)
    return config_from_fields(raw, base)


def config_from_fields(raw: Mapping[str, str], base: Config | None = None) -> Config:
    """Apply ``{field: value text}`` (a preset first, then the rest) onto ``base`` and
    validate."""
    raw = dict(raw)
    if "preset" in raw:
        env = raw.get("env", (base or Config()).env).strip()
        raw = {**preset_tokens(raw["preset"], env), **raw}
    try:
        overrides = OmegaConf.from_dotlist([f"{k}={v}" for k, v in raw.items()])
    except OmegaConfBaseException as e:
        raise ConfigError(f"could not parse arguments: {str(e).splitlines()[0]}") from None
    return _merge(base or Config(), overrides, raw)


def default_run_dir(cfg: Config, now: datetime.datetime | None = None) -> str:
    """``runs/<env>-<algo>-s<seed>-<YYYYmmdd-HHMMSS>`` (relative to the working directory)."""
    stamp = (now or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    return str(Path("runs") / f"{cfg.env}-{cfg.algo}-s{cfg.seed}-{stamp}")


def episode_length(cfg: Config) -> int:
    """T: ``cfg.episode_length``, or the task's when null."""
    return cfg.episode_length if cfg.episode_length is not None else TASKS[cfg.env].episode_length


def dher_records_needed(cfg: Config) -> int:
    """The matches one cycle can record: 2 points per step of each new episode, each with up to
    ``dher_partners`` partners."""
    return 2 * cfg.num_envs * (episode_length(cfg) + 1) * cfg.dher_partners


def resolve(cfg: Config, now: datetime.datetime | None = None) -> Config:
    """Fill every ``None`` default from the task's entry in ``tasks.TASKS``: epochs, n_cycles,
    gamma (1 - 1/T, T the episode length, as in baselines' HER), the reward weights (per task
    for rdher and archer, else 1), dher_records; and run_dir.

    With ``resume`` set, ``run_dir`` is the resumed directory.
    """
    task = TASKS[cfg.env]
    lam_r, lam_h = task.paper_lambdas if cfg.algo in WEIGHTED_ALGOS else (1.0, 1.0)
    run_dir = cfg.run_dir
    if cfg.resume is not None:
        if run_dir is not None and Path(run_dir).resolve() != Path(cfg.resume).resolve():
            raise ConfigError(
                f"run_dir={run_dir} differs from resume={cfg.resume}; a resumed run writes into "
                "the directory it resumes, so pass resume only"
            )
        run_dir = cfg.resume
    out = dataclasses.replace(
        cfg,
        epochs=cfg.epochs if cfg.epochs is not None else task.epochs,
        n_cycles=cfg.n_cycles if cfg.n_cycles is not None else task.n_cycles,
        gamma=cfg.gamma if cfg.gamma is not None else 1.0 - 1.0 / episode_length(cfg),
        lambda_r=cfg.lambda_r if cfg.lambda_r is not None else lam_r,
        lambda_h=cfg.lambda_h if cfg.lambda_h is not None else lam_h,
        run_dir=run_dir if run_dir is not None else default_run_dir(cfg, now),
        dher_records=cfg.dher_records if cfg.dher_records is not None
        else max(MIN_DHER_RECORDS, dher_records_needed(cfg)),
    )
    return validate(out)


def to_yaml(cfg: Config) -> str:
    """The config as YAML text, loadable by :func:`from_yaml`."""
    return OmegaConf.to_yaml(OmegaConf.structured(cfg))


def from_yaml(path: str | Path) -> Config:
    """Load and validate a config saved by :func:`to_yaml`; unknown keys are errors."""
    path = Path(path)
    try:
        node = OmegaConf.load(path)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except Exception as e:  # yaml errors have no common public base class here
        raise ConfigError(f"cannot read {path}: {str(e).splitlines()[0]}") from None
    try:
        return _merge(Config(), node, {})
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def continue_config(saved: Config, raw: Mapping[str, str], directory: str | Path) -> Config:
    """The config that continues a run or a sweep saved in ``directory`` as ``saved``:
    ``raw`` (``{field: value text}``) applied onto it and resolved, its ``run_dir`` the
    directory.

    Only :data:`RESUMABLE_KEYS` may differ from the saved config; anything else would change the
    learning problem or the checkpoint's shapes, so it is a ConfigError. This is the one resume
    check of both ``train`` and ``sweep``.
    """
    raw = {k: v for k, v in raw.items() if k not in ("resume", "run_dir")}
    new = config_from_fields(raw, base=dataclasses.replace(saved, run_dir=None, resume=None))
    new = resolve(dataclasses.replace(new, run_dir=str(directory), resume=str(directory)))
    changed = [k for k in FIELD_NAMES
               if k not in RESUMABLE_KEYS and getattr(new, k) != getattr(saved, k)]
    if changed:
        diffs = ", ".join(f"{k}: {getattr(saved, k)!r} -> {getattr(new, k)!r}" for k in changed)
        raise ConfigError(f"cannot change {diffs} when resuming {directory}")
    return new


def preset_sets_overlap(name: str | None) -> bool:
    """Whether preset ``name`` (None or unknown: no) turns ``overlap`` on."""
    preset = PRESETS.get((name or "").strip())
    return preset is not None and preset.values.get("overlap") is True


def resume_config(cfg: Config, argv: Sequence[str]) -> Config:
    """The config of a resumed run: ``<resume>/config.yaml`` with ``argv`` re-applied (see
    :func:`continue_config`)."""
    if cfg.resume is None:
        raise ConfigError("resume_config needs resume=<run dir>")
    if cfg.run_dir is not None and Path(cfg.run_dir).resolve() != Path(cfg.resume).resolve():
        raise ConfigError(
            f"run_dir={cfg.run_dir} differs from resume={cfg.resume}; a resumed run writes into "
            "the directory it resumes, so pass resume only"
        )
    saved = from_yaml(Path(cfg.resume) / "config.yaml")
    raw, _ = split_args(argv)
    return continue_config(saved, raw, cfg.resume)


F = TypeVar("F", bound=Callable[..., Any])


def main_guard(fn: F) -> F:
    """Decorate a CLI entry point: a ConfigError prints ``error: <msg>`` and exits with 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ConfigError as e:
            sys.stdout.flush()
            print(f"error: {e}", file=sys.stderr)
            raise SystemExit(2) from None

    return typing.cast(F, wrapper)
