"""The layering of docs/ARCHITECTURE.md ("Layers"), enforced: imports go downwards only, the parts of one level
that are siblings never import each other, training and eval never import the toolchain nor the procedural
city, and the entry points train.py / eval.py follow the level of their package. Each rule is checked on a
planted violation in a small fake package first.

Also: the package's own modules are imported at the top of a module (an import inside a function says why with a
`# lazy: <reason>` comment), and the tests mirror the package (tests/<subpackage>/).
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "openfly_agent"
LEVEL = {
    "constants": 0,
    "utils": 0,
    "model": 1,
    "data": 1,
    "sim": 1,
    "rollout": 2,
    "toolchain": 3,
    "training": 3,
    "eval": 3,
    "hub": 4,
    "recipe": 4,
}
SIBLINGS = ({"model", "data", "sim"}, {"toolchain", "training", "eval"})  # parts that never import each other
# part -> modules it never imports (a prefix covers the modules below it and their names): training and eval
# reach the simulator through sim's public modules (sim/embedded_scenes.py, sim/embedded.py, ...), never the
# procedural city, and never the data toolchain.
FORBIDDEN = dict.fromkeys(("training", "eval"), ("openfly_agent.toolchain", "openfly_agent.sim.city"))
ENTRY_POINTS = {"train.py": "training", "eval.py": "eval"}  # an entry point imports as its package does


def _module_of(path: Path, package: Path) -> str:
    """`openfly_agent.a.b` for `<package>/a/b.py`; an entry point outside the package is a module of no package."""
    if package not in path.parents:
        return path.stem
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(path: Path, package: Path) -> list[list[str]]:
    """The dotted names each import statement of `path` brings in, anywhere in the file (functions and
    TYPE_CHECKING blocks included): `import a.b` gives `a.b`; `from a import b` gives `a`, `a.b`; relative
    imports are resolved against the file's package."""
    own = _module_of(path, package)
    here = own if path.name == "__init__.py" else own.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [[alias.name] for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            source = node.module or ""
            if node.level:
                base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            found.append([source] + [f"{source}.{alias.name}" for alias in node.names])
    return found


def _part_of(name: str, package_name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if parts[0] == package_name and len(parts) > 1 else None


def _broken_rule(name: str, own: str, package_name: str) -> str | None:
    """Why importing `name` from part `own` breaks the layering (None: it does not)."""
    for prefix in FORBIDDEN.get(own, ()):
        forbidden = prefix.replace("openfly_agent", package_name, 1)
        if name.startswith(forbidden):  # `sim.city` covers `sim.city_vocab` too
            return f"{own} never imports {forbidden}"
    other = _part_of(name, package_name)
    if other is None or other == own or other not in LEVEL:
        return None
    if LEVEL[other] > LEVEL[own]:
        return f"{own} L{LEVEL[own]} -> {other} L{LEVEL[other]}: upwards"
    if any({own, other} <= group for group in SIBLINGS):
        return f"{own} and {other} are siblings: never each other"
    return None


def layering_violations(package: Path, entry_points: dict[Path, str] | None = None) -> list[str]:
    """One line per import statement that breaks a rule of the module docstring (the first name it brings in
    that does), for the package at `package` (its folder name is its import name) and the entry-point scripts
    `entry_points` (path -> the part it acts as)."""
    files = {path: path.relative_to(package).parts[0].removesuffix(".py") for path in package.rglob("*.py")}
    files.update(entry_points or {})
    problems = []
    for path, own in sorted(files.items()):
        if own not in LEVEL:
            continue
        for names in imported_names(path, package):
            broken = [(name, why) for name in names if (why := _broken_rule(name, own, package.name))]
            if broken:
                name, why = broken[0]
                problems.append(f"{path.relative_to(package.parent)}: imports {name} ({why})")
    return sorted(problems)


def test_the_layering_check_finds_each_planted_violation(tmp_path):
    package = tmp_path / "openfly_agent"
    clean = {
        "__init__.py": "",
        "constants.py": "",
        "utils/__init__.py": "from openfly_agent import constants\n",
        "model/__init__.py": "",
        "model/net.py": "from openfly_agent.utils import x\nfrom .. import constants\n",
        "sim/__init__.py": "",
        "sim/city.py": "",
        "sim/embedded_scenes.py": "from openfly_agent.sim.city import City\n",
        "rollout/__init__.py": "from openfly_agent.model.net import Net\nimport openfly_agent.sim.embedded_scenes\n",
        "training/__init__.py": "from openfly_agent.sim.embedded_scenes import scenes\n",
        "training/loop.py": "from openfly_agent.rollout import run\nfrom . import helpers\n",
        "toolchain/__init__.py": "from openfly_agent.sim import city\n",
        "eval/__init__.py": "",
        "hub/__init__.py": "from openfly_agent.eval import report\nfrom openfly_agent.training import loop\n",
    }
    _write(package, clean)
    entry = tmp_path / "train.py"
    entry.write_text("from openfly_agent.training import loop\n")
    assert layering_violations(package, {entry: "training"}) == []

    planted = {
        "model/up.py": "from openfly_agent.rollout import run\n",  # upwards
        "sim/sibling.py": "def f():\n    from ..model import net  # lazy: planted\n",  # L1 siblings, relative
        "eval/sibling.py": "from openfly_agent import training\n",  # L3 siblings
        "eval/city.py": "from openfly_agent.sim.city_vocab import COLORS\n",  # the procedural city
        "training/tool.py": "import openfly_agent.toolchain.generate\n",  # the toolchain (a sibling too)
    }
    _write(package, planted)
    entry.write_text("from openfly_agent.sim import city\n")
    assert layering_violations(package, {entry: "training"}) == [
        "openfly_agent/eval/city.py: imports openfly_agent.sim.city_vocab (eval never imports openfly_agent.sim.city)",
        "openfly_agent/eval/sibling.py: imports openfly_agent.training (eval and training are siblings: never each other)",
        "openfly_agent/model/up.py: imports openfly_agent.rollout (model L1 -> rollout L2: upwards)",
        "openfly_agent/sim/sibling.py: imports openfly_agent.model (sim and model are siblings: never each other)",
        "openfly_agent/training/tool.py: imports openfly_agent.toolchain.generate (training never imports "
        "openfly_agent.toolchain)",
        "train.py: imports openfly_agent.sim.city (training never imports openfly_agent.sim.city)",
    ]


def test_the_package_follows_the_layering():
    problems = layering_violations(PACKAGE, {REPO / name: part for name, part in ENTRY_POINTS.items()})
    assert not problems, "\n".join(problems)


# --- no import circle between the modules of a package ------------------------------------------------------


def _module_name(path: Path, root: Path) -> str:
    """`<root.name>.a.b` for `<root>/a/b.py` (a package's `__init__.py` is the package itself)."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_modules(path: Path, root: Path, modules: set[str]) -> set[str]:
    """Modules of `modules` that `path` imports anywhere (top level, in functions, under TYPE_CHECKING).

    `from pkg import name` counts as importing `pkg.name` when that is a module, else `pkg`; relative imports
    are resolved against the file's package.
    """
    own = _module_name(path, root)
    package = own if path.name == "__init__.py" else own.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                found.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source)
    return {m for m in found if m in modules and m != own}


def import_graph(root: Path) -> dict[str, set[str]]:
    """module -> the modules of the same top-level package (`root`) it imports."""
    paths = {_module_name(p, root): p for p in root.rglob("*.py")}
    return {name: _imported_modules(path, root, set(paths)) for name, path in paths.items()}


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Groups of modules that import each other, directly or through others (strongly connected, > 1 module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(module: str) -> None:  # Tarjan
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in sorted(graph[module]):
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            group = []
            while not group or group[-1] != module:
                group.append(stack.pop())
            if len(group) > 1:
                circles.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return circles


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)


def test_the_circle_check_finds_circles(tmp_path):
    root = tmp_path / "pkg"
    _write(
        root,
        {
            "__init__.py": "",
            "sub/__init__.py": "",
            "sub/a.py": "from .b import x\n",
            "sub/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.sub.c import y\n",
            "sub/c.py": "def f():\n    from . import a\n",
            "sub/d.py": "from pkg.sub import a\nimport pkg.sub.b\n",
            "e.py": "from pkg.sub import d\n",
        },
    )
    graph = import_graph(root)
    assert graph["pkg.sub.d"] == {"pkg.sub.a", "pkg.sub.b"} and graph["pkg.e"] == {"pkg.sub.d"}
    assert import_circles(graph) == [["pkg.sub.a", "pkg.sub.b", "pkg.sub.c"]]
    (root / "sub" / "c.py").write_text("import json\n")
    assert import_circles(import_graph(root)) == []


def test_no_import_circle_between_modules():
    circles = import_circles(import_graph(PACKAGE))
    assert not circles, "modules that import each other: " + "; ".join(" <-> ".join(c) for c in circles)


# --- the package's own modules are imported at module top ------------------------------------------------------


def _imports_own_module(node: ast.AST) -> bool:
    if isinstance(node, ast.Import):
        return any(alias.name.split(".")[0] == "openfly_agent" for alias in node.names)
    if isinstance(node, ast.ImportFrom):
        return node.level > 0 or (node.module or "").split(".")[0] == "openfly_agent"
    return False


def unexplained_function_imports(path: Path) -> list[str]:
    """Imports of `openfly_agent` modules inside a function of `path` with no `# lazy: <reason>` on their lines.

    A function-level import is for a heavy or optional dependency that importing the module must not pull in
    (or an import circle); the comment says which.
    """
    source = path.read_text()
    lines = source.splitlines()
    found = []

    def says_why(node: ast.stmt) -> bool:
        return any("# lazy:" in line for line in lines[node.lineno - 1 : node.end_lineno])

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if inside and _imports_own_module(child) and not says_why(child):
                found.append(f"{path}:{child.lineno}: {lines[child.lineno - 1].strip()}")
            visit(child, inside)

    visit(ast.parse(source, filename=str(path)), False)
    return found


def test_the_function_import_check_finds_unexplained_imports(tmp_path):
    path = tmp_path / "mod.py"
    path.write_text(
        "import openfly_agent.utils\n"
        "def f():\n"
        "    import json\n"
        "    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch\n"
        "    from . import sibling\n"
        "class C:\n"
        "    def g(self):\n"
        "        if True:\n"
        "            from openfly_agent.sim import (\n"
        "                city,\n"
        "            )\n"
    )
    assert unexplained_function_imports(path) == [
        f"{path}:5: from . import sibling",
        f"{path}:9: from openfly_agent.sim import (",
    ]


def test_own_modules_are_imported_at_module_top():
    scripts = [
        REPO / "train.py",
        REPO / "eval.py",
        *(REPO / "bench").glob("*.py"),
        *(REPO / "scripts").glob("*.py"),
    ]
    found = [
        line
        for path in sorted(PACKAGE.rglob("*.py")) + scripts
        for line in unexplained_function_imports(path)
    ]
    assert not found, "move these to the top, or say why not with `# lazy: <reason>`:\n" + "\n".join(found)


# --- the tests mirror the package ---------------------------------------------------------------------------

TESTS = Path(__file__).resolve().parent
REPOSITORY_WIDE_TESTS = {
    "test_config_defaults.py",
    "test_cli_help.py",
    "test_entry_point_errors.py",
    "test_docs.py",
    "test_eval_e2e.py",
    "test_layering.py",
    "test_paths.py",
    "test_self_contained.py",
    "test_suite_layout.py",
}


def test_tests_mirror_the_package_layout():
    """The tests of a subpackage live in tests/<subpackage>/ (those of bench/ in tests/bench/); only
    repository-wide tests sit at the root."""
    subpackages = {init.parent.name for init in PACKAGE.glob("*/__init__.py")} | {"bench"}
    problems = [
        f"tests/{path.name}: the tests of openfly_agent/<subpackage>/ go in tests/<subpackage>/"
        for path in sorted(TESTS.glob("test_*.py"))
        if path.name not in REPOSITORY_WIDE_TESTS
    ]
    problems += [
        f"tests/{folder.name}/: no subpackage openfly_agent/{folder.name}/"
        for folder in sorted(TESTS.iterdir())
        if folder.is_dir() and any(folder.glob("test_*.py")) and folder.name not in subpackages
    ]
    assert not problems, "\n".join(problems)
