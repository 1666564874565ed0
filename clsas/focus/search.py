"""The bounded 1-D search the delay and temperature stages maximise their metric with."""

from __future__ import annotations

import numpy as np

__all__ = ["bounded_search"]


def bounded_search(f, lo: float, hi: float, step: float, tol: float) -> tuple[float, float, int]:
    """Maximise a 1-D ``f`` on ``[lo, hi]``: a scan at ``step``, then golden-section search
    in the bracket around the best point, to ``tol``. Returns ``(x, f(x), evaluations)``."""
    n = max(3, int(np.ceil((hi - lo) / step)) + 1)
    xs = np.linspace(lo, hi, n)
    fs = np.array([f(x) for x in xs])
    k = int(np.argmax(fs))
    a, b = xs[max(k - 1, 0)], xs[min(k + 1, n - 1)]
    best_x, best_f = float(xs[k]), float(fs[k])
    g = (np.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    evals = n + 2
    while b - a > tol:
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
        evals += 1
    for x, fx in ((c, fc), (d, fd)):
        if fx > best_f:
            best_x, best_f = float(x), float(fx)
    return best_x, best_f, evals
