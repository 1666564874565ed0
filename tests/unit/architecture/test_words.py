"""The code, its tests and its benchmarks say what they do, not how they came to be: no issue
numbers, session counts or commit ids under ``clsas/``, ``kernels/``, ``tests/`` or in ``bench``'s
code (the changelog and the result pages keep the history)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
_ORDINALS = "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|fourteenth"
HISTORY = re.compile(rf"issue [0-9]+|([0-9]+(st|nd|rd|th)|{_ORDINALS}) session|commit [0-9a-f]{{7}}", re.IGNORECASE)
SCANNED = ("clsas", "kernels", "tests", "bench")  # bench/results, the pages of figures, keeps its history
SKIPPED = ("bench/results", "tests/unit/architecture/test_words.py")  # the pages; this file's own toy lines


def history_words(root: Path) -> list[str]:
    """``file:line: text`` of every line under ``root``'s :data:`SCANNED` folders (but not
    :data:`SKIPPED`) that cites an issue, a session or a commit."""
    found = []
    for path in sorted(p for folder in SCANNED for p in (root / folder).rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.suffix not in (".py", ".cl", ".h", ".c", ".toml", ".md", ".txt") or not path.is_file():
            continue
        if any(rel == s or rel.startswith(s + "/") for s in SKIPPED):
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if HISTORY.search(line):
                found.append(f"{rel}:{n}: {line.strip()}")
    return found


def test_the_library_carries_no_work_history():
    found = history_words(ROOT)
    assert not found, "say what the code does (history belongs in the changelog):\n" + "\n".join(found)


def test_the_scan_finds_history(tmp_path):
    (tmp_path / "clsas" / "cl").mkdir(parents=True)
    (tmp_path / "clsas" / "a.py").write_text('"""Fixed in issue 26."""\nx = 1  # the issue is the phase\n')
    (tmp_path / "kernels").mkdir()
    (tmp_path / "kernels" / "k.cl").write_text("// since the 3rd session\n// see commit 1a2b3c4d\n")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_a.py").write_text('"""Issue 17, part B."""\n# as found in the fifth session\n')
    (tmp_path / "bench" / "results").mkdir(parents=True)
    (tmp_path / "bench" / "b.py").write_text("x = 1  # the issue of noise\n")
    (tmp_path / "bench" / "results" / "r.md").write_text("# Figures (issue 31)\n")
    assert [f.split(": ", 1)[0] for f in history_words(tmp_path)] == ["clsas/a.py:1", "kernels/k.cl:1",
                                                                     "kernels/k.cl:2", "tests/test_a.py:1",
                                                                     "tests/test_a.py:2"]
