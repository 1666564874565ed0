"""The calibration of ``formation="auto"``'s cost model for one device (``clsas calibrate``).

``auto`` predicts each formation's time from counted work and a built-in model fitted on one
2-core CPU (:mod:`.timing`). On another device the times differ by a factor per formation;
:func:`calibrate_auto` measures it: dense planar scans of N x N stops 5.6 mm apart (about
lambda/2 at 30 kHz), three reflectors at 0.62-0.70 m, onto grids that grow with the aperture
(4 mm voxels over the middle two thirds of the aperture laterally, 0.58-0.74 m deep). For each N
it times bp, omega-k and FFBP at their defaults on the device (FFBP's remembered tree forgotten
first, so that its planning is timed; a call under 2 s repeated and the fastest kept), divides by
the built-in prediction, and stores the median per formation for the device
(:func:`.timing.store_calibration`), where ``auto`` reads it.

The benchmark package's crossover table (``python -m bench --formation --cases crossover``) uses
the same scans and timings and adds each formation's error and ``auto``'s choice.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["FORMS", "MIN_SIDE", "SIDES_FULL", "SIDES_QUICK", "best_time", "calibrate_auto", "calibration_case",
           "case_profiles", "factors_of", "time_formations", "warm_up"]

log = logging.getLogger(__name__)

SIDES_QUICK = (16, 24, 32, 48, 64)
SIDES_FULL = (16, 24, 32, 48, 64, 96, 128)
PITCH = 0.0056  # stop spacing, m
VOXEL = 0.004  # voxel spacing, m
FS = 96e3
FORMS = ("bp", "omega-k", "ffbp")
MIN_SIDE = 8

REPEAT_UNDER_S = 2.0  # a run shorter than this is repeated and the fastest kept (load spikes aside)
REPEAT_FOR_S = 1.0  # ... until this much time has been spent on it (at least two runs, at most REPEAT_MAX)
REPEAT_MAX = 7


def calibration_case(n: int, seed: int = 0):
    """(dataset, grid) of the N x N-stop scan (see the module notes)."""
    from ...physics.geometry import Scene, VoxelGrid, raster_aperture
    from ...physics.signals import lfm_chirp
    from ...synthesis.simulation import simulate

    side = PITCH * (n - 1)
    ap = raster_aperture(n, n, side, side)
    half = side / 3
    n_lat = int(round(2 * half / VOXEL)) + 1
    lat = np.linspace(-half, half, n_lat)
    grid = VoxelGrid(lat, lat, np.linspace(0.58, 0.74, 41))
    scale = min(1.0, side / 0.36)
    pts = np.array([[0.02 * scale, -0.01 * scale, 0.62], [-0.03 * scale, 0.02 * scale, 0.66],
                    [0.0, 0.03 * scale, 0.70]])
    w = lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = simulate(Scene(pts), ap, w, FS, snr_db=30, seed=seed,
                        chirp={"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 2e-3})
    return ds, grid


def case_profiles(ds, grid, selection=None):
    """The case's profiles over its grid's delay gate (matched filter)."""
    from ...compression import compress
    from ...types.rangegate import plan_reconstruction

    plan = plan_reconstruction(ds, grid, [])
    return compress(ds, gate_s=plan.gate_s, backend=selection)


def forget_tree() -> None:
    """Drop FFBP's remembered tree, so that its planning is part of the next timed call."""
    from .. import ffbp

    ffbp._LAST_TREE.clear()


def best_time(fn: Callable[[], Any]) -> tuple[float, Any]:
    """(seconds, result) of ``fn()``: one run if it took REPEAT_UNDER_S or more, else the fastest of
    at least two and at most REPEAT_MAX runs, repeated until REPEAT_FOR_S has been spent (on a shared
    2-core host a 0.1 s run varies by tens of per cent from one to the next)."""
    best, out, spent, runs = float("inf"), None, 0.0, 0
    while True:
        forget_tree()
        t = time.perf_counter()
        out = fn()
        took = time.perf_counter() - t
        best, spent, runs = min(best, took), spent + took, runs + 1
        if best >= REPEAT_UNDER_S or runs >= REPEAT_MAX or (runs >= 2 and spent >= REPEAT_FOR_S):
            return best, out


def warm_up(selection=None) -> None:
    """Build each formation's kernels on a small scan, outside any timing."""
    from .. import form

    ds, grid = calibration_case(12)
    prof = case_profiles(ds, grid, selection)
    for f in FORMS:
        form(prof, grid, f, backend=selection)


def time_formations(prof, grid, selection, say: Callable[[str], None]) -> tuple[list[dict], dict]:
    """Each of :data:`FORMS` timed on ``prof`` onto ``grid``: rows (``formation``, ``time_s``,
    ``backend``, ``predicted_builtin_s``) and the images by formation."""
    from .. import form
    from .predict import predict_time

    rows, images = [], {}
    for f in FORMS:
        say(f"calibration: {f} on {grid.size} voxels, {prof.n_meas} measurements")
        took, img = best_time(lambda f=f: form(prof, grid, f, backend=selection))
        images[f] = img
        rows.append({"formation": f, "time_s": took, "backend": img.backend,
                     "predicted_builtin_s": predict_time(f, prof, grid, selection, factors={})})
    return rows, images


def factors_of(rows: Sequence[dict]) -> dict[str, float]:
    """Per formation, the median of measured / built-in predicted time over ``rows``."""
    ratios: dict[str, list[float]] = {}
    for r in rows:
        if r.get("predicted_builtin_s"):
            ratios.setdefault(r["formation"], []).append(r["time_s"] / r["predicted_builtin_s"])
    return {f: float(np.median(x)) for f, x in ratios.items()}


def calibrate_auto(sides: Sequence[int] = SIDES_QUICK, *, backend: Any = None, device: Any = None,
                   store: bool = True, status: Callable[[str], None] | None = None) -> dict:
    """Measure ``formation="auto"``'s cost-model factors on a device and (by default) keep them.

    Parameters
    ----------
    sides : sequence of int
        N of the N x N-stop scans timed (each at least 8); default :data:`SIDES_QUICK` (about a
        minute on a 2-core CPU; :data:`SIDES_FULL` adds 96 and 128).
    backend, device
        Where to measure, as :func:`clsas.reconstruct` takes them (default: ``auto``'s device).
    store : bool
        Keep the factors for the device (:func:`clsas.formation.auto.timing.calibration_path`), where
        ``formation="auto"`` reads them.
    status : callable(str), optional
        Progress lines naming the step.

    Returns
    -------
    dict
        ``factors`` (formation -> measured / predicted time), ``rows`` (per side: the timings),
        ``device``, and ``path`` where stored.
    """
    from ... import cl
    from .timing import store_calibration

    sides = tuple(sides)
    if not sides or not all(isinstance(n, int | np.integer) and not isinstance(n, bool) and n >= MIN_SIDE
                            for n in sides):
        raise ValueError(f"sides must be integers of at least {MIN_SIDE} (stops a side), got {sides!r}")
    sel = cl.select(backend, device)
    say = status or (lambda s: log.info("%s", s))
    say(f"calibration: building the kernels on {sel.device}")
    warm_up(sel)
    per_side, rows = [], []
    for n in sides:
        ds, grid = calibration_case(int(n))
        prof = case_profiles(ds, grid, sel)
        timed, _ = time_formations(prof, grid, sel, say)
        per_side.append({"n": int(n), "voxels": grid.size, "measurements": ds.n_meas, "rows": timed})
        rows += timed
    factors = factors_of(rows)
    out = {"factors": factors, "rows": per_side, "device": sel.device, "sides": list(sides)}
    if store and factors:
        path = store_calibration(factors, sel, detail={"sides": list(sides)})
        out["path"] = str(path)
        say(f"calibration: {', '.join(f'{k} x{x:.2f}' for k, x in factors.items())}, kept in {path}")
    return out
