"""The ``"track"`` motion step of :func:`clsas.autofocus`, and the check that compares where things are.

:func:`track_step` estimates one line-of-sight path per stop from the phase differences of
neighbouring stops (:mod:`.track`), gauge-fixed (constant and tilt across the aperture set to
zero), and judges it *determined* where the even and the odd stops, tracked on their own, give
the same path to within ``tolerance_m`` (one way, RMS).

:func:`where_check` does not trust any similarity of images: it compares positions. The
brightest voxel of each of two disjoint sub-apertures' images (first and second half of the
stops in time; left and right) must not lie farther apart after the correction than before
(plus a resolution cell); and the brightest voxel of the whole image must not move by more than
two resolution cells unless the sub-apertures agree on its new place.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .track import gauge_free, half_agreement, track_phases

__all__ = ["track_step", "where_check", "resolution_cell_m"]

log = logging.getLogger("clsas.autofocus")


#: Most voxels the stop images keep (the brightest of the uncorrected image): time and memory.
MAX_VOXELS = 20_000


def _stop_images(engine, shift, c, stop, max_bytes, rep):
    """Each stop's image on the grid, or on its brightest voxels (memory, :data:`MAX_VOXELS`)."""
    n_stops = int(stop.max()) + 1
    voxels = None
    keep = min(max(int(max_bytes // (8 * n_stops)), 1), MAX_VOXELS)
    if engine.grid.size > keep:
        values = engine.image(shift, c)
        voxels = np.sort(np.argsort(np.abs(values))[-keep:])
        rep.notes.append(f"track: stop images on the {keep} brightest of {engine.grid.size} voxels")
    return engine.stop_images(shift, c, stop, voxels)


def track_step(fo, shift, c, stop, t_stop, xy, max_bytes: int, tolerance_m: float) -> tuple[np.ndarray, dict]:
    """``(p_stop, info)``: per-stop path corrections (true minus stated, two-way, m; constant and
    tilt removed) and ``info`` with ``determined``, ``halves_rms_m`` (one way), ``coherence_median``."""
    t = time.perf_counter()
    engine, rep = fo.engine, fo.rep
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    n_stops = len(first)
    if n_stops < 8:
        return np.zeros(n_stops), {"determined": False, "why": "fewer than 8 stops"}
    a = _stop_images(engine, shift, c, stop, max_bytes, rep)
    phi, info = track_phases(a, t_stop, xy)
    phi_even, phi_odd = half_agreement(a, t_stop, xy)
    del a
    to_path = np.asarray(c, float)[first] / (2 * np.pi * engine.prof.fc_hz)
    p = gauge_free(phi * to_path, xy)
    halves = gauge_free((phi_even - phi_odd) * to_path, xy)
    info["halves_rms_m"] = float(np.sqrt(np.mean(halves**2)) / 2)
    info["rms_m"] = float(np.sqrt(np.mean(p**2)) / 2)
    info["determined"] = bool(info["halves_rms_m"] <= tolerance_m)
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


def _peak(values, points):
    return points[int(np.argmax(np.abs(values)))]


def where_check(fo, shift, c, move, cells: float = 1.0, moved_cells: float = 2.0) -> dict:
    """Positions before and after the correction ``move`` (n_meas, 3), and whether it passes.

    Each pair of sub-apertures' brightest points must not lie more than ``cells`` resolution
    cells farther apart than before; the whole image's brightest point may move by more than
    ``moved_cells`` only where every sub-aperture puts its own within ``moved_cells`` of the
    new place (on the tuning seeds a right correction moved it by up to 1.9 cells: the
    defocused image's brightest point is not always the scene's).
    """
    points = fo.engine.grid.points()
    before_full = _peak(fo.engine.image(shift, c), points)
    after_full = _peak(fo.engine.image(shift, c, fo.ds.tx_positions + move, fo.ds.rx_positions + move), points)
    cell = resolution_cell_m(fo.ds, after_full)
    out = {"cell_m": cell, "peak_moved_m": float(np.linalg.norm(after_full - before_full))}
    passed = True
    agree_at_new = []
    for name, (a, b) in zip(fo.split_names, fo.splits, strict=False):
        pa0, pb0 = _peak(a.image(shift, c), points), _peak(b.image(shift, c), points)
        pa1, pb1 = _peak(a.image(shift, c, move), points), _peak(b.image(shift, c, move), points)
        d0, d1 = float(np.linalg.norm(pa0 - pb0)), float(np.linalg.norm(pa1 - pb1))
        out[f"{name}_apart_before_m"], out[f"{name}_apart_after_m"] = d0, d1
        passed &= d1 <= d0 + cells * cell
        agree_at_new.append(max(np.linalg.norm(pa1 - after_full), np.linalg.norm(pb1 - after_full))
                            <= moved_cells * cell)
    if out["peak_moved_m"] > moved_cells * cell and not all(agree_at_new):
        passed = False
    out["passed"] = bool(passed)
    return out
