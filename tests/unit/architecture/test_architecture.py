"""The shape of the package: no import cycle, the device layer imports nothing above it,
no function shadows a package, every module imports in a fresh interpreter, and the test markers
select what they say."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
PACKAGE = ROOT / "clsas"


def _modules() -> dict[str, Path]:
    mods = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = path
    return mods


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ``import from`` names (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    parts = package.split(".")
    base = parts[: len(parts) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph() -> dict[str, set[str]]:
    """module -> the clsas modules it imports, anywhere in its body (inside functions too).

    ``from package import name`` counts as importing ``package.name`` where that is a module. An
    import of the module's own ancestor package is left out: Python runs the ancestor first, so
    that edge cannot close a cycle at import time.
    """
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for module, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                base = _resolve(module, path, node)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in mods and "." in target:
                    target = target.rsplit(".", 1)[0]
                if target in mods and target != module and not module.startswith(target + "."):
                    graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    assert len(graph) > 50  # the walk found the package
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_device_layer_imports_nothing_above_it():
    graph = import_graph()
    above = {m: sorted(t for t in ts if not t.startswith("clsas.cl") and t != "clsas.validate")
             for m, ts in graph.items() if m == "clsas.cl" or m.startswith("clsas.cl.")}
    assert {m: ts for m, ts in above.items() if ts} == {}


# The floors of clsas, bottom first: a folder (or ground module) imports only from its own floor
# and the floors below it, at module level and inside functions alike. The extending guide draws
# the same table.
FLOORS = (
    ("ground", ("validate", "version", "registry", "cluster")),
    ("physics", ("physics",)),
    ("types", ("types",)),
    ("device", ("cl",)),
    ("data in", ("io", "synthesis")),
    ("algorithms", ("compression", "formation", "sparse", "inverse")),
    ("pipeline", ("pipeline",)),
    ("after the pipeline", ("focus", "preprocess", "presenting")),
    ("top", ("cli", "rig")),
)
# (from room, to room): the imports that still reach up a floor, each with its reason
KNOWN_UPWARD: dict[tuple[str, str], str] = {}


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def floor_violations(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    """The (room, room) pairs where an import reaches a higher floor."""
    level = {room: i for i, (_, rooms) in enumerate(FLOORS) for room in rooms}
    out = set()
    for a, targets in graph.items():
        ra = _room(a)
        if ra == "clsas":  # the package's __init__ gathers the public names of every floor
            continue
        for b in targets:
            rb = _room(b)
            if rb != "clsas" and level[rb] > level[ra]:
                out.add((ra, rb))
    return out


def test_every_room_has_a_floor():
    rooms = {_room(m) for m in _modules()} - {"clsas"}
    placed = {room for _, rooms in FLOORS for room in rooms}
    assert rooms == placed, f"not on a floor: {sorted(rooms - placed)}; gone: {sorted(placed - rooms)}"


def test_each_floor_imports_only_floors_below_it():
    found = floor_violations(import_graph())
    assert found <= set(KNOWN_UPWARD), f"imports that reach a higher floor: {sorted(found - set(KNOWN_UPWARD))}"
    stale = set(KNOWN_UPWARD) - found
    assert not stale, f"no longer reach up, take them off KNOWN_UPWARD: {sorted(stale)}"


def test_the_floor_check_sees_an_upward_import():
    graph = {"clsas.physics.sound": {"clsas.pipeline.reconstruction"}, "clsas.pipeline.reconstruction": set()}
    assert floor_violations(graph) == {("physics", "pipeline")}


def test_every_module_imports_in_a_fresh_interpreter():
    """Each module imported first in a clean interpreter (no other clsas module loaded before it), so
    an import that works only in the order the test suite happens to use is caught."""
    names = sorted(m for m in _modules() if not m.endswith("__main__"))
    code = (
        "import importlib, sys\n"
        "bad = []\n"
        f"for name in {names!r}:\n"
        "    for m in [m for m in sys.modules if m == 'clsas' or m.startswith('clsas.')]:\n"
        "        del sys.modules[m]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except ImportError as exc:\n"
        "        if 'No module named' in str(exc) and getattr(exc, 'name', '') and "
        "not exc.name.startswith('clsas'):\n"
        "            continue  # an optional dependency of that module (e.g. distributed)\n"
        "        bad.append(f'{name}: {type(exc).__name__}: {exc}')\n"
        "    except Exception as exc:\n"
        "        bad.append(f'{name}: {type(exc).__name__}: {exc}')\n"
        "print('\\n'.join(bad))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == ""


def test_no_function_shadows_a_package():
    """``clsas.compress``, ``clsas.autofocus``, ``clsas.simulate`` are the contract's functions; the
    packages that hold them are named otherwise, so ``import clsas.<package>`` gives the package."""
    import importlib

    import clsas

    children = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
                if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()}
    for name in sorted(children):
        module = importlib.import_module(f"clsas.{name}")
        attr = getattr(clsas, name)
        assert attr is module, f"clsas.{name} is {attr!r}, not the module {module.__name__}"
    for name in ("compress", "autofocus", "simulate", "reconstruct", "backproject"):
        assert callable(getattr(clsas, name)) and name not in children


@pytest.mark.parametrize("marker, some_test", [
    ("opencl", "kernels/test_backproject.py"),
    ("oclgrind", "kernels/test_oclgrind.py"),
    ("hw", "hw/test_rig.py"),
])
def test_markers_select_what_they_say(marker, some_test):
    if marker == "hw":  # test_rig.py skips as a whole without pyserial, and then nothing is selected
        pytest.importorskip("serial", reason="the rig tests need pyserial (pip install 'clsas[rig]')")
    res = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                          "-m", marker, str(ROOT / "tests" / some_test)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    selected = [line for line in res.stdout.splitlines() if "::" in line]
    assert selected, res.stdout[-2000:]
