"""Orbax checkpoints of a run: the latest training state and the best policy.

Layout under ``<run_dir>/checkpoints``::

    latest/<epoch>/{state,meta}   full training state (networks, optimisers, replay buffer, keys)
    best/<epoch>/{state,meta}     the policy of the best test epoch so far
    candidates/<epoch>/...        select_top > 1: the policies of the select_top best test epochs
    selected/<epoch>/...          select_top > 1: the one of them that did best on the selection
                                  episodes at the end of training (the run's policy)

Each directory but ``candidates`` keeps one step. Orbax writes a step into
``<epoch>.orbax-checkpoint-tmp-<t>`` and renames it to ``<epoch>`` once complete (atomic on
POSIX), so an integer-named directory is always a finished save. A process killed mid-save leaves
only a temporary directory, which is ignored on restore and removed by the next writer; the
previous step stays restorable.
"""

import contextlib
import json
import shutil
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from orbax.checkpoint import checkpoint_managers

from rdher_jax.runlog import json_default

# Beside the checkpoints, in the run directory: the choice the ``selected`` slot holds, as JSON.
SELECT_FILE = "selection.json"
_TMP_MARK = ".orbax-checkpoint-tmp"
_TRASH_PREFIX = ".deleting-"


class CheckpointError(RuntimeError):
    """A checkpoint is missing or does not fit the requested template (one-line message)."""

    def __init__(self, msg: str) -> None:
        super().__init__(" ".join(str(msg).split()))


def _remove(path: Path) -> None:
    """Delete a directory so that a kill midway never leaves a half-deleted step behind.

    The rename is atomic; the slow rmtree then only ever sees a name that is no step.
    """
    trash = path.with_name(f"{_TRASH_PREFIX}{path.name}-{uuid.uuid4().hex[:8]}")
    path.rename(trash)
    shutil.rmtree(trash, ignore_errors=True)


def _step_dirs(directory: Path) -> dict[int, Path]:
    return {int(p.name): p for p in directory.iterdir() if p.is_dir() and p.name.isdigit()}


def _tidy(directory: Path, keep_all: bool = False) -> None:
    """Remove unfinished saves, interrupted deletions and (unless ``keep_all``) steps older
    than the newest.

    Orbax deletes an old step only after the new one is renamed into place, so the highest
    integer-named step is complete and any lower one is a leftover of an interrupted deletion.
    """
    for p in directory.iterdir():
        if p.name.startswith(_TRASH_PREFIX) or _TMP_MARK in p.name:
            shutil.rmtree(p, ignore_errors=True)
    if keep_all:
        return
    steps = _step_dirs(directory)
    for step in sorted(steps)[:-1]:
        _remove(steps[step])


def _key_str(k: Any) -> str:
    for attr in ("name", "key", "idx"):  # GetAttrKey, DictKey/FlattenedIndexKey, SequenceKey
        if hasattr(k, attr):
            return str(getattr(k, attr))
    return str(k)


def _path_str(path: tuple) -> str:
    return ".".join(_key_str(k) for k in path) or "<root>"


def _template_spec(leaf: Any) -> tuple[tuple[int, ...], np.dtype | None]:
    dtype = getattr(leaf, "dtype", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        # Typed PRNG keys are stored as their raw uint32 key data.
        data = jax.eval_shape(jax.random.key_data, leaf)
        return tuple(data.shape), np.dtype(data.dtype)
    shape = tuple(getattr(leaf, "shape", np.shape(leaf)))
    # Python scalars carry no dtype of their own; only their shape () is checked.
    return shape, None if dtype is None else np.dtype(dtype)


def _mismatches(saved: Any, template: Any) -> list[str]:
    """Human-readable differences between checkpoint metadata and a restore template."""
    is_meta = lambda x: hasattr(x, "shape") and hasattr(x, "dtype")  # ArrayMetadata & co.
    have = {
        _path_str(p): (tuple(m.shape), m.dtype)
        for p, m in jax.tree_util.tree_flatten_with_path(saved, is_leaf=is_meta)[0]
    }
    want = {
        _path_str(p): _template_spec(leaf)
        for p, leaf in jax.tree_util.tree_flatten_with_path(template)[0]
    }
    # Structural differences first: they explain any shape differences that follow.
    out = [f"{k} missing from the checkpoint" for k in sorted(want) if k not in have]
    out += [f"{k} in the checkpoint but not in the template" for k in sorted(have) if k not in want]
    for k in sorted(want.keys() & have.keys()):
        (ws, wd), (hs, hd) = want[k], have[k]
        if ws != hs:
            out.append(f"{k} has shape {hs} in the checkpoint but {ws} in the template")
        elif wd is not None and hd is not None and np.dtype(hd) != wd:
            out.append(f"{k} has dtype {np.dtype(hd)} in the checkpoint but {wd} in the template")
    return out


def _arrays(tree: Any) -> Any:
    """numpy scalars (np.float32(1), np.int64(5)) as 0-d arrays, which orbax accepts."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if isinstance(x, np.generic) else x, tree)


def _host_tree(tree: Any) -> Any:
    """``tree`` for orbax to save: itself with one process; with several (a multi-process
    sweep), the same leaves as host arrays in nested dicts keyed as orbax keys them on disk.

    Orbax refuses to save a process-local ``jax.Array`` when JAX runs several processes, and
    some nodes turn host arrays back into ``jax.Array`` when rebuilt (brax's ``UInt64``), so
    the tree's own classes cannot carry host arrays there. The files are the same either way,
    and a restore into the original template gives its classes back.
    """
    if jax.process_count() == 1:
        return _arrays(tree)
    # orbax's own nested dicts and lists of the tree, empty nodes kept.
    plain = ocp.tree.serialize_tree(tree, keep_empty_nodes=True)
    return jax.tree_util.tree_map(np.asarray, plain)


def _options(collective: bool) -> ocp.options.MultiprocessingOptions:
    """Orbax's multi-process options of a slot.

    One process: orbax's defaults. Several (a multi-process sweep, ``rdher_jax.distributed``):
    a ``collective`` slot is saved by every process together, each writing the shards of a
    global ``jax.Array`` on its own devices (the sweep's latest state); any other slot is
    process 0's alone (a run's best policy, as host arrays, which orbax writes from process 0
    only).
    """
    if jax.process_count() == 1 or collective:
        return ocp.options.MultiprocessingOptions()
    return ocp.options.MultiprocessingOptions(primary_host=0, active_processes={0},
                                              barrier_sync_key_prefix="process0")


class _Slot:
    """One checkpoint directory holding a single step (``latest``, ``best``, ``selected``), or
    any number of them (``keep_all``: ``candidates``, whose steps its owner removes)."""

    def __init__(self, directory: Path, read_only: bool, collective: bool = False,
                 keep_all: bool = False) -> None:
        self.directory = directory
        self.read_only = read_only
        self.collective = collective
        self.keep_all = keep_all
        if not read_only:
            directory.mkdir(parents=True, exist_ok=True)
            if jax.process_index() == 0:  # one tidier of a directory all processes share
                _tidy(directory, keep_all)
        self._mgr: ocp.CheckpointManager | None = None

    @property
    def mgr(self) -> ocp.CheckpointManager:
        # Created lazily: a read-only slot may not exist yet, and orbax would refuse it.
        if self._mgr is None:
            options = ocp.CheckpointManagerOptions(
                preservation_policy=checkpoint_managers.LatestN(n=None if self.keep_all else 1),
                enable_async_checkpointing=False,  # "saved" must mean "on disk"
                # Read-only is enforced here rather than with orbax's read_only option,
                # which logs warnings on every open.
                # A writable slot made its directory itself (orbax cannot create it for
                # one process of several).
                create=not self.read_only and jax.process_count() == 1,
                cleanup_tmp_directories=False,  # _tidy did it, synchronously
                multiprocessing_options=_options(self.collective),
            )
            self._mgr = ocp.CheckpointManager(
                self.directory.absolute(),
                options=options,
                item_handlers={
                    "state": ocp.StandardCheckpointHandler(
                        multiprocessing_options=_options(self.collective)),
                    "meta": ocp.JsonCheckpointHandler(
                        multiprocessing_options=_options(self.collective)),
                },
            )
        return self._mgr

    def latest(self) -> int | None:
        if not self.directory.is_dir():
            return None
        if self.read_only:
            # Another process may be writing this run, and deletes the previous step right
            # after renaming a new one into place: a reload that catches that moment retries.
            for attempt in range(5):
                try:
                    self.mgr.reload()
                    break
                except FileNotFoundError:
                    if attempt == 4:
                        raise
                    time.sleep(0.05)
        return self.mgr.latest_step()

    def _check_writable(self) -> None:
        if self.read_only:
            raise CheckpointError(f"{self.directory} was opened read-only")

    def save(self, step: int, tree: Any, meta: Mapping[str, Any]) -> None:
        self._check_writable()
        meta = json.loads(json.dumps(dict(meta), default=json_default))
        # Steps at or after `step` come from a timeline abandoned by a resume; orbax would
        # silently skip saving an existing or older step, so they go first.
        stale = [s for s in self.mgr.all_steps() if s >= step]
        if self.keep_all:  # a step may be saved below a kept one
            stale = [s for s in stale if s == step]
        for s in stale:
            if jax.process_index() == 0:  # a collective slot's directory is shared
                _remove(self.directory / str(s))
        if stale:
            self.mgr.reload()
        args = ocp.args.Composite(
            state=ocp.args.StandardSave(tree if self.collective else _host_tree(tree)),
            meta=ocp.args.JsonSave(meta)
        )
        saved = self.mgr.save(step, args=args, force=True)
        self.mgr.wait_until_finished()
        if not saved or not (self.directory / str(step)).is_dir():
            raise CheckpointError(f"orbax did not write step {step} to {self.directory}")

    def meta(self, step: int | None = None) -> tuple[int, dict] | None:
        step = self.latest() if step is None else step
        if step is None:
            return None
        restored = self.mgr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        return step, dict(restored.meta)

    def steps(self) -> list[int]:
        if not self.directory.is_dir():
            return []
        self.latest()  # reloads a read-only slot
        return sorted(self.mgr.all_steps())

    def remove(self, step: int) -> None:
        self._check_writable()
        _remove(self.directory / str(step))
        self.mgr.reload()

    def restore(self, template: Any, step: int | None = None) -> tuple[int, Any, dict]:
        step = self.latest() if step is None else step
        if step is None:
            raise CheckpointError(f"no checkpoint in {self.directory}")
        template = _arrays(template)
        if template is not None:
            saved = self.mgr.item_metadata(step)["state"]
            saved = getattr(saved, "tree", saved)
            diff = _mismatches(saved, template)
            if diff:
                more = f" (and {len(diff) - 1} more)" if len(diff) > 1 else ""
                raise CheckpointError(
                    f"checkpoint {self.directory / str(step)} does not fit the template: "
                    f"{diff[0]}{more}"
                )
        multi = template is not None and jax.process_count() > 1 and not self.collective
        state_args = ocp.args.StandardRestore(_host_tree(template) if multi else template)
        restored = self.mgr.restore(
            step, args=ocp.args.Composite(state=state_args, meta=ocp.args.JsonRestore())
        )
        state = restored.state
        if multi:  # saved by _host_tree as nested dicts: back into the template's classes
            state = ocp.tree.deserialize_tree(state, template, keep_empty_nodes=True)
        return step, state, dict(restored.meta or {})

    def close(self) -> None:
        if self._mgr is not None:
            self._mgr.close()
            self._mgr = None


class Checkpointer:
    """Latest training state and best policy of one run, under ``<run_dir>/checkpoints``.

    Saves are synchronous: when ``save_*`` returns, the step is renamed into place on disk.
    ``latest=False`` or ``best=False`` leaves that slot out (a sweep keeps its runs' stacked
    latest state in the sweep directory and each run's best policy in the run's).
    ``read_only=True`` is for readers of a run that may still be training (evaluation,
    plotting): they never delete anything, including the writer's in-progress saves.
    """

    def __init__(self, run_dir: str | Path, read_only: bool = False, latest: bool = True,
                 best: bool = True, latest_name: str = "latest",
                 collective: bool = False, select: bool = False) -> None:
        self.directory = Path(run_dir) / "checkpoints"
        # A sweep keeps its stacked latest state in its own directory and each run's best
        # policy in the run's, so either slot can be left out. ``collective``: the latest state
        # is a global array that every process of a multi-process sweep saves together, under
        # a name of its own (``latest_name``).
        self._latest = (_Slot(self.directory / latest_name, read_only, collective)
                        if latest else None)
        self._best = _Slot(self.directory / "best", read_only) if best else None
        # The policy choice at the end of training (select_top > 1): written by a run that
        # keeps candidates (``select``), read by any reader (absent: the best policy is it).
        with_select = best and (select or read_only)
        self._candidates = (_Slot(self.directory / "candidates", read_only, keep_all=True)
                            if with_select else None)
        self._selected = _Slot(self.directory / "selected", read_only) if with_select else None
        self._slots = [s for s in (self._latest, self._best, self._candidates, self._selected)
                       if s is not None]

    def _slot(self, name: str) -> _Slot:
        slot = getattr(self, f"_{name}")
        if slot is None:
            raise CheckpointError(f"{self.directory} was opened without its {name} slot")
        return slot

    def save_latest(self, epoch: int, state: Any, meta: Mapping[str, Any]) -> None:
        """Save the full training state after ``epoch``, replacing the previous one."""
        self._slot("latest").save(epoch, state, meta)

    def save_best(self, epoch: int, policy: Any, meta: Mapping[str, Any]) -> None:
        """Save the policy of a new best epoch, replacing the previous best."""
        self._slot("best").save(epoch, policy, meta)

    def latest_epoch(self) -> int | None:
        """Epoch of the latest complete checkpoint, or None."""
        return self._slot("latest").latest()

    def best_epoch(self) -> int | None:
        """Epoch of the best-policy checkpoint, or None."""
        return self._slot("best").latest()

    def best_meta(self) -> dict | None:
        """Metadata saved with the best policy (e.g. its test success), or None."""
        found = self._slot("best").meta()
        return None if found is None else found[1]

    def save_candidate(self, epoch: int, policy: Any, meta: Mapping[str, Any]) -> None:
        """Keep the policy of ``epoch`` among the candidates for the final choice."""
        self._slot("candidates").save(epoch, policy, meta)

    def candidates(self) -> dict[int, dict]:
        """The kept candidates' metadata by epoch ({} where none are kept)."""
        slot = self._candidates
        if slot is None:
            return {}
        return {s: slot.meta(s)[1] for s in slot.steps()}

    def drop_candidate(self, epoch: int) -> None:
        self._slot("candidates").remove(epoch)

    def restore_candidate(self, epoch: int, template: Any) -> tuple[int, Any, dict]:
        return self._slot("candidates").restore(template, epoch)

    def save_selected(self, epoch: int, policy: Any, meta: Mapping[str, Any]) -> None:
        """Save the policy chosen among the candidates at the end of training."""
        self._slot("selected").save(epoch, policy, meta)

    def clear_selected(self) -> None:
        """Forget the choice (a resumed run trains on and chooses again when it ends)."""
        slot = self._slot("selected")
        for step in slot.steps():
            slot.remove(step)

    def selected_epoch(self) -> int | None:
        """Epoch of the policy chosen among the candidates, or None (no choice made, or a
        checkpointer opened without the slot)."""
        return None if self._selected is None else self._selected.latest()

    def policy_epoch(self) -> int | None:
        """Epoch of the run's policy: the selected one where a choice was made, else the best
        test epoch's; None without either."""
        chosen = self.selected_epoch()
        return self.best_epoch() if chosen is None else chosen

    def restore_policy(self, template: Any) -> tuple[int, Any, dict]:
        """``(epoch, policy, meta)`` of the run's policy (see :meth:`policy_epoch`)."""
        chosen = self.selected_epoch()
        return self.restore_best(template) if chosen is None else self._selected.restore(template)

    def restore_latest(self, template: Any) -> tuple[int, Any, dict]:
        """``(epoch, state, meta)`` of the latest checkpoint, restored into ``template``'s
        structure, shapes and dtypes (a mismatch raises CheckpointError)."""
        return self._slot("latest").restore(template)

    def restore_best(self, template: Any) -> tuple[int, Any, dict]:
        """``(epoch, policy, meta)`` of the best checkpoint, like :meth:`restore_latest`."""
        return self._slot("best").restore(template)

    def discard_after(self, epoch: int) -> None:
        """Delete checkpoints newer than ``epoch`` (a resume from ``epoch`` abandons them)."""
        for slot in self._slots:
            slot._check_writable()
            for step in slot.steps():
                if step > epoch:
                    slot.remove(step)

    def close(self) -> None:
        """Release orbax's resources; the object may be used again afterwards."""
        for slot in self._slots:
            slot.close()

    def __enter__(self) -> "Checkpointer":
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(Exception):
            self.close()
