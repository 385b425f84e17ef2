"""What each module of the package imports from the package, one line per module, and the rules
the graph keeps.

    python experiments/imports.py [repo root]   # default: this repository
    python experiments/imports.py --write       # and put it into docs/design.md

The env package (``envs/``, installed as ``rdher_jax.envs``) is a group of its own. The rules,
checked after the graph (exit status 1 on a violation; ``tests/test_packaging.py`` runs them):

- ``envs`` imports nothing from ``rdher_jax`` outside itself;
- no command line (``train``, ``sweep``, ``evaluate``) imports another;
- no module but the task registry (``envs/registry.py``) and ``tasks`` (the trainer's table,
  keyed by the registry's names) names a task: has a string that is a task's name (with or
  without gymnasium's ``-v4``). Prose that mentions one (docstrings, help text, messages) is
  documentation, not a second table.

docs/design.md shows its output. In-function imports count (they are still dependencies).
"""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path

ENVS = "rdher_jax.envs"
REGISTRY = "rdher_jax.envs.registry"
CLI = ("rdher_jax.train", "rdher_jax.sweep", "rdher_jax.evaluate")
# Modules allowed to name tasks: the registry, and the trainer's table keyed by its names.
TASK_TABLES = (REGISTRY, "rdher_jax.tasks")
# (module, task) pairs that may stay, and why.
ALLOWED_TASK_NAMES = {
    ("rdher_jax.config", "FetchReach"): "the default env=, checked against the registry as any",
}


def modules(root: Path) -> dict[str, Path]:
    out = {}
    for base, pkg in ((root / "rdher_jax", "rdher_jax"), (root / "envs", ENVS)):
        for f in sorted(base.rglob("*.py")):
            rel = f.relative_to(base).with_suffix("")
            if rel.parts[:1] == ("envs",) and pkg == "rdher_jax":
                continue  # a checkout's link to envs/, listed as envs itself
            out[".".join([pkg] + [p for p in rel.parts if p != "__init__"])] = f
    return out


def graph(root: Path) -> dict[str, list[str]]:
    mods = modules(root)
    out = {}
    for name, f in mods.items():
        pkg = name if f.name == "__init__.py" else name.rsplit(".", 1)[0]
        deps = set()
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                parts = pkg.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] if node.level else [])
                target = ".".join(x for x in (base, node.module or "") if x)
                subs = [f"{target}.{a.name}" for a in node.names]
                cands = subs if not node.module or any(s in mods for s in subs) else [target]
            elif isinstance(node, ast.Import):
                cands = [a.name for a in node.names]
            else:
                continue
            deps.update(c for c in cands if c in mods and c != name)
        out[name] = sorted(deps)
    return out


def task_names(root: Path) -> tuple[str, ...]:
    """The registry's task names, each also with gymnasium's version suffix, read from
    ``envs/registry.py`` under ``root`` (it imports nothing of the package); () where there is
    none."""
    path = root / "envs" / "registry.py"
    if not path.exists():
        return ()
    spec = importlib.util.spec_from_file_location("_registry_under_check", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses resolves annotations through it
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules[spec.name]
    return tuple(mod.TASK_NAMES) + tuple(f"{n}-{mod.GYMNASIUM_VERSION}" for n in mod.TASK_NAMES)


def violations(root: Path) -> list[str]:
    """Every break of the rules above, one line each."""
    out = []
    g = graph(root)
    for name, deps in g.items():
        if name == ENVS or name.startswith(ENVS + "."):
            out += [f"{name} imports {d}, outside envs" for d in deps
                    if not (d == ENVS or d.startswith(ENVS + "."))]
        if name in CLI:
            out += [f"command line {name} imports command line {d}" for d in deps if d in CLI]
    names = set(task_names(root))
    for name, f in modules(root).items():
        if name in TASK_TABLES:
            continue
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
                continue
            if node.value in names and (name, node.value) not in ALLOWED_TASK_NAMES:
                out.append(f"{name}:{node.lineno} names task {node.value!r} outside the "
                           "registry")
    return out


BEGIN, END = "<!-- imports.py: begin -->", "<!-- imports.py: end -->"
DOC = Path("docs") / "design.md"


def report(root: Path) -> tuple[str, list[str]]:
    """The graph and the rules' verdict as text, and the violations."""
    short = lambda m: m.removeprefix("rdher_jax.")  # noqa: E731
    g = graph(root)
    lines = []
    for title, envs in (("rdher_jax", False), ("envs (installed as rdher_jax.envs)", True)):
        lines.append(f"# {title}")
        lines += [f"{short(k):18s} -> {', '.join(short(x) for x in v) or '-'}"
                  for k, v in g.items() if (k == ENVS or k.startswith(ENVS + ".")) == envs]
    bad = violations(root)
    lines += [f"violation: {line}" for line in bad]
    if not bad:
        allowed = "; ".join(f"{m} names {t}: {why}" for (m, t), why in ALLOWED_TASK_NAMES.items())
        lines.append(f"# rules kept: envs imports only envs; no command line imports another; "
                     f"task names only in {', '.join(map(short, TASK_TABLES))} "
                     f"(allowed: {allowed})")
    return "\n".join(lines) + "\n", bad


def with_graph(doc: str, text: str) -> str:
    """``doc`` (docs/design.md) with the block between its markers replaced by ``text``."""
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n```\n{text}```\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    """``imports.py [root] [--write]``: print the graph; ``--write`` also puts it into
    docs/design.md between its markers. Exit 1 on a broken rule."""
    argv = sys.argv[1:] if argv is None else argv
    write = "--write" in argv
    paths = [a for a in argv if a != "--write"]
    root = Path(paths[0]) if paths else Path(__file__).resolve().parent.parent
    text, bad = report(root)
    print(text, end="")
    if write:
        doc = root / DOC
        doc.write_text(with_graph(doc.read_text(encoding="utf-8"), text), encoding="utf-8")
        print(f"wrote {doc}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
