"""The library's code and docstrings say what the code does, not how it came to be: no issue
numbers, session counts or commit ids under ``clsas/`` (the changelog keeps the history)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
HISTORY = re.compile(r"issue [0-9]+|[0-9]+(st|nd|rd|th) session|commit [0-9a-f]{7}")


def history_words(root: Path) -> list[str]:
    """``file:line: text`` of every line under ``root/clsas`` and ``root/kernels`` that cites an issue, a
    session or a commit."""
    found = []
    for path in sorted([*(root / "clsas").rglob("*"), *(root / "kernels").rglob("*")]):
        if path.suffix not in (".py", ".cl", ".h", ".c", ".toml", ".md", ".txt") or not path.is_file():
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if HISTORY.search(line):
                found.append(f"{path.relative_to(root).as_posix()}:{n}: {line.strip()}")
    return found


def test_the_library_carries_no_work_history():
    found = history_words(ROOT)
    assert not found, "say what the code does (history belongs in the changelog):\n" + "\n".join(found)


def test_the_scan_finds_history(tmp_path):
    (tmp_path / "clsas" / "cl").mkdir(parents=True)
    (tmp_path / "clsas" / "a.py").write_text('"""Fixed in issue 26."""\nx = 1  # the issue is the phase\n')
    (tmp_path / "kernels").mkdir()
    (tmp_path / "kernels" / "k.cl").write_text("// since the 3rd session\n// see commit 1a2b3c4d\n")
    assert [f.split(": ", 1)[0] for f in history_words(tmp_path)] == ["clsas/a.py:1", "kernels/k.cl:1",
                                                                     "kernels/k.cl:2"]
