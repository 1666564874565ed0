"""What a documented block prints, against what its page says it prints.

A page shows what a block prints in an ``output`` block right after it (blank lines, and one
``<!-- tolerance: N% -->`` line, may stand between them):

````markdown
```python
print(clsas.tcr_db(image, box))
```

```output
25.43755366822328
```
````

The comparison (``contributing.md`` states it for authors):

- text is compared exactly, except for whitespace: a run of spaces or newlines matches any
  other run, and whitespace next to punctuation may be absent (NumPy pads its columns by the
  width of the numbers);
- a number matches within ``RTOL`` (1 %) of the page's figure, or half a unit in its last
  printed digit, whichever is larger (``1.0e-5`` matches 1.04e-5; ``3`` echoes does not match 2);
  ``<!-- tolerance: 5% -->`` on the line before the output block widens it for that block;
- ``...`` stands for any text (a run time, a device name, an address).

A block with no ``output`` block must print nothing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

#: The language of a fenced block that shows what the block before it prints.
OUTPUT_LANG = "output"
#: Relative tolerance on a printed number, unless the page states another for the block.
RTOL = 0.01
TOLERANCE_LINE = re.compile(r"^<!--\s*tolerance\s*:\s*([0-9.]+)\s*%\s*-->$")
NUMBER = r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?"
_TOKENS = re.compile(rf"(\.\.\.)|({NUMBER})|(\s+)|(.)", re.DOTALL)


@dataclass(frozen=True)
class Expected:
    """A block's output as its page shows it: the text, the tolerance, the line of the output fence."""

    text: str
    rtol: float = RTOL
    line: int = 0


def _pattern(expected: str) -> tuple[re.Pattern, list[str]]:
    """A regular expression for ``expected`` (numbers captured), and its numbers as printed."""
    parts, numbers = [], []
    tokens = list(_TOKENS.finditer(expected.strip()))

    def wordlike(k: int) -> bool:
        return 0 <= k < len(tokens) and bool(tokens[k].group(2) or (tokens[k].group(4) or "").isalnum())

    for k, m in enumerate(tokens):
        dots, number, space, char = m.groups()
        if dots:
            parts.append(r".*?")
        elif number:
            parts.append(rf"({NUMBER}|nan|-?inf)")
            numbers.append(number)
        elif space:  # between words or numbers whitespace must stay (it separates them); elsewhere it may go
            parts.append(r"\s+" if wordlike(k - 1) and wordlike(k + 1) else r"\s*")
        else:
            parts += [re.escape(char)] if char.isalnum() else [r"\s*", re.escape(char), r"\s*"]
    return re.compile("".join(_merged(parts)), re.DOTALL), numbers


_SPACE = (r"\s*", r"\s+")


def _merged(parts: list[str]) -> list[str]:
    r"""``parts`` with each run of whitespace patterns as one (``\s+`` where any of them needs a
    space), and none beside ``...``'s ``.*?``, which takes whitespace itself: the same texts match,
    and a table's padded columns no longer give a mismatch exponentially many ways to be tried."""
    out: list[str] = []
    for part in parts:
        prev = out[-1] if out else None
        if part in _SPACE and prev in _SPACE:
            out[-1] = r"\s+" if r"\s+" in (part, prev) else r"\s*"
        elif part == r"\s*" and prev == ".*?":
            continue
        elif part == ".*?" and prev == r"\s*":
            out[-1] = part
        else:
            out.append(part)
    return out


def _half_unit(printed: str) -> float:
    """Half a unit in the last digit of a printed number: ``28.3`` -> 0.05, ``1.02e-05`` -> 5e-8."""
    mantissa, _, exponent = printed.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 0.5 * 10.0 ** (-decimals + (int(exponent) if exponent else 0))


def compare(expected: str, actual: str, rtol: float = RTOL) -> str | None:
    """None where ``actual`` is what ``expected`` shows (module notes), else what differs."""
    if not expected.strip():
        return None if not actual.strip() else f"prints\n{actual}\nbut the page shows no output for it"
    pattern, numbers = _pattern(expected)
    m = pattern.fullmatch(actual.strip())
    if m is None:
        return f"the text differs from the page's\n--- page:\n{expected.strip()}\n--- printed:\n{actual.strip()}"
    wrong = []
    for k, (shown, got) in enumerate(zip(numbers, m.groups(), strict=True)):
        e, a = float(shown), float(got)
        if not abs(a - e) <= max(rtol * abs(e), _half_unit(shown)):
            wrong.append(f"number {k + 1}: the page shows {shown}, it prints {got}")
    if wrong:
        return (f"numbers differ by more than {rtol:.0%} (or half a unit in the page's last digit): "
                + "; ".join(wrong) + f"\n--- page:\n{expected.strip()}\n--- printed:\n{actual.strip()}")
    return None


def output_after(lines: list[str], end: int) -> Expected | None:
    """The ``output`` block that follows a block ending at line index ``end`` (its closing fence),
    with its tolerance, or None."""
    i, rtol = end + 1, RTOL
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i < len(lines) and (m := TOLERANCE_LINE.match(lines[i].strip())):
        rtol = float(m.group(1)) / 100
        i += 1
        while i < len(lines) and not lines[i].strip():
            i += 1
    fence = re.match(r"^(`{3,})\s*([\w+-]*)", lines[i]) if i < len(lines) else None
    if not fence or fence.group(2).lower() != OUTPUT_LANG:
        return None
    j = i + 1
    while j < len(lines) and not lines[j].startswith(fence.group(1)):
        j += 1
    return Expected("\n".join(lines[i + 1: j]), rtol, i + 1)
