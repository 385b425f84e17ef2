"""The installed package holds every subpackage: a non-editable install (``pip install .``, or a
wheel) ships only the packages pyproject.toml lists, so one missing from the list breaks every
run outside an editable checkout (as ``rdher_jax.relabel`` once did)."""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")

ROOT = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed_for_installation():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]
    listed = set(cfg["setuptools"]["packages"])
    dirs = cfg["setuptools"].get("package-dir", {})
    expected = set()
    for name, src in {"rdher_jax": "rdher_jax", **dirs}.items():
        base = ROOT / src
        expected |= {".".join((name, *init.parent.relative_to(base).parts))
                     for init in base.rglob("__init__.py")}
    assert expected - listed == set(), f"not installed by pip install .: {expected - listed}"


def _imports_script():
    spec = importlib.util.spec_from_file_location("imports", ROOT / "experiments" / "imports.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_import_rules_hold():
    """envs imports nothing of rdher_jax outside itself, no command line imports another, and
    no module but the task registry and the trainer's table names a task
    (experiments/imports.py)."""
    assert _imports_script().violations(ROOT) == []


def test_the_import_rules_catch_a_break(tmp_path):
    (tmp_path / "envs").mkdir()
    shutil.copy(ROOT / "envs" / "registry.py", tmp_path / "envs" / "registry.py")
    (tmp_path / "envs" / "__init__.py").write_text("from rdher_jax import tasks\n")
    (tmp_path / "rdher_jax").mkdir()
    for name, text in {"__init__.py": "", "tasks.py": "T = {'FetchPush': 1}\n",
                       "train.py": "from . import sweep\n", "sweep.py": "",
                       "evaluate.py": "'''FetchPush, as a docstring.'''\nX = 'FetchPush-v4'\n"
                       }.items():
        (tmp_path / "rdher_jax" / name).write_text(text)
    assert sorted(_imports_script().violations(tmp_path)) == [
        "command line rdher_jax.train imports command line rdher_jax.sweep",
        "rdher_jax.envs imports rdher_jax.tasks, outside envs",
        "rdher_jax.evaluate:2 names task 'FetchPush-v4' outside the registry",
    ]


def test_the_trainer_table_has_one_row_per_registry_task():
    """``rdher_jax.tasks`` adds the trainer's and the paper's facts to the registry's tasks:
    the same tasks, in the same order."""
    from rdher_jax.envs import registry

    from rdher_jax import tasks

    assert tuple(tasks.TASKS) == registry.TASK_NAMES


def test_the_registry_imports_neither_jax_nor_mujoco():
    """The command line validates a config before JAX loads: the registry, the trainer's table
    and the config import neither JAX nor MuJoCo."""
    code = ("import sys, rdher_jax.envs.registry, rdher_jax.tasks, rdher_jax.config; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'mujoco')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout == "[]\n", (p.stdout, p.stderr)


def test_design_doc_shows_the_current_import_graph():
    """docs/design.md's graph is the one experiments/imports.py prints for this tree."""
    imports = _imports_script()
    doc = (ROOT / imports.DOC).read_text(encoding="utf-8")
    text, _ = imports.report(ROOT)
    assert imports.with_graph(doc, text) == doc, (
        "docs/design.md's import graph is stale: python experiments/imports.py --write")
