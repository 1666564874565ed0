"""NumPy twins of the pulse-compression kernels: float64, written to be read."""

from __future__ import annotations

import numpy as np


def matched_filter(
    signals: np.ndarray,
    ref_conj: np.ndarray,
    lag0: int,
    n_lags: int,
    rot: np.ndarray,
    rot0: np.ndarray,
    lag_step: int = 1,
) -> np.ndarray:
    """Twin of ``matched_filter`` and ``matched_fft`` in kernels/compress.cl.

    ``out[m, k] = rot0[m] rot[k] sum_n x[m, lag0 + D k + n] ref_conj[n]`` with ``D = lag_step``,
    where samples outside the recording are zero. Returns (n_meas, n_lags) complex128.
    """
    n_meas, n_samples = signals.shape
    n_ref = len(ref_conj)
    span = lag_step * (n_lags - 1) + n_ref  # samples read from lag0 on
    # zero-pad so that every lag in the window reads defined samples
    pad_lo = max(0, -lag0)
    pad_hi = max(0, lag0 + span - n_samples)
    x = np.pad(np.asarray(signals, np.float64), ((0, 0), (pad_lo, pad_hi)))
    start = lag0 + pad_lo
    out = np.empty((n_meas, n_lags), dtype=np.complex128)
    for m in range(n_meas):
        windows = np.lib.stride_tricks.sliding_window_view(x[m, start : start + span], n_ref)[::lag_step]
        out[m] = windows @ ref_conj
    return out * rot[None, :n_lags] * rot0[:, None]


def fmcw_dechirp(
    signals: np.ndarray,
    ref: np.ndarray,
    slope_hz_per_s: float,
    fs_hz: float,
    taus_s: np.ndarray,
    rvp: np.ndarray,
) -> np.ndarray:
    """Twin of ``fmcw_dechirp`` in kernels/compress.cl.

    ``out[m, k] = rvp[k] sum_n x[m, n] ref[n] exp(j 2 pi slope tau_k (n - c) / fs)`` over the
    ``len(ref)`` mixed samples, ``c`` their centre. Returns (n_meas, n_taus) complex128.
    """
    n_mix = min(len(ref), signals.shape[1])
    n = np.arange(n_mix) - 0.5 * (n_mix - 1)
    dechirped = np.asarray(signals[:, :n_mix], np.float64) * ref[None, :n_mix]
    out = np.empty((signals.shape[0], len(taus_s)), dtype=np.complex128)
    block = max(1, int(4e6 // n_mix))
    for k in range(0, len(taus_s), block):
        tau = taus_s[k : k + block]
        kernel = np.exp(2j * np.pi * np.outer(n, tau) * slope_hz_per_s / fs_hz)  # (n_mix, b)
        out[:, k : k + block] = dechirped @ kernel
    return out * rvp[None, : len(taus_s)]
