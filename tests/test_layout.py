"""The package layout that docs/architecture.md's "Layout" table states, checked against the
code (AST).

Each module imports only the jscratch modules its row allows (every module may import
``jscratch.errors``); no import cycle; no private
name (leading underscore) of one jscratch module used in another; no module over 800 lines; no
``sys.path`` edits in benchmarks, scripts or notebooks.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "jscratch"


def _module_name(path: Path) -> str:
    """``design/run`` for jscratch/design/run.py, ``design`` for jscratch/design/__init__.py."""
    rel = path.relative_to(PKG).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return "/".join(parts) if parts else ""


ARCHITECTURE = ROOT / "docs" / "architecture.md"
#: Every module may import the error family (docs/architecture.md states the rule).
ALWAYS_ALLOWED = {"errors"}


def _row_key(mod: str) -> str:
    """The layout row that covers ``mod`` (``bench/`` covers the whole bench package; a
    package's ``__init__`` and ``__main__`` are its face)."""
    if mod.startswith("bench"):
        return "bench/"
    return mod.removesuffix("/__main__")


def _layout_rules(text: str | None = None) -> dict[str, set[str] | None]:
    """Layout table rows of docs/architecture.md: module -> allowed jscratch imports (None:
    any)."""
    text = ARCHITECTURE.read_text() if text is None else text
    section = text.split("## Layout", 1)[1].split("\n## ", 1)[0]
    rules: dict[str, set[str] | None] = {}
    for line in section.splitlines():
        m = re.match(r"\| `([^`]+)` \|.*\| ([^|]*) \|$", line)
        if not m:
            continue
        allowed = m.group(2).strip()
        if allowed.startswith("any"):
            rules[m.group(1)] = None
            continue
        names = set()
        for item in allowed.split(","):
            item = re.sub(r"\(.*?\)", "", item).strip()
            if item and item != "-":
                names.add(item)
        rules[m.group(1)] = names
    return rules


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def _imports(path: Path, mod: str) -> set[str]:
    """jscratch modules imported by ``path`` (as layout names: ``design/run``, ``bvh``)."""
    tree = ast.parse(path.read_text())
    known = set(_modules())
    out = set()

    def add(dotted: str):
        parts = dotted.split(".")[1:]
        while parts and "/".join(parts) not in known:
            parts = parts[:-1]
        if parts:
            out.add("/".join(parts))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jscratch."):
                    add(a.name)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "jscratch":
                for a in node.names:
                    add(f"jscratch.{a.name}")
            elif node.module.startswith("jscratch."):
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    add(full if "/".join(full.split(".")[1:]) in known else node.module)
    out.discard(mod)
    return out


def _allowed(imported: str, allowed: set[str]) -> bool:
    if imported in allowed or imported in ALWAYS_ALLOWED:
        return True
    if "design/*" in allowed and imported.startswith("design"):
        return True
    return imported.split("/")[0] + "/" in allowed


def _layout_problems(rules: dict[str, set[str] | None]) -> list[str]:
    """Modules without a row, and imports their row does not allow."""
    problems = []
    for mod, path in sorted(_modules().items()):
        if mod == "":  # the package face re-exports the public API
            continue
        key = _row_key(mod)
        if key not in rules:
            if mod in ("design", "design/__main__"):  # the design package's face
                continue
            problems.append(f"{mod}: no layout row in docs/architecture.md")
            continue
        allowed = rules[key]
        if allowed is None:
            continue
        own = {key.rstrip("/")}
        for imp in sorted(_imports(path, mod)):
            if _row_key(imp) in own or _allowed(imp, allowed):
                continue
            problems.append(f"{mod} imports {imp}, not in its docs/architecture.md row")
    return problems


def test_every_module_has_a_layout_row_and_imports_only_what_it_allows():
    problems = _layout_problems(_layout_rules())
    assert not problems, "\n".join(problems)


def test_errors_imports_no_jscratch_module_and_every_module_may_import_it():
    rules = _layout_rules()
    assert rules["errors"] == set()
    assert not _imports(PKG / "errors.py", "errors")
    assert _allowed("errors", set()) and not _allowed("bvh", set())


def test_the_layout_check_can_fail():
    """A table that forbids an import the code makes is reported."""
    rules = _layout_rules()
    rules["designfile"] = set()  # designfile imports machine and scene
    problems = _layout_problems(rules)
    assert any(p.startswith("designfile imports ") for p in problems), problems


def test_no_import_cycle_between_top_level_modules():
    graph = {}
    for mod, path in _modules().items():
        if "/" in mod or mod in ("",):
            continue
        graph[mod] = {i for i in _imports(path, mod) if "/" not in i and i in _modules()}
    state: dict[str, int] = {}

    def visit(n, stack):
        state[n] = 1
        for m in graph.get(n, ()):
            if state.get(m) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack + [n, m]))
            if not state.get(m):
                visit(m, stack + [n])
        state[n] = 2

    for n in graph:
        if not state.get(n):
            visit(n, [])


def _private_uses(path: Path) -> list[str]:
    """``from jscratch.x import _y`` and ``x._y`` where ``x`` names a jscratch module."""
    tree = ast.parse(path.read_text())
    aliases = set()
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jscratch"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(f"from {node.module} import {a.name}")
                aliases.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jscratch"):
                    aliases.add(a.asname or a.name.split(".")[0])
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in aliases and node.attr.startswith("_")
                and not node.attr.startswith("__")):
            out.append(f"{node.value.id}.{node.attr}")
    return out


def _sources():
    yield from PKG.rglob("*.py")
    for d in ("benchmarks", "scripts"):
        yield from (ROOT / d).rglob("*.py")


def test_no_private_name_crosses_modules():
    bad = {str(p.relative_to(ROOT)): u for p in _sources() if (u := _private_uses(p))}
    assert not bad, bad


def test_modules_at_most_800_lines():
    long = {str(p.relative_to(ROOT)): n for p in PKG.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 800}
    assert not long, long


def test_no_sys_path_edits_outside_tests():
    found = []
    for p in _sources():
        if "sys.path" in p.read_text():
            found.append(str(p.relative_to(ROOT)))
    for nb in (ROOT / "notebooks").glob("*.ipynb"):
        cells = json.loads(nb.read_text())["cells"]
        if any("sys.path" in "".join(c.get("source", [])) for c in cells):
            found.append(str(nb.relative_to(ROOT)))
    assert not found, found


@pytest.mark.parametrize("bad_import", ["from jscratch.grid import _bin", "bvh._arrays(x)"])
def test_the_private_name_check_can_fail(tmp_path, bad_import):
    p = tmp_path / "m.py"
    p.write_text(f"from jscratch import bvh\n{bad_import}\n")
    assert _private_uses(p)


def test_every_public_name_of_every_module_exists():
    """`from m import *` works for every module: each name in its `__all__` is defined there."""
    import importlib
    import pkgutil

    import jscratch

    missing = []
    for info in pkgutil.walk_packages(jscratch.__path__, "jscratch."):
        if info.name.endswith("__main__"):
            continue
        mod = importlib.import_module(info.name)
        missing += [f"{info.name}.{n}" for n in getattr(mod, "__all__", ()) if not hasattr(mod, n)]
    assert missing == []
