"""Where the library reads the environment and where it draws (CONTRIBUTING's rules, read from the
source): environment variables only in the device layer (``clsas/cl/``) and the command line
(``clsas/cli/``); matplotlib only in the modules that present (``types/pictures.py``,
``Image.plot``, ``inspection.py``'s ``draw_inspection``, the command line), and never a
``matplotlib.use``: the caller's backend is the caller's."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
ENVIRONMENT_READERS = ("clsas/cl/", "clsas/cli/")
DRAWERS = ("clsas/types/pictures.py", "clsas/types/image.py", "clsas/presenting/inspection.py", "clsas/cli/")


def _sources(root: Path):
    for path in sorted((root / "clsas").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        yield rel, ast.parse(path.read_text(encoding="utf-8"), rel)


def environment_reads(root: Path) -> list[str]:
    """``file:line`` of every ``os.environ`` / ``os.getenv`` (or a bare ``environ``/``getenv`` imported from os)."""
    found = []
    for rel, tree in _sources(root):
        for node in ast.walk(tree):
            named = (isinstance(node, ast.Attribute) and node.attr in ("environ", "getenv", "putenv")
                     or isinstance(node, ast.ImportFrom) and node.module == "os"
                     and any(a.name in ("environ", "getenv", "putenv") for a in node.names))
            if named:
                found.append(f"{rel}:{node.lineno}")
    return found


def matplotlib_uses(root: Path) -> tuple[list[str], list[str]]:
    """(``file:line`` of every import of matplotlib, ``file:line`` of every ``matplotlib.use(...)``)."""
    imports, uses = [], []
    for rel, tree in _sources(root):
        for node in ast.walk(tree):
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "matplotlib" for a in node.names) \
                    or isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "matplotlib":
                imports.append(f"{rel}:{node.lineno}")
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "use" \
                    and isinstance(node.func.value, ast.Name) and node.func.value.id in ("matplotlib", "mpl"):
                uses.append(f"{rel}:{node.lineno}")
    return imports, uses


def test_only_the_device_layer_and_the_command_line_read_the_environment():
    outside = [w for w in environment_reads(ROOT) if not w.startswith(ENVIRONMENT_READERS)]
    assert not outside, f"environment read outside {ENVIRONMENT_READERS} (take it as a parameter): {outside}"


def test_only_the_presenting_modules_draw_and_none_picks_a_backend():
    imports, uses = matplotlib_uses(ROOT)
    assert not uses, f"matplotlib.use in the library (it changes the caller's backend): {uses}"
    outside = [w for w in imports if not w.startswith(DRAWERS)]
    assert not outside, f"matplotlib imported outside {DRAWERS}: {outside}"


def test_the_scans_see_what_they_should(tmp_path):
    (tmp_path / "clsas" / "cl").mkdir(parents=True)
    (tmp_path / "clsas" / "cl" / "device.py").write_text("import os\nx = os.environ.get('PYOPENCL_CTX')\n")
    (tmp_path / "clsas" / "physics").mkdir()
    (tmp_path / "clsas" / "types").mkdir()
    (tmp_path / "clsas" / "physics" / "sound.py").write_text(
        "import os\nfrom os import getenv\n\n\ndef f():\n    import matplotlib\n    matplotlib.use('Agg')\n"
        "    return os.getenv('X')\n")
    (tmp_path / "clsas" / "types" / "pictures.py").write_text("from matplotlib.figure import Figure\n")
    sound = "clsas/physics/sound.py"
    assert environment_reads(tmp_path) == ["clsas/cl/device.py:2", f"{sound}:2", f"{sound}:8"]
    assert matplotlib_uses(tmp_path) == ([f"{sound}:6", "clsas/types/pictures.py:1"], [f"{sound}:7"])
