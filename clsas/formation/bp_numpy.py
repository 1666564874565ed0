"""NumPy twins of kernels/backproject.cl (float64, written to be read) and of kernels/records.cl (the
carrier records backproject.cl reads, complex64 as the kernel makes them)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..physics.beam import BeamWeights, pair_weights


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
    beam : clsas.physics.beam.BeamWeights, optional
        Weight (or gate) each pair by the two-way beam (:func:`clsas.physics.beam.pair_weights`);
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


# fc dtau, carrier cycles per profile sample, up to which backproject.cl's sub-sample rotation
# (a polynomial for |angle| <= 0.6 pi) holds; coarser profiles are upsampled first
MAX_CYCLES_PER_SAMPLE = 0.6


def upsample_factor(fc_hz: float, dtau_s: float) -> int:
    """The smallest integer factor that brings a profile to :data:`MAX_CYCLES_PER_SAMPLE` or less."""
    return max(1, int(np.ceil(abs(fc_hz) * dtau_s / MAX_CYCLES_PER_SAMPLE - 1e-9)))


def upsample(prof: np.ndarray, up: int) -> np.ndarray:
    """(n, L) profiles -> (n, (L - 1) up + 1) by linear interpolation between their samples
    (their linear interpolation is unchanged)."""
    n, L = prof.shape
    fine = np.zeros((n, (L - 1) * up + 1), prof.dtype)
    for i in range(up):
        fine[:, i : (L - 1) * up : up] = (1 - i / up) * prof[:, :-1] + (i / up) * prof[:, 1:]
    fine[:, -1] = prof[:, -1]
    return fine


def upsample_adjoint(fine: np.ndarray, up: int) -> np.ndarray:
    """The adjoint of :func:`upsample`: (n, (L - 1) up + 1) -> (n, L)."""
    n = fine.shape[0]
    L = (fine.shape[1] - 1) // up + 1
    out = np.zeros((n, L), fine.dtype)
    out[:, -1] = fine[:, -1]
    for i in range(up):
        part = fine[:, i : (L - 1) * up : up]
        out[:, :-1] += (1 - i / up) * part
        out[:, 1:] += (i / up) * part
    return out


def carrier_factors(n_records: int, tau0_s, dtau_s: float, fc_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The two factors of :func:`carrier_rotation`, complex64, each computed in double precision
    and reduced to a turn: ``(n_records,) exp(j 2 pi fc dtau (k + 1/2))`` and
    ``(n_meas,) exp(j 2 pi fc tau0_m)``."""
    cycles = fc_hz * dtau_s
    k = np.arange(n_records)
    s0 = np.asarray(tau0_s, float) / dtau_s
    return (np.exp(2j * np.pi * np.mod(cycles * (k + 0.5), 1.0)).astype(np.complex64),
            np.exp(2j * np.pi * np.mod(cycles * s0, 1.0)).astype(np.complex64))


def carrier_rotation(n_records: int, tau0_s, dtau_s: float, fc_hz: float) -> np.ndarray:
    """(n_meas, n_records) complex64: ``exp(j 2 pi fc dtau (k + 1/2 + tau0_m / dtau))``, the
    carrier at the middle of record k, the product of :func:`carrier_factors` in complex64."""
    rot, rot0 = carrier_factors(n_records, tau0_s, dtau_s, fc_hz)
    return rot[None, :] * rot0[:, None]


def carrier_records(data: np.ndarray, n_lags: int, tau0_s, dtau_s: float, fc_hz: float):
    """The profiles as kernels/backproject.cl reads them (the twin of records.cl's
    ``carrier_records``): record k of measurement m holds samples
    k and k + 1, both rotated by :func:`carrier_rotation`, so that the kernel's carrier is the
    sub-sample rotation only.

    ``data`` (n_meas, <= n_lags) is zero-padded to ``n_lags`` samples. Where ``fc dtau`` exceeds
    :data:`MAX_CYCLES_PER_SAMPLE` the profile is first upsampled (:func:`upsample`). Returns
    ``(records (n_meas, n_lags', 2) complex64, dtau', phi = 2 pi fc dtau')``.
    """
    n_meas = data.shape[0]
    prof = np.zeros((n_meas, n_lags), np.complex64)
    prof[:, : data.shape[1]] = data
    up = upsample_factor(fc_hz, dtau_s)
    if up > 1:
        prof, dtau_s = upsample(prof, up), dtau_s / up
    rot = carrier_rotation(prof.shape[1], tau0_s, dtau_s, fc_hz)
    pairs = np.zeros((n_meas, prof.shape[1], 2), np.complex64)  # p[n_lags] = 0
    np.multiply(prof, rot, out=pairs[:, :, 0])
    np.multiply(prof[:, 1:], rot[:, :-1], out=pairs[:, :-1, 1])
    return pairs, dtau_s, 2 * np.pi * fc_hz * dtau_s
