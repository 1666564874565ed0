"""Autofocus: motion, sound speed and delay estimated from the scan itself, as far as it determines them.

A hand-held aperture is not where the dataset says, the air is not the temperature it states,
and the transducers add a delay nobody measured; each defocuses the image. Sharpness alone
over-fits: the motion's constant, its tilt across the aperture and a range shift are invisible
to any focus metric, and a flexible motion buys a sharper, wrong image. So :func:`autofocus`
judges each parameter before applying it, and reports each (``report.parameters``: estimate,
uncertainty, determined, applied). The steps (``methods``, applied in this order):

1. ``"direct"`` (the default, alone): the delay of each recording from the direct
   speaker-to-microphone sound (:mod:`.direct`), group delay and per-stop timing, which the
   physics determines. Without direct sound the delay is *not determined* and stays 0;
2. ``"delay"``: without direct sound, the sharpest global delay of the first and of the second
   half of the stops (:mod:`.split`), applied only where they agree (``delay_tolerance_s``);
3. ``"phase"``: one phase per stop by exact coordinate ascent (:mod:`.phases`), read as a
   line-of-sight move, its constant and tilt (the gauge) projected out. Held out
   (:func:`.stage_motion_steps._held_out_phases`): each interleaved half's phases, predicted onto
   the other, must sharpen it (``heldout_gain``); and disjoint sub-apertures (first and second half in
   time, left and right) must agree better by :data:`.stage_motion.MOTION_GAIN` and none less
   (:mod:`.stage_motion`, ``check_margin``);
4. ``"points"``: the stops' phases that the image's strong points
   share, the left singular vector of their per-stop contributions (rank one, no point taken as
   the reference), unwrapped in time and fitted in the hand's band, the points picked again
   after each pass (:mod:`.points`). *Determined* where the points are still coherent after it
   (isolated points, not the speckle of a surface); applied only where the disjoint
   sub-apertures' images agree better by :data:`.stage_motion.MOTION_GAIN`; else the other
   motion steps named run (``"track"`` in the bench). Where ``"track"`` is named it runs after
   ``"points"`` passes too, and its correction replaces the points' where it passes its own
   decision and the sub-apertures agree better after it (on a surface the strong points are
   speckle peaks);
5. ``"track"``: one line-of-sight path per stop from the phase
   differences of neighbouring stops' images (in time and on the next row), integrated over
   the graph of neighbours (no per-stop phase is unwrapped on its own), refined in a smooth
   basis of stop time (the hand's 0.2-5 Hz band) plus the tilt, constant and tilt then set to
   zero (:mod:`.track`). *Determined* where the even and the odd stops, tracked apart, give the
   same path within ``track_tolerance_m``, or the target's two sides, tracked apart with every
   stop, within :data:`.stage_motion_track.REGION_TOLERANCE_M`; applied only where the
   sub-apertures' images agree better by :data:`.stage_motion.MOTION_GAIN` and the check on
   positions passes (:func:`.stage_motion_track.where_check`: the brightest points of disjoint
   sub-apertures must not lie farther apart after it, and the image's brightest point moves only
   where they agree);
6. ``"los"``, ``"3d"``, ``"pga"``: smooth line-of-sight and 3-D motion by L-BFGS with analytic
   gradients (``kernels/autofocus.cl`` and its NumPy twin), phase-gradient autofocus on strong
   points (:mod:`.pga`); nothing held out, so the sub-apertures must agree better;
7. ``"temperature"``: the sharpest air temperature of each half of the stops (the motion
   applied), within the thermometer's ± ``temperature_range_c``; applied only where their
   uncertainty is within ``temperature_tolerance_c`` and neither is at the search's edge.

Every scalar estimate (the delay, the per-stop timing, the temperature) is then applied only
where it differs from the stated value by more than its uncertainty allows and changes the
delays enough to matter (:mod:`.significance`); an error-free scan keeps its stated values.

:data:`FOCUS_METHODS` (direct, phase, temperature) is not the default: on held-out scenes the focus steps
made a third of the scenes worse (see docs/guide/autofocus.md). The whole
correction must not make the sub-apertures agree less than the direct sound's delay alone does;
else, or where nothing was determined, the input comes back (``report.improved`` False, a note
says why).

The code follows the stages (:func:`.run.run` takes them in this order, each a
:class:`.state.Stage` with ``estimate`` and ``check`` on a :class:`.state.FocusState`):
:mod:`.stage_delay` (1-2), :mod:`.stage_motion` (3-6; its steps in :mod:`.stage_motion_steps`
and :mod:`.stage_motion_track`), :mod:`.stage_temperature` (7), :mod:`.final_check` (the whole
correction; :mod:`.final_consistency` with ``consistency_iter``). :class:`AutofocusOptions`
holds the keywords of :func:`autofocus`, checked once.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from .consistency import Consistency, data_consistency
from .options import DEFAULT_METHODS, FOCUS_METHODS, METHODS, AutofocusOptions
from .report import AutofocusReport

__all__ = ["AutofocusOptions", "AutofocusReport", "Consistency", "DEFAULT_METHODS", "FOCUS_METHODS", "METHODS",
           "autofocus", "data_consistency", "score"]

log = logging.getLogger(__name__)

def autofocus(dataset: Dataset, grid: VoxelGrid, *, methods: tuple[str, ...] | list[str] = DEFAULT_METHODS,
              metric: str = "sharpness", n_basis: int | None = None, motion_bandwidth_hz: float = 5.0,
              temperature_range_c: float = 5.0, max_delay_s: float = 5e-4, per_stop_delay: bool = True,
              max_iter: int = 40, phase_sweeps: int = 4, max_stop_bytes: int = 1 << 30,
              pga_min_coherence: float | None = None, pga_max_points: int = 32,
              temperature_tolerance_c: float = 0.35, delay_tolerance_s: float = 1e-6, check_margin: float = 0.01,
              phase_region_m: float | None = None, heldout_gain: float = 0.2, track_tolerance_m: float = 2.5e-3,
              consistency_iter: int = 0, backend: str | None = None, device: Any = None,
              progress: Callable[[str, int, float], None] | None = None, force: bool = False
              ) -> tuple[Dataset, AutofocusReport]:
    """Estimate motion, sound speed and delay from the scan, and correct the dataset.

    Parameters
    ----------
    dataset : Dataset
    grid : VoxelGrid
        Where the focus is measured: the scene, not much more (empty voxels add nothing but
        time). Spacing about a third of the wavelength or finer.
    methods : sequence of {"direct", "temperature", "delay", "phase", "points", "track", "los", "3d", "pga"}
        The steps (see the module docstring); order is fixed. Default: the direct sound's delay
        alone (for the held-out figures of each, see docs/guide/autofocus.md).
    metric : {"sharpness", "entropy"}; see :func:`clsas.focus.metrics.metric_and_weight`.
    n_basis : int, optional
        Smooth functions for the line-of-sight and 3-D motion; default enough for motion up to
        ``motion_bandwidth_hz`` over the scan's duration (from ``timestamps``), else a quarter
        of the stops.
    motion_bandwidth_hz : float
        Highest frequency of the motion to correct, Hz (used with ``timestamps``).
    temperature_range_c : float
        The prior on the air: the thermometer's reading (``temperature_c``) is right to ± this,
        °C; the search covers that range, and an optimum at its edge is "not determined".
    max_delay_s : float
        The prior on the hardware: the largest delay error looked for (the direct sound's search
        window, the ``"delay"`` search), s.
    per_stop_delay : bool
        Keep each recording's own direct-path delay (timing jitter) rather than their median.
    max_iter, phase_sweeps : int
        L-BFGS iterations per stage of ``"los"`` and ``"3d"``; most sweeps of ``"phase"``.
    max_stop_bytes : int
        Memory for ``"phase"``'s per-stop images (complex64), bytes; past it, the brightest voxels.
    pga_min_coherence : float, optional
        ``"pga"`` uses only points whose per-stop contributions add up this coherently (0 to 1;
        default :data:`clsas.focus.pga.PGA_MIN_COHERENCE`).
    pga_max_points : int
        Most strong points ``"pga"`` uses (the brightest that qualify).
    temperature_tolerance_c, delay_tolerance_s, track_tolerance_m : float
        Applied only where the uncertainty (from the two halves of the stops) is at most this;
        ``"track"``: the even and odd stops' paths within it (RMS, one way, m), or the target's sides' within 0.5 mm.
    check_margin : float
        Sub-aperture images' agreement (0 to 1) must not fall by more (``"phase"``), or must
        rise by at least this (``"3d"``, ``"los"``, ``"pga"``).
    heldout_gain : float
        Each interleaved half's phases, predicted onto the other, must raise its log-sharpness
        by at least this.
    phase_region_m : float, optional
        Search the phases on a fine local grid of this half-size at the brightest voxel, m
        (None: on ``grid``; see docs/guide/autofocus.md).
    consistency_iter : int
        0 (default): off. Else a last check that trusts no image, :func:`data_consistency` with
        this many iterations before and after the correction (:mod:`.final_consistency`).
    backend, device, force : as for :func:`clsas.reconstruct`.
    progress : callable(step, n_images, metric), optional; called after every image formed.

    Returns
    -------
    (Dataset, AutofocusReport)
        The corrected dataset (new ``t0_s``, ``temperature_c``/``c_mps`` and positions; a provenance
        record ``autofocus``) with only what the scan determined and the check passed; or the input
        itself (``report.improved`` False, a note says why).
    """
    _check_data(dataset, grid, progress)
    return _focus(dataset, grid, AutofocusOptions(
        methods=methods, metric=metric, n_basis=n_basis, motion_bandwidth_hz=motion_bandwidth_hz,
        temperature_range_c=temperature_range_c, max_delay_s=max_delay_s, per_stop_delay=per_stop_delay,
        max_iter=max_iter, phase_sweeps=phase_sweeps, max_stop_bytes=max_stop_bytes,
        pga_min_coherence=pga_min_coherence, pga_max_points=pga_max_points,
        temperature_tolerance_c=temperature_tolerance_c, delay_tolerance_s=delay_tolerance_s,
        check_margin=check_margin, phase_region_m=phase_region_m, heldout_gain=heldout_gain,
        track_tolerance_m=track_tolerance_m, consistency_iter=consistency_iter, backend=backend, device=device,
        force=force), progress)


def _check_data(dataset, grid, progress) -> None:
    """:func:`autofocus`'s arguments beside its options, checked (its options check themselves)."""
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    if progress is not None and not callable(progress):
        raise TypeError("progress must be callable(step, n_images, metric)")
    if dataset.n_meas < 4:
        raise ValueError(f"dataset: autofocus needs at least 4 measurements, got {dataset.n_meas}")


def _focus(dataset, grid, options: AutofocusOptions, progress) -> tuple[Dataset, AutofocusReport]:
    """The checked request run: the grid against the scan's echoes first (a grid beside the
    target leaves nothing to focus on; its warning leads the report's notes), then the steps."""
    from ..types.sanity import check_grid_against_data
    from .run import run

    grid_check = check_grid_against_data(dataset, grid, where="autofocus")
    out, report = run(dataset, grid, options, progress=progress, started=time.perf_counter())
    report.notes[:0] = list(grid_check.warnings)
    return out, report


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

