"""Timing and fitting helpers of the benchmark suite."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from clsas.presenting.rates import cpu_name  # the benchmarks name their machine as clsas bench does

__all__ = ["cpu_name", "timed", "fit_exponent", "jsonable"]


def timed(fn: Callable[[], object], repeats: int, warmup: bool = True) -> list[float]:
    """Wall times of ``repeats`` calls of ``fn``, after one untimed warm-up call.

    ``fn`` is called ``repeats + 1`` times with ``warmup`` (the first call's side effects, such
    as appending a kernel time, happen too), ``repeats`` times without.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    if warmup:
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def seconds(t: float) -> str:
    """A run time for a report: milliseconds under 0.1 s (a GPU's times), else seconds."""
    return f"{t * 1e3:.3g} ms" if t < 0.1 else f"{t:.2f} s"


def source_commit() -> str | None:
    """The git commit clsas runs from (short hash, ``+dirty`` where tracked files differ from it),
    so that a stored result names its code; None outside a git checkout or without git."""
    import subprocess
    from pathlib import Path

    import clsas

    root = Path(clsas.__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=5)
        if head.returncode != 0 or not head.stdout.strip():
            return None
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("+dirty" if dirty else "")


def times(x: float) -> str:
    """A speed-up for a report: three digits (0.31x, 15.1x, 174x, 1234x)."""
    return f"{x:.3g}x" if x < 1000 else f"{x:.0f}x"


def fit_exponent(sizes, times) -> float:
    """Least-squares slope of log(time) against log(size): cost ~ size^exponent."""
    x = np.log(np.asarray(sizes, float))
    y = np.log(np.asarray(times, float))
    if len(x) < 2 or not np.all(np.isfinite(x)) or not np.all(np.isfinite(y)) or np.ptp(x) == 0:
        raise ValueError("fit_exponent needs at least two distinct positive sizes and positive times")
    return float(np.polyfit(x, y, 1)[0])


def jsonable(x):
    """``x`` with NumPy scalars as Python numbers, tuples as lists, keys as strings and NaN/Inf as
    None (``null``), so that ``json.dumps`` writes it."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x
