"""select_top: the run's policy chosen at the end among its best test epochs' policies."""

import csv
import json
import random
from pathlib import Path

import pytest

from rdher_jax import policy_test
from rdher_jax import train as train_mod
from rdher_jax.checkpoint import Checkpointer
from rdher_jax.config import Config, ConfigError, parse_args, resolve
from rdher_jax.outputs import Progress

TINY = dict(env="FetchReach", n_cycles=2, n_batches=4, batch_size=32, buffer_size=2000,
            num_envs=2, n_test_rollouts=10, hidden=32, progress=False, seed=2,
            select_top=3, select_episodes=8)


def _top(successes: list[float], top: int) -> list[int]:
    """The epochs (1-based) of the ``top`` best test successes; of equals, the later ones."""
    order = sorted(range(len(successes)), key=lambda e: (successes[e], e), reverse=True)
    return sorted(e + 1 for e in order[:top])


def test_observe_keeps_the_top_epochs_ties_to_the_later():
    rng = random.Random(0)
    for top in (1, 2, 3, 5):
        progress = Progress.fresh(["a", "b"])
        seen: list[list[float]] = [[], []]
        for epoch in range(1, 40):
            rows = {i: {"test_success": rng.choice([0.0, 0.1, 0.5, 0.9, 1.0])} for i in (0, 1)}
            new_best, new_kept = progress.observe(rows, window=3, top=top)
            for i in (0, 1):
                seen[i].append(rows[i]["test_success"])
                assert (i in new_best) == (seen[i][-1] >= max(seen[i][:-1], default=-1.0))
                if top == 1:
                    assert new_kept == []
                    continue
                # An epoch is kept exactly when it is among the top epochs so far...
                assert (i in new_kept) == (epoch in _top(seen[i], top))
                # ... and the kept successes are those of the top epochs.
                assert sorted(progress.kept[i]) == sorted(
                    seen[i][e - 1] for e in _top(seen[i], top))


def _read(run: Path) -> list[float]:
    with open(run / "metrics.csv", newline="") as f:
        return [float(r["test_success"]) for r in csv.DictReader(f)]


def _train(tmp_path: Path, name: str, **kw) -> Path:
    cfg = resolve(Config(**{**TINY, **kw}, run_dir=str(tmp_path / name)))
    train_mod.train(cfg, log=lambda *a: None)
    return Path(cfg.run_dir)


def test_selected_policy_is_the_best_candidate_on_its_episodes(tmp_path):
    run = _train(tmp_path, "run", epochs=6)
    successes = _read(run)
    ckpt = Checkpointer(run, read_only=True)
    kept = ckpt.candidates()
    assert sorted(kept) == _top(successes, 3)
    assert all(kept[e]["test_success"] == pytest.approx(successes[e - 1]) for e in kept)
    # The best slot still holds the best test epoch; the run's policy is the selected one.
    assert ckpt.best_epoch() == _top(successes, 1)[0]
    _, _, meta = ckpt.restore_policy(None)
    scores = {int(e): c["selection_success"] for e, c in meta["candidates"].items()}
    assert sorted(scores) == sorted(kept)
    chosen = max(scores, key=lambda e: (scores[e], e))
    assert ckpt.policy_epoch() == meta["epoch"] == chosen
    assert json.loads((run / policy_test.SELECT_FILE).read_text()) == meta
    # The recorded score is the selected policy's success on the selection episodes: evaluate
    # on the same key and episode count gives it again; the retest says which policy it tests.
    again = policy_test.evaluate(run, episodes=8, seed=policy_test.SELECT_SEED + TINY["seed"])
    assert again["epoch"] == chosen and again["selected"]
    assert again["success"] == pytest.approx(scores[chosen])
    assert policy_test.retest(run, 4).startswith(f"retest: the selected policy (epoch {chosen})")

    # A resumed run forgets its choice, keeps its candidates and chooses again at the end:
    # the same candidates and the same choice as one run of as many epochs.
    short = _train(tmp_path, "short", epochs=3)
    assert Checkpointer(short, read_only=True).policy_epoch() is not None
    cfg = parse_args([f"resume={short}", "epochs=6"])
    train_mod.train(train_mod.load_resume_config(cfg, [f"resume={short}", "epochs=6"]),
                    log=lambda *a: None)
    resumed = Checkpointer(short, read_only=True)
    assert resumed.candidates() == kept
    assert resumed.restore_policy(None)[2]["candidates"] == meta["candidates"]
    assert json.loads((short / policy_test.SELECT_FILE).read_text())["candidates"] == \
        meta["candidates"]


def test_select_top_one_keeps_no_candidates_and_bad_values_are_refused(tmp_path):
    run = _train(tmp_path, "one", epochs=2, select_top=1)
    assert not (run / "checkpoints" / "candidates").exists()
    ckpt = Checkpointer(run, read_only=True)
    assert ckpt.candidates() == {} and ckpt.policy_epoch() == ckpt.best_epoch()
    for bad in ("select_top=0", "select_episodes=0"):
        with pytest.raises(ConfigError):
            resolve(parse_args([bad]))
