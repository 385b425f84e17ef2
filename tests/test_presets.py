"""``preset=fast`` against its values written out here, not read back from ``PRESETS``."""

import dataclasses

import pytest

from rdher_jax.config import Config, parse_args

# What docs/performance.md's 'preset=fast' section and bench_learning measured; a change to
# PRESETS that is not a change to these numbers is a bug.
FAST = {
    "num_envs": 1,
    "n_batches": 40,
    "layers": 2,
    "action_l2": 0.0,
    "target_every": 2,
    "polyak": 0.99,
    "target_noise": 0.2,
    "policy_delay": 2,
    "terminal": "exact",
    "dher_fraction": 0.2,
    "overlap": True,
}


def test_fast_preset_values() -> None:
    cfg = parse_args(["preset=fast"])
    assert cfg.preset == "fast"
    got = {k: getattr(cfg, k) for k in FAST}
    assert got == FAST
    for k, v in FAST.items():
        assert type(getattr(cfg, k)) is type(v), k  # 0.0 stays a float, 1 an int
    # Every other key keeps its default: the preset changes exactly these.
    default = Config()
    others = [f.name for f in dataclasses.fields(Config) if f.name not in (*FAST, "preset")]
    assert {k: getattr(cfg, k) for k in others} == {k: getattr(default, k) for k in others}


@pytest.mark.parametrize("argv", [["preset=fast", "polyak=0.9"], ["polyak=0.9", "preset=fast"]])
def test_explicit_key_overrides_the_preset(argv) -> None:
    cfg = parse_args(argv)
    assert cfg.polyak == 0.9
    assert {k: getattr(cfg, k) for k in FAST if k != "polyak"} == {
        k: v for k, v in FAST.items() if k != "polyak"}


def test_override_back_to_the_default_value() -> None:
    # terminal=none is the default: an explicit value equal to the default still wins.
    cfg = parse_args(["preset=fast", "terminal=none", "layers=3"])
    assert (cfg.terminal, cfg.layers) == ("none", 3)
    assert (cfg.num_envs, cfg.policy_delay) == (1, 2)
