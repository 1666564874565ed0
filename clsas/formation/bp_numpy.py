"""NumPy twin of kernels/backproject.cl: float64, written to be read."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..beam import BeamWeights, pair_weights


def backproject(
    data: np.ndarray,
    tau0_s: np.ndarray,
    dtau_s: float,
    fc_hz: float,
    tx_positions: np.ndarray,
    rx_positions: np.ndarray,
    c_mps: float | np.ndarray,
    points_m: np.ndarray,
    progress: Callable[[int, int], None] | None = None,
    beam: BeamWeights | None = None,
) -> np.ndarray:
    """Sum over measurements of the linearly interpolated profile times the carrier.

    Parameters
    ----------
    data : (n_meas, n_lags) complex baseband profiles; sample ``k`` of row ``m`` is delay
        ``tau0_s[m] + k dtau_s``.
    c_mps : float or (n_meas,) array
        Speed of sound, m/s; an array gives each measurement its own.
    points_m : (n_vox, 3) voxel centres, m.
    beam : clsas.beam.BeamWeights, optional
        Weight (or gate) each pair by the two-way beam (:func:`clsas.beam.pair_weights`);
        None: every pair counts fully (omnidirectional).

    Returns
    -------
    (n_vox,) complex128 image values.
    """
    n_meas, n_lags = data.shape
    out = np.zeros(len(points_m), dtype=np.complex128)
    c = np.broadcast_to(np.asarray(c_mps, float), (n_meas,))
    for m in range(n_meas):
        path = np.linalg.norm(points_m - tx_positions[m], axis=1) + np.linalg.norm(
            points_m - rx_positions[m], axis=1
        )
        tau = path / c[m]
        idx = (tau - tau0_s[m]) / dtau_s
        inside = (idx >= 0) & (idx <= n_lags - 1)  # no wrap-around, no clamping to the edge
        i0 = np.clip(np.floor(idx), 0, n_lags - 2).astype(np.int64)
        w = idx - i0
        value = (1 - w) * data[m, i0] + w * data[m, i0 + 1]
        if beam is not None:
            value = value * pair_weights(beam.luts, tx_positions[m], rx_positions[m], beam.tx_dir[m],
                                         beam.rx_dir[m], points_m, beam.gate)
        out += np.where(inside, value * np.exp(2j * np.pi * fc_hz * tau), 0)
        if progress is not None:
            progress(m + 1, n_meas)
    return out
