"""The installed package holds every subpackage: a non-editable install (``pip install .``, or a
wheel) ships only the packages pyproject.toml lists, so one missing from the list breaks every
run outside an editable checkout (as ``rdher_jax.relabel`` once did)."""

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
