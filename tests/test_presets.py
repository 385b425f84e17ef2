"""``preset=fast`` against its documentation: the table of keys, defaults and values in
docs/performance.md is what a reader trusts, so the code must set exactly what it says."""

import dataclasses
import re
from pathlib import Path

import pytest

from rdher_jax.config import PRESETS, Config, parse_args

DOC = Path(__file__).resolve().parents[1] / "docs" / "performance.md"


def _value(text: str):
    """A table cell's value as the config holds it: '0.2 (clipped at 0.5)' -> 0.2."""
    word = text.strip().strip("`").split(" (")[0].strip().strip("`")
    if word in ("true", "false"):
        return word == "true"
    for cast in (int, float):
        try:
            return cast(word)
        except ValueError:
            pass
    return word


def documented_fast() -> dict[str, tuple]:
    """{key: (default, fast)} from the 'preset=fast' table of docs/performance.md."""
    text = DOC.read_text(encoding="utf-8")
    section = text.split("## FetchPush on a 2-core CPU: `preset=fast`", 1)[1]
    table = section.split("| key | default | `fast` | why |", 1)[1].split("\n\n", 1)[0]
    rows = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        keys = re.findall(r"`(\w+)`", cells[0])
        defaults, fast = cells[1].split(", "), cells[2].split(", ")
        assert len(keys) == len(defaults) == len(fast), line
        rows.update({k: (_value(d), _value(f)) for k, d, f in zip(keys, defaults, fast,
                                                                    strict=True)})
    return rows


def test_fast_preset_is_the_documented_table() -> None:
    doc = documented_fast()
    assert doc, "no preset=fast table found in docs/performance.md"
    assert set(doc) == set(PRESETS["fast"].values), "the table and the preset list other keys"
    cfg, default = parse_args(["preset=fast"]), Config()
    for k, (doc_default, doc_fast) in doc.items():
        assert getattr(default, k) == doc_default, f"{k}: default {getattr(default, k)!r}"
        assert getattr(cfg, k) == doc_fast, f"{k}: preset=fast sets {getattr(cfg, k)!r}"
        assert type(getattr(cfg, k)) is type(getattr(default, k)), k  # 0.0 stays a float
    # Every other key keeps its default: the preset changes exactly the documented keys.
    others = [f.name for f in dataclasses.fields(Config) if f.name not in (*doc, "preset")]
    assert {k: getattr(cfg, k) for k in others} == {k: getattr(default, k) for k in others}


def test_the_table_reader_sees_a_changed_value(tmp_path, monkeypatch) -> None:
    """The check can fail: a table that documents another value is caught."""
    text = DOC.read_text(encoding="utf-8").replace("| `layers` | 3 | 2 |", "| `layers` | 3 | 4 |")
    fake = tmp_path / "performance.md"
    fake.write_text(text)
    monkeypatch.setattr(__import__(__name__), "DOC", fake)
    with pytest.raises(AssertionError, match="layers"):
        test_fast_preset_is_the_documented_table()


@pytest.mark.parametrize("argv", [["preset=fast", "polyak=0.9"], ["polyak=0.9", "preset=fast"]])
def test_explicit_key_overrides_the_preset(argv) -> None:
    cfg = parse_args(argv)
    fast = PRESETS["fast"].values
    assert cfg.polyak == 0.9
    assert {k: getattr(cfg, k) for k in fast if k != "polyak"} == {
        k: v for k, v in fast.items() if k != "polyak"}


def test_override_back_to_the_default_value() -> None:
    # terminal=none is the default: an explicit value equal to the default still wins.
    cfg = parse_args(["preset=fast", "terminal=none", "layers=3"])
    assert (cfg.terminal, cfg.layers) == ("none", 3)
    assert (cfg.num_envs, cfg.policy_delay) == (1, 2)


def documented_budgets() -> dict[str, tuple[int, int, dict]]:
    """{task: (epochs, env steps, {key: value})} from the per-task table under the preset's."""
    text = DOC.read_text(encoding="utf-8")
    table = text.split("| task | `epochs` under `preset=fast` | env steps | other keys |", 1)[1]
    rows = {}
    for line in table.split("\n\n", 1)[0].strip().splitlines()[1:]:
        task, epochs, steps, other = (c.strip() for c in line.strip().strip("|").split("|"))
        keys = dict(kv.split("=") for kv in re.findall(r"`(\w+=[^`]+)`", other))
        rows[task] = (int(epochs), int(steps.replace(",", "")),
                      {k: _value(v) for k, v in keys.items()})
    return rows


def test_fast_budget_per_task_is_the_documented_table() -> None:
    from rdher_jax.config import episode_length, resolve
    from rdher_jax.tasks import TASKS

    doc = documented_budgets()
    assert doc == {t: (task.preset_values["fast"]["epochs"], doc[t][1],
                       {k: v for k, v in task.preset_values["fast"].items() if k != "epochs"})
                   for t, task in TASKS.items() if "fast" in task.preset_values}
    for task, (epochs, steps, other) in doc.items():
        for argv in (["preset=fast", f"env={task}"], [f"env={task}", "preset=fast"]):
            cfg = resolve(parse_args(argv))
            assert cfg.epochs == epochs, (argv, cfg.epochs)
            assert cfg.epochs * cfg.n_cycles * cfg.num_envs * episode_length(cfg) == steps
        assert {k: getattr(cfg, k) for k in other} == other
        # An explicit key wins, and the preset's own values are the same for every task.
        assert parse_args(["preset=fast", f"env={task}", "epochs=3"]).epochs == 3
        assert parse_args(["preset=fast", f"env={task}", "n_critics=1"]).n_critics == 1
        assert parse_args(["preset=fast", f"env={task}"]).n_batches == PRESETS["fast"].values[
            "n_batches"]
    # A task without its own budget keeps its default epochs.
    assert resolve(parse_args(["preset=fast", "env=FetchReach"])).epochs == TASKS[
        "FetchReach"].epochs
