"""Disjoint sub-apertures: what the scan determines, and a check that is not the objective.

The stops are split into two disjoint halves (:func:`split_halves`: the first and second half in
time, or the left and right half of the aperture), each with an engine of its own
(:class:`~clsas.focus.engine.FocusEngine` on its measurements), so that a parameter can be
estimated twice from independent data, and a correction judged by whether the two halves'
images agree better after it:

- a scalar (air temperature, a delay from sharpness) is *determined* where the two halves'
  estimates agree (:func:`agreement`: half their difference is the uncertainty of their mean)
  and neither sits at the edge of its search (a bound is not an estimate);
- the check (:func:`magnitude_correlation`) compares where two sub-apertures put the energy;
  the sharpness the estimates maximised plays no part in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .engine import FocusEngine

__all__ = ["Half", "split_halves", "magnitude_correlation", "agreement"]


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


def split_halves(ds, grid, stop: np.ndarray, xy: np.ndarray, how: str = "time", **engine_options
                 ) -> tuple[Half, Half] | None:
    """Two disjoint sub-apertures of ``ds`` as :class:`Half` (None: fewer than 8 stops).

    ``how="time"``: the first and the second half of the stops in time (on a raster, two bands
    of rows; the hand's motion in one says little about the other); ``"x"``: the stops left and
    right of the carriage's median x (``xy`` (n_stops, 2), m).
    """
    n_stops = int(stop.max()) + 1
    if n_stops < 8:
        return None
    if how == "time":
        side = np.arange(n_stops) >= n_stops // 2
    else:
        side = xy[:, 0] > np.median(xy[:, 0])
        if side.all() or not side.any():
            return None
    out = []
    for s in (False, True):
        stops = np.flatnonzero(side == s)
        local = np.full(n_stops, -1)
        local[stops] = np.arange(len(stops))
        rows = np.flatnonzero(side[stop] == s)
        out.append(Half(rows, stops, local[stop[rows]], FocusEngine(ds.subset(rows), grid, **engine_options)))
    return out[0], out[1]


def magnitude_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of ``|a|`` and ``|b|`` over the voxels: how well two sub-apertures'
    images agree where they put the energy (a shift below a resolution cell, such as the
    constant and tilt of the motion that no focus metric sees, changes it little)."""
    x = np.abs(np.asarray(a).ravel()).astype(np.float64)
    y = np.abs(np.asarray(b).ravel()).astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    den = np.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / den) if den > 0 else 0.0


def agreement(x_a: float, x_b: float, lo: float, hi: float, tolerance: float) -> dict:
    """Two halves' estimates of one scalar in the search ``[lo, hi]``: their mean, its
    uncertainty (half their difference), whether at an edge, and whether determined (within
    ``tolerance`` and at no edge)."""
    edge = any(min(x - lo, hi - x) <= 0.05 * (hi - lo) for x in (x_a, x_b))
    sigma = 0.5 * abs(x_a - x_b)
    return {"estimate": 0.5 * (x_a + x_b), "uncertainty": sigma, "halves": (x_a, x_b), "at_edge": edge,
            "determined": bool(sigma <= tolerance and not edge)}

