"""The second stage of :func:`clsas.autofocus`: the motion, behind a check that is not the sharpness it maximised.

The motion is estimated on all stops (``"phase"``: per-stop phases, the start for large motion;
``"los"``: a smooth line-of-sight search; ``"3d"``: the carriage's 3-D displacement in a smooth
basis over stop time, its constant and tilt projected out; ``"pga"``: strong points), then
checked on two pairs of disjoint sub-apertures (:mod:`.split`: the first and second half of the
stops in time, and the left and right half of the carriage's x): the images of each pair must
agree (correlation of magnitudes) better after the correction than before, by ``check_margin``
on average and worse on neither. Sharpness over-fits by concentrating each sub-aperture's
energy wherever its own errors and speckle allow, which the other sub-aperture does not share.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from .motion import default_basis_size, los_directions, motion_basis, optimise_los, optimise_xyz
from .report import ParameterEstimate
from .stage_motion_steps import _focus_centre, _per_stop_mean, _pga_step, _phase_step
from .state import FocusState

__all__ = ["MotionEstimate", "MotionStage", "carriage_3d", "estimate_motion"]


@dataclass(frozen=True, eq=False)
class MotionEstimate:
    """The carriage's displacement (n_meas, 3), m (zeros where it did not pass), and whether it
    passed the motion's checks (held out, sub-apertures, positions: see the module docstring)."""

    move: np.ndarray
    passed: bool


class MotionStage:
    """The motion methods named (``"phase"``, ``"points"``, ``"track"``, ``"los"``, ``"3d"``,
    ``"pga"``), on all stops; runs where one is named and the scan has sub-apertures to check with."""

    name = "motion"

    def runs(self, state: FocusState) -> bool:
        return state.options.motion and state.halves is not None

    def estimate(self, state: FocusState) -> MotionEstimate:
        """:func:`estimate_motion`: the estimate and its checks, which the motion steps make as
        they go (``"points"`` decides whether ``"track"`` replaces it)."""
        return MotionEstimate(*estimate_motion(state))

    def check(self, state: FocusState, estimate: MotionEstimate) -> bool:
        """Whether the motion passed the checks :func:`estimate_motion` made (recorded in ``rep.check``)."""
        return estimate.passed

    def update(self, state: FocusState, estimate: MotionEstimate, passed: bool) -> FocusState:
        return replace(state, move=estimate.move) if passed else state


def estimate_motion(fo: FocusState) -> tuple[np.ndarray, bool]:
    """The carriage's displacement (n_meas, 3), m, and whether it passed the check (zeros where not)."""
    ds, o, stop, t_stop, xy = fo.ds, fo.options, fo.stop, fo.t_stop, fo.xy
    methods, margin, max_bytes = o.methods, o.check_margin, o.max_stop_bytes
    t = time.perf_counter()
    c = fo.c_stated
    shift = fo.t0_at(c) - ds.t0_s
    others = set(methods) & {"phase", "track", "los", "3d", "pga"}
    if "points" in methods:
        found = points_step(fo, shift, c, stop, t_stop, xy, margin, others)
        if found is not None and "track" in others:
            return _points_or_track(fo, found, shift, c, stop, t_stop, xy, max_bytes), True
        if found is not None or not others:
            return (found, True) if found is not None else (np.zeros((ds.n_meas, 3)), False)
    p_stop, centre = _phase_paths(fo, methods, shift, c, stop, t_stop, xy, o.phase_sweeps, max_bytes)
    track = None
    if "track" in methods:
        from .stage_motion_track import track_step

        p_stop, track = track_step(fo, shift, c, stop, t_stop, xy, max_bytes, o.track_tolerance_m)
    if "los" in methods:
        p_stop = _line_of_sight(fo, shift, c, p_stop)
    move = _carriage_move(fo, shift, c, p_stop, centre)
    before = fo.split_agreement(shift, c, None)
    after = fo.split_agreement(shift, c, move)
    if track is not None and set(methods) & {"phase", "3d", "los", "pga"} == set():
        return _track_decision(fo, shift, c, move, track, before, after)
    passed = _motion_passed(fo.rep.check.get("phase_heldout"), methods, move, before, after, margin)
    _record_motion(fo, methods, move, before, after, passed, margin, time.perf_counter() - t)
    return (move, True) if passed else (np.zeros((ds.n_meas, 3)), False)


def _line_of_sight(fo: FocusState, shift, c_est, p_stop) -> np.ndarray:
    """``p_stop`` plus the line-of-sight path changes per stop (a smooth motion basis), m."""
    rep, o, stop, t_stop = fo.rep, fo.options, fo.stop, fo.t_stop
    t = time.perf_counter()
    k = o.n_basis or default_basis_size(t_stop, len(t_stop), o.motion_bandwidth_hz, fo.ds.timestamps is not None)
    basis = motion_basis(t_stop, fo.xy, min(k, max(len(t_stop) - 3, 1)))
    rep.n_basis = basis.shape[1]
    if rep.n_basis == 0:
        rep.notes.append("line of sight: too few stops for a motion basis; not estimated")
        return p_stop
    stages = sorted({min(s, rep.n_basis) for s in (4, 12, rep.n_basis // 2, rep.n_basis) if s > 0})
    dp, info = optimise_los(fo.engine, shift - p_stop[stop] / c_est, c_est, stop, basis, stages, o.max_iter,
                            rep.history, callback=fo.progress)
    rep.stages.append({"step": "los", "metric": info["stages"][-1]["metric"],
                       "evaluations": info["evaluations"], "stages": info["stages"],
                       "time_s": time.perf_counter() - t})
    return p_stop + dp


def _phase_paths(fo, methods, shift, c, stop, t_stop, xy, sweeps, max_bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """Each stop's path-length error from the per-stop phase search (zeros without ``"phase"``), with
    the range and cross-range gauge removed, and the focus centre of a local phase region (or None)."""
    ds, rep, engine = fo.ds, fo.rep, fo.engine
    p_stop = np.zeros(len(t_stop))
    centre = None
    if "phase" not in methods:
        return p_stop, centre
    ph_engine, centre = _local_engine(fo, shift, c) if fo.options.phase_region_m is not None else (engine, None)

    def local_metric(sh, cc, step):
        return fo.metric_of(ph_engine.image(sh, cc), step)

    p_stop = _phase_step(ph_engine, ds, ph_engine.grid, shift, c, stop, sweeps, max_bytes, local_metric,
                         rep.history, fo.progress, rep, margin=fo.options.heldout_gain)
    # the gauge no focus metric sees: a constant path is a range shift, one linear in the
    # carriage's x and y a shift across; the phase search leaves them free, so they go
    nuis, _ = np.linalg.qr(np.c_[np.ones(len(t_stop)), xy - xy.mean(axis=0)])
    return p_stop - nuis @ (nuis.T @ p_stop), centre


def _carriage_move(fo: FocusState, shift, c, p_stop, centre) -> np.ndarray:
    """The path-length errors as a carriage displacement along the lines of sight to the focus
    centre, refined in 3-D (``"3d"``) and by phase-gradient autofocus (``"pga"``) where named."""
    ds, rep, engine, methods, stop = fo.ds, fo.rep, fo.engine, fo.options.methods, fo.stop
    if centre is None:
        centre = _focus_centre(engine, engine.grid, shift - p_stop[stop] / c, c)
    rep.focus_centre_m = centre
    move = (-0.5 * p_stop[stop])[:, None] * los_directions(ds, centre)
    if "3d" in methods:
        move = carriage_3d(fo, shift, c, move)
    if "pga" in methods:
        move, _ = _pga_step(engine, ds, shift, c, stop, fo.xy, move, fo.options.pga_options, fo.image_metric, rep)
    return move


def _motion_passed(held, methods, move, before, after, margin) -> bool:
    """The motion's check: with phases alone, the held-out halves' verdict, the sub-aperture pairs
    agreeing better by :data:`MOTION_GAIN` on average and none agreeing less; otherwise, on all
    stops, the sub-aperture pairs agreeing better on average (by ``margin``)."""
    gain = np.asarray(after) - np.asarray(before)
    if held is not None and set(methods) & {"3d", "los", "pga"} == set():
        return bool(held["passed"] and gain.mean() >= MOTION_GAIN and gain.min() > -margin and np.any(move != 0))
    return bool(gain.mean() > margin and gain.min() > -margin and (held is None or held["passed"]))


def _record_motion(fo, methods, move, before, after, passed, margin, seconds) -> None:
    """The motion's estimate, check, stage and (when it failed) the note, in the report."""
    rep = fo.rep
    held = rep.check.get("phase_heldout")
    rms = float(np.sqrt(np.mean(np.sum(move**2, axis=1))))
    pairs = ", ".join(f"{n} {b:.3f} -> {a:.3f}" for n, b, a in zip(fo.split_names, before, after, strict=True))
    if held is not None:
        pairs += "; held out (phases of the even stops on the odd and back): " + ", ".join(
            f"sharpness {r['sharpness_before']:.3f} -> {r['sharpness_after']:.3f}, agreement "
            f"{r['agreement_before']:.3f} -> {r['agreement_after']:.3f}" for k, r in held.items() if k != "passed")
    rep.check.update({f"motion_{n}_before": b for n, b in zip(fo.split_names, before, strict=True)})
    rep.check.update({f"motion_{n}_after": a for n, a in zip(fo.split_names, after, strict=True)})
    rep.check["motion_passed"] = passed
    used = "+".join(m for m in methods if m in ("phase", "los", "3d", "pga"))
    rep.parameters["motion"] = ParameterEstimate(
        "motion", "m RMS", rms, float("nan"), passed, False,
        f"{used} on all stops ({rep.n_basis or 'per-stop'} functions per axis); sub-aperture images agree "
        f"(magnitude correlation): {pairs}")
    rep.stages.append({"step": "motion", "methods": used, "agreement_before": list(before),
                       "agreement_after": list(after), "passed": passed, "time_s": seconds})
    if not passed:
        rep.notes.append(f"motion: the disjoint sub-apertures' images do not agree better after it ({pairs}; margin "
                         f"{margin:g}): the sharpness over-fits, or the scan does not determine the motion; "
                         "not applied")


#: ``"phase"``, ``"points"`` and ``"track"`` are applied only where the disjoint sub-apertures' images agree
#: better after them by at least this (the mean over the pairs of the magnitude correlation's
#: rise): a motion that explains no disagreement is not applied. On the scene family's tuning
#: seeds the point scenes with hand motion rose by 0.30-0.66 and the one scene "points" made worse
#: by 0.08; on error-free scans "track" rose by at most 0.07, on scans with 3 mm of motion by 0.17
#: or more.
MOTION_GAIN = 0.1

#: Below this :func:`.track.nearest_coherence` the closest stops' images differ by more than
#: the motion does (the stops are too far apart for the target's speckle) and the report says
#: so. On the family's tuning seeds "track" reached 1 dB only at 0.92 and failed at 0.21-0.69;
#: a note, it changes no estimate.
SAMPLING_COHERENCE = 0.8


def points_step(fo, shift, c, stop, t_stop, xy, margin, others=frozenset()) -> np.ndarray | None:
    """``"points"`` (:mod:`.points`): the carriage's displacement (n_meas, 3), m, where the estimate
    is determined and the sub-apertures agree better after it by :data:`MOTION_GAIN`; else None
    (the other motion steps named, ``others``, then run), with a note saying why."""
    from .points import points_paths
    from .stage_motion_track import resolution_cell_m

    ds, rep, engine = fo.ds, fo.rep, fo.engine
    t = time.perf_counter()
    centre = _focus_centre(engine, engine.grid, shift, c)
    p_stop, info = points_paths(engine, shift, c, stop, t_stop, xy, min_separation_m=resolution_cell_m(ds, centre))
    passed, pairs = False, ""
    if info["determined"]:
        centre = _focus_centre(engine, engine.grid, shift - p_stop[stop] / c, c)
        move = (-0.5 * p_stop[stop])[:, None] * los_directions(ds, centre)
        before = np.asarray(fo.split_agreement(shift, c, None))
        after = np.asarray(fo.split_agreement(shift, c, move))
        gain = after - before
        passed = bool(gain.mean() >= MOTION_GAIN and gain.min() > -margin)
        pairs = ", ".join(f"{n} {b:.3f} -> {a:.3f}" for n, b, a in zip(fo.split_names, before, after, strict=True))
        rep.check.update({f"points_{n}_before": b for n, b in zip(fo.split_names, before, strict=True)})
        rep.check.update({f"points_{n}_after": a for n, a in zip(fo.split_names, after, strict=True)})
        if not passed:
            info["why"] = (f"the disjoint sub-apertures' images agree better by {gain.mean():.3f} on average "
                           f"(at least {MOTION_GAIN:g} needed; {pairs})")
    rep.check["points_passed"] = passed
    rep.stages.append({"step": "points", **{k: v for k, v in info.items() if k != "update_rms_m"},
                       "passed": passed, "time_s": time.perf_counter() - t})
    if not passed:
        then = f"{', '.join(sorted(others))} run instead" if others else "no other motion step named: motion left at 0"
        rep.notes.append(f"points: not applied ({info.get('why', 'not determined')}); {then}")
        if not others:
            rep.parameters["motion"] = ParameterEstimate(
                "motion", "m RMS (one way)", info.get("rms_m", float("nan")), float("nan"), info["determined"],
                False, f"points: {info.get('why', 'not determined')}; not applied")
        return None
    if others - {"track"}:
        rep.notes.append(f"points: applied; {', '.join(sorted(others - {'track'}))} not run (points passed its check)")
    rep.focus_centre_m = centre
    rep.check["motion_passed"] = True
    rep.parameters["motion"] = ParameterEstimate(
        "motion", "m RMS (one way)", info["rms_m"], float("nan"), True, False,
        f"points: the stops' phases common to {info['points']} strong points (rank one), unwrapped in time and "
        f"smooth in the hand's band; their median coherence after it {info['coherence']:.2f}; sub-aperture "
        f"images agree (magnitude correlation): {pairs}")
    return move


def _points_or_track(fo, points_move, shift, c, stop, t_stop, xy, max_bytes) -> np.ndarray:
    """After ``"points"`` passed: ``"track"`` too, and its correction instead where it passes its
    own decision (:func:`_track_decision`) and the disjoint sub-apertures agree better after it
    than after the points' (the mean over the pairs). On a surface that the strong points only
    sample (speckle peaks that pass for points) the neighbours' phases hold more of the motion:
    on the family's tuning sets this took 3 scenes from -2.7, -2.6 and -1.2 dB to within 0.2 dB
    and changed none for the worse."""
    from .stage_motion_track import track_step

    rep, engine = fo.rep, fo.engine
    kept = (rep.parameters.get("motion"), len(rep.notes), rep.focus_centre_m, dict(rep.check), len(rep.stages))
    points_after = float(np.mean([rep.check[f"points_{n}_after"] for n in fo.split_names]))
    p_stop, track = track_step(fo, shift, c, stop, t_stop, xy, max_bytes, fo.options.track_tolerance_m)
    centre = _focus_centre(engine, engine.grid, shift - p_stop[stop] / c, c)
    move = (-0.5 * p_stop[stop])[:, None] * los_directions(fo.ds, centre)
    # the uncorrected sub-apertures' agreement is what "points" measured (same shift and speed)
    before = [rep.check[f"points_{n}_before"] for n in fo.split_names]
    after = fo.split_agreement(shift, c, move)
    move, passed = _track_decision(fo, shift, c, move, track, before, after)
    track_after = float(np.mean(after))
    if passed and track_after > points_after:
        rep.focus_centre_m = centre
        rep.notes.append(f"track: applied instead of points (the sub-apertures agree at {track_after:.3f} after it, "
                         f"{points_after:.3f} after the points')")
        return move
    rep.parameters["motion"], rep.focus_centre_m = kept[0], kept[2]
    del rep.notes[kept[1]:]
    rep.check.clear()
    rep.check.update(kept[3])
    # its stage stays, marked unused; the motion decision it added goes
    rep.stages[kept[4]:] = [dict(st, used=False) for st in rep.stages[kept[4]:] if st.get("step") == "track"]
    rep.notes.append("track: run too, not used (" + (f"the sub-apertures agree at {track_after:.3f} after it, "
                     f"{points_after:.3f} after the points'" if passed else "it did not pass its own decision") + ")")
    return points_move


def _track_decision(fo, shift, c, move, track, before, after) -> tuple[np.ndarray, bool]:
    """``"track"`` alone: applied where determined (the even and odd stops agree, or the target's
    two sides do) and where the check on positions (:func:`.stage_motion_track.where_check`) passes."""
    from .stage_motion_track import REGION_TOLERANCE_M, where_check

    rep = fo.rep
    where = where_check(fo, shift, c, move) if track["determined"] else {"passed": False}
    gain = float(np.mean(after) - np.mean(before))
    explains = gain >= MOTION_GAIN
    passed = bool(track["determined"] and where["passed"] and np.any(move != 0) and explains)
    rep.check.update({f"motion_{n}_before": b for n, b in zip(fo.split_names, before, strict=True)})
    rep.check.update({f"motion_{n}_after": a for n, a in zip(fo.split_names, after, strict=True)})
    rep.check.update({f"where_{k}": v for k, v in where.items()})
    rep.check["motion_passed"] = passed
    nearest = track.get("coherence_nearest", float("nan"))
    how = (f"track: neighbouring stops' phase differences, integrated (median coherence "
           f"{track.get('coherence_median', 0):.2f}, closest stops {nearest:.2f}); even and odd stops tracked "
           f"apart differ by {track.get('halves_rms_m', float('nan')) * 1e3:.2f} mm RMS (one way; determined at "
           f"<= {fo.options.track_tolerance_m * 1e3:.2f} mm), the target's two sides by "
           f"{track.get('regions_rms_m', float('nan')) * 1e3:.2f} mm (at <= {REGION_TOLERANCE_M * 1e3:.2f} mm)")
    sampling = sampling_note(track, bool(track["determined"]))
    if sampling:
        rep.notes.append(sampling)
    if track["determined"]:
        how += ("; positions: " + ", ".join(f"{k} {v:.3g}" for k, v in where.items() if k != "passed")
                + ("" if where["passed"] else " (the correction moves the image's features apart: not applied)"))
    # each half's path is off by about the halves' difference / sqrt(2); the whole, with twice
    # the data, by about half the difference (the closer of the two splits)
    apart = float(np.fmin(track.get("halves_rms_m", np.nan), track.get("regions_rms_m", np.nan)))
    rep.parameters["motion"] = ParameterEstimate("motion", "m RMS (one way)", track.get("rms_m", float("nan")),
                                                 0.5 * apart, track["determined"], False, how)
    rep.stages.append({"step": "motion", "methods": "track", "passed": passed, "where": where})
    if not passed:
        rep.notes.append("motion: " + ("not determined by this scan (neither the even and odd stops nor the "
                                       "target's two sides agree on it)" if not track["determined"]
                                       else "the check on positions failed" if not where["passed"]
                                       else f"the disjoint sub-apertures' images agree better by {gain:.3f} after "
                                            f"it (at least {MOTION_GAIN:g} needed): nothing to correct")
                         + "; not applied")
        return np.zeros((fo.ds.n_meas, 3)), False
    return move, True


def sampling_note(track: dict, determined: bool = False) -> str:
    """A note where the closest stops' images are too unlike for their phases to carry the
    motion reliably (:data:`SAMPLING_COHERENCE`), else ``""``; ``determined``: the motion
    passed its own test all the same."""
    coh = track.get("coherence_nearest", float("nan"))
    if not np.isfinite(coh) or coh >= SAMPLING_COHERENCE:
        return ""
    head = (f"motion: the closest stops' images agree at a coherence of only {coh:.2f} (< {SAMPLING_COHERENCE:g}): "
            "the stops are far apart for the target's speckle (about lambda R / 2D for a target D across at range "
            "R), so neighbouring stops differ by more than the motion does")
    if determined:
        return (head + "; scans like this were mostly not determined in the scene family, this one passed the "
                "tests above (docs/guide/autofocus.md, 'When the motion can be found')")
    return (head + " and the motion is not reliably determined by this scan; stops closer together (on the "
            "scene family's surfaces \"track\" succeeded only where the finer pitch was under about 0.36 "
            "lambda R / 2D) or a smaller target region would help (docs/guide/autofocus.md, 'When the motion can "
            "be found')")


def _local_engine(fo, shift, c):
    """A :class:`FocusEngine` on a fine grid (a quarter of the shortest wavelength) of half-size
    ``fo.options.phase_region_m`` around the image's brightest voxel, and that voxel, m."""
    from ..physics.geometry import VoxelGrid
    from .engine import FocusEngine

    engine = fo.engine
    values = engine.image(shift, c)
    centre = engine.grid.points()[int(np.argmax(np.abs(values)))]
    f_max = max(engine.ds.chirp.get("f_start_hz", 0.0), engine.ds.chirp.get("f_stop_hz", 0.0)) or \
        2 * engine.prof.fc_hz
    step = float(np.min(engine.ds.c_per_meas)) / f_max / 4
    r = fo.options.phase_region_m
    ax = np.arange(-r, r + 0.5 * step, step)
    grid = VoxelGrid(centre[0] + ax, centre[1] + ax, centre[2] + ax)
    return FocusEngine(engine.ds, grid, backend=engine.selection, **fo.engine_options), centre


def carriage_3d(fo: FocusState, shift, c_est, move) -> np.ndarray:
    """The carriage's 3-D displacement per measurement (n_meas, 3), m, started from ``move``."""
    t = time.perf_counter()
    stop, t_stop, xy, o = fo.stop, fo.t_stop, fo.xy, fo.options
    start = _per_stop_mean(move, stop)
    k = o.n_basis or default_basis_size(t_stop, len(t_stop), o.motion_bandwidth_hz, fo.ds.timestamps is not None)
    basis = motion_basis(t_stop, xy, min(k, max(len(t_stop) - 3, 1))) if k < len(t_stop) else None
    nuis, _ = np.linalg.qr(np.c_[np.ones(len(t_stop)), xy - xy.mean(axis=0)])
    if basis is not None:
        # the carriage moves smoothly: the start keeps the line-of-sight move's part in the basis;
        # what is left is the per-stop estimates' noise and the line of sight's turn, not motion
        start = basis @ (basis.T @ start)
    else:  # the gauge no focus metric sees: the constant and the tilt, out
        start = start - nuis @ (nuis.T @ start)
    d, info = optimise_xyz(fo.engine, shift, c_est, stop, start, o.max_iter, fo.rep.history, callback=fo.progress,
                           basis=basis)
    fo.rep.n_basis = info["functions"]
    fo.rep.stages.append({"step": "3d", "metric": info["metric"], "evaluations": info["evaluations"],
                          "time_s": time.perf_counter() - t})
    return d[stop]
