"""Architecture rules read from the source: no private name imported across packages (nor by a
test), no library function over 80 lines, no import cycle between the rooms of the package.

A *package* here is a directory under ``clsas/``; a top-level module (``clsas/types/dataset.py``) counts
as its own package. Within one package private imports are fine. A private name is one that
starts with ``_`` (not a dunder), whether it is the imported name (``from clsas.types.dataset import
_UNITS``, ``from clsas import _validate``) or a module on the path (``from clsas.validate import
install_hint``).

Run as a script to list what the rules find: ``python tests/unit/architecture/test_architecture_private.py``.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
PACKAGE = ROOT / "clsas"
MAX_LINES = 80

# cross-package private imports still to remove (file, imported module, name); none may be added
KNOWN_PRIVATE: set[tuple[str, str, str]] = set()

# functions over MAX_LINES still to split (file, qualified name); none may be added
KNOWN_LONG: set[tuple[str, str]] = set()


def _modules():
    """(path relative to the root, dotted module name, its package, parsed tree) of every module."""
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT)
        parts = list(rel.with_suffix("").parts)
        is_init = parts[-1] == "__init__"
        name = ".".join(parts[:-1] if is_init else parts)
        package = name if (is_init or len(parts) == 2) else ".".join(parts[:-1])
        yield rel.as_posix(), name, package, is_init, ast.parse(path.read_text(encoding="utf-8"), str(rel))


def _package_of(module: str) -> str:
    """The package a dotted module belongs to: itself for a directory or a top-level module."""
    path = ROOT.joinpath(*module.split("."))
    if path.is_dir() or module.count(".") <= 1:
        return module
    return module.rsplit(".", 1)[0]


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _imported_module(node: ast.ImportFrom, name: str, is_init: bool) -> str:
    """The absolute module a ``from ... import`` in module ``name`` (a package's ``__init__`` where
    ``is_init``) names, its relative dots resolved."""
    if not node.level:
        return node.module or ""
    base = name.split(".") if is_init else name.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def private_imports() -> list[tuple[str, int, str, str]]:
    """(file, line, imported module, private name) of every private import across packages."""
    found = []
    for rel, name, package, is_init, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _imported_module(node, name, is_init)
                pairs = [(target, a.name) for a in node.names]
            elif isinstance(node, ast.Import):
                pairs = [(a.name.rsplit(".", 1)[0], a.name.rsplit(".", 1)[-1]) for a in node.names if "." in a.name]
            else:
                continue
            for target, imported in pairs:
                if target != "clsas" and not target.startswith("clsas."):
                    continue
                # the first private step on the way decides the package it is private to
                steps = target.split(".")
                private_step = next((k for k, step in enumerate(steps) if _private(step)), None)
                if private_step is not None:
                    owner = ".".join(steps[:private_step])
                elif _private(imported):
                    owner = _package_of(target)
                else:
                    continue
                if owner != package:
                    found.append((rel, node.lineno, target, imported))
    return found


def long_functions() -> list[tuple[str, str, int]]:
    """(file, qualified name, lines) of every function over MAX_LINES, docstring included."""
    found = []

    def visit(node, rel, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                qual = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    n = child.end_lineno - child.lineno + 1
                    if n > MAX_LINES:
                        found.append((rel, qual, n))
                visit(child, rel, qual + ".")
            else:
                visit(child, rel, prefix)

    for rel, _, _, _, tree in _modules():
        visit(tree, rel, "")
    return found


def test_the_rules_see_what_they_should(tmp_path, monkeypatch):
    """The scan itself: a private import across packages and a long function are found, a private
    import within a package and a short function are not."""
    pkg = tmp_path / "clsas"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "_helpers.py").write_text("x = 1\n")
    (pkg / "top.py").write_text("from ._helpers import x\nfrom .a.inner import _y, z\n")
    (pkg / "a" / "__init__.py").write_text("from .inner import _y\n")
    (pkg / "a" / "inner.py").write_text("_y = z = 1\n\n\ndef f():\n" + "    pass\n" * MAX_LINES
                                        + "\n\ndef g():\n    pass\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    assert sorted(private_imports()) == [("clsas/top.py", 1, "clsas._helpers", "x"),
                                         ("clsas/top.py", 2, "clsas.a.inner", "_y")]
    assert long_functions() == [("clsas/a/inner.py", "f", MAX_LINES + 1)]


def test_no_private_name_is_imported_across_packages():
    found = {(f, target, what) for f, _, target, what in private_imports()}
    new = sorted(found - KNOWN_PRIVATE)
    assert not new, "private names imported across packages (make them public):\n" + "\n".join(map(str, new))


def test_no_library_function_is_over_80_lines():
    found = {(f, q) for f, q, _ in long_functions()}
    new = sorted(found - KNOWN_LONG)
    assert not new, f"functions over {MAX_LINES} lines (split them into named stages):\n" + "\n".join(map(str, new))


@pytest.mark.parametrize("known, scan", [(KNOWN_PRIVATE, "private"), (KNOWN_LONG, "long")])
def test_known_exceptions_are_still_there(known, scan):
    """An exception that has been fixed is taken off its list, so that it cannot come back."""
    if scan == "private":
        found = {(f, target, what) for f, _, target, what in private_imports()}
    else:
        found = {(f, q) for f, q, _ in long_functions()}
    stale = sorted(known - found)
    if stale:
        pytest.skip(f"fixed elsewhere, take off the list: {stale}")


if __name__ == "__main__":
    imports = private_imports()
    print(f"{len(imports)} private imports across packages:")
    for row in imports:
        print("  {}:{}  from {} import {}".format(*row), "(known)" if (row[0], row[2], row[3]) in KNOWN_PRIVATE else "")
    longs = long_functions()
    print(f"{len(longs)} functions over {MAX_LINES} lines:")
    for row in longs:
        print("  {}  {}  {} lines".format(*row), "(known)" if row[:2] in KNOWN_LONG else "")


def private_imports_in_tests(tests: Path) -> list[str]:
    """Every import under ``tests`` of a private name of the library or the benchmark package: a
    private name (``from clsas.x import _y``) or a private module on the path (``from clsas.io._common
    import y``, ``import clsas.io._common``)."""
    found = []
    for path in sorted(tests.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in ("clsas", "bench"):
                dotted = [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                dotted = [a.name for a in node.names if a.name.split(".")[0] in ("clsas", "bench")]
            else:
                continue
            found += [f"{path.name}:{node.lineno}: {d}" for d in dotted if any(map(_private, d.split(".")))]
    return found


def test_no_test_imports_a_private_name():
    """Tests use what the library and the benchmark package offer (a helper worth testing on its
    own gets a public name)."""
    found = private_imports_in_tests(ROOT / "tests")
    assert not found, found


def test_the_private_import_scan_of_tests_sees_what_it_should(tmp_path):
    (tmp_path / "test_x.py").write_text(
        "from clsas.types.dataset import _UNITS, load\n"      # found: a private name
        "from clsas.io._common import reader\n"         # found: a private module on the path
        "import clsas.preprocess._base\n"               # found
        "from bench.report import _table\n"             # found: the benchmark package too
        "from conftest import oclgrind_missing as _x\n"  # not: a test kit, renamed privately
        "from clsas.io import import_scan\n"            # not: public
        "import numpy._core\n")                         # not: another library
    assert [f.split(": ", 1)[1] for f in private_imports_in_tests(tmp_path)] == [
        "clsas.types.dataset._UNITS", "clsas.io._common.reader", "clsas.preprocess._base", "bench.report._table"]


def _room(module: str) -> str:
    """A module's room: its package directory under clsas/, or the top-level module itself."""
    parts = module.split(".")
    if len(parts) >= 2 and ((PACKAGE / parts[1]).is_dir() or (PACKAGE / f"{parts[1]}.py").is_file()):
        return ".".join(parts[:2])
    return "clsas"  # the package's __init__ (or a name it defines)


def _imports():
    """(room, imported room, module-level?, where) for every import of a clsas module by another room."""
    for rel, name, _package, is_init, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mod = _imported_module(node, name, is_init)
                targets = [f"{mod}.{a.name}" for a in node.names] if mod == "clsas" else [mod]
            else:
                continue
            for t in targets:
                if t.split(".")[0] == "clsas" and _room(t) != _room(name):
                    yield _room(name), _room(t), node.col_offset == 0, f"{rel}:{node.lineno}"


def room_problems() -> tuple[list[str], list[str]]:
    """(rooms on a module-level import cycle, lazy imports that reach up to a room importing the caller's)."""
    edges = list(_imports())
    top: dict[str, set[str]] = {}
    for a, b, module_level, _ in edges:
        if module_level:
            top.setdefault(a, set()).add(b)

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in top.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    cycles = sorted({a for a in top if a in reach(a)})
    upward = [f"{where}: {a} -> {b}" for a, b, module_level, where in edges if not module_level and a in reach(b)]
    return cycles, upward


def test_no_import_cycle_and_no_upward_lazy_import():
    """Module-level imports between the rooms of clsas form no cycle, and no import inside a
    function reaches up to a room that imports the caller's room (which would be a cycle hidden
    from import time)."""
    cycles, upward = room_problems()
    assert not cycles, f"module-level import cycles through {cycles}"
    assert not upward, upward


def test_the_room_rules_see_what_they_should(tmp_path, monkeypatch):
    """A module-level cycle and a lazy import upward are found; a lazy import downward is not."""
    pkg = tmp_path / "clsas"
    (pkg / "low").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "low" / "__init__.py").write_text("def f():\n    from clsas import high\n")   # upward, lazily
    (pkg / "high.py").write_text("from clsas import low\n\n\ndef g():\n    from clsas import side\n")
    (pkg / "side.py").write_text("")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    assert room_problems() == ([], ["clsas/low/__init__.py:2: clsas.low -> clsas.high"])
    (pkg / "side.py").write_text("from clsas import high\n")
    (pkg / "high.py").write_text("from clsas import low, side\n")
    (pkg / "low" / "__init__.py").write_text("")
    assert room_problems() == (["clsas.high", "clsas.side"], [])
