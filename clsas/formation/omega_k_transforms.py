"""The spatial-frequency windows and the exact inverse DFT onto the grid's lateral axes of ω-k
(steps 3 and 6 of :mod:`clsas.formation.omega_k`), shared by the planar and the line-scan steps."""

from __future__ import annotations

import numpy as np

__all__ = ["DIRECT_MAX", "dft_axis", "edge_window"]

DIRECT_MAX = 1 << 15  # entries of the largest DFT matrix dft_axis multiplies by directly


def dft_axis(a: np.ndarray, k: np.ndarray, x: np.ndarray, workers) -> np.ndarray:
    """``out[i, ...] = sum_q a[q, ...] exp(i k_q x_i)`` for evenly spaced ``k`` (any order) and ``x``.

    A chirp-z (Bluestein) transform: exact, O((Q + n) log(Q + n)) per line; where the
    ``n x Q`` matrix of the DFT is small (up to ``DIRECT_MAX`` entries, e.g. a 64-voxel axis
    from 256 wavenumbers), its product with ``a`` instead (one BLAS call, several times faster
    than the three FFTs at the sizes of everyday scans; the same values to float rounding).
    """
    import scipy.fft

    Q, n = len(k), len(x)
    if n == 1 or Q == 1 or n * Q <= DIRECT_MAX:
        e = np.exp(1j * np.outer(x, k)).astype(np.result_type(a.dtype, np.complex64))
        return np.tensordot(e, a, axes=(1, 0))
    order = np.argsort(k)
    k = k[order]
    a = a[order]
    dk, dx = k[1] - k[0], x[1] - x[0]
    w = dk * dx
    q = np.arange(Q)
    i = np.arange(n)
    dt = a.dtype
    pre = np.exp(1j * (q * dk * x[0] + 0.5 * w * q * q)).astype(dt)
    L = scipy.fft.next_fast_len(Q + n - 1)
    m = np.arange(-(Q - 1), n)
    chirp = np.zeros(L, dt)
    chirp[np.mod(m, L)] = np.exp(-0.5j * w * m * m)
    shape = (-1,) + (1,) * (a.ndim - 1)
    y = scipy.fft.fft(a * pre.reshape(shape), L, axis=0, workers=workers)
    y *= scipy.fft.fft(chirp).reshape(shape)
    conv = scipy.fft.ifft(y, axis=0, workers=workers)[:n]
    post = np.exp(1j * (k[0] * x + 0.5 * w * i * i)).astype(dt)
    return conv * post.reshape(shape)


def edge_window(kq: np.ndarray, edge: float, taper: float, window: str | None) -> np.ndarray:
    """Weight of each spatial frequency ``kq`` of a band whose edge is ``edge`` rad/m: a Hann
    window over the band (``window="hann"``), else 1 with the band's outer ``taper`` under a raised
    cosine (0: a hard edge)."""
    r = np.abs(kq) / edge
    if window == "hann":
        return np.cos(0.5 * np.pi * np.clip(r, 0, 1)) ** 2
    if taper <= 0:
        return (r <= 1).astype(float)
    ramp = np.clip((r - (1 - taper)) / taper, 0, 1)
    return 0.5 * (1 + np.cos(np.pi * ramp))
