"""One-off tool: move the long README's sections into the guide pages and write the short README.

    python docs/migrate_readme.py                         # README.md is still the long one
    python docs/migrate_readme.py --source main:README.md # README.md is already short: read a long
                                                          # one from git (any <rev>:<path>) or a file

Merging the branch that made the site (issue 32) into a main whose README has grown meanwhile:
``git merge issue-32`` (README.md conflicts, or comes out short), then, before committing,
``python docs/migrate_readme.py --source HEAD:README.md`` (HEAD is main's side: the long README)
and ``git add README.md docs/guide``.

Every ``## `` section of the README goes to the guide page that ``PAGES`` names for its title
(first match wins; a ``### `` section goes with its parent unless ``SUBSECTIONS`` names it), in
README order, below that page's hand-written header (``docs/guide_src/<page>.md``). The text before
the first ``## `` goes to ``PREAMBLE_PAGE``. A ``## `` title that no pattern matches stops the
script before it writes anything: add a row to ``PAGES`` (nothing is dropped silently). Then the
short README is written from ``docs/README.template.md``.

The result depends only on the long README and the files under docs/, so running it twice on the
same README gives the same pages (page = header + migrated sections). Once it has run on the final
README, the guide pages are the source: edit them directly.

Rewrites made to the migrated text, so that the site builds with warnings as errors:

- a path ``bench/results/<stem>.<ext>`` in backticks becomes a link to the generated benchmark page
  of that result (``docs/benchmarks/<stem>.md``, written at build time by docs/_ext/benchpages.py),
  where such a result exists, so figures quoted in the guide point at their device, date and peer;
- a code block containing a text listed in ``MARKS`` gets the HTML comment that tests/test_docs.py reads before it
  (``<!-- no-run: reason -->`` or ``<!-- slow: reason -->``), unless one is there already.
"""

from __future__ import annotations

import argparse
import itertools
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# '## ' title (regular expression, case-insensitive) -> guide page, first match wins
PAGES: list[tuple[str, str]] = [
    (r"^the two commands", "first-image"),
    (r"^python api", "first-image"),
    (r"first (day|hour|image)|getting started|quick ?start", "first-image"),
    (r"large volume|out[- ]of[- ]core|dask|cluster|tiles|past memory", "large-volumes"),
    (r"super-?resolution|sparse|model-based", "super-resolution"),
    (r"image formation|formation", "fast-formation"),
    (r"own data|measured data|import|airsas|preprocess", "own-data"),
    (r"autofocus", "autofocus"),
    (r"command line|\bcli\b", "command-line"),
    (r"\brig\b|acquir|stage|sound card", "rig"),
    (r"backend|device|kernel", "devices-and-kernels"),
    (r"dataset file|image file|file|export|picture", "files"),
    (r"physics|paper", "physics"),
    (r"organi[sz]ed|extending|architecture|code map|plug-?in", "extending"),
    (r"benchmark", "benchmarks"),
]
# '### ' title (regular expression) -> guide page, where it should not follow its parent
SUBSECTIONS: list[tuple[str, str]] = []
PREAMBLE_PAGE = "first-image"
GUIDE = ["first-image", "own-data", "rig", "command-line", "super-resolution", "fast-formation",
         "autofocus", "large-volumes", "devices-and-kernels", "files", "physics", "extending",
         "benchmarks"]

# code blocks tests/test_docs.py should not run as they are: (text in the block, mark)
MARKS: list[tuple[str, str]] = [
    ('import_airsas("small_features_cutout_20k"',
     "no-run: needs the public AirSAS scans, downloaded outside the repository"),
    ("out, report = clsas.autofocus(ds, grid)",
     "slow: autofocus with every default method, about 30 s on 2 loaded cores"),
    ("from clsas.sparse import superres, Echoes, delay_error, crb_delays",
     "slow: CBP-Polar on every recording of the page's scan, about 15 s on 2 loaded cores"),
]

BENCH_PATH = re.compile(r"(?<!\[)`bench/results/([^`<>*{}\s]+?)\.(?:json|md|png|\*|\{[^`]*\})`")
GENERATED = ("<!-- This page was assembled by docs/migrate_readme.py from docs/guide_src/{page}.md and\n"
             "     the README's sections; edit it directly once the README has been migrated. -->\n\n")


def read_source(source: str | None) -> str:
    """The long README's text: README.md, a file, or ``<rev>:<path>`` read from git."""
    if source is None:
        path = ROOT / "README.md"
    elif ":" in source and not Path(source).exists():
        return subprocess.run(["git", "show", source], cwd=ROOT, check=True, capture_output=True,
                              text=True).stdout
    else:
        path = Path(source)
    return path.read_text(encoding="utf-8")


def split_sections(text: str) -> tuple[str, list[tuple[str, str, str]]]:
    """The preamble and ``(title, parent title, text)`` per ``## `` or ``### `` section.

    Headings inside fenced code blocks are not headings.
    """
    preamble: list[str] = []
    sections: list[tuple[str, str, list[str]]] = []
    parent = ""
    fence = None
    for line in text.splitlines(keepends=True):
        stripped = line.lstrip()
        if fence is None and stripped.startswith(("```", "~~~")):
            fence = stripped[:3]
        elif fence is not None and stripped.startswith(fence):
            fence = None
        elif fence is None and re.match(r"#{2,3} ", line):
            title = line.lstrip("#").strip()
            if line.startswith("## "):
                parent = title
                sections.append((title, "", []))
            else:
                sections.append((title, parent, []))
        (sections[-1][2] if sections else preamble).append(line)
    return "".join(preamble), [(t, p, "".join(lines)) for t, p, lines in sections]


def page_of(title: str, parent: str, pages_of_parents: dict[str, str]) -> str:
    """The guide page of a section; raises SystemExit naming a ``## `` title no row maps."""
    if parent:
        for pattern, page in SUBSECTIONS:
            if re.search(pattern, title, re.IGNORECASE):
                return page
        return pages_of_parents[parent]
    for pattern, page in PAGES:
        if re.search(pattern, title, re.IGNORECASE):
            return page
    raise SystemExit(f"migrate_readme: the README section '## {title}' has no guide page; add a row to "
                     f"PAGES in docs/migrate_readme.py (nothing was written)")


def rewrite(text: str) -> str:
    """Benchmark paths as links to their generated pages; MARKS before their code blocks."""
    def link(match: re.Match) -> str:
        stem = match.group(1)
        if any((ROOT / "bench" / "results").glob(f"{stem}.*")):
            return f"[{match.group(0)}](../benchmarks/{stem}.md)"
        return match.group(0)

    text = BENCH_PATH.sub(link, text)
    lines = text.splitlines(keepends=True)
    out: list[str] = []
    fence = None
    for i, line in enumerate(lines):
        if fence is None and line.startswith("```"):
            fence = line[: len(line) - len(line.lstrip("`"))]
            body = "".join(itertools.takewhile(lambda x, f=fence: not x.startswith(f), lines[i + 1:]))
            previous = next((p for p in reversed(out) if p.strip()), "")
            for needle, mark in MARKS:
                if needle in body and not previous.lstrip().startswith("<!--"):
                    out.append(f"<!-- {mark} -->\n")
                    break
        elif fence is not None and line.startswith(fence):
            fence = None
        out.append(line)
    return "".join(out)


def assemble(readme: str) -> dict[str, str]:
    """Guide page name -> its full text (header + migrated sections)."""
    preamble, sections = split_sections(readme)
    if preamble + "".join(text for _, _, text in sections) != readme:  # every line has a home
        raise SystemExit("migrate_readme: the sections do not add up to the README (a bug here)")
    parts: dict[str, list[str]] = {page: [] for page in GUIDE}
    intro = re.sub(r"\A\s*# [^\n]*\n", "", preamble).strip()
    if intro:
        parts[PREAMBLE_PAGE].append(intro + "\n")
    parents: dict[str, str] = {}
    for title, parent, text in sections:
        page = page_of(title, parent, parents)
        if not parent:
            parents[title] = page
        if page not in parts:
            raise SystemExit(f"migrate_readme: page {page!r} is not in GUIDE")
        parts[page].append(text.rstrip() + "\n")
    pages = {}
    for page, texts in parts.items():
        header = (DOCS / "guide_src" / f"{page}.md").read_text(encoding="utf-8").rstrip() + "\n"
        body = "\n".join(rewrite(t) for t in texts)
        pages[page] = GENERATED.format(page=page) + header + ("\n" + body if body else "")
    return pages


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", help="the long README: a file or <rev>:<path> (default README.md)")
    ap.add_argument("--check", action="store_true", help="only map the sections; write nothing")
    args = ap.parse_args(argv)
    readme = read_source(args.source)
    template = (DOCS / "README.template.md").read_text(encoding="utf-8")
    if readme.strip() == template.strip():
        raise SystemExit("migrate_readme: README.md is already the short one; pass --source <rev>:README.md "
                         "with a long README (e.g. --source main:README.md)")
    pages = assemble(readme)
    for page, text in pages.items():
        n = sum(1 for line in text.splitlines() if line.startswith("## "))
        sys.stdout.write(f"docs/guide/{page}.md: {n} sections, {len(text.splitlines())} lines\n")
    if args.check:
        return 0
    for page, text in pages.items():
        (DOCS / "guide" / f"{page}.md").write_text(text, encoding="utf-8")
    (ROOT / "README.md").write_text(template, encoding="utf-8")
    sys.stdout.write(f"README.md: {len(template.splitlines())} lines\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
