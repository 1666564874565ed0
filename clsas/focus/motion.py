"""Line-of-sight motion: a smooth basis over the stops and its sharpness optimisation."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from ..physics.scan_errors import stop_index

__all__ = ["motion_basis", "optimise_los", "optimise_xyz", "los_directions", "stops_of"]

log = logging.getLogger(__name__)


def stops_of(ds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(stop (n_meas,), stop time (n_stops,), carriage xy (n_stops, 2))``; the time axis is
    the dataset's ``timestamps`` where it has them, else the stop order."""
    stop = stop_index(ds.tx_positions, ds.stage_positions)
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    t = np.arange(len(first), dtype=float) if ds.timestamps is None else ds.timestamps[first] - ds.timestamps[first[0]]
    ref = ds.stage_positions if ds.stage_positions is not None else 0.5 * (ds.tx_positions + ds.rx_positions)
    return stop, np.asarray(t, float), ref[first, :2]


def motion_basis(t: np.ndarray, xy: np.ndarray, n_basis: int) -> np.ndarray:
    """(n_stops, k) orthonormal smooth functions of stop time, orthogonal to 1, x and y.

    Cosines ``cos(pi j (t - t_0) / T)``, j = 1..n_basis, in order of frequency (so the first
    columns are the smoothest and a prefix is a coarser basis). The components a focus metric
    cannot see (a constant path error: a range shift; one linear in the carriage's x and y: a
    tilt, an image shift) are projected out; k <= n_basis.
    """
    n = len(t)
    span = max(float(t.max() - t.min()), 1e-12)
    dt = span / max(n - 1, 1)
    tt = (t - t.min() + 0.5 * dt) / (span + dt)
    j = np.arange(1, n_basis + 1)
    b = np.cos(np.pi * tt[:, None] * j[None, :])
    nuis = np.c_[np.ones(n), xy - xy.mean(axis=0)]
    q, _ = np.linalg.qr(nuis)
    keep = np.linalg.norm(q, axis=0) > 0
    q = q[:, keep]
    b = b - q @ (q.T @ b)
    qb, r = np.linalg.qr(b)
    ok = np.abs(np.diag(r)) > 1e-6 * max(np.abs(np.diag(r)).max(initial=0.0), 1e-300)
    return qb[:, ok]


def los_directions(ds, centre_m: np.ndarray) -> np.ndarray:
    """(n_meas, 3) unit vectors from each pair's midpoint to ``centre_m``."""
    u = centre_m[None, :] - 0.5 * (ds.tx_positions + ds.rx_positions)
    return u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)


def optimise_los(engine, base_shift_s: np.ndarray, c_mps: np.ndarray, stop: np.ndarray, basis: np.ndarray,
                 stages: list[int], max_iter: int, history: list, callback: Callable | None = None
                 ) -> tuple[np.ndarray, dict]:
    """Maximise the focus metric over per-stop path corrections ``p = basis[:, :k] @ a`` (m).

    A correction p (true minus stated bistatic path, m) reads measurement m's profile at
    ``tau - (-p / c)``. L-BFGS-B with the analytic gradient, on nested bases of ``stages``
    columns (coarse to fine), each started from the last. Returns ``(p per stop, info)``.
    """
    from scipy.optimize import minimize

    scale = 1e-3  # parameters in mm of path
    info = {"stages": [], "evaluations": 0}
    p = np.zeros(basis.shape[0])
    a_prev = np.zeros(0)
    for k in stages:
        b = basis[:, :k]
        x0 = np.r_[a_prev, np.zeros(k - len(a_prev))]
        evals = {"n": 0, "best": -np.inf}

        def fun(a, b=b, evals=evals):
            pm = (b @ a) * scale
            shift = base_shift_s - pm[stop] / c_mps
            m, sums, _ = engine.evaluate(shift, c_mps)
            # dM/dp_m = col0 / c_m, summed over the measurements of each stop
            g_stop = np.bincount(stop, sums[:, 0] / c_mps, minlength=b.shape[0])
            evals["n"] += 1
            if m > evals["best"]:
                evals["best"] = m
            history.append(m)
            if callback is not None:
                callback("los", len(history), m)
            return -m, -(b.T @ g_stop) * scale

        res = minimize(fun, x0, jac=True, method="L-BFGS-B", options={"maxiter": max_iter, "gtol": 1e-9,
                                                                        "ftol": 1e-10})
        a_prev = res.x
        p = (b @ res.x) * scale
        info["stages"].append({"basis": k, "metric": float(-res.fun), "evaluations": evals["n"],
                               "message": str(res.message)})
        info["evaluations"] += evals["n"]
        log.info("autofocus los: %d functions, metric %.5g after %d evaluations (%s)", k, -res.fun, evals["n"],
                 res.message)
    return p, info


def default_basis_size(t: np.ndarray, n_stops: int, bandwidth_hz: float, timed: bool) -> int:
    """Functions needed for motion up to ``bandwidth_hz`` over the scan's duration (timed
    stops), else a quarter of the stops; at least 2, at most n_stops - 3."""
    k = math.ceil(2 * bandwidth_hz * float(t.max() - t.min())) + 1 if timed else n_stops // 4
    return int(max(2, min(k, n_stops - 3)))


def optimise_xyz(engine, shift_s: np.ndarray, c_mps: np.ndarray, stop: np.ndarray, start_m: np.ndarray,
                 max_iter: int, history: list, callback: Callable | None = None, basis: np.ndarray | None = None
                 ) -> tuple[np.ndarray, dict]:
    """Maximise the focus metric over a 3-D carriage displacement per stop (m).

    ``start_m`` (n_stops, 3) is where the search begins (e.g. the line-of-sight estimate); the
    speaker and microphones of a stop move together. The change from the start is
    ``basis @ a`` per axis (``basis`` (n_stops, k), e.g. :func:`motion_basis`; None: one free
    displacement per stop). L-BFGS-B with the analytic gradient (``dM/d(carriage shift of m)
    = sums[m, 1:4] / c_m``, summed over each stop's measurements).
    Returns ``(displacement (n_stops, 3), info)``.
    """
    from scipy.optimize import minimize

    scale = 1e-3  # parameters in mm
    start = np.asarray(start_m, float)
    n_stops = start.shape[0]
    b = np.eye(n_stops) if basis is None else np.asarray(basis, float)
    tx0, rx0 = engine.ds.tx_positions, engine.ds.rx_positions
    evals = {"n": 0}

    def fun(x):
        d = start + (b @ x.reshape(-1, 3)) * scale
        m, sums, _ = engine.evaluate(shift_s, c_mps, True, tx0 + d[stop], rx0 + d[stop])
        g = np.stack([np.bincount(stop, sums[:, 1 + k] / c_mps, minlength=n_stops) for k in range(3)], axis=1)
        evals["n"] += 1
        history.append(m)
        if callback is not None:
            callback("3d", len(history), m)
        return -m, -(b.T @ g).ravel() * scale

    res = minimize(fun, np.zeros(3 * b.shape[1]), jac=True, method="L-BFGS-B",
                   options={"maxiter": max_iter, "gtol": 1e-9, "ftol": 1e-10})
    log.info("autofocus 3d: metric %.5g after %d evaluations (%s)", -res.fun, evals["n"], res.message)
    return start + (b @ res.x.reshape(-1, 3)) * scale, {"metric": float(-res.fun), "evaluations": evals["n"],
                                                          "functions": b.shape[1], "message": str(res.message)}
