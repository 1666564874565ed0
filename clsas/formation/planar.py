"""Planar, uniform apertures: the lattice behind a set of measurements, and its well-sampled cone.

A planar uniform aperture has every speaker and microphone on one plane normal to a grid axis,
the midpoints of the speaker-microphone pairs on a regular 2-D lattice (every lattice point
once, in any visiting order: raster, serpentine, shuffled) and one fixed speaker-microphone
offset. Several microphones per stop give one such lattice per offset (a *group*); the
wavenumber-domain formation (:mod:`clsas.formation.omega_k`) images each group and sums them.

The well-sampled cone
---------------------
A lattice with spacing ``d`` samples the data's spatial frequency up to ``pi / d`` (rad/m). The
echo of a voxel seen from a stop at angle ``theta`` from the plane's normal varies along that
axis at ``2 k sin(theta)`` (``k = 2 pi f / c``, two-way path), so the aperture samples it without
aliasing while ``2 k_max sin(theta) <= pi / d``, i.e. ``sin(theta) <= c / (4 f_max d)`` (a stop
spacing of lambda/4 covers every angle). :func:`well_sampled_cone` marks the voxels that *every*
stop of the aperture sees within that angle on both lattice axes, with a margin (``margin``,
default 0.8 of the limit). This is the region where a wavenumber-domain formation on the
aperture's own lattice reproduces backprojection; outside it, backprojection adds contributions
of stops that see the voxel at aliased angles (the grating lobes), which ω-k does not form. The
benchmark (:mod:`bench.formation`) and the tests measure errors inside this mask.
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass

import numpy as np

from .. import validate as v
from ..physics.geometry import VoxelGrid

__all__ = ["Lattice", "PlanarAperture", "NotPlanarUniform", "planar_aperture", "well_sampled_cone", "cone_of"]

ALTERNATIVES = "use formation='ffbp' (any trajectory) or formation='bp' (exact backprojection) instead"


class NotPlanarUniform(ValueError):
    """The measurements do not form a planar, uniform aperture (the message says why)."""

    def __init__(self, why: str):
        self.why = why
        super().__init__(f"omega-k needs a planar, uniform aperture: {why}; {ALTERNATIVES}")


@dataclass(frozen=True)
class Lattice:
    """One offset group: measurements whose midpoints lie on a regular lattice of the plane.

    Coordinates are in the aperture frame ``(u, v, w)``: ``w`` is the plane's normal axis.
    """

    index: np.ndarray  # (n,) the measurements of this group
    iu: np.ndarray  # (n,) lattice column of each measurement
    iv: np.ndarray  # (n,) lattice row
    origin_uv: tuple[float, float]  # midpoint of lattice point (0, 0), m
    spacing_uv: tuple[float, float]  # lattice spacing, m
    shape: tuple[int, int]  # (n_u, n_v)
    baseline_uvw: np.ndarray  # (3,) speaker minus microphone, m (in the plane: w = 0)

    @property
    def extent_uv(self) -> np.ndarray:
        """(2, 2) first and last lattice coordinate along u and v, m."""
        o, d, n = np.asarray(self.origin_uv), np.asarray(self.spacing_uv), np.asarray(self.shape)
        return np.stack([o, o + d * (n - 1)], axis=1)


@dataclass(frozen=True)
class PlanarAperture:
    """The plane (normal along grid axis ``axis`` at ``w_m``) and its offset groups."""

    axis: int  # 0, 1 or 2: the normal's grid axis
    w_m: float  # the plane's coordinate along that axis
    groups: tuple[Lattice, ...]

    @property
    def perm(self) -> tuple[int, int, int]:
        """Grid axes in aperture order (u, v, w)."""
        return {0: (1, 2, 0), 1: (2, 0, 1), 2: (0, 1, 2)}[self.axis]


def _axis_values(values: np.ndarray, tol: float, what: str) -> tuple[np.ndarray, float, float, int]:
    """Lattice indices of ``values`` on an evenly spaced axis: (index, origin, spacing, count)."""
    order = np.argsort(values, kind="stable")
    sv = values[order]
    breaks = np.flatnonzero(np.diff(sv) > tol)
    starts = np.r_[0, breaks + 1]
    centres = np.array([sv[s:e].mean() for s, e in zip(starts, np.r_[starts[1:], len(sv)], strict=True)])
    n = len(centres)
    if n < 2:
        raise NotPlanarUniform(f"the stops span a single {what} value (a lattice needs at least 2 per axis)")
    step = (centres[-1] - centres[0]) / (n - 1)
    if np.max(np.abs(centres - (centres[0] + step * np.arange(n)))) > tol:
        raise NotPlanarUniform(f"the stops' {what} coordinates are not evenly spaced (tolerance {tol:.2g} m)")
    idx = np.empty(len(values), np.int64)
    idx[order] = np.repeat(np.arange(n), np.diff(np.r_[starts, len(sv)]))
    if np.max(np.abs(values - (centres[0] + step * idx))) > tol:
        raise NotPlanarUniform(f"a stop is off the lattice along {what} by more than {tol:.2g} m")
    return idx, float(centres[0]), float(step), n


def planar_aperture(tx: np.ndarray, rx: np.ndarray, grid: VoxelGrid, tol_m: float) -> PlanarAperture:
    """Find the plane, offset groups and lattices of ``tx``/``rx``, or raise :class:`NotPlanarUniform`.

    Parameters
    ----------
    tx, rx : (n, 3) arrays
        Speaker and microphone positions, m.
    grid : VoxelGrid
        The image grid: it must lie on one side of the plane, off it.
    tol_m : float
        How far a position may be off the plane or off the lattice, m (a position error e
        costs a phase of up to 2 k e).
    """
    key = _aperture_key(tx, rx, grid, tol_m)
    with _APERTURES_LOCK:
        hit = _APERTURES.get(key)
    if hit is not None:
        if isinstance(hit, NotPlanarUniform):
            raise NotPlanarUniform(hit.why)
        return hit
    try:
        ap = _planar_aperture(tx, rx, grid, tol_m)
    except NotPlanarUniform as exc:
        _remember(key, exc)
        raise
    _remember(key, ap)
    return ap


# formation="auto" sizes omega-k (planar_aperture) and omega-k then forms the image: the same
# analysis twice per request, a few ms each at 1e3-1e4 stops; the last few are remembered by
# the positions' digest (their bytes, the grid's axes and the tolerance), answers and refusals
_APERTURES: dict[bytes, object] = {}
_APERTURES_KEPT = 8
_APERTURES_LOCK = threading.Lock()  # Dask workers' threads may form images side by side


def _aperture_key(tx: np.ndarray, rx: np.ndarray, grid: VoxelGrid, tol_m: float) -> bytes:
    h = hashlib.blake2b(digest_size=20)
    for a in (tx, rx, grid.x_m, grid.y_m, grid.z_m):
        a = np.ascontiguousarray(a, np.float64)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(np.float64(tol_m).tobytes())
    return h.digest()


def _remember(key: bytes, value) -> None:
    with _APERTURES_LOCK:
        _APERTURES.pop(key, None)
        _APERTURES[key] = value
        while len(_APERTURES) > _APERTURES_KEPT:
            _APERTURES.pop(next(iter(_APERTURES)))


def _planar_aperture(tx: np.ndarray, rx: np.ndarray, grid: VoxelGrid, tol_m: float) -> PlanarAperture:
    pts = np.concatenate([tx, rx])
    bounds = grid.bounds()
    candidates = [a for a in (2, 0, 1) if np.ptp(pts[:, a]) <= 2 * tol_m]
    if not candidates:
        raise NotPlanarUniform(f"the speakers and microphones are not on one plane normal to x, y or z "
                               f"(within {tol_m:.2g} m)")
    axis = None
    for a in candidates:
        w = float(np.mean(pts[:, a]))
        if bounds[a, 0] > w or bounds[a, 1] < w:
            axis = a
            break
    if axis is None:
        _groups(tx, rx, candidates[0], tol_m)  # a stop pattern that is no lattice says so first
        raise NotPlanarUniform("the grid crosses the aperture's plane (it must lie on one side of it)")
    return PlanarAperture(axis, float(np.mean(pts[:, axis])), _groups(tx, rx, axis, tol_m))


def _groups(tx: np.ndarray, rx: np.ndarray, axis: int, tol_m: float) -> tuple[Lattice, ...]:
    """The offset groups and their lattices in the plane normal to ``axis``."""
    perm = {0: (1, 2, 0), 1: (2, 0, 1), 2: (0, 1, 2)}[axis]
    mid = 0.5 * (tx + rx)[:, perm]
    base = (tx - rx)[:, perm]
    # offset groups: one per distinct speaker-microphone offset
    key = np.round(base / max(tol_m, 1e-12)).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    n_groups = int(inverse.max()) + 1
    if n_groups > 1 and n_groups * 4 > len(tx):
        raise NotPlanarUniform(f"the speaker-microphone offset changes from stop to stop ({n_groups} different "
                               f"offsets in {len(tx)} measurements; a rotating rig?)")
    groups = []
    for g in range(inverse.max() + 1):
        index = np.flatnonzero(inverse == g)
        b = base[index]
        if np.max(np.abs(b - b.mean(axis=0))) > tol_m:
            raise NotPlanarUniform(f"the speaker-microphone offset varies by more than {tol_m:.2g} m")
        iu, u0, du, nu = _axis_values(mid[index, 0], tol_m, "u (first in-plane axis)")
        iv, v0, dv, nv = _axis_values(mid[index, 1], tol_m, "v (second in-plane axis)")
        flat = iu * nv + iv
        if len(index) != nu * nv or len(np.unique(flat)) != len(flat):
            raise NotPlanarUniform(f"{len(index)} measurements do not fill a {nu} x {nv} lattice once each "
                                   "(missing or repeated stops)")
        bl = b.mean(axis=0)
        bl[2] = 0.0
        for a in (index, iu, iv, bl):  # shared by every caller of a remembered aperture
            a.setflags(write=False)
        groups.append(Lattice(index, iu, iv, (u0, v0), (du, dv), (nu, nv), bl))
    return tuple(groups)


def _max_sin(lateral: np.ndarray, other: np.ndarray, depth: np.ndarray) -> np.ndarray:
    return np.abs(lateral) / np.sqrt(lateral**2 + other**2 + depth**2)


def well_sampled_cone(tx: np.ndarray, rx: np.ndarray, grid: VoxelGrid, f_max_hz: float, c_mps: float,
                      margin: float = 0.8, tol_m: float | None = None) -> np.ndarray:
    """Boolean mask (grid.shape) of the voxels that every stop sees at an unaliased angle.

    A voxel is inside when, for every lattice group and every stop (its speaker-microphone
    midpoint), ``2 (2 pi f_max / c) sin(theta_a) <= margin * pi / d_a`` on each lattice axis
    ``a``, where ``sin(theta_a)`` is the direction cosine of the stop-to-voxel line along that
    axis and ``d_a`` the lattice spacing. Raises :class:`NotPlanarUniform` when the aperture
    has no lattice (the cone is not defined for it).

    Parameters
    ----------
    tx, rx : (n, 3) arrays, m
    grid : VoxelGrid
    f_max_hz : float
        Highest frequency imaged (the band's top), Hz.
    c_mps : float
        Speed of sound, m/s.
    margin : float
        Fraction of the Nyquist angle's sine that counts as well sampled (default 0.8).
    tol_m : float, optional
        Lattice tolerance (default ``c / f_max / 100``).
    """
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    tx = v.array("tx", tx, shape=(None, 3))
    rx = v.array("rx", rx, shape=(len(tx), 3))
    f_max_hz = v.positive("f_max_hz", f_max_hz)
    c_mps = v.positive("c_mps", c_mps)
    margin = v.positive("margin", margin)
    tol = c_mps / f_max_hz / 100 if tol_m is None else v.positive("tol_m", tol_m)
    return cone_of(planar_aperture(tx, rx, grid, tol), grid, f_max_hz, c_mps, margin)


def cone_of(ap: PlanarAperture, grid: VoxelGrid, f_max_hz: float, c_mps: float, margin: float = 0.8,
            max_sine: float = 1.0) -> np.ndarray:
    """:func:`well_sampled_cone` of an aperture already analysed (``planar_aperture``'s result
    for this grid; arguments as there, not validated again). ``max_sine``: the sine of the
    steepest angle from the normal at which a stop contributes at all (a transducer beam's edge,
    1 without beams): pairs beyond it are left out by bp and ω-k alike, so their aliasing does
    not count."""
    axes = [grid.x_m, grid.y_m, grid.z_m]
    pu, pv, pw = (axes[i] for i in ap.perm)
    U, V, W = np.meshgrid(pu, pv, np.abs(pw - ap.w_m), indexing="ij")
    k2 = 2 * 2 * np.pi * f_max_hz / c_mps
    inside = np.ones(U.shape, bool)
    for g in ap.groups:
        (u0, u1), (v0, v1) = g.extent_uv
        # nearest in-plane distance to the lattice's rectangle along the other axis
        dv = np.maximum(0.0, np.maximum(v0 - V, V - v1))
        du = np.maximum(0.0, np.maximum(u0 - U, U - u1))
        su = np.minimum(np.maximum(_max_sin(U - u0, dv, W), _max_sin(U - u1, dv, W)), max_sine)
        sv = np.minimum(np.maximum(_max_sin(V - v0, du, W), _max_sin(V - v1, du, W)), max_sine)
        inside &= (k2 * su <= margin * np.pi / g.spacing_uv[0]) & (k2 * sv <= margin * np.pi / g.spacing_uv[1])
    # back to the grid's (x, y, z) order
    inv = np.argsort(ap.perm)
    return np.transpose(inside, inv)
