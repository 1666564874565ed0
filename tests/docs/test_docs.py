"""The documentation's code runs: the Python blocks of the guide pages (docs/guide/*.md) and of
the README, and the Examples sections of the public docstrings (the API reference's examples).

Convention (CONTRIBUTING.md): a fenced ``python`` block runs, unless the line before it (blank
lines skipped) is an HTML comment ``<!-- no-run: reason -->`` (never run: a fragment, hardware,
a download) or ``<!-- slow: reason -->`` (run only with ``-m slow``); the info string
``python no-run`` also skips a block. A page's blocks run in order in one namespace, in a fresh
Python process whose working directory is a temporary folder, so later blocks see what earlier
ones defined and the files they wrote. Other languages (bash, toml) are not run here.
"""

from __future__ import annotations

import doctest
import importlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs" / "guide").glob("*.md"))]
FENCE = re.compile(r"^(`{3,})\s*([\w+-]*)([^\n`]*)$")
MARK = re.compile(r"^<!--\s*(no-run|slow)\s*:\s*(.*?)\s*-->\s*$")
# the public contract and the other names the API reference documents
API = ["lfm_chirp", "analytic", "raster_aperture", "circular_aperture", "helical_aperture",
       "aperture_from_csv", "Aperture", "VoxelGrid", "Scene", "Wall", "simulate", "Dataset", "load",
       "reconstruct", "compress", "backproject", "Profiles", "Image", "ReconstructionPlan", "Backprojector",
       "superres", "delay_error", "coherence", "autofocus", "tcr_db", "compare", "resolution_limits",
       "speed_of_sound", "air_absorption_db_per_m", "io.import_scan", "sparse.Echoes", "cl.select",
       "cl.Selection", "registry.Registry", "preprocess.apply"]
SLOW_API: set[str] = set()


def code_blocks(path: Path) -> list[tuple[int, str, str | None, str]]:
    """``(line, language, mark, code)`` per fenced block of a Markdown file; mark is
    ``"no-run"``, ``"slow"`` or None."""
    blocks = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang, rest = m.group(1), m.group(2).lower(), m.group(3)
        start = i
        i += 1
        body = []
        while i < len(lines) and not lines[i].startswith(fence):
            body.append(lines[i])
            i += 1
        i += 1
        previous = next((ln for ln in reversed(lines[:start]) if ln.strip()), "")
        mark = MARK.match(previous.strip())
        kind = mark.group(1) if mark else ("no-run" if "no-run" in rest else None)
        blocks.append((start + 1, lang, kind, "\n".join(body) + "\n"))
    return blocks


def python_blocks(path: Path, *, slow: bool) -> list[tuple[int, str]]:
    """The blocks of ``path`` to run: Python, not no-run, slow ones only when ``slow``."""
    return [(line, code) for line, lang, kind, code in code_blocks(path)
            if lang in ("python", "py", "python3") and kind != "no-run" and (slow or kind != "slow")]


def run_page(path: Path, blocks: list[tuple[int, str]], cwd: Path) -> None:
    """Run the blocks in one namespace in a fresh process; fail with the block's line."""
    script = ["import sys", "ns = {'__name__': '__main__'}"]
    for line, code in blocks:
        name = f"{path.relative_to(ROOT)}:{line}"
        script.append(f"exec(compile({code!r}, {name!r}, 'exec'), ns)")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", "\n".join(script)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, f"{path.name}: a code block failed\n{proc.stderr[-4000:]}"


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


@pytest.mark.parametrize("path", [p for p in PAGES if python_blocks(p, slow=False)],
                         ids=_ids([p for p in PAGES if python_blocks(p, slow=False)]))
def test_page_code_runs(path, tmp_path):
    run_page(path, python_blocks(path, slow=False), tmp_path)


SLOW_PAGES = [p for p in PAGES if any(kind == "slow" for _, _, kind, _ in code_blocks(p))]


@pytest.mark.slow
@pytest.mark.parametrize("path", SLOW_PAGES, ids=_ids(SLOW_PAGES))
def test_page_code_runs_with_slow_blocks(path, tmp_path):
    run_page(path, python_blocks(path, slow=True), tmp_path)


def test_marks_give_a_reason():
    for path in PAGES:
        text = path.read_text(encoding="utf-8")
        for comment in re.findall(r"<!--\s*(?:no-run|slow)\b[^>]*-->", text):
            assert MARK.match(comment) and MARK.match(comment).group(2), f"{path.name}: {comment} has no reason"


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 150


def _globs() -> dict:
    """What a docstring example may take as imported (numpydoc's convention): numpy as np, clsas."""
    import numpy as np

    import clsas
    return {"np": np, "clsas": clsas}


def _api_object(name: str):
    module, _, attr = ("clsas." + name).rpartition(".")
    return getattr(importlib.import_module(module), attr)


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_API else n for n in API])
def test_docstring_example_runs(name, tmp_path, monkeypatch):
    """The example on the name's API page runs: its docstring's Examples section, or, for a function
    whose docstring has no room for one (the 80-line rule counts docstrings) or that another branch is
    changing, the page's example in
    docs/api/examples/<full name>.rst."""
    obj = _api_object(name)
    page_example = ROOT / "docs" / "api" / "examples" / f"clsas.{name}.rst"
    monkeypatch.chdir(tmp_path)
    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    if page_example.exists():
        text = page_example.read_text(encoding="utf-8")
        tests = [doctest.DocTestParser().get_doctest(text, _globs(), name, str(page_example), 0)]
    else:
        assert "Examples\n" in (obj.__doc__ or ""), f"{name}: no Examples section and no {page_example.name}"
        tests = [t for t in finder.find(obj, name, globs=_globs()) if t.examples]
    assert tests and tests[0].examples, f"{name}: no doctest examples"
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} docstring example(s) failed (see the output above)"


