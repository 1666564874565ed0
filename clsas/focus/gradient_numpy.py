"""NumPy twin of kernels/autofocus.cl (float64, readable): the focus metric's gradient sums.

This is the specification of the OpenCL kernel and its fallback where no device exists.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def focus_gradient(
    data: np.ndarray,
    tau0_s: np.ndarray,
    dtau_s: float,
    fc_hz: float,
    tx_positions: np.ndarray,
    rx_positions: np.ndarray,
    c_mps: float | np.ndarray,
    points_m: np.ndarray,
    weight: np.ndarray,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Per-measurement sums that give a focus metric's gradient through backprojection.

    The image is ``I(v) = sum_m s_m(tau_m(v))`` (:func:`clsas.formation.bp_numpy.backproject`):
    ``s_m`` is the analytic profile (baseband ``data`` with the carrier restored, linearly
    interpolated) and ``tau_m(v) = path_m(v) / c_m`` with ``path_m(v) = |v - tx_m| + |v - rx_m|``.
    For a metric ``M`` with ``dM = sum_v Re(conj(G(v)) dI(v))``, let
    ``r_m(v) = Re(conj(G(v)) s'_m(tau_m(v)))`` (``s' = ds/dtau``, the slope of the interpolation).

    Parameters
    ----------
    data : (n_meas, n_lags) complex baseband profiles (``Profiles.data``).
    tau0_s : (n_meas,) delay of each row's sample 0, s.
    dtau_s : float, delay step, s.
    fc_hz : float, carrier, Hz.
    tx_positions, rx_positions : (n_meas, 3) m.
    c_mps : float or (n_meas,) speed of sound, m/s.
    points_m : (n_vox, 3) voxel centres, m.
    weight : (n_vox,) complex ``G``.

    Returns
    -------
    (n_meas, 5) float64
        Columns ``sum_v r``, ``sum_v r * (-(u_tx + u_rx))`` for x, y, z (``u``: unit vectors from
        the transducer to the voxel) and ``sum_v r * path``. Hence ``dM/d(delay shift of m)
        = -col0`` (the profile read ``delta`` later: ``s_m(tau - delta)``), ``dM/d(carriage
        shift of m) = col1:4 / c_m`` and ``dM/dc_m = -col4 / c_m**2``.
    """
    n_meas, n_lags = data.shape
    c = np.broadcast_to(np.asarray(c_mps, float), (n_meas,))
    g = np.asarray(weight, np.complex128)
    out = np.zeros((n_meas, 5))
    for m in range(n_meas):
        dt = points_m - tx_positions[m]
        dr = points_m - rx_positions[m]
        nt = np.linalg.norm(dt, axis=1)
        nr = np.linalg.norm(dr, axis=1)
        path = nt + nr
        tau = path / c[m]
        idx = (tau - tau0_s[m]) / dtau_s
        inside = (idx >= 0) & (idx <= n_lags - 1)
        i0 = np.clip(np.floor(idx), 0, n_lags - 2).astype(np.int64)
        w = idx - i0
        a, b = data[m, i0], data[m, i0 + 1]
        value = (1 - w) * a + w * b
        slope = (b - a) / dtau_s
        deriv = (slope + 2j * np.pi * fc_hz * value) * np.exp(2j * np.pi * fc_hz * tau)
        r = np.where(inside, (np.conj(g) * deriv).real, 0.0)
        u = dt / np.maximum(nt, 1e-9)[:, None] + dr / np.maximum(nr, 1e-9)[:, None]
        out[m, 0] = r.sum()
        out[m, 1:4] = -(r[:, None] * u).sum(axis=0)
        out[m, 4] = (r * path).sum()
        if progress is not None:
            progress(m + 1, n_meas)
    return out
