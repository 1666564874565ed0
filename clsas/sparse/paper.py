"""The paper's 1-D super-resolution problem (its Fig. 4 and 6): two shifted decaying exponentials
on a 1 kHz grid, and one cell of its grid-spacing x regularisation sweep.

A small, exact problem to see what each sparse method (:data:`clsas.sparse.SPARSE_METHODS`) does
with the grid spacing Delta and the regularisation lam; ``examples/fig6_heatmaps.py`` draws the
sweep, and the benchmark package times it.
"""

from __future__ import annotations

import time

import numpy as np

from .atoms import Atom, Dictionary
from .metrics import Echoes, delay_error

__all__ = ["GRID_DELTAS", "GRID_LAM_FRACS", "GRID_METHODS", "grid_cell", "grid_problem"]

GRID_DELTAS = (0.0125, 0.025, 0.05, 0.1, 0.2)
GRID_LAM_FRACS = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3)
GRID_METHODS = ("bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar")


def grid_problem(alpha: float = 8.0, fs_hz: float = 1000.0, noise: float = 1e-4, seed: int = 4):
    """(atom, signal, truth) of the paper's 1-D problem (Fig. 4 and 6)."""
    from .atoms import decaying_exponential

    truth = Echoes([0.31, 0.47], [1.0, 0.8])
    atom = Atom(decaying_exponential(alpha), fs_hz, 1000,
                derivative=lambda t: np.where(t >= 0, (1 - alpha * t) * np.exp(-alpha * np.maximum(t, 0)), 0))
    b = truth.signal(atom) + noise * np.random.default_rng(seed).normal(size=atom.n)
    return atom, b, truth


def grid_cell(method: str, delta_s: float, lam_frac: float) -> dict:
    """One cell of the Delta x lam grid: eq. 5 error and run time of one method.

    As in the paper, BPDN's answer is every active atom (exact, duality gap 1e-7), and the
    convex CBPs' every echo above 1e-3 of the largest; no echo cap but refined CBP-Polar's 8.
    """
    from .registry import sparse_echoes

    if method not in GRID_METHODS:
        raise ValueError(f"method must be one of {GRID_METHODS}, got {method!r}")
    atom, b, truth = grid_problem()
    d = Dictionary(atom, delta_s, tau0_s=0.0, n_atoms=int(round(1.0 / delta_s)))
    t = time.perf_counter()
    opts = {"bpdn": {"group": False, "tol": 1e-7}}.get(method, {})
    est = sparse_echoes(method, d, b, lam_frac=lam_frac, amplitudes="positive",
                        max_echoes=8 if method == "cbp-polar" else d.k, **opts)
    elapsed = time.perf_counter() - t
    return {"method": method, "delta_s": delta_s, "lam_frac": lam_frac,
            "error": float(delay_error(est, truth, b, atom).total), "time_s": elapsed}


