"""The stored benchmark results stay a small curated set, and every citation of one in the README
and the docs pages names a file that is there.

``bench/results/`` keeps the newest result per benchmark that a docs page shows (older runs are in
the repository's history: ``git log -- bench/results``). A page cites a result as a path
(``bench/results/<name>``, with ``*`` or ``{a,b}`` where it names several), as a link to its
generated page (``../benchmarks/<stem>.md`` or ``{doc}`...<../benchmarks/<stem>>```), as a bare
file name (``2026-11-28-beams.md``) or as the tail of one (``...-held-out-2.md``).
"""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"
MAX_FILES = 40
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "guide").glob("*.md")),
         RESULTS / "README.md"]  # the folder's own list of what it keeps

PATH = re.compile(r"bench/results/([0-9][^\s`'\")\]]*)")
PAGE_LINK = re.compile(r"benchmarks/(\d{4}-\d\d-\d\d-[^\s`'\")>\]]+?)(?:\.md)?(?=[)>])")
BARE_NAME = re.compile(r"(?<![\w/.-])(\d{4}-\d\d-\d\d-[\w.{},*-]*?\.(?:md|json|jsonl|png|log|\*|\{[\w,]+\}))(?![\w])")
TAIL = re.compile(r"\.\.\.(-[\w.{},-]+\.(?:md|json|png|\*))")


def _expand(pattern: str) -> list[str]:
    """``a{b,c}d`` -> ``[abd, acd]`` (nested braces are not used in the pages)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [x for alt in m.group(1).split(",") for x in _expand(pattern[:m.start()] + alt + pattern[m.end():])]


def _stored() -> list[str]:
    return sorted(p.name for p in RESULTS.iterdir() if p.is_file())


def citations(text: str) -> list[tuple[str, str]]:
    """``(kind, pattern)`` for each citation of a stored result in a page's text; kind is
    ``"path"`` (a file name, glob or brace pattern), ``"page"`` (a stem) or ``"tail"``."""
    found = [("path", m.group(1).rstrip(".,;:")) for m in PATH.finditer(text)]
    found += [("page", m.group(1)) for m in PAGE_LINK.finditer(text)]
    without_paths = PATH.sub("", text)
    found += [("path", m.group(1)) for m in BARE_NAME.finditer(without_paths)]
    found += [("tail", m.group(1)) for m in TAIL.finditer(text)]
    return found


def unresolved(text: str, stored: list[str]) -> list[str]:
    """The citations in ``text`` that name no stored file (each brace alternative must match)."""
    stems = {name.rsplit(".", 1)[0] for name in stored}
    missing = []
    for kind, pattern in citations(text):
        for alt in _expand(pattern):
            if kind == "page":
                ok = alt in stems
            elif kind == "tail":
                ok = any(fnmatch.fnmatch(name, "*" + alt) for name in stored)
            else:
                ok = any(fnmatch.fnmatch(name, alt) for name in stored)
            if not ok:
                missing.append(f"{kind} {alt}")
    return missing


def test_the_stored_results_are_a_small_set():
    files = [p for p in RESULTS.rglob("*") if p.is_file()]
    assert len(files) <= MAX_FILES, (f"bench/results holds {len(files)} files, more than {MAX_FILES}: keep the "
                                     "newest result per benchmark that a docs page shows")
    assert (RESULTS / "README.md").is_file()


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_cited_result_is_stored(page):
    missing = unresolved(page.read_text(encoding="utf-8"), _stored())
    assert not missing, f"{page.relative_to(ROOT)} cites results that bench/results does not hold: {missing}"


def test_the_citation_check_sees_each_form():
    """The check finds a missing file in each form a page uses, and accepts stored ones."""
    stored = ["2026-11-28-beams.md", "2026-11-28-autofocus-family-held-out-2.md",
              "2026-11-28-autofocus-family-held-out-2.png"]
    good = ("`bench/results/2026-11-28-beams.md`; [x](../benchmarks/2026-11-28-beams.md); "
            "`bench/results/2026-11-28-autofocus-family-held-out-2.{md,png}`; `...-held-out-2.md`; "
            "{doc}`result <../benchmarks/2026-11-28-beams>`; `bench/results/2026-11-28-*.md`; "
            "`bench/results/<date>-stress-<host>.*`")
    assert unresolved(good, stored) == []
    bad = {"`bench/results/2026-11-27-beams.md`": "path 2026-11-27-beams.md",
           "[x](../benchmarks/2026-11-27-beams.md)": "page 2026-11-27-beams",
           "{doc}`result <../benchmarks/2026-11-27-beams>`": "page 2026-11-27-beams",
           "`bench/results/2026-11-28-beams.{json,md}`": "path 2026-11-28-beams.json",
           "(`2026-11-28-formation-vm-final-dense.md`)": "path 2026-11-28-formation-vm-final-dense.md",
           "[`...-held-out-2-before.md`](x)": "tail -held-out-2-before.md",
           "`bench/results/2026-11-25-scale-*`": "path 2026-11-25-scale-*"}
    for text, expected in bad.items():
        assert expected in unresolved(text, stored), text
