"""Autofocus: motion, sound speed and delay estimated from the scan itself.

A hand-held aperture is not where the dataset says, the air is not the temperature it states,
and the transducers add a delay nobody measured; each defocuses the image. :func:`autofocus`
estimates, in this order (each step selectable in ``methods``):

1. ``"direct"``: the delay of each recording from the direct speaker-to-microphone sound
   (:mod:`.direct`): group delay and per-stop timing jitter (and ``c`` where the rig has
   several speaker-to-microphone distances);
2. ``"temperature"``: the air temperature (so ``c``) that makes the image sharpest, a scan then
   a bounded 1-D search; the direct-path delays follow each candidate ``c``;
3. ``"delay"``: where no direct sound is found, a global delay from sharpness (weakly
   determined: a delay mostly shifts the image);
4. ``"phase"``: one phase per stop by exact coordinate ascent of the sharpness over the
   stops' own images (:mod:`.phases`), read as a line-of-sight path per stop: the global
   start that large motion (a radian of two-way phase or more) needs;
5. ``"los"``: per-stop line-of-sight path corrections in a smooth basis over the stop times
   (:mod:`.motion`), maximising sharpness with analytic gradients through backprojection
   (``kernels/autofocus.cl`` and its NumPy twin), coarse to fine, from the ``"phase"``
   estimate where there is one;
6. ``"3d"``: the carriage's 3-D displacement per stop (the line of sight differs between
   reflectors seen at different angles), from the line-of-sight estimate on, its change in the
   same smooth basis per axis, by the same analytic gradient;
7. ``"pga"``: phase-gradient autofocus on strong points (:mod:`.pga`): each stop's own 3-D
   displacement, from the phases of its contributions to the image's strong isolated points;
   applied only where at least four points are coherent enough to be points (not on an
   extended target) and the image gets sharper. Not in the default.

It returns the corrected dataset and an :class:`AutofocusReport`, and never an image less
sharp than the input's: if the final metric is not above the input's, the input comes back
(``report.improved`` False, and a note says so).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .. import validate as v
from ..dataset import Dataset
from ..geometry import VoxelGrid
from ..physics import speed_of_sound
from .metrics import METRICS
from .report import AutofocusReport

__all__ = ["AutofocusReport", "DEFAULT_METHODS", "METHODS", "autofocus", "score"]

log = logging.getLogger(__name__)

METHODS = ("direct", "temperature", "delay", "phase", "los", "3d", "pga")
DEFAULT_METHODS = ("direct", "temperature", "delay", "phase", "3d")


def autofocus(dataset: Dataset, grid: VoxelGrid, *, methods: tuple[str, ...] | list[str] = DEFAULT_METHODS,
              metric: str = "sharpness", n_basis: int | None = None, motion_bandwidth_hz: float = 5.0,
              temperature_range_c: float = 15.0, max_delay_s: float = 5e-4, per_stop_delay: bool = True,
              max_iter: int = 40, phase_sweeps: int = 4, max_stop_bytes: int = 1 << 30,
              pga_min_coherence: float | None = None, pga_max_points: int = 32, backend: str | None = None,
              device: Any = None, progress: Callable[[str, int, float], None] | None = None,
              force: bool = False) -> tuple[Dataset, AutofocusReport]:
    """Estimate motion, sound speed and delay from the scan, and correct the dataset.

    Parameters
    ----------
    dataset : Dataset
    grid : VoxelGrid
        Where the focus is measured: the scene, not much more (empty voxels add nothing but
        time). Spacing about a third of the wavelength or finer.
    methods : sequence of {"direct", "temperature", "delay", "phase", "los", "3d", "pga"}
        The steps to run (see the module docstring); order is fixed. The default leaves out
        ``"los"`` (the smooth line-of-sight search, which ``"3d"`` contains) and ``"pga"``
        (for scenes of a few isolated strong points).
    metric : {"sharpness", "entropy"}
        See :func:`clsas.focus.metrics.metric_and_weight`.
    n_basis : int, optional
        Smooth functions for the line-of-sight and 3-D motion; default enough for motion up to
        ``motion_bandwidth_hz`` over the scan's duration (from ``timestamps``), else a quarter
        of the stops.
    motion_bandwidth_hz : float
        Highest frequency of the motion to correct, Hz (used with ``timestamps``).
    temperature_range_c : float
        The temperature search covers the stated value ± this, °C.
    max_delay_s : float
        The largest delay error looked for (direct sound search window, delay search), s.
    per_stop_delay : bool
        Keep each recording's own direct-path delay (timing jitter) rather than their median.
    max_iter : int
        L-BFGS iterations per stage of the line-of-sight search, and of the 3-D search.
    phase_sweeps : int
        Most sweeps of the per-stop phase search (``"phase"``).
    max_stop_bytes : int
        Memory for the per-stop images of ``"phase"`` (complex64, stops x voxels), bytes; past
        it, only the brightest voxels of the image are kept.
    pga_min_coherence : float, optional
        ``"pga"`` uses only points whose per-stop contributions add up this coherently (0 to 1;
        default :data:`clsas.focus.pga.PGA_MIN_COHERENCE`).
    pga_max_points : int
        Most strong points ``"pga"`` uses (the brightest that qualify).
    backend, device, force : as for :func:`clsas.reconstruct`.
    progress : callable(step, n_images, metric), optional
        Called after every image the search forms.

    Returns
    -------
    (Dataset, AutofocusReport)
        The corrected dataset (new ``t0_s``, ``temperature_c``/``c_mps`` and positions moved
        along the line of sight; a provenance record ``autofocus``), or the input itself when
        the image did not get sharper.
    """
    options = _checked(dataset, grid, methods, metric, n_basis, motion_bandwidth_hz, temperature_range_c,
                       max_delay_s, per_stop_delay, max_iter, phase_sweeps, max_stop_bytes, pga_min_coherence,
                       pga_max_points, progress)
    from .run import run

    return run(dataset, grid, backend=backend, device=device, progress=progress, force=force,
               started=time.perf_counter(), **options)


def _checked(dataset, grid, methods, metric, n_basis, motion_bandwidth_hz, temperature_range_c, max_delay_s,
             per_stop_delay, max_iter, phase_sweeps, max_stop_bytes, pga_min_coherence, pga_max_points,
             progress) -> dict:
    """:func:`autofocus`'s arguments checked, as the keyword arguments of :func:`clsas.focus.run.run`."""
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    if isinstance(methods, str) or not all(isinstance(m, str) for m in methods):
        raise TypeError(f"methods must be a sequence of names from {METHODS}, got {methods!r}")
    for m in methods:
        v.choice("methods", m, METHODS)
    if not methods:
        raise ValueError(f"methods must name at least one of {METHODS}")
    v.choice("metric", metric, METRICS)
    if n_basis is not None:
        n_basis = v.positive_int("n_basis", n_basis)
    bw = v.positive("motion_bandwidth_hz", motion_bandwidth_hz)
    t_range = v.non_negative("temperature_range_c", temperature_range_c)
    max_delay = v.non_negative("max_delay_s", max_delay_s)
    max_iter = v.positive_int("max_iter", max_iter)
    phase_sweeps = v.positive_int("phase_sweeps", phase_sweeps)
    max_stop_bytes = v.positive_int("max_stop_bytes", max_stop_bytes)
    pga_options = {"max_points": v.positive_int("pga_max_points", pga_max_points)}
    if pga_min_coherence is not None:
        coh = v.non_negative("pga_min_coherence", pga_min_coherence)
        if coh > 1:
            raise ValueError(f"pga_min_coherence must be in [0, 1], got {pga_min_coherence!r}")
        pga_options["min_coherence"] = coh
    if progress is not None and not callable(progress):
        raise TypeError("progress must be callable(step, n_images, metric)")
    if dataset.n_meas < 4:
        raise ValueError(f"dataset: autofocus needs at least 4 measurements, got {dataset.n_meas}")
    return {"methods": tuple(methods), "metric": metric, "n_basis": n_basis, "bandwidth_hz": bw,
            "temperature_range_c": t_range, "max_delay_s": max_delay, "per_stop_delay": bool(per_stop_delay),
            "max_iter": max_iter, "phase_sweeps": phase_sweeps, "max_stop_bytes": max_stop_bytes,
            "pga_options": pga_options}


def score(report: AutofocusReport, dataset: Dataset) -> dict:
    """Estimates against the truth that a simulation stored in ``dataset.truth``.

    Returns a dict with (where the truth has them): ``group_delay_error_s`` (estimated minus
    true group delay), ``t0_error_rms_s`` (per measurement), ``temperature_error_c``,
    ``los_residual_rms_m`` (one-way line-of-sight error left after the corrections, at the
    focus centre, with the constant and the part linear in x and y, which no focus metric
    sees, removed from both), ``los_error_rms_m`` (the same before correction) and
    ``los_residual_raw_rms_m`` (nothing removed).
    """
    truth = dataset.truth
    if not truth:
        raise ValueError("dataset has no truth (simulate(..., position_error=...) and the other errors store it)")
    out: dict = {}
    if "t0_s" in truth and report.t0_s is not None:
        t0 = np.asarray(truth["t0_s"], float)
        out["t0_error_rms_s"] = float(np.sqrt(np.mean((report.t0_s - t0) ** 2)))
        true_gd = float(np.median(dataset.t0_s - t0))
        out["group_delay_error_s"] = report.group_delay_s - true_gd
    if "temperature_c" in truth:
        out["temperature_error_c"] = float(report.temperature_c - np.mean(truth["temperature_c"]))
    if "tx_positions" in truth and report.focus_centre_m is not None:
        from .motion import stops_of

        stop, _, xy = stops_of(dataset)
        first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
        vc = report.focus_centre_m

        def path(tx, rx):
            return np.linalg.norm(vc - tx, axis=1) + np.linalg.norm(vc - rx, axis=1)

        true_dp = (path(truth["tx_positions"], truth["rx_positions"]) - path(dataset.tx_positions,
                                                                           dataset.rx_positions))[first]
        est = report.los_path_m if report.los_path_m is not None else np.zeros(len(first))
        nuis = np.c_[np.ones(len(first)), xy - xy.mean(axis=0)]

        def detrend(x):
            coef, *_ = np.linalg.lstsq(nuis, x, rcond=None)
            return x - nuis @ coef

        out["los_error_rms_m"] = float(np.sqrt(np.mean(detrend(true_dp) ** 2)) / 2)
        out["los_residual_rms_m"] = float(np.sqrt(np.mean(detrend(est - true_dp) ** 2)) / 2)
        out["los_residual_raw_rms_m"] = float(np.sqrt(np.mean((est - true_dp) ** 2)) / 2)
    return out


def _speed(temperature_c) -> np.ndarray:
    return np.asarray(speed_of_sound(temperature_c), float)
