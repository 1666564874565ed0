"""Transmit waveforms (eq. 2 of the paper), tapers and analytic signals."""

from __future__ import annotations

import logging

import numpy as np

from .. import validate as v

__all__ = ["lfm_chirp", "analytic", "chirp_times", "tukey_taper"]


def _check_band(f_start_hz: float, f_stop_hz: float, fs_hz: float) -> tuple[float, float, float]:
    fs = v.sampling_rate("fs_hz", fs_hz)
    f1 = v.non_negative("f_start_hz", f_start_hz)
    f2 = v.non_negative("f_stop_hz", f_stop_hz)
    nyq = fs / 2
    for name, f in (("f_start_hz", f1), ("f_stop_hz", f2)):
        if f >= nyq:
            raise ValueError(
                f"{name}={f:g} Hz is at or above the Nyquist frequency fs_hz/2 = {nyq:g} Hz"
            )
    return f1, f2, fs


def chirp_times(duration_s: float, fs_hz: float) -> np.ndarray:
    """Sample times ``n / fs_hz`` for ``n = 0 .. round(duration_s * fs_hz) - 1``, in s."""
    fs = v.positive("fs_hz", fs_hz)
    dur = v.positive("duration_s", duration_s)
    n = int(round(dur * fs))
    if n < 2:
        raise ValueError(
            f"duration_s={dur:g} s gives {n} sample(s) at fs_hz={fs:g}; need at least 2"
        )
    return np.arange(n) / fs


def tukey_taper(n: int, fraction: float) -> np.ndarray:
    """Tukey window of ``n`` samples whose cosine edges take ``fraction`` of the length."""
    fraction = v.non_negative("taper", fraction)
    if fraction > 1:
        raise ValueError(f"taper must be in [0, 1], got {fraction:g}")
    if fraction == 0 or n < 2:
        return np.ones(n)
    # scipy.signal.windows.tukey, written out so that importing clsas needs no scipy.signal
    width = int(np.floor(fraction * (n - 1) / 2.0))
    k = np.arange(n, dtype=np.float64)
    w = np.ones(n)
    lo = k < width + 1
    w[lo] = 0.5 * (1 + np.cos(np.pi * (-1 + 2.0 * k[lo] / fraction / (n - 1))))
    hi = k > n - width - 2
    w[hi] = 0.5 * (1 + np.cos(np.pi * (-2.0 / fraction + 1 + 2.0 * k[hi] / fraction / (n - 1))))
    return w


def lfm_chirp(
    f_start_hz: float,
    f_stop_hz: float,
    duration_s: float,
    fs_hz: float,
    taper: float = 0.0,
) -> np.ndarray:
    """Linear FM chirp, eq. 2 of the paper: ``cos(xi/2 t^2 + omega t)`` on ``[0, T)``.

    Parameters
    ----------
    f_start_hz, f_stop_hz : float
        Instantaneous frequency at ``t = 0`` and ``t = T``, in Hz; both below ``fs_hz / 2``.
        A down-chirp (``f_stop_hz < f_start_hz``) is allowed.
    duration_s : float
        Length ``T`` in s.
    fs_hz : float
        Sample rate in Hz.
    taper : float
        Fraction of the length taken by Tukey (cosine) edges; 0 gives the paper's hard on/off
        edges, 0.2 a smooth atom suitable for continuous basis pursuit.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(round(duration_s * fs_hz),)``.

    Notes
    -----
    The paper writes ``cos(xi t^2 + omega t)`` with ``xi = 2 pi (f2 - f1) / T``; its
    instantaneous frequency then sweeps to ``2 f2 - f1``. We use ``xi / 2`` so the sweep ends
    at ``f_stop_hz`` as the paper intends (its own derivation writes ``psi = xi/2 t^2 + w t``).

    Examples
    --------
    >>> import clsas
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, 96e3, taper=0.1)   # the paper's band, 5 ms
    >>> chirp.shape
    (480,)
    """
    f1, f2, fs = _check_band(f_start_hz, f_stop_hz, fs_hz)
    if max(f1, f2) < v.LEAST_BAND_HZ and v.positive("duration_s", duration_s) >= 0.5:
        logging.getLogger("clsas").warning(
            "lfm_chirp: a %g s chirp of %g-%g Hz; if these are ms and kHz, give s and Hz "
            "(lfm_chirp(%g, %g, %g, fs_hz))", duration_s, f1, f2, f1 * 1e3, f2 * 1e3, duration_s * 1e-3)
    t = chirp_times(duration_s, fs)
    T = len(t) / fs
    xi = 2 * np.pi * (f2 - f1) / T
    phase = 0.5 * xi * t**2 + 2 * np.pi * f1 * t
    return np.cos(phase) * tukey_taper(len(t), taper)


def analytic(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Analytic signal ``x + j H{x}`` along ``axis`` (complex128).

    Parameters
    ----------
    x : numpy.ndarray
        Real signal(s), any shape.
    axis : int
        The time axis.

    Returns
    -------
    numpy.ndarray
        complex128, the shape of ``x``; its real part is ``x``.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> z = clsas.analytic(np.cos(2 * np.pi * 0.1 * np.arange(100)))
    >>> z.dtype, bool(np.allclose(z.real, np.cos(2 * np.pi * 0.1 * np.arange(100))))
    (dtype('complex128'), True)
    """
    arr = v.array("x", x, dtype=np.float64)
    n = arr.shape[axis]
    h = np.zeros(n)
    h[0] = 1.0
    if n % 2 == 0:
        h[n // 2] = 1.0
        h[1 : n // 2] = 2.0
    else:
        h[1 : (n + 1) // 2] = 2.0
    shape = [1] * arr.ndim
    shape[axis] = n
    return np.fft.ifft(np.fft.fft(arr, axis=axis) * h.reshape(shape), axis=axis)
