"""NumPy twin of kernels/ffbp.cl: float64, written to be read.

Three steps, each the specification of one kernel entry (see :mod:`clsas.formation.ffbp_tree`
for the tables and the sample layout):

- :func:`form_leaves` (``ffbp_leaf``): each leaf's sub-image by exact backprojection of its
  measurements onto its spherical grid, with the node's reference carrier removed;
- :func:`merge` (``ffbp_merge``): each parent's sub-image as the sum of its children's,
  interpolated at the parent's samples (``taps`` points per axis, least-squares band-limited
  or Lagrange weights from a table), each child's reference carrier restored and the
  parent's removed;
- :func:`to_grid` (``ffbp_merge`` with a Cartesian parent): the sum of the top sub-images at
  the voxels, with their carriers restored.

A sub-image of node ``n`` at point ``P`` is ``sum_m bp_m(P) exp(-j 2 pi kref ref_n(P))``, where
``bp_m`` is exact backprojection's term of measurement ``m`` and ``ref_n(P) = |P - T_n| + |P - R_n|``
the path through the node's mean speaker and microphone positions (m).
"""

from __future__ import annotations

import numpy as np

from ..physics.beam import BeamWeights, pair_weights
from .ffbp_tree import BLOCK, Level

__all__ = ["RES", "INTERPOLATORS", "lagrange", "least_squares", "weight_table", "table_weights", "sample_points",
           "form_leaves", "merge", "to_grid"]

CHUNK = 1 << 16  # samples per vectorised pass
RES = 64  # weight-table entries per sample of position
INTERPOLATORS = ("lsq", "lagrange")
LSQ_BAND = 0.375  # design band of the least-squares weights, x the Nyquist rate / oversample


def lagrange(t: np.ndarray, taps: int) -> np.ndarray:
    """(taps, n) weights of the Lagrange polynomial through nodes 0..taps-1, at ``t``."""
    t = np.atleast_1d(np.asarray(t, float))
    w = np.ones((taps, len(t)))
    for j in range(taps):
        for k in range(taps):
            if k != j:
                w[j] *= (t - k) / (j - k)
    return w


def least_squares(t: np.ndarray, taps: int, nu: float) -> np.ndarray:
    """(taps, n) weights at ``t`` that interpolate every signal band-limited to ``|f| <= nu``
    cycles per sample with the least squared error, averaged over that band.

    Solves ``G w = b`` with ``G_kl = sinc(2 nu (k - l))`` and ``b_k = sinc(2 nu (k - t))``: the
    normal equations of fitting ``exp(j 2 pi f t)`` by the taps' ``exp(j 2 pi f k)`` over the band.
    At ``nu = 0.25`` (twice the Nyquist rate) 4 taps err by -30 dB at worst, Lagrange's by -19 dB.
    """
    t = np.atleast_1d(np.asarray(t, float))
    k = np.arange(taps)
    gram = np.sinc(2 * nu * (k[:, None] - k[None, :])) + 1e-10 * np.eye(taps)
    rhs = np.sinc(2 * nu * (k[:, None] - t[None, :]))
    return np.linalg.solve(gram, rhs)


def weight_table(taps: int, oversample: float, interpolator: str = "lsq") -> np.ndarray:
    """(taps * RES + 1, taps) weights at positions ``t = -0.5 + i / RES`` of the stencil.

    ``oversample`` is the sampling rate over the Nyquist rate of the signals interpolated: the
    least-squares weights are designed for ``|f| <= LSQ_BAND / oversample`` cycles per sample.
    The sub-images' rates are bounds (the largest local frequency anywhere in a node's region,
    at the band's top), so most of their energy lies well inside them: a design band of 0.375
    of the bound erred 7 dB less than 0.55 on a dense raster (32 x 32 stops, depth 3) and 14 dB
    less on a 360-stop circle (depth 2), at the same cost.
    """
    t = -0.5 + np.arange(taps * RES + 1) / RES
    if interpolator == "lagrange":
        return lagrange(t, taps).T.copy()
    return least_squares(t, taps, min(0.5, LSQ_BAND / oversample)).T.copy()


def table_weights(table: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(taps, n) weights at stencil positions ``t``, linearly interpolated from ``table``."""
    taps = table.shape[1]
    x = np.clip((np.asarray(t, float) + 0.5) * RES, 0.0, taps * RES - 1e-9)
    i = np.floor(x).astype(np.int64)
    a = x - i
    return ((1 - a)[:, None] * table[i] + a[:, None] * table[i + 1]).T


def sample_points(level: Level, start: int, stop: int):
    """Nodes, world points (k, 3) and validity of packed samples ``start .. stop - 1``."""
    idx = np.arange(start, stop)
    node = np.repeat(np.arange(level.n_nodes), -(-np.prod(level.ints[:, :3], axis=1) // BLOCK))[idx // BLOCK]
    g, it = level.geom[node], level.ints[node]
    local = idx - it[:, 3]
    nr, nv = it[:, 0], it[:, 2]
    inside = local < np.prod(it[:, :3], axis=1)
    ir = local % nr
    iuv = local // nr
    iv, iu = iuv % nv, iuv // nv
    r = g[:, 18] + ir * g[:, 21]
    u = g[:, 19] + iu * g[:, 22]
    v = g[:, 20] + iv * g[:, 23]
    q = 1.0 - u**2 - v**2
    valid = inside & (q > 0)
    s = np.sqrt(np.maximum(q, 0.0))
    p = g[:, 0:3] + r[:, None] * (u[:, None] * g[:, 3:6] + v[:, None] * g[:, 6:9] + s[:, None] * g[:, 9:12])
    return node, p, valid


def _ref(p: np.ndarray, g: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p - g[:, 12:15], axis=1) + np.linalg.norm(p - g[:, 15:18], axis=1)


def form_leaves(data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps, level: Level, kref: float,
                beam: BeamWeights | None = None) -> np.ndarray:
    """Leaf sub-images, (level.size,) complex128.

    Parameters
    ----------
    data : (n_meas, n_lags) complex baseband profiles, in tree order
    tau0_s : (n_meas,) delay of sample 0, s; dtau_s: delay step, s; fc_hz: carrier, Hz
    tx, rx : (n_meas, 3) m; c_mps : (n_meas,) m/s (all in tree order)
    level : the leaves; kref : reference cycles per metre of path
    beam : each pair weighted by its two-way beam at the sample (boresights in tree order;
        :func:`clsas.physics.beam.pair_weights`), as bp weights it at a voxel
    """
    n_lags = data.shape[1]
    out = np.zeros(level.size, np.complex128)
    counts = level.ints[:, 5] - level.ints[:, 4]
    for a in range(0, level.size, CHUNK):
        b = min(level.size, a + CHUNK)
        node, p, valid = sample_points(level, a, b)
        g, it = level.geom[node], level.ints[node]
        ref = _ref(p, g)
        acc = np.zeros(b - a, np.complex128)
        for j in range(int(counts.max())):
            has = valid & (j < counts[node])
            m = np.where(has, it[:, 4] + j, 0)
            path = np.linalg.norm(p - tx[m], axis=1) + np.linalg.norm(p - rx[m], axis=1)
            tau = path / c_mps[m]
            idx = (tau - tau0_s[m]) / dtau_s
            inside = has & (idx >= 0) & (idx <= n_lags - 1)
            i0 = np.clip(np.floor(idx), 0, n_lags - 2).astype(np.int64)
            w = idx - i0
            val = (1 - w) * data[m, i0] + w * data[m, i0 + 1]
            if beam is not None:
                val = val * pair_weights(beam.luts, tx[m], rx[m], beam.tx_dir[m], beam.rx_dir[m], p, beam.gate)
            acc += np.where(inside, val * np.exp(2j * np.pi * (fc_hz * tau - kref * ref)), 0)
        out[a:b] = acc
    return out


def _interpolate(values: np.ndarray, level: Level, child: np.ndarray, p: np.ndarray, tables) -> np.ndarray:
    """Child sub-images (nodes ``child``) interpolated at points ``p``; 0 outside their grids.

    ``tables`` = (range table, angle table) of :func:`weight_table`. The stencil is centred on
    the point (``taps // 2`` samples at or below it), and shifted inwards at a grid's edges."""
    taps = tables[0].shape[1]
    g, it = level.geom[child], level.ints[child]
    d = p - g[:, 0:3]
    r = np.linalg.norm(d, axis=1)
    u = np.sum(d * g[:, 3:6], axis=1) / r
    v = np.sum(d * g[:, 6:9], axis=1) / r
    front = np.sum(d * g[:, 9:12], axis=1) > 0
    n = it[:, 0:3]
    ok = front
    starts, weights = [], []
    for ax, coord in enumerate((r, u, v)):
        f = (coord - g[:, 18 + ax]) * g[:, 24 + ax]
        ok = ok & (f >= -0.5) & (f <= n[:, ax] - 0.5)
        f = np.clip(f, -1.0, n[:, ax].astype(float))
        s = np.clip(np.floor(f).astype(np.int64) - (taps // 2 - 1), 0, n[:, ax] - taps)
        starts.append(s)
        weights.append(table_weights(tables[min(ax, 1)], f - s))
    acc = np.zeros(len(p), np.complex128)
    for ju in range(taps):
        for jv in range(taps):
            base = it[:, 3] + ((starts[1] + ju) * n[:, 2] + starts[2] + jv) * n[:, 0] + starts[0]
            wuv = weights[1][ju] * weights[2][jv]
            for jr in range(taps):
                acc += wuv * weights[0][jr] * values[base + jr]
    return np.where(ok, acc, 0)


def merge(values: np.ndarray, children: Level, parents: Level, kref: float, tables) -> np.ndarray:
    """Parent sub-images from their children's ``values``: (parents.size,) complex128."""
    out = np.zeros(parents.size, np.complex128)
    for a in range(0, parents.size, CHUNK):
        b = min(parents.size, a + CHUNK)
        node, p, valid = sample_points(parents, a, b)
        it = parents.ints[node]
        ref_p = _ref(p, parents.geom[node])
        acc = np.zeros(b - a, np.complex128)
        for j in range(int((it[:, 7] - it[:, 6]).max())):
            child = it[:, 6] + j
            val = _interpolate(values, children, child, p, tables)
            ref_c = _ref(p, children.geom[child])
            acc += val * np.exp(2j * np.pi * kref * (ref_c - ref_p))
        out[a:b] = np.where(valid, acc, 0)
    return out


def to_grid(values: np.ndarray, children: Level, points_m: np.ndarray, kref: float, tables) -> np.ndarray:
    """The image at ``points_m`` (n_vox, 3): (n_vox,) complex128, the sum of every child's
    interpolated sub-image with its reference carrier restored."""
    out = np.zeros(len(points_m), np.complex128)
    for a in range(0, len(points_m), CHUNK):
        p = points_m[a:a + CHUNK]
        for c in range(children.n_nodes):
            child = np.full(len(p), c)
            val = _interpolate(values, children, child, p, tables)
            out[a:a + len(p)] += val * np.exp(2j * np.pi * kref * _ref(p, children.geom[child]))
    return out
