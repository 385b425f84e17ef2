"""What each module of the package imports from the package: one line per module.

    python experiments/imports.py [repo root]   # default: this repository

docs/design.md shows its output before and after the one-driver change. In-function imports
count (they are still dependencies).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path


def modules(root: Path) -> dict[str, Path]:
    out = {}
    for base, pkg in ((root / "rdher_jax", "rdher_jax"), (root / "envs", "rdher_jax.envs")):
        for f in sorted(base.rglob("*.py")):
            rel = f.relative_to(base).with_suffix("")
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


def main() -> None:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent
    short = lambda m: m.removeprefix("rdher_jax.")  # noqa: E731
    for k, v in graph(root).items():
        print(f"{short(k):18s} -> {', '.join(short(x) for x in v) or '-'}")


if __name__ == "__main__":
    main()
