"""Two disjoint halves of the stops: what the scan determines, and a check that is not the objective.

The stops are split into two interleaved halves in time order (even and odd stops). Each
half has an engine of its own (:class:`~clsas.focus.engine.FocusEngine` on its measurements),
so every parameter can be estimated twice from independent data:

- a scalar (air temperature, a delay from sharpness) is *determined* where the two halves'
  estimates agree (their half difference is the uncertainty of their mean) and neither sits at
  the edge of its search;
- the motion, coefficients of a smooth basis over stop time (3 per function: x, y, z), keeps
  each coefficient shrunk by how well the halves agree (``a^2 / (a^2 + sigma^2)``, with ``a``
  the mean and ``sigma`` the half difference): a coefficient the halves disagree on is noise
  fitted by the sharpness, and goes;
- the check (:func:`coherence`): each half's image, corrected with the motion the *other* half
  estimated (held out), must agree with the other half's better than the uncorrected halves do.
  The sharpness that the estimates maximised plays no part in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .engine import FocusEngine

__all__ = ["Half", "split_halves", "coherence", "combine", "agreement"]


@dataclass
class Half:
    """One half of the stops.

    Attributes
    ----------
    rows : (n,) measurement indices into the dataset.
    stops : (n_stops_half,) the full scan's stop numbers of this half, in time order.
    local : (n,) each row's stop within the half (0 .. n_stops_half - 1).
    engine : FocusEngine on these measurements.
    """

    rows: np.ndarray
    stops: np.ndarray
    local: np.ndarray
    engine: FocusEngine

    def image(self, shift_s, c_mps, move=None) -> np.ndarray:
        """The half's image at full-scan per-measurement ``shift_s``, ``c_mps`` and carriage
        displacement ``move`` (n_meas, 3) (None: none)."""
        r = self.rows
        ds = self.engine.ds
        tx = rx = None
        if move is not None:
            tx, rx = ds.tx_positions + move[r], ds.rx_positions + move[r]
        c = np.broadcast_to(np.asarray(c_mps, float), (len(shift_s),))[r]
        return self.engine.image(np.asarray(shift_s)[r], c, tx, rx)


def split_halves(ds, grid, stop: np.ndarray, **engine_options) -> tuple[Half, Half] | None:
    """The even and odd stops of ``ds`` as two :class:`Half` (None: fewer than 8 stops)."""
    n_stops = int(stop.max()) + 1
    if n_stops < 8:
        return None
    out = []
    for parity in (0, 1):
        rows = np.flatnonzero(stop % 2 == parity)
        stops = np.arange(parity, n_stops, 2)
        sub = ds.subset(rows)
        out.append(Half(rows, stops, stop[rows] // 2, FocusEngine(sub, grid, **engine_options)))
    return out[0], out[1]


def coherence(a: np.ndarray, b: np.ndarray) -> float:
    """``|sum conj(a) b| / sqrt(sum |a|^2 sum |b|^2)``: 1 where two complex images are the same
    up to scale and phase, near 0 for independent speckle."""
    a = np.asarray(a, np.complex128).ravel()
    b = np.asarray(b, np.complex128).ravel()
    den = np.sqrt(float(np.vdot(a, a).real) * float(np.vdot(b, b).real))
    return float(abs(np.vdot(a, b)) / den) if den > 0 else 0.0


def agreement(x_a: float, x_b: float, lo: float, hi: float, tolerance: float) -> dict:
    """Two halves' estimates of one scalar in the search ``[lo, hi]``: their mean, its
    uncertainty (half their difference), whether at an edge, and whether determined (within
    ``tolerance`` and at no edge)."""
    edge = any(min(x - lo, hi - x) <= 0.05 * (hi - lo) for x in (x_a, x_b))
    sigma = 0.5 * abs(x_a - x_b)
    return {"estimate": 0.5 * (x_a + x_b), "uncertainty": sigma, "halves": (x_a, x_b), "at_edge": edge,
            "determined": bool(sigma <= tolerance and not edge)}


def combine(coef_a: np.ndarray, coef_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two halves' motion coefficients (k, 3) to one: ``(applied, sigma, determined)``.

    ``applied = a * a^2 / (a^2 + sigma^2)`` with ``a`` their mean and ``sigma`` half their
    difference (the uncertainty of the mean); ``determined`` where ``|a| > 2 sigma``.
    """
    a = 0.5 * (coef_a + coef_b)
    sigma = 0.5 * np.abs(coef_a - coef_b)
    w = a**2 / np.maximum(a**2 + sigma**2, 1e-300)
    return a * w, sigma, np.abs(a) > 2 * sigma


def fit_half_motion(half: Half, shift_s: np.ndarray, c_mps: np.ndarray, basis: np.ndarray, *, use_phase: bool,
                    use_3d: bool, sweeps: int, max_bytes: int, max_iter: int, history: list,
                    progress=None) -> tuple[np.ndarray, dict]:
    """One half's carriage motion as coefficients (k, 3) of ``basis`` (n_stops, k), m.

    ``"phase"`` (``use_phase``): per-stop phases of the half's stop images, read as a
    line-of-sight path and a move along it, projected on the basis (the global start for large
    motion; kept where it sharpens the half's image by more than fitting noise does).
    ``"3d"`` (``use_3d``): L-BFGS on the coefficients from there (:func:`.motion.optimise_xyz`).
    """
    from .metrics import metric_and_weight
    from .motion import los_directions, optimise_xyz
    from .phases import PHASE_MIN_GAIN, phase_to_path, stop_phase_search

    eng, r = half.engine, half.rows
    sh = np.asarray(shift_s)[r]
    ch = np.broadcast_to(np.asarray(c_mps, float), (len(shift_s),))[r]
    b = basis[half.stops]
    n_h = len(half.stops)
    coef = np.zeros((basis.shape[1], 3))
    info = {"phase_kept": False, "evaluations": 0,
            "metric_start": float(metric_and_weight(eng.image(sh, ch), eng.metric)[0])}
    if use_phase and n_h >= 3:
        voxels = None
        if n_h * eng.grid.size * 8 > max_bytes:
            keep = max(int(max_bytes // (8 * n_h)), 1)
            voxels = np.sort(np.argsort(np.abs(eng.image(sh, ch)))[-keep:])
        a = eng.stop_images(sh, ch, half.local, voxels)
        phi, _ = stop_phase_search(a, sweeps=sweeps, history=history, callback=progress)
        del a
        first = np.r_[0, np.flatnonzero(np.diff(half.local)) + 1]
        p = phase_to_path(phi, ch[first], eng.prof.fc_hz)
        m_before = metric_and_weight(eng.image(sh, ch), eng.metric)[0]
        values = eng.image(sh - p[half.local] / ch, ch)
        if metric_and_weight(values, eng.metric)[0] > m_before + PHASE_MIN_GAIN:
            info["phase_kept"] = True
            mag2 = np.abs(values) ** 2
            centre = (eng.grid.points() * mag2[:, None]).sum(axis=0) / max(mag2.sum(), 1e-300)
            move = (-0.5 * p[half.local])[:, None] * los_directions(eng.ds, centre)
            n = np.bincount(half.local, minlength=n_h)
            start = np.stack([np.bincount(half.local, move[:, k], n_h) / n for k in range(3)], axis=1)
            coef = np.linalg.lstsq(b, start, rcond=None)[0]
    if use_3d:
        d, res = optimise_xyz(eng, sh, ch, half.local, b @ coef, max_iter, history, callback=progress, basis=b)
        coef = np.linalg.lstsq(b, d, rcond=None)[0]
        info["evaluations"], info["metric_end"] = res["evaluations"], res["metric"]
    return coef, info
