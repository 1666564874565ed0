"""Steps 1-2 of ω-k (:mod:`clsas.formation.omega_k`): every measurement's frequency samples.

Each profile is zero-padded, FFT'd along delay and brought onto one wavenumber grid (a
per-measurement speed of sound by a direct DFT at its own frequencies), with backprojection's
linear-interpolation response applied; the band kept is the run of frequency samples whose
energy reaches ``band_tol**2`` of the strongest's. Shared by the planar and the line-scan Stolt
steps.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["spectra"]


def spectra(data, tau0, dtau, fc, c, pad_time, band_tol, workers):
    """(S (n_meas, n_f) complex, f (n_f,) Hz, c_ref): profile spectra on one wavenumber grid.

    ``S[m, j] df`` is measurement m's contribution at frequency ``f_j`` (for ``c_ref``), with
    backprojection's linear-interpolation response applied.
    """
    import scipy.fft

    n_meas, n_lags = data.shape
    n_fft = scipy.fft.next_fast_len(int(math.ceil(pad_time * n_lags)))
    fb = scipy.fft.fftfreq(n_fft, dtau)
    spec = scipy.fft.fft(data, n_fft, axis=1, workers=workers)
    energy = np.sum(np.abs(spec) ** 2, axis=0)
    # the band: the run of bins (in frequency order) from the first to the last whose energy
    # is at least band_tol^2 of the strongest bin's, above zero Hz
    srt = np.argsort(fb)
    strong = np.flatnonzero(energy[srt] >= band_tol**2 * energy.max())
    if energy.max() == 0:
        raise ValueError("profiles: all zero, nothing to image")
    bins = srt[strong.min(): strong.max() + 1]
    bins = bins[fb[bins] + fc != 0]  # zero Hz carries nothing to an image
    f_b = fb[bins]
    df = 1.0 / (n_fft * dtau)
    c_arr = np.broadcast_to(np.asarray(c, float), (n_meas,))
    c_ref = float(np.mean(c_arr))
    lin = np.sinc(f_b * dtau) ** 2
    if np.ptp(c_arr) <= 1e-9 * c_ref:
        s = spec[:, bins] * np.exp(-2j * np.pi * np.outer(tau0, f_b))
    else:  # one speed of sound per measurement: its own frequencies of the common kappa grid
        s = np.empty((n_meas, len(bins)), np.complex128)
        n = np.arange(n_lags)
        for m0 in range(0, n_meas, 256):
            m1 = min(n_meas, m0 + 256)
            f_m = (fc + f_b)[None, :] * (c_arr[m0:m1, None] / c_ref) - fc  # baseband, (b, n_f)
            e = np.exp(-2j * np.pi * f_m[:, None, :] * (tau0[m0:m1, None, None] + n[None, :, None] * dtau))
            s[m0:m1] = np.einsum("bn,bnf->bf", data[m0:m1], e) * (c_arr[m0:m1, None] / c_ref)
            s[m0:m1] *= (np.sinc(f_m * dtau) ** 2) / lin[None, :]
    s *= dtau * df * lin[None, :]
    e = energy[bins]
    strong20 = np.flatnonzero(e >= 1e-2 * e.max())  # the -20 dB band's highest |frequency|
    f_top = float(np.abs(fc + f_b[strong20]).max())
    return s, fc + f_b, c_ref, f_top
