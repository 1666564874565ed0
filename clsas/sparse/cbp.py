"""Continuous basis pursuit: CBP-Taylor and the convex CBP-Polar SOCP (cvxpy, positive
amplitudes, Ekanadham et al. 2011). CBP-Polar refined (BPDN support, nlopt delays) is in
:mod:`clsas.sparse.refined`."""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np

from .. import validate as v
from .atoms import Dictionary
from .bpdn import ShiftOperator, _check, _resolve_lam
from .metrics import Echoes
from .refined import cbp_polar_refined

__all__ = ["cbp_taylor", "cbp_polar", "cbp_polar_refined"]

log = logging.getLogger(__name__)


def _positive_only(amplitudes, name):
    if amplitudes != "positive":
        raise ValueError(
            f"{name} is the convex method of Ekanadham et al., which assumes positive amplitudes; "
            f"use method='cbp-polar' (the refined one) for amplitudes={amplitudes!r}"
        )


def cvxpy_memory_gib(n_rows: int, n_cols: int) -> float:
    """A rough bound on the memory (GiB) cvxpy and Clarabel take for ``|b - M z|^2 + ...`` with a
    dense ``(n_rows, n_cols)`` M: the matrix and its sparse canonical copies (about 4 of it) and
    the quadratic form ``M^T M`` with its factorisation (about 3 of it), float64."""
    return 8.0 * (4.0 * n_rows * n_cols + 3.0 * float(n_cols) ** 2) / 2**30


def _check_memory(name: str, n_rows: int, n_cols: int, max_memory_gib: float) -> float:
    """Refuse a problem whose estimate exceeds ``max_memory_gib``, with the numbers."""
    limit = v.positive("max_memory_gib", max_memory_gib)
    need = cvxpy_memory_gib(n_rows, n_cols)
    if need > limit:
        raise ValueError(
            f"{name}: the cvxpy problem would take about {need:.1f} GiB ({n_rows} rows x {n_cols} variables), "
            f"more than max_memory_gib={limit:g}: coarsen delta_s, shorten the signal, raise max_memory_gib, "
            f"or use method='bpdn' or 'cbp-polar' (matrix-free)")
    return need


def _solve(prob, name):
    import cvxpy as cp

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob.solve(solver="CLARABEL")
    except cp.error.SolverError as exc:
        raise RuntimeError(f"{name}: the solver failed ({exc})") from exc
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise RuntimeError(f"{name}: solver status {prob.status}")
    return prob.status, int(prob.solver_stats.num_iters or 0)


def _window_weights(D: np.ndarray) -> np.ndarray:
    """Each atom's l1 weight: its norm on the window over the largest (1 for an atom inside the
    window, less for one the window cuts), at least 1/2 (an atom that holds almost nothing of
    the window is not made free to fit what is left at its edge). Unweighted, a cut echo costs as much lam per unit of
    amplitude as a whole one while explaining a fraction of the energy, and the convex programs
    spread it over neighbouring atoms; weighted, a cut echo is one echo again."""
    norms = np.linalg.norm(D, axis=0)
    return np.maximum(norms / max(float(norms.max(initial=0.0)), 1e-300), 0.5)


def merge_coincident(taus: np.ndarray, amps: np.ndarray, tol_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Echoes closer than ``tol_s`` merged into one (amplitudes summed, the delay weighted by
    ``|amplitude|``), sorted by delay. A convex CBP cannot move an atom beyond its cell, so an
    echo near the boundary between two cells comes out as both atoms pushed to it: two echoes
    at one delay, which are one."""
    order = np.argsort(taus, kind="stable")
    taus, amps = np.asarray(taus, float)[order], np.asarray(amps)[order]
    if len(taus) < 2:
        return taus, amps
    groups = np.split(np.arange(len(taus)), np.flatnonzero(np.diff(taus) >= tol_s) + 1)
    w = np.abs(amps)
    new_taus = np.array([np.average(taus[g], weights=w[g]) if w[g].sum() > 0 else taus[g].mean() for g in groups])
    return new_taus, np.array([amps[g].sum() for g in groups])


def _echoes_from(taus, amps, rel_threshold, method, status, iters, t_start, info, tol_s):
    keep = np.abs(amps) > rel_threshold * max(np.abs(amps).max(initial=0.0), 1e-300)
    taus, amps = merge_coincident(taus[keep], amps[keep], tol_s)
    return Echoes(taus, amps, method, status, iters, time.perf_counter() - t_start, info)


def cbp_taylor(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="positive",
               rel_threshold: float = 1e-3, max_memory_gib: float = 4.0) -> Echoes:
    """CBP-Taylor: ``min |b - F c - G d|^2 + lam sum w_i c_i`` s.t. ``|d_i| <= c_i`` (G = Delta/2 f';
    ``w_i`` the atom's norm on the window over a whole atom's, at least 1/2, 1 but for atoms the
    window cuts). Echoes closer than Delta/4 are merged (:func:`merge_coincident`).

    ``amplitudes="positive"`` is Ekanadham et al.'s convex program. For signed or complex
    amplitudes (echoes of unknown phase) the same idea is kept convex with a bound ``t_i``:
    ``min |b - F c - G d|^2 + lam sum t`` s.t. ``|c_i| <= t_i``, ``|d_i| <= t_i``; the shift is
    ``Re(d_i / c_i) Delta / 2``, clipped to the cell. This relaxation lets d's phase differ
    from c's, so it is looser than the positive program; refined CBP-Polar has no such gap.
    """
    import cvxpy as cp

    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    lam, lmax = _resolve_lam(ShiftOperator(dictionary), b, amplitudes, lam, lam_frac)
    cplx = amplitudes == "complex"
    _check_memory("cbp-taylor", (2 if cplx else 1) * len(b), (4 if cplx else 2) * dictionary.k, max_memory_gib)
    F, G = dictionary.taylor()
    k = dictionary.k
    w = _window_weights(F)
    if amplitudes == "positive":
        c = cp.Variable(k, nonneg=True)
        d = cp.Variable(k)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(b - F @ c - G @ d) + lam * (w @ c)), [cp.abs(d) <= c])
    elif amplitudes == "real":
        c, d, t = cp.Variable(k), cp.Variable(k), cp.Variable(k, nonneg=True)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(b - F @ c - G @ d) + lam * (w @ t)),
                          [cp.abs(c) <= t, cp.abs(d) <= t])
    else:
        # complex, written in real and imaginary parts: the same program, and cvxpy builds it
        # about 4x faster than from complex variables
        M = np.block([[F.real, -F.imag, G.real, -G.imag], [F.imag, F.real, G.imag, G.real]])
        z, t = cp.Variable(4 * k), cp.Variable(k, nonneg=True)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(np.r_[b.real, b.imag] - M @ z) + lam * (w @ t)),
                          [cp.SOC(t, cp.vstack([z[:k], z[k:2 * k]]), axis=0),
                           cp.SOC(t, cp.vstack([z[2 * k:3 * k], z[3 * k:]]), axis=0)])
    status, iters = _solve(prob, "cbp-taylor")
    if amplitudes == "complex":
        zv = np.asarray(z.value)
        cv, dv = zv[:k] + 1j * zv[k:2 * k], zv[2 * k:3 * k] + 1j * zv[3 * k:]
    else:
        cv, dv = np.asarray(c.value), np.asarray(d.value)
    if amplitudes == "positive":
        cv = np.maximum(cv.real, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.abs(cv) > 0, np.real(dv / np.where(np.abs(cv) > 0, cv, 1)), 0.0)
    shift = np.clip(ratio, -1, 1) * dictionary.delta / 2
    return _echoes_from(dictionary.taus + shift, cv, rel_threshold, "cbp-taylor", status, iters, t_start,
                        {"lam": lam, "lam_max": lmax}, dictionary.delta / 4)


def cbp_polar(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="positive",
              rel_threshold: float = 1e-3, max_memory_gib: float = 4.0) -> Echoes:
    """Convex CBP-Polar (SOCP): ``|(u_i, v_i)| <= r c_i``, ``u_i >= r cos(theta) c_i``, penalty
    ``lam sum w_i c_i`` (``w_i`` as in :func:`cbp_taylor`);
    delay = grid + (Delta/2) atan2(v, u) / theta. Refused before it is built where its memory
    estimate exceeds ``max_memory_gib`` (see :func:`cbp_taylor`)."""
    import cvxpy as cp

    t_start = time.perf_counter()
    _positive_only(amplitudes, "cbp-polar (convex)")
    b = _check(dictionary, b, amplitudes)
    lam, lmax = _resolve_lam(ShiftOperator(dictionary), b, amplitudes, lam, lam_frac)
    _check_memory("cbp-polar (convex)", len(b), 3 * dictionary.k, max_memory_gib)
    P = dictionary.polar()
    k = dictionary.k
    c, u, w = cp.Variable(k, nonneg=True), cp.Variable(k), cp.Variable(k)
    cons = [cp.SOC(P.r * c, cp.vstack([u, w]), axis=0), u >= P.r * np.cos(P.theta) * c]
    weights = _window_weights(dictionary.matrix())
    prob = cp.Problem(cp.Minimize(cp.sum_squares(b - P.C @ c - P.U @ u - P.V @ w) + lam * (weights @ c)), cons)
    status, iters = _solve(prob, "cbp-polar (convex)")
    cv = np.maximum(c.value, 0.0)
    shift = (dictionary.delta / 2) * np.arctan2(w.value, u.value) / P.theta
    return _echoes_from(dictionary.taus + shift, cv, rel_threshold, "cbp-polar-socp", status, iters, t_start,
                        {"lam": lam, "lam_max": lmax, "r": P.r, "theta": P.theta}, dictionary.delta / 4)
