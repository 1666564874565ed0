"""Per-stop line-of-sight paths from the phase differences of neighbouring stops (``"track"``).

A hand-held scan is smooth in time: at 50 stops a second, motion of a few millimetres in a
0.2-5 Hz band moves the path by well under a quarter wavelength from one stop to the next. Two
neighbouring stops (in time, or in space on the next row) also see the target from almost the
same direction, so their backprojected images ``A_s`` and ``A_t`` agree up to the phase of
their path difference: ``arg sum_v conj(A_t) A_s = phi_t - phi_s`` (+ speckle), where
``I = sum_s exp(j phi_s) A_s`` is the corrected image. No image needs to be in focus first and
no focus metric is maximised, so there is no sharper-but-wrong optimum to climb to.

The differences are integrated over the graph of neighbours by weighted least squares
(:func:`integrate_phases`: the time chain first, whose steps are small enough not to wrap, then
every edge unwrapped against the current solution, with robust weights). The constant is the
gauge of the graph; the constant and the tilt across the aperture are removed by the caller.
A smooth refinement (:func:`smooth_refine`) then fits the path in a band-limited basis of stop
time (the hand's band, :data:`DEFAULT_CUTOFF_HZ`), plus the tilt columns.

*Determination* (:func:`half_agreement`): the even and the odd stops in time, each integrated
on its own (disjoint data, the same motion), must give the same path (gauge removed) to within
``tolerance`` of path; else the motion is not determined by this scan.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["DEFAULT_CUTOFF_HZ", "neighbour_edges", "pair_phases", "integrate_phases", "smooth_refine",
           "track_phases", "nearest_coherence", "half_agreement", "region_agreement", "gauge_free"]

log = logging.getLogger(__name__)

#: Highest frequency of the hand motion the smooth refinement keeps, Hz (HandMotion: 0.2-5 Hz).
DEFAULT_CUTOFF_HZ = 6.0


def neighbour_edges(xy: np.ndarray, lags: tuple[int, ...] = (1, 2, 3), k_spatial: int = 6) -> np.ndarray:
    """(n_edges, 2) stop pairs ``(s, t)``, ``s < t``: neighbours in time (``lags`` stops apart,
    stops in time order) and the ``k_spatial`` nearest in the carriage's plane (``xy`` (n, 2), m)."""
    from scipy.spatial import cKDTree

    n = len(xy)
    pairs = [np.c_[np.arange(n - lag), np.arange(lag, n)] for lag in lags if lag < n]
    k = min(k_spatial + 1, n)
    if k > 1:
        _, nb = cKDTree(np.asarray(xy, float)).query(xy, k=k)
        nb = np.asarray(nb).reshape(n, k)[:, 1:]
        s = np.repeat(np.arange(n), k - 1)
        pairs.append(np.c_[np.minimum(s, nb.ravel()), np.maximum(s, nb.ravel())])
    e = np.unique(np.concatenate(pairs, axis=0), axis=0) if pairs else np.zeros((0, 2), int)
    return e[e[:, 0] != e[:, 1]]


def pair_phases(a: np.ndarray, edges: np.ndarray, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Phase difference (rad) and coherence (0 to 1) of each edge's two stop images.

    ``arg sum_v conj(a_t) a_s`` and ``|sum conj(a_t) a_s| / (||a_s|| ||a_t||)``; ``a`` is
    (n_stops, n_vox) complex.
    """
    norm = np.sqrt(np.sum(a.real.astype(np.float64) ** 2 + a.imag.astype(np.float64) ** 2, axis=1))
    g = np.empty(len(edges), np.complex128)
    for i in range(0, len(edges), chunk):
        e = edges[i:i + chunk]
        g[i:i + chunk] = np.einsum("ev,ev->e", np.conj(a[e[:, 1]]), a[e[:, 0]], dtype=np.complex128)
    coh = np.abs(g) / np.maximum(norm[edges[:, 0]] * norm[edges[:, 1]], 1e-300)
    return np.angle(g), np.clip(coh, 0.0, 1.0)


def _solve(n: int, edges: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares ``phi_t - phi_s = d`` over the edges, mean of ``phi`` 0."""
    lap = np.zeros((n, n))
    np.add.at(lap, (edges[:, 0], edges[:, 0]), w)
    np.add.at(lap, (edges[:, 1], edges[:, 1]), w)
    np.add.at(lap, (edges[:, 0], edges[:, 1]), -w)
    np.add.at(lap, (edges[:, 1], edges[:, 0]), -w)
    rhs = np.zeros(n)
    np.add.at(rhs, edges[:, 1], w * d)
    np.add.at(rhs, edges[:, 0], -w * d)
    lap += np.full((n, n), max(float(w.mean()), 1e-12) / n)  # the gauge: mean 0
    return np.linalg.solve(lap, rhs)


def integrate_phases(n: int, edges: np.ndarray, angle: np.ndarray, coherence: np.ndarray, *, n_irls: int = 6,
                     robust_rad: float = 0.5) -> np.ndarray:
    """Per-stop phases (rad, mean 0, not wrapped) from the edges' wrapped differences.

    The chain of consecutive stops (lag 1) first, then every edge unwrapped against the
    current solution and solved again with weights ``coh^2 / (1 - coh^2)`` (the inverse
    variance of a coherence estimate's phase) times a Cauchy weight of the residual.
    """
    w = coherence**2 / (1 - coherence**2 + 1e-3)
    chain = edges[:, 1] - edges[:, 0] == 1
    if np.unique(edges[chain].ravel()).size == n:
        phi = _solve(n, edges[chain], angle[chain], w[chain])
    else:
        phi = np.zeros(n)
    for _ in range(n_irls):
        pred = phi[edges[:, 1]] - phi[edges[:, 0]]
        r = np.angle(np.exp(1j * (angle - pred)))
        phi = _solve(n, edges, pred + r, w / (1 + (r / robust_rad) ** 2))
    return phi


def region_agreement(a: np.ndarray, points: np.ndarray, t: np.ndarray, xy: np.ndarray,
                     **options) -> tuple[np.ndarray, np.ndarray]:
    """The phases of all the stops tracked twice: on the voxels either side of a cut across the
    bright region, at the intensity-weighted median along its longest horizontal axis (weights
    the uncorrected image's intensity ``|sum_s a_s|^2``). ``points`` (n_vox, 3), m, are the
    columns' voxels.

    The two sides hold different scatterers, so their speckle (and their noise) differ while
    the motion is the same: where the stops sample the target finely enough for the neighbours'
    phases to carry the motion, both sides give one path. Unlike :func:`half_agreement` it keeps
    every stop, so the stops' pitch (and the neighbours' coherence) is that of the scan.
    Returns ``(phi_a, phi_b)`` (n_stops,) rad; both NaN where a side would hold fewer than 2
    voxels (no second look: the caller's test then fails).
    """
    a = np.asarray(a)
    w = np.abs(a.sum(axis=0, dtype=np.complex128)) ** 2
    h = np.asarray(points, float)[:, :2]
    h = h - np.average(h, axis=0, weights=w + 1e-300)
    axis = np.linalg.eigh((h * w[:, None]).T @ h)[1][:, -1]
    along = h @ axis
    order = np.argsort(along)
    cw = np.cumsum(w[order])
    cut = along[order][min(int(np.searchsorted(cw, 0.5 * cw[-1])), len(order) - 1)]
    sides = (along <= cut, along > cut)
    if min(int(side.sum()) for side in sides) < 2:
        nan = np.full(a.shape[0], np.nan)
        return nan, nan.copy()
    phi_a, _ = track_phases(a[:, sides[0]], t, xy, **options)
    phi_b, _ = track_phases(a[:, sides[1]], t, xy, **options)
    return phi_a, phi_b


def gauge_free(p: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``p`` (n_stops,) less its least-squares constant and tilt in the carriage's x and y (only
    the tilts the stops span: a line scan has one)."""
    q, r = np.linalg.qr(np.c_[np.ones(len(p)), xy - xy.mean(axis=0)])
    d = np.abs(np.diag(r))
    q = q[:, d > 1e-9 * max(d.max(initial=0.0), 1e-300)]
    return p - q @ (q.T @ p)


def smooth_basis(t: np.ndarray, xy: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """Orthonormal columns: cosines of stop time up to ``cutoff_hz``, and the carriage's x and y."""
    n = len(t)
    dt = float(np.median(np.diff(np.sort(t)))) if n > 1 else 1.0
    span = float(t.max() - t.min()) + dt
    k = min(int(np.ceil(2 * cutoff_hz * span)) + 1, n)
    b = np.c_[xy - xy.mean(axis=0), np.cos(np.pi * ((t - t.min() + 0.5 * dt) / span)[:, None] * np.arange(k))]
    q, r = np.linalg.qr(b)
    d = np.abs(np.diag(r))
    return q[:, d > 1e-8 * max(d.max(initial=0.0), 1e-300)]


def smooth_refine(a: np.ndarray, t: np.ndarray, xy: np.ndarray, phi: np.ndarray, *,
                  cutoff_hz: float = DEFAULT_CUTOFF_HZ, n_iter: int = 10) -> np.ndarray:
    """From ``phi``: each stop's phase against the image of the others, unwrapped against
    ``phi`` and fitted in a band-limited basis of stop time ``t`` (s) plus the tilt, repeated."""
    basis = smooth_basis(t, xy, cutoff_hz)
    a2 = np.sum(np.abs(a) ** 2, axis=1)
    phi = np.asarray(phi, float).copy()
    for _ in range(n_iter):
        image = (np.exp(1j * phi)[:, None] * a).sum(axis=0, dtype=np.complex128)
        z = np.conj(a) @ image - np.exp(1j * phi) * a2
        res = np.angle(z * np.exp(-1j * phi))
        w = np.abs(z) ** 2
        w = np.minimum(w, 4 * np.median(w))
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(basis * sw[:, None], (phi + res) * sw, rcond=None)
        new = basis @ coef
        step = float(np.sqrt(np.mean((new - phi) ** 2)))
        phi = new
        if step < 1e-3:
            break
    return phi


def track_phases(a: np.ndarray, t: np.ndarray, xy: np.ndarray, *, cutoff_hz: float | None = DEFAULT_CUTOFF_HZ,
                 lags: tuple[int, ...] = (1, 2, 3), k_spatial: int = 6) -> tuple[np.ndarray, dict]:
    """Per-stop phases (rad; stops in time order ``t``, s) from neighbouring stops' images.

    Returns ``(phi, info)``: ``info`` has ``coherence_median`` of the edges, ``coherence_nearest``
    (:func:`nearest_coherence`) and ``edges``. ``cutoff_hz`` None: no smooth refinement.
    """
    a = np.asarray(a)
    edges = neighbour_edges(xy, lags, k_spatial)
    angle, coh = pair_phases(a, edges)
    phi = integrate_phases(a.shape[0], edges, angle, coh)
    if cutoff_hz is not None:
        phi = smooth_refine(a, t, xy, phi, cutoff_hz=cutoff_hz)
    return phi, {"coherence_median": float(np.median(coh)) if len(coh) else 0.0,
                 "coherence_nearest": nearest_coherence(xy, edges, coh), "edges": int(len(edges))}


def nearest_coherence(xy: np.ndarray, edges: np.ndarray, coherence: np.ndarray) -> float:
    """Median coherence of the edges no longer than 1.1 times the stops' pitch (the median
    distance from a stop to its nearest neighbour, in the carriage's plane): how alike the
    images of the closest stops are, before any correction (motion changes their phase, not
    their coherence). Near 1 where the stops sample the target finer than its speckle (about
    ``lambda R / 2D`` for a target ``D`` across at range ``R``); near 0 where they do not, and
    there neighbouring stops' phases say nothing about the motion. NaN without edges."""
    xy = np.asarray(xy, float)
    edges = np.asarray(edges, int).reshape(-1, 2)
    if len(edges) == 0:
        return float("nan")
    length = np.linalg.norm(xy[edges[:, 0]] - xy[edges[:, 1]], axis=1)
    d = np.full(len(xy), np.inf)
    np.minimum.at(d, edges[:, 0], length)
    np.minimum.at(d, edges[:, 1], length)
    pitch = float(np.median(d[np.isfinite(d)]))
    return float(np.median(np.asarray(coherence)[length <= 1.1 * pitch]))


def half_agreement(a: np.ndarray, t: np.ndarray, xy: np.ndarray, **options) -> tuple[np.ndarray, np.ndarray]:
    """The phases of the even and of the odd stops in time, each tracked on its own and
    interpolated (linearly, in stop order) to all stops: ``(phi_even, phi_odd)`` (n_stops,) rad."""
    n = a.shape[0]
    out = []
    for h in (0, 1):
        idx = np.arange(h, n, 2)
        phi, _ = track_phases(a[idx], t[idx], xy[idx], **options)
        out.append(np.interp(np.arange(n), idx, phi))
    return out[0], out[1]
