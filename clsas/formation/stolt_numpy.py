"""The Stolt mapping and its interpolation: NumPy twin of kernels/stolt.cl, and the steps around it.

For one spatial-frequency column ``(ku, kv)`` the wavenumber-domain image at depth ``z`` is a
sum over the frequency samples ``j`` of the data (two-way wavenumber ``k_j = 4 pi f_j / c``):

    T(z) = sum_j c_j exp(i kz_j z),   kz_j = sqrt(k_j^2 - ku^2 - kv^2)       (the Stolt mapping)

with non-uniform ``kz_j``. It is evaluated on the grid's evenly spaced depths as a type-1
non-uniform FFT: each ``c_j`` is spread onto ``M >= 2 n_z`` cells of the folded ``kz`` axis
with an "exponential of semicircle" kernel of width ``W`` cells (Barnett et al., FINUFFT),
the cells are inverse-FFT'd, and the result is divided by the kernel's Fourier transform
(de-apodisation). The spreading is what :func:`spread` (and the OpenCL kernel) computes; the
rest is :func:`columns_to_depths`. With ``M = 2 n_z`` the relative error is about
``10^-(W-1)`` (1e-3 at ω-k's default ``W = 4``, far under the method's own error), whatever
the spacing of the ``kz_j``: no resampling onto a uniform ``kz`` grid is needed, and no
Jacobian either, since the sum runs over the uniform frequency samples themselves. Folding
the ``kz`` axis modulo ``2 pi / dz`` makes depths sampled more coarsely than the data's
bandwidth come out as backprojection samples them (exactly, not aliased twice).

Per sample, the kernel forms the strengths ``c_j`` from the data spectrum ``D``:

    c_j = D_j * w(s) * 2 pi k_j / kz_j^2 * (1 + i / (kz_j z_ref)) * exp(i kz_j z_c + i alpha_j / z_ref)
    alpha_j = (kz_j / 8) (|b|^2 - (b . k_perp)^2 / k_j^2)

where ``2 pi k (i z / kz^2 - 1 / kz^3) exp(i kz z)`` is the exact 2-D Fourier transform of
backprojection's kernel ``exp(i k r)`` (the derivative in ``k`` of Weyl's expansion of
``exp(i k r) / r``); the ``i z`` factor is applied per depth afterwards and the ``1/kz^3`` term
is kept to first order about ``z_ref`` (a relative 1e-3 term, error < 1e-5). ``alpha_j / z``
is the bistatic correction: for a speaker and microphone ``b`` apart, the path differs from
twice the midpoint range by ``(|b|^2 - (b . u)^2) / (4 R)`` (u: the look direction), which at
the stationary point of the plane-wave component becomes ``alpha / z``. ``exp(i alpha / z)``
is expanded about ``z_ref`` as ``exp(i alpha / z_ref) sum_p (i alpha u)^p / p!`` with
``u = 1/z - 1/z_ref``: each power ``p`` is one spread of ``c_j alpha_j^p`` (a *term*),
so the correction stays exact to the tolerance over any depth range without slabs.
``w(s)`` is a raised-cosine window on ``s = |k_perp| / k_j`` (the sine of the look angle)
from ``s1`` to ``s2``: components steeper than any voxel-stop pair sees carry nothing to the
image and are dropped.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["StoltParams", "spread", "direct", "deapodization", "columns_to_depths", "terms_to_depths", "es_beta",
           "DIRECT_COST", "SPREAD_COST", "depth_path", "direct_work", "spread_work"]

# relative time per column of the two ways to the depths (n_f samples, n_z depths, t terms, W
# cells): direct 2.0 n_f n_z (1 + 0.2 (t - 1)) + 49 n_f, spread 18.2 n_f t W + 121 n_z t (the
# spread kernel, the cells' inverse FFT and the sum of terms); a non-negative least-squares fit
# to both timed on 72 column sets (2048 and 8192 columns, n_f 20-300, n_z 20-256, 1-3 terms)
# on the 2-core AMD EPYC VM with PoCL: "auto" then loses at most 1.37x (near ties)
DIRECT_COST = (2.0, 49.0)
SPREAD_COST = (18.2, 121.0)


def es_beta(width: int) -> float:
    """Shape of the exponential-of-semicircle kernel for an upsampling of 2 (FINUFFT's 2.30 W)."""
    return 2.30 * width


@dataclass(frozen=True)
class StoltParams:
    """What the Stolt kernel needs besides the data: the output depths and the corrections.

    Depths ``z`` are measured from the aperture's plane, m.
    """

    dz_m: float  # spacing of the output depths
    zc_m: float  # depth of output plane l = 0 (the planes are zc + l dz, l = -nz//2 ...)
    zref_m: float  # reference depth of the bistatic and 1/kz^3 expansions
    baseline_uv: tuple[float, float]  # speaker minus microphone, in-plane, m
    n_cells: int  # M: cells of the folded kz axis
    width: int  # W: kernel width in cells
    n_terms: int  # powers of alpha spread (1: no bistatic correction beyond z_ref)
    s1: float  # look-angle sine where the window starts to fall
    s2: float  # ... and where it reaches zero

    @property
    def beta(self) -> float:
        return es_beta(self.width)


def stolt_strengths(spec: np.ndarray, k: np.ndarray, ku: np.ndarray, kv: np.ndarray, p: StoltParams):
    """(c0, alpha, pos, valid) per (column, sample): strength, bistatic alpha, position in cells."""
    kp2 = (ku**2 + kv**2)[:, None]
    kk = k[None, :]
    kz2 = kk**2 - kp2
    valid = kz2 > 0
    # negative frequencies (baseband profiles wider than their carrier, e.g. the sparse methods'
    # rendered pulses) are exp(i k r) with k < 0: the same formulas with kz of k's sign
    kz = np.sign(kk) * np.sqrt(np.where(valid, kz2, 1.0))
    s = np.sqrt(kp2) / np.abs(kk)
    ramp = np.clip((s - p.s1) / max(p.s2 - p.s1, 1e-12), 0.0, 1.0)
    w = np.where(valid, 0.5 * (1 + np.cos(np.pi * ramp)), 0.0)
    bu, bv = p.baseline_uv
    proj = (bu * ku + bv * kv)[:, None]
    alpha = (kz / 8) * (bu**2 + bv**2 - proj**2 / kk**2)
    amp = w * 2 * np.pi * kk / kz**2 * (1 + 1j / (kz * p.zref_m))
    phase = kz * p.zc_m + alpha / p.zref_m
    c0 = spec * amp * np.exp(1j * phase)
    pos = kz * p.dz_m * p.n_cells / (2 * np.pi)
    return c0, alpha, pos, valid & (w > 0)


def _es(x: np.ndarray, width: int, beta: float) -> np.ndarray:
    """The kernel at ``x`` cells from its centre (zero outside |x| < W/2)."""
    t = 2 * x / width
    inside = np.abs(t) < 1
    return np.where(inside, np.exp(beta * (np.sqrt(np.clip(1 - t * t, 0, None)) - 1)), 0.0)


def spread(spec: np.ndarray, k: np.ndarray, ku: np.ndarray, kv: np.ndarray, p: StoltParams) -> np.ndarray:
    """Stolt mapping and spreading (the NumPy twin of ``stolt_spread`` in kernels/stolt.cl).

    Parameters
    ----------
    spec : (n_cols, n_f) complex
        Data spectrum per spatial-frequency column and frequency sample (all per-sample
        weights, such as the frequency step, already applied).
    k : (n_f,) float
        Two-way wavenumber ``4 pi f / c`` of each sample, rad/m (negative for negative
        frequencies, where ``kz`` takes k's sign; zero is skipped).
    ku, kv : (n_cols,) float
        The columns' spatial frequencies, rad/m.
    p : StoltParams

    Returns
    -------
    (n_terms, n_cols, n_cells) complex128: the spread cells of each term.
    """
    n_cols = spec.shape[0]
    c0, alpha, pos, valid = stolt_strengths(np.asarray(spec, np.complex128), np.asarray(k, float), ku, kv, p)
    M, W = p.n_cells, p.width
    first = np.ceil(pos - W / 2)
    rows = np.arange(n_cols)[:, None] * M
    out = np.zeros((p.n_terms, n_cols * M), np.complex128)
    for t in range(W):
        cell = first + t
        wt = np.where(valid, _es(cell - pos, W, p.beta), 0.0)
        idx = (rows + np.mod(cell, M).astype(np.int64)).ravel()
        val = c0 * wt
        for term in range(p.n_terms):
            v = (val * alpha**term).ravel()
            out[term] += np.bincount(idx, v.real, n_cols * M) + 1j * np.bincount(idx, v.imag, n_cols * M)
    return out.reshape(p.n_terms, n_cols, M)


def direct(spec: np.ndarray, k: np.ndarray, ku: np.ndarray, kv: np.ndarray, p: StoltParams, n_z: int,
           factors: np.ndarray, chunk: int = 256) -> np.ndarray:
    """The Stolt sum evaluated directly at the depths (the NumPy twin of ``stolt_depths`` in
    kernels/stolt.cl): what :func:`spread` then :func:`terms_to_depths` approximate, exactly.

    ``out[c, l] = sum_p factors[p, l] sum_j c0[c, j] alpha[c, j]^p exp(i kz[c, j] (l - n_z // 2) dz)``
    (``c0`` carries the phase at ``zc``). Its work is ``n_cols n_f n_z``, the spread's
    ``n_cols (n_f W n_terms + M log M)``: for few samples and depths it is the cheaper.

    Parameters
    ----------
    spec, k, ku, kv, p
        As for :func:`spread` (``n_cells`` and ``width`` unused).
    n_z : int
        Output depths (``zc + (l - n_z // 2) dz``).
    factors : (n_terms, n_z) complex
        Weight of each power of alpha per depth.

    Returns
    -------
    (n_cols, n_z) complex128.
    """
    n_z = int(n_z)
    factors = np.asarray(factors)
    if factors.shape != (p.n_terms, n_z):
        raise ValueError(f"factors must have shape ({p.n_terms}, {n_z}) (n_terms, n_z), got {factors.shape}")
    spec = np.asarray(spec, np.complex128)
    k = np.asarray(k, float)
    ell = (np.arange(n_z) - n_z // 2) * p.dz_m
    out = np.zeros((spec.shape[0], n_z), np.complex128)
    for c0_ in range(0, spec.shape[0], chunk):
        sl = slice(c0_, c0_ + chunk)
        c0, alpha, _, valid = stolt_strengths(spec[sl], k, np.asarray(ku)[sl], np.asarray(kv)[sl], p)
        c0 = np.where(valid, c0, 0.0)
        alpha = np.where(valid, alpha, 0.0)
        kz = np.sign(k)[None, :] * np.sqrt(np.where(valid, k[None, :] ** 2 - (ku[sl] ** 2 + kv[sl] ** 2)[:, None], 1.0))
        e = np.exp(1j * kz[:, :, None] * ell[None, None, :])  # (cols, n_f, n_z)
        g = np.zeros(alpha.shape + (n_z,), np.complex128)
        for q in range(p.n_terms - 1, -1, -1):  # sum_p factors[p] alpha^p, Horner
            g = g * alpha[:, :, None] + factors[q][None, None, :]
        out[sl] = np.einsum("cf,cfz->cz", c0, e * g)
    return out


def deapodization(n_z: int, p: StoltParams) -> np.ndarray:
    """``1 / phi_hat(l h)`` for the output planes ``l = -n_z//2 ...``: the kernel's transform undone."""
    return _deapodization(int(n_z), int(p.width), float(p.beta), int(p.n_cells)).copy()


@functools.lru_cache(maxsize=16)
def _deapodization(n_z: int, width: int, beta: float, n_cells: int) -> np.ndarray:
    """Memoised: the Gauss-Legendre quadrature is the same for every chunk of columns."""
    x, wq = np.polynomial.legendre.leggauss(64)
    x = x * width / 2
    wq = wq * width / 2
    phi = _es(x, width, beta)
    ell = np.arange(n_z) - n_z // 2
    h = 2 * np.pi / n_cells
    phi_hat = (wq * phi * np.cos(np.outer(ell * h, x))).sum(axis=1)
    return 1.0 / phi_hat


def columns_to_depths(cells: np.ndarray, n_z: int, p: StoltParams, workers: int | None = None) -> np.ndarray:
    """Spread cells (n_terms, n_cols, M) -> each term at the output depths (n_terms, n_cols, n_z)."""
    import scipy.fft

    M = p.n_cells
    b = scipy.fft.ifft(cells, axis=-1, workers=workers)
    ell = np.arange(n_z) - n_z // 2
    return b[..., np.mod(ell, M)] * (M * deapodization(n_z, p)).astype(b.dtype)


def terms_to_depths(cells: np.ndarray, n_z: int, p: StoltParams, factors: np.ndarray,
                    workers: int | None = None, overwrite: bool = False) -> np.ndarray:
    """``sum_p factors[p, z] columns_to_depths(cells)[p, :, z]``, in the cells' precision.

    What ω-k needs of :func:`columns_to_depths`: the terms weighted per depth (the bistatic
    expansion's ``(i u_z)^p / p!``) and summed. The weights, the de-apodisation and ``M`` are
    folded into one (n_terms, n_z) table, and the depths are read as the two contiguous runs
    of the inverse FFT they are (no gather, no float64 promotion).

    Parameters
    ----------
    cells : (n_terms, n_cols, M) complex
    n_z : int
    p : StoltParams
    factors : (n_terms, n_z) complex
    workers : int, optional
        FFT threads.
    overwrite : bool
        The inverse FFT may work in ``cells`` (for a caller that has no further use of them:
        no copy of the cells is made).

    Returns
    -------
    (n_cols, n_z) complex, the dtype of ``cells`` (left as it was unless ``overwrite``).
    """
    import scipy.fft

    M = p.n_cells
    if not 1 <= int(n_z) <= M:
        raise ValueError(f"n_z must be between 1 and the cells per column ({M}), got {n_z!r}")
    b = scipy.fft.ifft(cells, axis=-1, workers=workers, overwrite_x=bool(overwrite))
    coef = (np.asarray(factors) * (M * deapodization(n_z, p))[None, :]).astype(b.dtype)
    h = n_z // 2  # planes l = -h .. -1 sit at the FFT's end, l = 0 .. n_z - h - 1 at its start
    out = np.empty(b.shape[1:2] + (n_z,), b.dtype)
    out[:, :h] = b[0, :, M - h:] * coef[0, :h]
    out[:, h:] = b[0, :, : n_z - h] * coef[0, h:]
    for q in range(1, b.shape[0]):
        out[:, :h] += b[q, :, M - h:] * coef[q, :h]
        out[:, h:] += b[q, :, : n_z - h] * coef[q, h:]
    return out


def depth_path(choice: str, n_f: int, n_z: int, width: int, terms: int, opencl: bool = True) -> str:
    """How the Stolt sum reaches the depths: ``"direct"`` (the sum at each depth) or ``"spread"``
    (the non-uniform FFT); ``"auto"`` takes the one :data:`DIRECT_COST` and :data:`SPREAD_COST`
    predict faster on OpenCL, and the spread on the NumPy twins (``opencl`` False)."""
    if choice != "auto":
        return choice
    if not opencl:
        return "spread"  # NumPy's direct sum is the slower twin (0.50 s against 0.12 s at 32 x 32 stops)
    return "direct" if direct_work(n_f, n_z, terms) <= spread_work(n_f, n_z, width, terms) else "spread"


def direct_work(n_f: int, n_z: int, terms: int) -> float:
    """Relative time per column of the direct sum (:data:`DIRECT_COST`)."""
    return DIRECT_COST[0] * n_f * n_z * (1 + 0.2 * (terms - 1)) + DIRECT_COST[1] * n_f


def spread_work(n_f: int, n_z: int, width: int, terms: int) -> float:
    """Relative time per column of the spread, the cells' FFT and the terms' sum (:data:`SPREAD_COST`)."""
    return SPREAD_COST[0] * n_f * terms * width + SPREAD_COST[1] * n_z * terms
