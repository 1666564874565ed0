"""The geometry of fast factorized backprojection: the sub-aperture tree and its sub-image grids.

Everything here is float64 NumPy, shared by the NumPy twin and the OpenCL plans: which
measurements form each sub-aperture, the local spherical frame of each sub-image, and how
finely each sub-image is sampled. The kernels only follow these tables.

A node (sub-aperture) holds the measurements ``m0 .. m1 - 1`` of the tree order. Its sub-image
lives on a grid in local spherical coordinates about its centre ``O`` (the mean of its
measurements' tx-rx midpoints): range ``r = |P - O|`` and the direction cosines
``u = (P - O)·e1 / r``, ``v = (P - O)·e2 / r`` in a frame whose third axis ``w`` looks from ``O``
at the centre of the imaged grid. A point is ``P = O + r (u e1 + v e2 + sqrt(1 - u² - v²) w)``.
Samples are stored range-fastest: index ``(iu * nv + iv) * nr + ir`` after the node's offset in
its level's packed buffer (offsets are multiples of :data:`BLOCK`).

Sampling (cycles per metre of range, per unit of direction cosine): a measurement's term in
the sub-image, with the carrier of the node's reference path removed, oscillates along each
coordinate at ``f d tau_m / dq - f0 d tau_ref / dq`` (about ``f / c`` times the measurement's
two-way offset from the node's mean speaker and microphone across the line of sight, in angle;
about the band's half width ``2 (f - f0) / c`` in range). The largest of these over the node's
measurements, the band's two ends and a lattice of its region sets the Nyquist rate (near
field, bistatic pairs and each measurement's speed of sound included); each axis is sampled at
``oversample`` (angles) or ``range_oversample`` times it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["BLOCK", "NG", "NI", "Level", "Tree", "build_tree", "estimate_band", "split_sizes", "max_depth"]

BLOCK = 64  # samples per block of the packed level buffers (a work-group's worth)
NG = 32  # floats per node in Level.geom
NI = 8  # ints per node in Level.ints
# geom columns: O(0:3) e1(3:6) e2(6:9) w(9:12) T(12:15) R(15:18) origin r0,u0,v0 (18:21)
# step dr,du,dv (21:24) inverse step (24:27), 27..31 unused
# ints columns: nr nu nv offset m0 m1 c0 c1
U2_GRID = 0.9  # the grid must lie within asin(sqrt(0.9)) = 72 degrees of every sub-aperture's axis
U2_KEEP = 0.97  # directions kept when a parent's grid is mapped into its children
LATTICE = 7  # points per edge of the face lattices that bound a region


@dataclass
class Level:
    """The nodes of one depth of the tree and the packed layout of their sub-images."""

    geom: np.ndarray  # (n_nodes, NG) float64
    ints: np.ndarray  # (n_nodes, NI) int64
    size: int  # samples in the packed buffer, padding included (a multiple of BLOCK)

    @property
    def n_nodes(self) -> int:
        return len(self.ints)

    @property
    def samples(self) -> int:
        """Samples in use (padding excluded)."""
        return int(np.prod(self.ints[:, :3], axis=1).sum())

    def block_node(self) -> np.ndarray:
        """(size // BLOCK,) int32: the node each block of the packed buffer belongs to."""
        blocks = -(-np.prod(self.ints[:, :3], axis=1) // BLOCK)
        return np.repeat(np.arange(self.n_nodes, dtype=np.int32), blocks)


@dataclass
class Tree:
    """Sub-apertures, their sub-image grids and the constants of the phase reference."""

    order: np.ndarray  # (n_meas,) measurement indices in tree order
    levels: list[Level]  # levels[0]: the root's children (depth 1) ... levels[-1]: the leaves
    factor: int
    f0_hz: float  # reference frequency (centre of the band) removed from every sub-image
    c_ref_mps: float  # speed of sound of the reference path
    band_hz: tuple[float, float]  # the band the sampling is designed for
    notes: list[str] = field(default_factory=list)

    @property
    def depth(self) -> int:
        return len(self.levels)

    @property
    def kref(self) -> float:
        """Reference carrier cycles per metre of path, ``f0 / c_ref``."""
        return self.f0_hz / self.c_ref_mps

    def describe(self) -> str:
        rows = [f"FFBP depth {self.depth}, factor {self.factor}, band {self.band_hz[0]:.0f}-{self.band_hz[1]:.0f} Hz"]
        for d, lev in enumerate(self.levels, 1):
            n = lev.ints[:, 5] - lev.ints[:, 4]
            rows.append(f"depth {d}: {lev.n_nodes} sub-apertures of {n.min()}-{n.max()} measurements, "
                        f"{lev.samples:,} samples (grids up to {lev.ints[:, :3].max(axis=0).tolist()} r,u,v)")
        return "\n".join(rows + self.notes)


def max_depth(n_meas: int, factor: int) -> int:
    """The deepest tree whose leaves keep at least one measurement."""
    d = 0
    while factor ** (d + 1) <= n_meas:
        d += 1
    return d


LEAF = 16  # measurements per leaf by default: a leaf is formed by backprojection, which costs about
# what a merge level costs per sample at 16 measurements (4 taps per axis, factor 4)


def default_depth(n_meas: int, factor: int) -> int:
    """Leaves of at least :data:`LEAF` measurements (or 1 level where the aperture has fewer)."""
    d = 0
    while n_meas // factor ** (d + 1) >= LEAF:
        d += 1
    return max(d, min(1, max_depth(n_meas, factor)))


def split_sizes(factor: int) -> list[int]:
    """``factor`` as successive splits (its prime factors): 4 -> [2, 2], so that a square patch
    becomes quadrants, not strips."""
    out, n, p = [], factor, 2
    while n > 1:
        while n % p == 0:
            out.append(p)
            n //= p
        p += 1
    return out


def _split_axis(points: np.ndarray) -> np.ndarray:
    """The direction of largest spread: a coordinate axis unless a principal axis beats it by 1 %."""
    centred = points - points.mean(axis=0)
    cov = centred.T @ centred
    best = int(np.argmax(np.diag(cov)))
    axis = np.eye(3)[best]
    vals, vecs = np.linalg.eigh(cov)
    if vals[-1] > 1.01 * cov[best, best]:
        axis = vecs[:, -1]
    return axis


def _split(idx: np.ndarray, centres: np.ndarray, parts: list[int]) -> list[np.ndarray]:
    if not parts:
        return [idx]
    proj = centres[idx] @ _split_axis(centres[idx])
    ordered = idx[np.argsort(proj, kind="stable")]
    out = []
    for chunk in np.array_split(ordered, parts[0]):
        out += _split(chunk, centres, parts[1:])
    return out


def estimate_band(data: np.ndarray, dtau_s: float, fc_hz: float, tail: float = 1e-4) -> tuple[float, float]:
    """The band holding all but ``tail`` of the profiles' energy, in Hz (carrier included).

    The profiles are complex baseband (rotated by ``exp(-j 2 pi fc tau)``); their spectrum,
    summed over rows (each tapered by a Hann window, so that the cut at the gate's ends does not
    leak), is cut where the cumulative energy passes ``tail / 2`` and ``1 - tail / 2``.
    """
    n = data.shape[1]
    nfft = max(64, 1 << int(np.ceil(np.log2(2 * n))))
    rows = data if len(data) <= 4096 else data[np.linspace(0, len(data) - 1, 4096).astype(int)]
    taper = np.hanning(n + 2)[1:-1]  # the rows are cut at the gate: no leakage from their edges
    power = np.zeros(nfft)
    for k in range(0, len(rows), 512):
        power += (np.abs(np.fft.fft(rows[k:k + 512] * taper, nfft, axis=1)) ** 2).sum(axis=0)
    f = np.fft.fftfreq(nfft, dtau_s)
    order = np.argsort(f)
    f, power = f[order], power[order]
    total = power.sum()
    if not total > 0:
        return fc_hz - 0.5 / (2 * dtau_s), fc_hz + 0.5 / (2 * dtau_s)
    cum = np.cumsum(power) / total
    lo = f[min(np.searchsorted(cum, tail / 2), nfft - 1)]
    hi = f[min(np.searchsorted(cum, 1 - tail / 2), nfft - 1)]
    df = f[1] - f[0]
    return fc_hz + lo - df, fc_hz + hi + df


def _frames(centres: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rows e1, e2, w: w from each centre towards ``target``."""
    w = target - centres
    norm = np.linalg.norm(w, axis=1)
    if np.any(norm < 1e-6):
        raise ValueError("grid: its centre coincides with a sub-aperture's centre; FFBP needs the grid in front "
                         "of the aperture (use formation='bp')")
    w = w / norm[:, None]
    ref = np.eye(3)[np.argmin(np.abs(w), axis=1)]
    e1 = ref - np.sum(ref * w, axis=1)[:, None] * w
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(w, e1)
    return np.stack([e1, e2, w], axis=1)


def _to_local(points: np.ndarray, geom: np.ndarray) -> tuple[np.ndarray, ...]:
    """(r, u, v, w-component) of ``points`` (..., k, 3) in the frames of ``geom`` (..., NG)."""
    d = points - geom[..., None, 0:3]
    r = np.linalg.norm(d, axis=-1)
    r_safe = np.maximum(r, 1e-12)
    u = np.einsum("...kc,...c->...k", d, geom[..., 3:6]) / r_safe
    v = np.einsum("...kc,...c->...k", d, geom[..., 6:9]) / r_safe
    wc = np.einsum("...kc,...c->...k", d, geom[..., 9:12])
    return r, u, v, wc


def _face_lattice(lo: np.ndarray, hi: np.ndarray, n: int = LATTICE) -> np.ndarray:
    """Points on the faces of the boxes [lo, hi] (..., 3): (..., k, 3)."""
    t = np.linspace(0.0, 1.0, n)
    a, b = np.meshgrid(t, t, indexing="ij")
    a, b = a.ravel(), b.ravel()
    faces = []
    for axis in range(3):
        others = [i for i in range(3) if i != axis]
        for side in (0.0, 1.0):
            f = np.zeros((len(a), 3))
            f[:, axis] = side
            f[:, others[0]] = a
            f[:, others[1]] = b
            faces.append(f)
    unit = np.concatenate(faces)
    return lo[..., None, :] + unit * (hi - lo)[..., None, :]


def _polar_to_world(rp: np.ndarray, up: np.ndarray, vp: np.ndarray, geom: np.ndarray) -> np.ndarray:
    s = np.sqrt(np.maximum(0.0, 1.0 - up**2 - vp**2))
    dirs = (up[..., None] * geom[..., None, 3:6] + vp[..., None] * geom[..., None, 6:9]
            + s[..., None] * geom[..., None, 9:12])
    return geom[..., None, 0:3] + rp[..., None] * dirs


def _regions(geom, grid_bounds, parent_geom, parent_ints, factor, chunk=2048) -> np.ndarray:
    """(n, 6) r_lo, r_hi, u_lo, u_hi, v_lo, v_hi of the region each node's grid must cover."""
    nn = len(geom)
    box = np.zeros((nn, 6))
    for a in range(0, nn, chunk):
        b = min(nn, a + chunk)
        g = geom[a:b]
        if parent_geom is None:
            pts = _face_lattice(grid_bounds[:, 0], grid_bounds[:, 1])[None].repeat(b - a, axis=0)
            r, u, v, wc = _to_local(pts, g)
            if np.any(wc <= 0) or np.any(u**2 + v**2 > U2_GRID):
                worst = np.degrees(np.arcsin(np.sqrt(np.clip(np.max(np.where(wc > 0, u**2 + v**2, 1)), 0, 1))))
                raise ValueError(
                    f"grid: seen from a sub-aperture it spans up to {worst:.0f} degrees off the line of sight "
                    f"(FFBP handles up to {np.degrees(np.arcsin(np.sqrt(U2_GRID))):.0f}); image it with "
                    "formation='bp', or a grid that lies in front of the aperture")
            keep = np.ones_like(r, bool)
        else:
            pg = parent_geom[a // factor:-(-b // factor)]
            pi = parent_ints[a // factor:-(-b // factor)]
            lo = pg[:, 18:21]
            hi = lo + pg[:, 21:24] * (pi[:, 0:3] - 1)
            lat = _face_lattice(lo, hi)  # (n_parent, k, 3) in (r, u, v)
            ok = lat[..., 1] ** 2 + lat[..., 2] ** 2 <= U2_KEEP
            world = np.repeat(_polar_to_world(lat[..., 0], lat[..., 1], lat[..., 2], pg), factor, axis=0)
            ok = np.repeat(ok, factor, axis=0)
            first = a - (a // factor) * factor
            world, ok = world[first:first + b - a], ok[first:first + b - a]
            r, u, v, wc = _to_local(world, g)
            keep = ok & (wc > 0)
            if not np.all(keep.any(axis=1)):
                raise ValueError("grid: a sub-aperture sees none of its parent's grid in front of it; use "
                                 "formation='bp' for this geometry")
        box[a:b] = np.stack([np.where(keep, r, np.inf).min(1), np.where(keep, r, -np.inf).max(1),
                             np.where(keep, u, np.inf).min(1), np.where(keep, u, -np.inf).max(1),
                             np.where(keep, v, np.inf).min(1), np.where(keep, v, -np.inf).max(1)], axis=1)
    return box


def _unit_sum(p: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The sum of the unit vectors from ``x`` and from ``y`` (m, 3) to the points ``p`` (m, k, 3)."""
    out = np.zeros_like(p)
    for q in (x, y):
        d = p - q[:, None, :]
        out += d / np.sqrt(np.einsum("mkj,mkj->mk", d, d))[..., None]
    return out


def _rates(geom, box, tx, rx, c, sizes, band, f0, c_ref, chunk=2048):
    """(fr, fu, fv) per node: the largest local frequency, in cycles per metre of range and per
    unit of direction cosine, of any of its measurements' terms at any frequency of the band,
    over a 3 x 3 x 3 lattice of its region (corners, edge and face centres).

    A term of measurement m at frequency f varies as ``exp(j 2 pi (f tau_m(P) - f0 tau_ref(P)))``;
    its local frequency along a coordinate q is ``f d tau_m / dq - f0 d tau_ref / dq``, with
    ``d |P - x| / dq`` the unit vector from x to P dotted with ``dP/dq``. The lattice, the
    reference's term and the frame are the node's; only the unit vectors from each measurement's
    transducers are per measurement (their dot products with the node's frame vectors give the
    three derivatives: ``dP/dr = n``, ``dP/du = r (e1 - u/s w)``, ``dP/dv = r (e2 - v/s w)``).
    """
    nn = len(geom)
    node_of = np.repeat(np.arange(nn), sizes)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    t = np.linspace(0.0, 1.0, 3)
    tr, tu, tv = np.meshgrid(t, t, t, indexing="ij")
    unit = np.stack([tr.ravel(), tu.ravel(), tv.ravel()], axis=1)  # (k, 3)
    lo, hi = box[:, [0, 2, 4]], box[:, [1, 3, 5]]
    lat = lo[:, None, :] + unit[None] * (hi - lo)[:, None, :]  # (nn, k, 3) r, u, v
    r, u, v = lat[..., 0], lat[..., 1], lat[..., 2]
    s = np.sqrt(np.maximum(1.0 - u**2 - v**2, 0.04))
    e1, e2, w = geom[:, 3:6], geom[:, 6:9], geom[:, 9:12]
    p = geom[:, None, 0:3] + r[..., None] * (u[..., None] * e1[:, None] + v[..., None] * e2[:, None]
                                              + s[..., None] * w[:, None])

    def derivatives(vec, rows):  # (d/dr, d/du, d/dv) of the paths whose unit-vector sum is vec
        a1, a2, aw = (np.einsum("mkj,mj->mk", vec, f[rows]) for f in (e1, e2, w))
        rr, uu, vv, ss = r[rows], u[rows], v[rows], s[rows]
        return uu * a1 + vv * a2 + ss * aw, rr * (a1 - uu / ss * aw), rr * (a2 - vv / ss * aw)

    every = np.arange(nn)
    d_ref = [f0 * d / c_ref for d in derivatives(_unit_sum(p, geom[:, 12:15], geom[:, 15:18]), every)]
    per_meas = np.zeros((len(node_of), 3))
    for a in range(0, len(node_of), chunk):
        nodes = node_of[a:a + chunk]
        cm = c[a:a + chunk, None]
        d_tau = derivatives(_unit_sum(p[nodes], tx[a:a + chunk], rx[a:a + chunk]), nodes)
        for q in range(3):
            dt, dr = d_tau[q] / cm, d_ref[q][nodes]
            fq = np.maximum(np.abs(band[0] * dt - dr), np.abs(band[1] * dt - dr))
            per_meas[a:a + chunk, q] = fq.max(axis=1)
    rates = np.maximum.reduceat(per_meas, starts, axis=0)
    return rates[:, 0], rates[:, 1], rates[:, 2]


def _sample_grids(box: np.ndarray, steps: np.ndarray, taps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each node's sub-image grid over its region ``box`` (nn, 6) at no more than ``steps`` (nn, 3):
    (counts (nn, 3), origin (nn, 3) m, steps (nn, 3) m), at least ``taps`` samples per axis."""
    nn = len(box)
    counts = np.zeros((nn, 3), np.int64)
    origin = np.zeros((nn, 3))
    steps = steps.copy()
    for ax in range(3):
        lo_, hi_ = box[:, 2 * ax], box[:, 2 * ax + 1]
        extent = hi_ - lo_
        step = np.minimum(steps[:, ax], np.maximum(extent, 1e-6) / max(taps - 1, 1))
        cnt = np.maximum(np.ceil(extent / step - 1e-9).astype(np.int64) + 2, taps)
        origin[:, ax] = 0.5 * (lo_ + hi_) - 0.5 * (cnt - 1) * step
        counts[:, ax] = cnt
        steps[:, ax] = step
    return counts, origin, steps


def build_tree(
    tx: np.ndarray, rx: np.ndarray, c_mps: np.ndarray, grid_bounds: np.ndarray, band_hz: tuple[float, float], *,
    depth: int, factor: int, oversample: float, range_oversample: float, taps: int,
) -> Tree:
    """The sub-aperture tree of ``depth`` levels and the sampled grids of its sub-images.

    Parameters
    ----------
    tx, rx : (n_meas, 3) float64, m
    c_mps : (n_meas,) float64, m/s
    grid_bounds : (3, 2) first and last voxel centre on each axis, m
    band_hz : (f_lo, f_hi), Hz
        Frequencies the images hold (carrier included).
    depth, factor : int
        Levels below the root, children per node (``factor ** depth <= n_meas``).
    oversample, range_oversample : float
        Sampling rate over the Nyquist rate in the angles and in range.
    taps : int
        Interpolation stencil per axis (every grid keeps at least this many samples per axis).
    """
    f_lo, f_hi = band_hz
    f0 = 0.5 * (f_lo + f_hi)
    c_ref = float(np.mean(c_mps))
    sets, order, rank = _subapertures(0.5 * (tx + rx), depth, factor)
    tx_o, rx_o, c_o = tx[order], rx[order], c_mps[order]
    levels: list[Level] = []
    parent_geom = parent_ints = None
    for d in range(1, depth + 1):
        ints = _node_ranges(sets[d], rank, factor, last=d == depth)
        sizes, starts = ints[:, 5] - ints[:, 4], ints[:, 4]
        geom = _node_frames(tx_o, rx_o, starts, sizes, grid_bounds.mean(axis=1))
        # the region each node must cover: the grid's box (depth 1) or its parent's grid
        box = _regions(geom, grid_bounds, parent_geom, parent_ints, factor)
        # sampling: the largest local frequency of any measurement's term over the node's region
        fr, fu, fv = _rates(geom, box, tx_o, rx_o, c_o, sizes, (f_lo, f_hi), f0, c_ref)
        steps = np.stack([1.0 / (2 * fr * range_oversample), 1.0 / (2 * np.maximum(fu, 1e-9) * oversample),
                          1.0 / (2 * np.maximum(fv, 1e-9) * oversample)], axis=1)
        levels.append(_sampled_level(geom, ints, *_sample_grids(box, steps, taps)))
        parent_geom, parent_ints = geom, ints
    return Tree(order, levels, factor, f0, c_ref, (f_lo, f_hi))


def _subapertures(centres: np.ndarray, depth: int, factor: int):
    """The tree's node sets, top down (each a list of measurement index arrays), the measurement
    order its leaves give, and each measurement's rank in that order."""
    n = len(centres)
    sets = [[np.arange(n)]]
    parts = split_sizes(factor)
    for _ in range(depth):
        sets.append([child for s in sets[-1] for child in _split(s, centres, parts)])
    order = np.concatenate(sets[-1]) if depth else np.arange(n)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    return sets, order, rank


def _node_ranges(nodes, rank: np.ndarray, factor: int, last: bool) -> np.ndarray:
    """A level's integer record: each node's first and past-last measurement in the leaf order and,
    above the leaves, its first and past-last child."""
    nn = len(nodes)
    ints = np.zeros((nn, NI), np.int64)
    ints[:, 4] = [rank[s].min() for s in nodes]
    ints[:, 5] = [rank[s].max() + 1 for s in nodes]
    if not last:
        ints[:, 6] = np.arange(nn) * factor
        ints[:, 7] = ints[:, 6] + factor
    return ints


def _node_frames(tx_o: np.ndarray, rx_o: np.ndarray, starts: np.ndarray, sizes: np.ndarray,
                 target: np.ndarray) -> np.ndarray:
    """A level's geometry record: each node's phase centre, its frame facing ``target`` and its mean
    speaker and microphone positions (the sampled grid's part is filled by :func:`_sampled_level`)."""
    nn = len(sizes)
    t_mean = np.add.reduceat(tx_o, starts) / sizes[:, None]
    r_mean = np.add.reduceat(rx_o, starts) / sizes[:, None]
    geom = np.zeros((nn, NG))
    geom[:, 0:3] = 0.5 * (t_mean + r_mean)
    geom[:, 3:12] = _frames(geom[:, 0:3], target).reshape(nn, 9)
    geom[:, 12:15] = t_mean
    geom[:, 15:18] = r_mean
    return geom


def _sampled_level(geom: np.ndarray, ints: np.ndarray, counts: np.ndarray, origin: np.ndarray,
                   steps: np.ndarray) -> Level:
    """The level with its nodes' sampled grids (origin, steps, counts) and their offsets in one
    buffer, each padded to whole blocks."""
    geom[:, 18:21] = origin
    geom[:, 21:24] = steps
    geom[:, 24:27] = 1.0 / steps
    ints[:, 0:3] = counts
    per_node = np.prod(counts, axis=1)
    padded = -(-per_node // BLOCK) * BLOCK
    ints[:, 3] = np.concatenate([[0], np.cumsum(padded)[:-1]])
    return Level(geom, ints, int(padded.sum()))
