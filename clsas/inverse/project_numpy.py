"""NumPy twin of kernels/project.cl: the forward projector, float64, written to be read.

It is the exact adjoint of :func:`clsas.formation.bp_numpy.backproject`: the same bistatic
path, linear-interpolation weights, window test, carrier and (optional) beam weight, transposed
and conjugated.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..physics.beam import BeamWeights, pair_weights


def project(
    values: np.ndarray,
    tau0_s: np.ndarray,
    dtau_s: float,
    n_lags: int,
    fc_hz: float,
    tx_positions: np.ndarray,
    rx_positions: np.ndarray,
    c_mps: float | np.ndarray,
    points_m: np.ndarray,
    progress: Callable[[int, int], None] | None = None,
    beam: BeamWeights | None = None,
) -> np.ndarray:
    """Complex voxels -> complex baseband range profiles (the adjoint of backprojection).

    Parameters
    ----------
    values : (n_vox,) complex voxel values (linear amplitude).
    tau0_s : (n_meas,) delay of each profile's first sample, s.
    dtau_s : float
        Lag step, s.
    n_lags : int
        Samples per profile (at least 2).
    fc_hz : float
        Carrier of the baseband profiles, Hz.
    tx_positions, rx_positions : (n_meas, 3) positions, m.
    c_mps : float or (n_meas,) array
        Speed of sound, m/s; an array gives each measurement its own.
    points_m : (n_vox, 3) voxel centres, m.
    beam : clsas.physics.beam.BeamWeights, optional
        Weight (or gate) each pair by the two-way beam (:func:`clsas.physics.beam.pair_weights`), as
        :func:`clsas.formation.bp_numpy.backproject` does with the same weights (so this stays
        its adjoint); None: omnidirectional.

    Returns
    -------
    (n_meas, n_lags) complex128 profiles: ``p[m, k] = sum_v conj(B[v, (m, k)]) values[v]`` with
    ``B`` the backprojection's weights (see kernels/project.cl).
    """
    n_meas = len(tau0_s)
    out = np.zeros((n_meas, n_lags), dtype=np.complex128)
    c = np.broadcast_to(np.asarray(c_mps, float), (n_meas,))
    x = np.asarray(values, np.complex128)
    for m in range(n_meas):
        path = np.linalg.norm(points_m - tx_positions[m], axis=1) + np.linalg.norm(
            points_m - rx_positions[m], axis=1
        )
        tau = path / c[m]
        idx = (tau - tau0_s[m]) / dtau_s
        inside = (idx >= 0) & (idx <= n_lags - 1)
        i0 = np.clip(np.floor(idx), 0, n_lags - 2).astype(np.int64)[inside]
        w = (idx[inside] - i0)
        val = x[inside] * np.exp(-2j * np.pi * fc_hz * tau[inside])
        if beam is not None:
            val = val * pair_weights(beam.luts, tx_positions[m], rx_positions[m], beam.tx_dir[m], beam.rx_dir[m],
                                     points_m[inside], beam.gate)
        for part, lags in (((1 - w) * val, i0), (w * val, i0 + 1)):
            out[m] += np.bincount(lags, part.real, n_lags) + 1j * np.bincount(lags, part.imag, n_lags)
        if progress is not None:
            progress(m + 1, n_meas)
    return out
