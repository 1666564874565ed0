"""Per-stop line-of-sight paths from the image's strong points, as one pattern they share (``"points"``).

A stop's contribution to a point scatterer's voxel is ``alpha_k exp(j phi_s)`` (plus the other
echoes of the same range shell and noise): the point's own amplitude, and the stop's path error as
a phase, the same for every point. So the matrix ``a_sk`` of the stops' contributions to the
strong points is rank one, and its left singular vector (columns normalised) holds the stops'
phases: no point's phase is taken as a reference, no image has to be in focus first, and no
focus metric is maximised. The phases are unwrapped in time order (a hand moves smoothly: at 50
stops a second the path changes by well under a quarter wavelength from one stop to the next),
fitted in a band-limited basis of stop time plus the tilt (:func:`.track.smooth_basis`), turned
into a path, and the constant and the tilt across the aperture (the gauge) removed. The points
are the local maxima of the corrected image, picked again after each update (a point whose
voxel is off its true place by a few millimetres adds its own tilt, which the gauge removes and
the other points average).

Where the scene has no isolated points (an extended surface, speckle) the matrix is not rank
one: a speckle blob's phase changes with the look angle. Measured on the tuning seeds of the
scene family, the per-point coherence ``|sum_s a_sk|^2 / (n sum_s |a_sk|^2)`` of the points
after the correction has a median of 0.18-0.67 on point scenes and 0.03-0.13 on surfaces and
sphere caps (with one plane at 0.34); the estimate is *determined* only at :data:`MIN_COHERENCE`
or more, and with at least :data:`MIN_POINTS` points.

With the scatterers' true positions the estimate reaches 0.13-0.15 mm RMS (one way) on the
tuning point scenes at 3 mm of hand motion; with the picked positions it converges to
0.16-0.35 mm in 6 passes.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .pga import _coherence, _per_stop, local_maxima, point_samples
from .track import DEFAULT_CUTOFF_HZ, gauge_free, smooth_basis

__all__ = ["DYNAMIC_RANGE_DB", "MIN_COHERENCE", "MIN_POINTS", "MIN_STOPS", "pick_points", "common_phases",
           "points_paths"]

log = logging.getLogger("clsas.autofocus")

#: Least median coherence of the points after the correction for the estimate to count (see above).
MIN_COHERENCE = 0.15
#: Fewest points the estimate needs (two already tell a shared phase from each one's own: family seed 22 has two).
MIN_POINTS = 2
#: Fewest stops: a path smooth in the hand's band has to be fewer functions than there are stops.
MIN_STOPS = 8
#: A point whose contributions correlate less than this with the common pattern is dropped.
MIN_SHARE = 0.3


#: Points are picked within this of the brightest, dB: a defocused point's own side lobes reach
#: 14-20 dB under its peak, and a side lobe taken as a point has phases of its own (family seed
#: 22: two points, six picks and no estimate within 20 dB; the two points within 14).
DYNAMIC_RANGE_DB = 14.0


def pick_points(grid, values: np.ndarray, *, max_points: int = 12, min_separation_m: float = 0.02,
                dynamic_range_db: float = DYNAMIC_RANGE_DB) -> np.ndarray:
    """(K, 3) positions, m: the brightest local maxima of ``|values|`` within ``dynamic_range_db``
    (:func:`.pga.local_maxima`), left where they are (not moved to their peaks: in a defocused
    image that moves them, and the estimate, with the blur)."""
    return local_maxima(grid, values, max_points=max_points, min_separation_m=min_separation_m,
                        dynamic_range_db=dynamic_range_db)


def common_phases(a_stop: np.ndarray) -> tuple[np.ndarray, int]:
    """``(z, kept)``: per stop, the complex gain the points share (``a_stop`` (n_stops, K), its
    columns normalised; the left singular vector of the largest singular value, weighted by it),
    and how many points were kept (those correlating at least :data:`MIN_SHARE` with it)."""
    m = a_stop / np.maximum(np.linalg.norm(a_stop, axis=0), 1e-300)
    u, _, vh = np.linalg.svd(m, full_matrices=False)
    share = np.abs(u[:, 0].conj() @ m)
    keep = share >= MIN_SHARE
    if 2 <= keep.sum() < len(keep):
        m = m[:, keep]
        _, _, vh = np.linalg.svd(m, full_matrices=False)
    return m @ vh[0].conj(), int(keep.sum())


def smooth_unwrapped(z: np.ndarray, t: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The phases of ``z`` unwrapped in time order and fitted in ``basis`` (weights ``|z|^2``, capped
    at 4 times their median), rad. Stops under a tenth of the median weight take no part in the
    unwrapping (a near-zero gain has a random phase, and a slip there would shift every later
    stop by a turn): each is unwrapped against its neighbours' phase, interpolated in time."""
    w = np.abs(z) ** 2
    order = np.argsort(t, kind="stable")
    good = order[w[order] >= 0.1 * np.median(w)]
    ph = np.empty(len(z))
    if len(good) < 2:
        good = order
    ph[good] = np.unwrap(np.angle(z[good]))
    rest = np.setdiff1d(order, good)
    if len(rest):
        near = np.interp(t[rest], t[good], ph[good])
        ph[rest] = near + np.angle(z[rest] * np.exp(-1j * near))
    sw = np.sqrt(np.minimum(w, 4 * np.median(w)))
    coef, *_ = np.linalg.lstsq(basis * sw[:, None], ph * sw, rcond=None)
    return basis @ coef


def points_paths(engine, shift: np.ndarray, c: np.ndarray, stop: np.ndarray, t_stop: np.ndarray, xy: np.ndarray, *,
                 min_separation_m: float, max_points: int = 12, cutoff_hz: float = DEFAULT_CUTOFF_HZ, n_iter: int = 6,
                 tol_m: float = 2e-5) -> tuple[np.ndarray, dict]:
    """``(p_stop, info)``: per-stop path corrections (true minus stated, two-way, m; gauge removed)
    from the strong points (module docstring), and ``info`` with ``points``, ``coherence``
    (median after the correction), ``iterations``, ``update_rms_m`` and ``determined``."""
    started = time.perf_counter()
    ds = engine.ds
    n_stops = len(t_stop)
    info: dict = {"update_rms_m": [], "iterations": 0, "points": 0, "coherence": 0.0, "determined": False}
    if n_stops < MIN_STOPS:
        info["why"] = f"{n_stops} stops (at least {MIN_STOPS} needed for a smooth path to be told from its noise)"
        return np.zeros(n_stops), info
    c = np.broadcast_to(np.asarray(c, float), (ds.n_meas,))
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    to_path = c[first] / (2 * np.pi * engine.prof.fc_hz)
    basis = smooth_basis(np.asarray(t_stop, float), xy, cutoff_hz)
    p = np.zeros(n_stops)
    pts = np.zeros((0, 3))
    for _ in range(n_iter):
        sh = shift - p[stop] / c
        pts = pick_points(engine.grid, engine.image(sh, c), max_points=max_points, min_separation_m=min_separation_m)
        if len(pts) < MIN_POINTS:
            info["why"] = f"{len(pts)} local maxima within {DYNAMIC_RANGE_DB:g} dB (at least {MIN_POINTS} needed)"
            return np.zeros(n_stops), info
        a, _ = point_samples(engine, sh, c, ds.tx_positions, ds.rx_positions, pts)
        z, info["points"] = common_phases(_per_stop(a, stop, n_stops))
        new = gauge_free(p - smooth_unwrapped(z, t_stop, basis) * to_path, xy)
        rms = float(np.sqrt(np.mean((new - p) ** 2)) / 2)  # the change, gauge removed (one way)
        p = new
        info["update_rms_m"].append(rms)
        info["iterations"] += 1
        if rms < tol_m:
            break
    sh = shift - p[stop] / c  # the points of the corrected image, and how coherent they now are
    pts = pick_points(engine.grid, engine.image(sh, c), max_points=max_points, min_separation_m=min_separation_m)
    if len(pts) >= MIN_POINTS:
        a, _ = point_samples(engine, sh, c, ds.tx_positions, ds.rx_positions, pts)
        info["coherence"] = float(np.median(_coherence(_per_stop(a, stop, n_stops))))
    info["determined"] = bool(info["coherence"] >= MIN_COHERENCE and info["points"] >= MIN_POINTS
                              and len(pts) >= MIN_POINTS)
    if len(pts) < MIN_POINTS or info["points"] < MIN_POINTS:
        info["why"] = (f"{min(len(pts), info['points'])} point(s) share the stops' phases (at least {MIN_POINTS} "
                       "needed)")
    elif not info["determined"]:
        info["why"] = (f"the points' median coherence after the correction is {info['coherence']:.2f} (under "
                       f"{MIN_COHERENCE:g}: not isolated points, an extended surface or speckle)")
    info["rms_m"] = float(np.sqrt(np.mean(p**2)) / 2)
    info["time_s"] = time.perf_counter() - started
    log.info("autofocus points: %d points, %d passes, %.2f mm RMS (one way), coherence %.2f", info["points"],
             info["iterations"], info["rms_m"] * 1e3, info["coherence"])
    return p, info
