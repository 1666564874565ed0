"""The documentation's code runs and prints what the pages say: the Python blocks of the guide
pages (docs/guide/*.md) and of the README, the example scripts the pages show with their output,
and the Examples sections of the public docstrings (the API reference's examples).

Convention (CONTRIBUTING.md): a fenced ``python`` block runs, unless the line before it (blank
lines skipped) is an HTML comment ``<!-- no-run: reason -->`` (never run: a fragment, hardware,
a download) or ``<!-- slow: reason -->`` (run only with ``-m slow``); the info string
``python no-run`` also skips a block. A page's blocks run in order in one namespace, in a fresh
Python process whose working directory is a temporary folder, so later blocks see what earlier
ones defined and the files they wrote. What a block prints is compared with the ``output``
block that follows it on the page (``tests/doc_output.py``: numbers within 1 %, text exact up to
whitespace, ``...`` for anything); a block without one must print nothing. A ``bash`` block of
``python examples/NAME.py ...`` lines followed by an ``output`` block is run the same way.
Other bash and toml blocks are not run here.
"""

from __future__ import annotations

import doctest
import importlib
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from doc_output import OUTPUT_LANG, Expected, compare, output_after

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
# pages whose blocks do not yet all show their output: there a block without an output block may print
OUTPUTS_PENDING: dict[str, str] = {}
# python blocks that show their output but cannot run here (a download): (page, a line of the block) -> the test
OUTPUT_CHECKED_ELSEWHERE = {
    ("own-data.md", 'ds = clsas.io.import_airsas("small_features_cutout_20k", background="bg_20k")'):
        "tests/docs/test_readme_blocks.py::test_your_own_data_python_prints_what_the_page_shows",
    ("benchmarks.md", "python -m bench --rates"):
        "tests/docs/test_readme_blocks.py::test_rates_command_prints_what_the_page_shows",
}
EXAMPLE_LINE = re.compile(r"^python3? (examples/[\w-]+\.py)((?: [^#]*)?)(?:#.*)?$")


def code_blocks(path: Path) -> list[tuple[int, str, str | None, str, Expected | None]]:
    """``(line, language, mark, code, output)`` per fenced block of a Markdown file (``output``
    blocks are not blocks of their own: they are the output of the block before them); mark is
    ``"no-run"``, ``"slow"`` or None; output is the ``output`` block after it, or None."""
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
        end, i = i, i + 1
        if lang == OUTPUT_LANG:
            continue
        previous = next((ln for ln in reversed(lines[:start]) if ln.strip()), "")
        mark = MARK.match(previous.strip())
        kind = mark.group(1) if mark else ("no-run" if "no-run" in rest else None)
        blocks.append((start + 1, lang, kind, "\n".join(body) + "\n", output_after(lines, end)))
    return blocks


def python_blocks(path: Path, *, slow: bool) -> list[tuple[int, str, Expected | None]]:
    """The blocks of ``path`` to run, with what they print: Python, not no-run, slow ones only when ``slow``."""
    return [(line, code, out) for line, lang, kind, code, out in code_blocks(path)
            if lang in ("python", "py", "python3") and kind != "no-run" and (slow or kind != "slow")]


RUNNER = """
import contextlib, io, json, sys
blocks = json.load(open(sys.argv[1], encoding="utf-8"))
ns = {"__name__": "__main__"}
printed = []
for name, code in blocks:
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            exec(compile(code, name, "exec"), ns)
    finally:
        printed.append(buf.getvalue())
        json.dump(printed, open(sys.argv[2], "w", encoding="utf-8"))
"""


def run_page(path: Path, blocks: list[tuple[int, str, Expected | None]], cwd: Path) -> None:
    """Run the blocks in one namespace in a fresh process; fail with the block's line where one
    fails or prints other than its output block shows (on a page of ``OUTPUTS_PENDING``, only the
    blocks that show an output are compared)."""
    names = [f"{path.relative_to(ROOT)}:{line}" for line, _, _ in blocks]
    (cwd / ".blocks.json").write_text(json.dumps([[n, code] for n, (_, code, _) in zip(names, blocks, strict=True)]))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", RUNNER, ".blocks.json", ".printed.json"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{path.name}: a code block failed\n{proc.stderr[-4000:]}"
    printed = json.loads((cwd / ".printed.json").read_text(encoding="utf-8"))
    wrong = [f"{name}: {why}" for name, (_, _, out), text in zip(names, blocks, printed, strict=True)
             if (why := compare(out.text, text, out.rtol) if out else
                 (None if path.name in OUTPUTS_PENDING else compare("", text)))]
    assert not wrong, "\n\n".join(wrong)


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


@pytest.mark.parametrize("path", [p for p in PAGES if python_blocks(p, slow=False)],
                         ids=_ids([p for p in PAGES if python_blocks(p, slow=False)]))
def test_page_code_runs(path, tmp_path):
    run_page(path, python_blocks(path, slow=False), tmp_path)


SLOW_PAGES = [p for p in PAGES if any(kind == "slow" for _, _, kind, _, _ in code_blocks(p))]


@pytest.mark.slow
@pytest.mark.parametrize("path", SLOW_PAGES, ids=_ids(SLOW_PAGES))
def test_page_code_runs_with_slow_blocks(path, tmp_path):
    run_page(path, python_blocks(path, slow=True), tmp_path)


def example_runs() -> list[tuple[Path, int, list[list[str]], Expected]]:
    """``(page, line, commands, output)`` per shell block that runs example scripts and shows their output."""
    runs = []
    for path in PAGES:
        for line, lang, _, code, out in code_blocks(path):
            if lang in ("bash", "sh", "console") and out and "examples/" in code:
                commands = [EXAMPLE_LINE.match(ln.strip()) for ln in code.splitlines() if ln.strip()]
                assert all(commands), f"{path.name}:{line}: an output block after lines other than python examples/..."
                runs.append((path, line, [[m.group(1), *shlex.split(m.group(2))] for m in commands], out))
    return runs


@pytest.mark.parametrize("run", example_runs(), ids=[f"{p.name}:{n}" for p, n, _, _ in example_runs()])
def test_example_prints_what_the_page_shows(run, tmp_path):
    """The example scripts a page runs print what the page shows (run from a temporary folder, so
    what they write lands there)."""
    path, line, commands, out = run
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               MPLBACKEND="Agg")
    printed = ""
    for script, *args in commands:
        proc = subprocess.run([sys.executable, str(ROOT / script), *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, f"{path.name}:{line}: {script} failed\n{proc.stderr[-4000:]}"
        printed += proc.stdout
    why = compare(out.text, printed, out.rtol)
    assert why is None, f"{path.name}:{line}: {why}"
    for written in sorted((tmp_path / "examples" / "out").glob("*.md")):
        shipped, ran = _figures(ROOT / "examples" / "out" / written.name), _figures(written)
        assert shipped.keys() == ran.keys(), f"examples/out/{written.name}: not the rows and columns the example writes"
        wrong = [f"{key}: {why}" for key in ran if (why := compare(shipped[key], ran[key], out.rtol))]
        assert not wrong, f"examples/out/{written.name} differs from what the example writes now:\n" + "\n".join(wrong)


def _figures(md: Path) -> dict[tuple[str, str], str]:
    """``(row, column) -> cell`` of the Markdown tables of an example's output file, without the
    columns that hold run times or devices (they differ from run to run and machine to machine)."""
    cells, header = {}, None
    for row in md.read_text(encoding="utf-8").splitlines():
        if not row.startswith("|") or set(row) <= set("|-: "):
            header = None if not row.startswith("|") else header
            continue
        fields = [f.strip() for f in row.strip("|").split("|")]
        if header is None:
            header = fields
            continue
        for name, cell in zip(header[1:], fields[1:], strict=False):
            if not re.search(r"time|device", name):
                cells[(fields[0], name)] = cell
    return cells


def test_every_output_block_is_checked():
    """An ``output`` block follows a block that a test runs and compares: a python block, run here
    or listed in ``OUTPUT_CHECKED_ELSEWHERE``, or a shell block of example scripts."""
    examples = {(p, n) for p, n, _, _ in example_runs()}
    for path in PAGES:
        lines = path.read_text(encoding="utf-8").splitlines()
        fences = [n + 1 for n, ln in enumerate(lines) if (m := FENCE.match(ln)) and m.group(2).lower() == OUTPUT_LANG]
        owned = []
        for line, lang, kind, code, out in code_blocks(path):
            if out is None:
                continue
            elsewhere = [k for k in OUTPUT_CHECKED_ELSEWHERE if k[0] == path.name and k[1] in code]
            checked = ((lang in ("python", "py", "python3") and kind != "no-run") or (path, line) in examples
                       or bool(elsewhere))
            assert checked, f"{path.name}:{line}: shows an output that no test compares"
            owned.append(out.line)
        assert sorted(owned) == fences, f"{path.name}: an output block at line(s) " \
            f"{sorted(set(fences) - set(owned))} follows no block (only blank lines may stand between)"


def test_marks_give_a_reason():
    for path in PAGES:
        text = path.read_text(encoding="utf-8")
        for comment in re.findall(r"<!--\s*(?:no-run|slow)\b[^>]*-->", text):
            assert MARK.match(comment) and MARK.match(comment).group(2), f"{path.name}: {comment} has no reason"


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 100


def test_readme_states_the_held_out_claim_in_one_sentence_with_its_link():
    """What clsas tunes and where it is judged: one sentence in the README, the evidence one link away."""
    paragraphs = (ROOT / "README.md").read_text(encoding="utf-8").split("\n\n")
    claim = [p for p in paragraphs if "never saw" in p]
    assert len(claim) == 1, "the README states the held-out claim once"
    text = " ".join(claim[0].split())
    assert len(re.findall(r"[.!?](?:\s|$)", text)) == 1, f"not one sentence: {text}"
    assert "(docs/guide/benchmarks.md#how-choices-are-judged)" in text
    assert "how-choices-are-judged" in _anchors(ROOT / "docs" / "guide" / "benchmarks.md")


def _anchors(page: Path) -> set[str]:
    """The anchors of a page's headings, as GitHub and MyST make them (lower case, spaces to hyphens)."""
    return {re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            for m in re.finditer(r"^#{1,6} (.*)$", page.read_text(encoding="utf-8"), re.MULTILINE)}


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




@pytest.mark.parametrize(("shown", "printed", "same"), [
    ("[array([0.1 , 0.05, 1.2 ])]", "[array([0.1, 0.05, 1.2])]", True),   # NumPy's padding
    ("25.4", "25.43755366822328", True),                                  # within 1 %
    ("25.4", "26.1", False),
    ("3 echoes", "2 echoes", False),                                      # a count is exact
    ("1.02e-05", "1.04e-05", False),
    ("True uff", "False uff", False),                                     # text is exact
    ("as recorded", "asrecorded", False),                                 # words stay apart
    ("TCR 17.6 dB   ... s on ...", "TCR 17.6 dB 0.87 s on Intel(R) OpenCL", True),
    ("a\n  b", "a b", True),                                              # any run of whitespace
    ("", "", True),
    ("", "something\n", False),                                           # no output block: prints nothing
    ("x", "x\ny", False),
    # a row missing from a table padded with spaces is refused (at once: whitespace runs next to
    # ``...`` are one pattern, not several that split each run every way)
    ("...\nnumpy bp ...\nnumpy ffbp ...\nnumpy reconstruct ...\nwrote ...",
     "\n".join(f"numpy{' ' * 40}{s}{' ' * 30}1.2 ms   3 %" for s in ("bp", "omega-k", "reconstruct")) + "\nwrote x",
     False),
    ("...\nnumpy bp ...\nnumpy ffbp ...\nwrote ...",
     "\n".join(f"numpy{' ' * 40}{s}{' ' * 30}1.2 ms   3 %" for s in ("bp", "ffbp")) + "\nwrote x", True),
])
def test_output_comparison(shown, printed, same):
    assert (compare(shown, printed) is None) is same


def test_output_block_tolerance_line(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("```python\nprint(1.04)\n```\n\n<!-- tolerance: 5% -->\n```output\n1.0\n```\n"
                    "```python\nprint(2)\n```\n")
    blocks = code_blocks(page)
    assert [(b[1], b[4].text if b[4] else None) for b in blocks] == [("python", "1.0"), ("python", None)]
    assert blocks[0][4].rtol == pytest.approx(0.05) and compare("1.0", "1.04", blocks[0][4].rtol) is None


def test_consistency_help_states_the_rule_the_gate_uses(capsys):
    """``--consistency``'s help gives the withdrawal threshold the gate applies."""
    from clsas.cli import main
    from clsas.focus.final_consistency import REVERT_RATIO

    with pytest.raises(SystemExit):
        main(["autofocus", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"excess ratio over {REVERT_RATIO:g}" in text and "unexplained as before" not in text
