"""Config parsing, validation, resolution and the CLI error contract."""

import dataclasses
import datetime
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rdher_jax.config import (
    ENV_NAMES,
    FIELD_NAMES,
    Config,
    ConfigError,
    from_yaml,
    help_text,
    main_guard,
    parse_args,
    resolve,
    resume_config,
    to_yaml,
)

# The smallest CLI that behaves like the trainer's: parse argv, print the config.
CLI = (
    "import sys; from rdher_jax.config import main_guard, parse_args; "
    "main_guard(lambda: print(parse_args(sys.argv[1:])))()"
)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", CLI, *args], capture_output=True, text=True, timeout=60
    )


def test_defaults() -> None:
    cfg = parse_args([])
    assert cfg == Config()
    assert (cfg.env, cfg.algo, cfg.seed) == ("FetchReach", "her", 0)
    assert cfg.epochs is None and cfg.n_cycles is None and cfg.gamma is None
    assert (cfg.n_batches, cfg.batch_size, cfg.num_envs, cfg.n_test_rollouts) == (40, 256, 2, 10)
    assert cfg.buffer_size == 1_000_000
    assert (cfg.backend, cfg.scene, cfg.hidden, cfg.layers) == ("auto", "auto", 256, 3)
    assert (cfg.actor_lr, cfg.critic_lr, cfg.polyak, cfg.action_l2) == (1e-3, 1e-3, 0.95, 1.0)
    assert (cfg.noise_eps, cfg.random_eps, cfg.replay_k) == (0.2, 0.3, 4)
    assert (cfg.lambda_r, cfg.lambda_h) == (None, None)
    assert (resolve(cfg).lambda_r, resolve(cfg).lambda_h) == (1.0, 1.0)
    assert cfg.run_dir is None and cfg.resume is None
    assert (cfg.checkpoint_every, cfg.tensorboard, cfg.progress) == (1, False, True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 1  # type: ignore[misc]


def test_overrides_are_typed() -> None:
    cfg = parse_args(
        [
            "env=FetchSlide",
            "seed=7",
            "epochs=3",
            "actor_lr=2e-4",
            "gamma=0.9",
            "tensorboard=true",
            "progress=false",
            "run_dir=out/x",
            "epochs=4",
        ]
    )
    assert cfg.env == "FetchSlide" and cfg.seed == 7
    assert cfg.epochs == 4  # the later token wins
    assert isinstance(cfg.actor_lr, float) and cfg.actor_lr == 2e-4
    assert cfg.gamma == 0.9 and cfg.tensorboard is True and cfg.progress is False
    assert cfg.run_dir == "out/x"
    assert parse_args(["epochs=5", "epochs=null"]).epochs is None
    assert parse_args(["polyak=1"]).polyak == 1.0  # ints are accepted for floats


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["epochz=3"], "unknown key 'epochz' (did you mean epochs?)"),
        (["env.x=1"], "unknown key 'env.x'"),
        (["seed=abc"], "invalid value 'abc' for seed (expected int)"),
        (["epochs=2.5"], "invalid value '2.5' for epochs (expected int|null)"),
        (["progress=maybe"], "for progress (expected bool)"),
        (["seed"], "malformed argument 'seed': expected key=value"),
        (["=3"], "malformed argument"),
        (
            ["env=FetchSlid"],
            "unknown env 'FetchSlid' (did you mean FetchSlide?); valid: " + ", ".join(ENV_NAMES),
        ),
        (["algo=td3"], "unknown algo 'td3'"),
        (["backend=cuda"], "unknown backend 'cuda'"),
        (["scene=new"], "unknown scene 'new'"),
        (["target_clip=none"], "unknown target_clip 'none'"),
        (["epochs=0"], "epochs must be a positive integer"),
        (["batch_size=-1"], "batch_size must be a positive integer"),
        (["seed=-1"], "seed must be in [0, 2**32)"),
        (["random_eps=1.5"], "random_eps must be in [0, 1]"),
        (["polyak=-0.1"], "polyak must be in [0, 1]"),
        (["critic_lr=0"], "critic_lr must be > 0"),
        (["gamma=1.0"], "gamma must be in (0, 1)"),
        (["stop_success=1.5"], "stop_success must be in (0, 1] or null"),
        (["stop_success=0"], "stop_success must be in (0, 1] or null"),
        (["stop_window=0"], "stop_window must be a positive integer"),
        (["actor_lr=nan"], "actor_lr must be a finite number"),
        (["replay_k=-1"], "replay_k must be >= 0"),
        (["batch_size=512", "buffer_size=100"], "must not exceed buffer_size"),
        (["goal_speed=0.01"], "goal_speed applies to the moving tasks"),
        (["env=FetchPushMoving", "goal_speed=-0.01"], "goal_speed must be >= 0"),
        (["episode_length=0"], "episode_length must be a positive integer"),
        (["episode_length=3", "n_step=4"], "n_step must be <= the episode length 3"),
    ],
)
def test_errors_are_one_line(argv: list[str], fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_args(argv)
    msg = str(info.value)
    assert fragment in msg
    assert "\n" not in msg


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["nope=1"], "unknown key 'nope'"),
        (["seed=x"], "invalid value 'x' for seed"),
        (["env=Foo"], "valid: FetchReach, FetchPush, FetchSlide, FetchPickAndPlace"),
        (["seed"], "malformed argument"),
        (["gamma=2"], "gamma must be in (0, 1)"),
    ],
)
def test_cli_error_exit_code_and_stderr(argv: list[str], fragment: str) -> None:
    proc = run_cli(*argv)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ") and fragment in lines[0]


def test_cli_success_and_help() -> None:
    ok = run_cli("env=FetchPush", "seed=3")
    assert ok.returncode == 0, ok.stderr
    assert "env='FetchPush'" in ok.stdout and "seed=3" in ok.stdout
    helped = run_cli("env=FetchPush", "--help")
    assert helped.returncode == 0 and helped.stderr == ""
    for name in FIELD_NAMES:
        assert f"\n  {name}: " in helped.stdout
    assert "epochs: int|null = null" in helped.stdout
    assert "buffer_size: int = 1000000" in helped.stdout


def test_help_in_process(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        parse_args(["-h"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out == help_text()
    for f in dataclasses.fields(Config):
        assert f.metadata["help"].split()[0] in out


def test_main_guard_passes_results_and_other_errors() -> None:
    assert main_guard(lambda x: x + 1)(1) == 2
    with pytest.raises(KeyError):
        main_guard(lambda: {}["x"])()
    with pytest.raises(SystemExit) as info:
        main_guard(lambda: parse_args(["bad"]))()
    assert info.value.code == 2


def test_resolve() -> None:
    now = datetime.datetime(2024, 5, 6, 7, 8, 9)
    reach = resolve(Config(), now=now)
    assert (reach.epochs, reach.n_cycles) == (5, 10)
    assert reach.gamma == pytest.approx(0.98)
    assert reach.run_dir == str(Path("runs") / "FetchReach-her-s0-20240506-070809")
    slide = resolve(parse_args(["env=FetchSlide", "algo=ddpg", "seed=2"]), now=now)
    assert (slide.epochs, slide.n_cycles) == (50, 50)
    assert slide.run_dir == str(Path("runs") / "FetchSlide-ddpg-s2-20240506-070809")
    kept = resolve(parse_args(["epochs=3", "n_cycles=4", "gamma=0.9", "run_dir=a"]))
    assert (kept.epochs, kept.n_cycles, kept.gamma, kept.run_dir) == (3, 4, 0.9, "a")
    assert resolve(parse_args(["resume=runs/old"])).run_dir == "runs/old"
    # T sets the default discount and the DHER ring; a null episode_length stays null (old
    # runs' config.yaml files resume unchanged).
    long = resolve(parse_args(["env=FetchPushMoving", "algo=dher", "episode_length=200"]))
    assert long.gamma == pytest.approx(1 - 1 / 200)
    assert long.dher_records == max(65536, 2 * 2 * 201 * 8)
    big = resolve(parse_args(["env=FetchPushMoving", "algo=dher", "episode_length=200",
                              "num_envs=64"]))
    assert big.dher_records == 2 * 64 * 201 * 8
    assert reach.episode_length is None and reach.goal_speed is None
    with pytest.raises(ConfigError, match="differs from resume"):
        resolve(parse_args(["resume=runs/old", "run_dir=runs/new"]))


def test_yaml_round_trip(tmp_path: Path) -> None:
    cfg = resolve(parse_args(["env=FetchPickAndPlace", "seed=5", "tensorboard=true"]))
    path = tmp_path / "config.yaml"
    path.write_text(to_yaml(cfg))
    assert from_yaml(path) == cfg
    path.write_text(to_yaml(cfg) + "bogus: 1\n")
    with pytest.raises(ConfigError, match="unknown key 'bogus'"):
        from_yaml(path)
    path.write_text(to_yaml(cfg).replace("seed: 5", "seed: five"))
    with pytest.raises(ConfigError, match="invalid value"):
        from_yaml(path)
    with pytest.raises(ConfigError, match="does not exist"):
        from_yaml(tmp_path / "missing.yaml")


def test_resume_config(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    saved = resolve(parse_args(["env=FetchPush", "seed=3", f"run_dir={run}"]))
    (run / "config.yaml").write_text(to_yaml(saved))
    argv = [f"resume={run}", "epochs=80", "progress=false"]
    cfg = resume_config(parse_args(argv), argv)
    assert (cfg.env, cfg.seed, cfg.epochs, cfg.progress) == ("FetchPush", 3, 80, False)
    assert cfg.run_dir == str(run) and cfg.resume == str(run)
    argv = [f"resume={run}", "hidden=64"]
    with pytest.raises(ConfigError, match="cannot change hidden: 256 -> 64"):
        resume_config(parse_args(argv), argv)
    with pytest.raises(ConfigError, match="does not exist"):
        argv = [f"resume={tmp_path / 'nowhere'}"]
        resume_config(parse_args(argv), argv)


@pytest.mark.parametrize(
    "env, algo, want",
    [("FetchReach", "rdher", (2.0, 1.0)), ("FetchPickAndPlace", "rdher", (2.0, 1.0)),
     ("FetchPush", "rdher", (4.0, 0.5)), ("FetchSlide", "archer", (4.0, 0.5)),
     ("FetchPushMoving", "rdher", (4.0, 0.5)), ("FetchPush", "dher", (1.0, 1.0)),
     ("FetchSlide", "her", (1.0, 1.0))],
)
def test_reward_weights_default_per_algo_and_task(env, algo, want) -> None:
    cfg = resolve(parse_args([f"env={env}", f"algo={algo}"]))
    assert (cfg.lambda_r, cfg.lambda_h) == want
    # An explicit weight wins over the paper's default, and only for that weight.
    cfg = resolve(parse_args([f"env={env}", f"algo={algo}", "lambda_h=3"]))
    assert (cfg.lambda_r, cfg.lambda_h) == (want[0], 3.0)


@pytest.mark.parametrize(
    "arg, msg",
    [("dher_fraction=1.5", "dher_fraction must be in [0, 1]"),
     ("dher_tol=0", "dher_tol must be > 0"),
     ("cher_candidates=8", "cher_candidates (8) must be >= batch_size (256)"),
     ("algo=dher dher_records=100", "dher_records (100) must be >="),
     ("algo=rdher num_envs=200 dher_records=65536", "dher_records (65536) must be >="),
     ("cher_growth=0.5", "cher_growth must be >= 1")],
)
def test_relabel_options_are_checked(arg, msg) -> None:
    with pytest.raises(ConfigError, match=re.escape(msg)):
        parse_args(arg.split())


@pytest.mark.parametrize("algo", ["ddpg", "her", "archer", "cher", "dher", "rdher"])
def test_every_algo_takes_thousands_of_envs(algo) -> None:
    # The ring of DHER matches is sized from num_envs unless given, and checked only where
    # DHER runs: a GPU-sized run needs no extra key.
    cfg = resolve(parse_args([f"algo={algo}", "num_envs=4096"]))
    assert cfg.dher_records == max(65536, 2 * 4096 * 51 * 8)
    small = resolve(parse_args([f"algo={algo}"]))
    assert small.dher_records == 65536
    # An explicit ring that is too small for DHER is not an error for the others.
    if algo in ("dher", "rdher"):
        with pytest.raises(ConfigError, match="dher_records"):
            parse_args([f"algo={algo}", "num_envs=4096", "dher_records=65536"])
    else:
        parse_args([f"algo={algo}", "num_envs=4096", "dher_records=65536"])


def test_presets_resolve_to_their_documented_values() -> None:
    from rdher_jax.config import PRESETS

    for name, preset in PRESETS.items():
        cfg = parse_args([f"preset={name}", "env=FetchPush"])
        assert cfg.preset == name and cfg.env == "FetchPush"
        for key, value in preset.values.items():
            assert getattr(cfg, key) == value, key
        # --help lists every value of every preset.
        text = help_text()
        line = " ".join(text[text.index(f"\n  {name}: "):].split("\n\n")[0].split())
        for key, value in preset.values.items():
            assert f"{key}={str(value).lower() if isinstance(value, bool) else value}" in line
    fast = PRESETS["fast"].values
    assert parse_args(["preset=fast"]).n_batches == fast["n_batches"]
    # Explicit keys win, before or after the preset.
    for argv in (["preset=fast", "n_batches=7"], ["n_batches=7", "preset=fast"]):
        cfg = parse_args(argv)
        assert cfg.n_batches == 7 and cfg.target_every == fast["target_every"]
    # No preset: the paper-faithful defaults.
    assert parse_args([]).preset is None and parse_args([]).target_every == 0
    with pytest.raises(ConfigError, match="unknown preset 'fsat' \\(did you mean fast\\?\\)"):
        parse_args(["preset=fsat"])
    # A preset survives the YAML round trip that resume relies on.
    cfg = resolve(parse_args(["preset=fast", "env=FetchPush"]), now=datetime.datetime(2026, 1, 1))
    assert from_yaml_text(to_yaml(cfg)) == cfg


def from_yaml_text(text: str) -> Config:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "config.yaml"
        p.write_text(text)
        return from_yaml(p)


def test_start_up_takes_its_host_devices_from_the_one_parse(tmp_path, monkeypatch):
    """overlap=true (given, through a preset, or saved in a resumed run) is what asks start-up
    for a second host device; the parse that decides it is the trainer's own."""
    from rdher_jax import config as config_mod
    from rdher_jax.startup import for_config
    from rdher_jax.train import parse_train_args

    monkeypatch.setitem(config_mod.PRESETS, "ov", config_mod.Preset("test", {"overlap": True}))

    def devices(*argv):
        return for_config(parse_train_args(list(argv))).host_devices

    assert devices("overlap=true") == devices("overlap=True", "env=FetchPush") == 2
    assert devices() == devices("overlap=false") == 1
    assert devices("preset=ov") == 2 and devices("preset=ov", "overlap=false") == 1
    for overlap in (True, False):
        run = tmp_path / f"run{overlap}"
        run.mkdir()
        saved = config_mod.resolve(Config(overlap=overlap, run_dir=str(run)))
        (run / "config.yaml").write_text(config_mod.to_yaml(saved))
        assert devices(f"resume={run}") == (2 if overlap else 1)
    with pytest.raises(ConfigError, match="unknown preset|preset"):
        devices("preset=nosuch")


def test_target_clip_default_is_the_committed_rows_clip() -> None:
    assert Config().target_clip == "weighted"
