"""Sizes and tables of the FFT matched filter (``matched_fft`` in kernels/compress.cl)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FftLayout", "fft_layout"]


@dataclass
class FftLayout:
    """Sizes and tables of the FFT matched filter (``matched_fft`` in kernels/compress.cl)."""

    s_lo: int
    n_in: int
    log2_n: int
    log2_nd: int
    bin0: int
    idx0: int
    n_lags: int
    twiddles: np.ndarray
    spec: np.ndarray
    post: np.ndarray

    @property
    def n_fft(self) -> int:
        return 1 << self.log2_n


def fft_layout(ref_analytic, fs, fc, s_lo, n_in, lag_read, lag_step, n_lags, rot) -> FftLayout:
    """FFT sizes so that no gated lag wraps around, and the reference spectrum on the kept bins."""
    n_ref, d = len(ref_analytic), lag_step
    l_max = lag_read + d * (n_lags - 1)
    need = max(n_in - min(lag_read, 0), l_max + n_ref, 2 * d)
    log2_n = int(np.ceil(np.log2(need)))
    n = 1 << log2_n
    nd = n // d
    bin0 = int(round(fc * n / fs))
    jj = np.where(np.arange(nd) < nd // 2, np.arange(nd), np.arange(nd) - nd)
    spec = np.conj(np.fft.fft(ref_analytic, n))[(bin0 + jj) % n] / n
    k = np.arange(n_lags)
    shift = (bin0 * (lag_read + d * k)) % n  # exact: integers
    post = rot * np.exp(2j * np.pi * shift / n)
    twiddles = np.exp(-2j * np.pi * np.arange(n) / n)
    idx0 = (lag_read % n) // d
    return FftLayout(s_lo, n_in, log2_n, log2_n - int(np.log2(d)), bin0, idx0, n_lags, twiddles, spec, post)
