"""The ``"track"`` motion step of :func:`clsas.autofocus`, and the check that compares where things are.

:func:`track_step` estimates one line-of-sight path per stop from the phase differences of
neighbouring stops (:mod:`.track`), gauge-fixed (constant and tilt across the aperture set to
zero), and judges it *determined* where the even and the odd stops, tracked on their own, give
the same path to within ``tolerance_m`` (one way, RMS), or where the two sides of the target,
tracked on their own with every stop, give it to within :data:`REGION_TOLERANCE_M`.

:func:`where_check` does not trust any similarity of images: it compares positions. Two
disjoint sub-apertures' images (first and second half of the stops in time; left and right)
must still find each other's brightest points bright after the correction (a correction that
focuses each on a scatterer of its own moves them apart); and the brightest voxel of the whole
image must not move by more than two resolution cells unless the sub-apertures agree on its new
place.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .track import gauge_free, half_agreement, region_agreement, track_phases

__all__ = ["track_step", "where_check", "resolution_cell_m"]

log = logging.getLogger("clsas.autofocus")


#: The two sides of the target (:func:`.track.region_agreement`) must give one path to within
#: this, m RMS one way, for the motion to be determined when the even and the odd stops do not
#: (halving the stops doubles their pitch, and on a surface that alone can decorrelate the
#: neighbours). Tuning sets 0-11 and 2000-2029 of the family: the sides agreed to 0.26-0.37 mm
#: where the path was within 0.5 rad of the truth, 0.70-7.1 mm where it was 0.86-2.2 rad off.
REGION_TOLERANCE_M = 0.5e-3

#: Most voxels the stop images keep (the brightest of the uncorrected image): time and memory.
MAX_VOXELS = 20_000


def _stop_images(engine, shift, c, stop, max_bytes, rep):
    """Each stop's image on the grid, or on its brightest voxels (memory, :data:`MAX_VOXELS`),
    and those voxels' positions (n_vox, 3), m."""
    n_stops = int(stop.max()) + 1
    voxels = None
    keep = min(max(int(max_bytes // (8 * n_stops)), 1), MAX_VOXELS)
    if engine.grid.size > keep:
        values = engine.image(shift, c)
        voxels = np.sort(np.argsort(np.abs(values))[-keep:])
        rep.notes.append(f"track: stop images on the {keep} brightest of {engine.grid.size} voxels")
    points = engine.grid.points()
    return engine.stop_images(shift, c, stop, voxels), points if voxels is None else points[voxels]


def track_step(fo, shift, c, stop, t_stop, xy, max_bytes: int, tolerance_m: float) -> tuple[np.ndarray, dict]:
    """``(p_stop, info)``: per-stop path corrections (true minus stated, two-way, m; constant and
    tilt removed) and ``info`` with ``determined``, ``halves_rms_m`` (one way), ``coherence_median``."""
    t = time.perf_counter()
    engine, rep = fo.engine, fo.rep
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    n_stops = len(first)
    if n_stops < 8:
        return np.zeros(n_stops), {"determined": False, "why": "fewer than 8 stops"}
    a, points = _stop_images(engine, shift, c, stop, max_bytes, rep)
    phi, info = track_phases(a, t_stop, xy)
    phi_even, phi_odd = half_agreement(a, t_stop, xy)
    phi_a, phi_b = region_agreement(a, points, t_stop, xy)
    del a
    to_path = np.asarray(c, float)[first] / (2 * np.pi * engine.prof.fc_hz)
    p = gauge_free(phi * to_path, xy)

    def apart(x, y):  # RMS difference of two paths, one way, gauge removed, m
        return float(np.sqrt(np.mean(gauge_free((x - y) * to_path, xy) ** 2)) / 2)

    info["halves_rms_m"] = apart(phi_even, phi_odd)
    info["regions_rms_m"] = apart(phi_a, phi_b)
    info["rms_m"] = float(np.sqrt(np.mean(p**2)) / 2)
    info["determined"] = bool(info["halves_rms_m"] <= tolerance_m or info["regions_rms_m"] <= REGION_TOLERANCE_M)
    info["time_s"] = time.perf_counter() - t
    rep.stages.append({"step": "track", **info})
    log.info("autofocus track: %.2f mm RMS (one way), halves differ by %.2f mm, coherence %.2f",
             info["rms_m"] * 1e3, info["halves_rms_m"] * 1e3, info["coherence_median"])
    return p, info


def resolution_cell_m(ds, centre: np.ndarray) -> float:
    """The larger of the range resolution ``c / 2B`` and the cross-range ``lambda R / 2D`` at ``centre``, m."""
    f0, f1 = ds.chirp.get("f_start_hz"), ds.chirp.get("f_stop_hz")
    c = float(np.mean(ds.c_per_meas))
    if not f0 or not f1:
        return 0.02
    mid = 0.5 * (ds.tx_positions + ds.rx_positions)
    r = float(np.median(np.linalg.norm(mid - centre, axis=1)))
    span = float(max(np.ptp(mid[:, 0]), np.ptp(mid[:, 1]), 1e-3))
    lam = c / (0.5 * (f0 + f1))
    return max(c / (2 * abs(f1 - f0)), lam * r / (2 * span))


def _support(values: np.ndarray, points: np.ndarray, at: np.ndarray, radius_m: float) -> float:
    """The brightest ``|values|`` within ``radius_m`` of ``at``, over the brightest anywhere (0 to 1)."""
    mag = np.abs(values)
    near = np.linalg.norm(points - at, axis=1) <= radius_m
    return float(mag[near].max(initial=0.0) / max(float(mag.max()), 1e-300))


def _mutual(va, vb, points, radius_m) -> float:
    """How well two images agree on where their brightest points are: each one's brightest point
    is this bright (relative to its own brightest) in the other, the smaller of the two."""
    pa, pb = points[int(np.argmax(np.abs(va)))], points[int(np.argmax(np.abs(vb)))]
    return min(_support(vb, points, pa, radius_m), _support(va, points, pb, radius_m))


def where_check(fo, shift, c, move, *, drop: float = 0.1, enough: float = 0.5, moved_cells: float = 2.0) -> dict:
    """Positions before and after the correction ``move`` (n_meas, 3), and whether it passes.

    For each pair of disjoint sub-apertures (:attr:`fo.splits`), the *mutual support*: each
    image's brightest point, how bright the other image is within a resolution cell of it
    (relative to its own brightest), the smaller of the two. After the correction it must not
    fall by more than ``drop``, unless it is at least ``enough``: the sub-apertures must not put
    their brightest points in places the other finds dim. And the whole image's brightest point
    may move by more than ``moved_cells`` cells only where every sub-aperture is at least half
    as bright at its new place as at its own brightest.
    """
    points = fo.engine.grid.points()
    full0 = fo.engine.image(shift, c)
    full1 = fo.engine.image(shift, c, fo.ds.tx_positions + move, fo.ds.rx_positions + move)
    p0, p1 = points[int(np.argmax(np.abs(full0)))], points[int(np.argmax(np.abs(full1)))]
    cell = resolution_cell_m(fo.ds, p1)
    out = {"cell_m": cell, "peak_moved_m": float(np.linalg.norm(p1 - p0))}
    passed = True
    at_new = []
    for name, (a, b) in zip(fo.split_names, fo.splits, strict=False):
        va1, vb1 = a.image(shift, c, move), b.image(shift, c, move)
        m0 = _mutual(a.image(shift, c), b.image(shift, c), points, cell)
        m1 = _mutual(va1, vb1, points, cell)
        out[f"{name}_support_before"], out[f"{name}_support_after"] = m0, m1
        passed &= m1 >= m0 - drop or m1 >= enough
        at_new.append(min(_support(va1, points, p1, cell), _support(vb1, points, p1, cell)) >= 0.5)
    if out["peak_moved_m"] > moved_cells * cell and not all(at_new):
        passed = False
    out["passed"] = bool(passed)
    return out
