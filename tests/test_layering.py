"""Imports go downwards only (DESIGN.md layout): L0 constants/utils, L1 model|data|sim, L2 toolchain|training|eval, L3 hub."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "openfly_agent"
LEVEL = {
    "constants": 0,
    "utils": 0,
    "model": 1,
    "data": 1,
    "sim": 1,
    "toolchain": 2,
    "training": 2,
    "eval": 2,
    "hub": 3,
}
SIBLINGS_FORBIDDEN = {"model", "data", "sim"}  # L1 parts never import each other


def _part_of(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "openfly_agent" or len(parts) < 2:
        return None
    return parts[1]


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append(node.module)
    return found


def test_imports_go_downwards_only():
    problems = []
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE)
        own = rel.parts[0].removesuffix(".py") if len(rel.parts) > 0 else None
        if own not in LEVEL:
            continue
        for module in _imports(path):
            other = _part_of(module)
            if other is None or other == own or other not in LEVEL:
                continue
            if LEVEL[other] > LEVEL[own] or (own in SIBLINGS_FORBIDDEN and other in SIBLINGS_FORBIDDEN):
                problems.append(f"{rel}: imports {module} ({own} L{LEVEL[own]} -> {other} L{LEVEL[other]})")
    assert not problems, "\n".join(problems)
