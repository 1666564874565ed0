"""The autofocus pipeline behind :func:`clsas.autofocus` (inputs already checked there).

Every parameter is estimated only as far as the scan determines it: the delay from the direct
sound (none without it: not determined, 0); the motion on all stops, applied only where
disjoint sub-apertures' images agree better after it (:mod:`.motion_steps`); the temperature
from the first and second half of the stops, kept only where the two agree (:mod:`.split`). A
last check on the whole correction decides what comes back.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from .consistency_gate import consistency_gate
from .direct import DirectPath, direct_arrivals
from .engine import FocusEngine
from .metrics import metric_and_weight
from .motion import stops_of
from .motion_steps import estimate_motion
from .options import AutofocusOptions
from .report import AutofocusReport, ParameterEstimate
from .significance import delay_floor_s, delay_spread_s, judge
from .split import agreement, split_halves
from .state import SPLIT_NAMES, Delays, FocusState
from .steps import _bounded_search, _los_path, _record

__all__ = ["run"]

log = logging.getLogger("clsas.autofocus")

FINAL_TOLERANCE = 0.005  # the returned correction may lower a sub-aperture pair's agreement by at most this


def run(ds, grid, options: AutofocusOptions, *, progress, started) -> tuple:
    """The stages of :func:`clsas.autofocus` in turn: the direct sound, a delay, the motion, the
    temperature; then the check and the corrected dataset (or the input) and the report."""
    o, state = options, _start(ds, grid, options, progress)
    direct = find_direct(state) if "direct" in o.methods else None
    state = replace(state, delays=delay_parameters(state, direct))
    if o.motion and state.halves is not None:
        move, motion_ok = estimate_motion(state)
        if motion_ok:
            state = replace(state, move=move)
    if "temperature" in o.methods and o.temperature_range_c > 0 and state.halves is not None:
        state = replace(state, d_temp=temperature(state))
    return _finish(state, started)


def _start(ds, grid, o: AutofocusOptions, progress) -> FocusState:
    """The state the stages start from: the engine, the stops, the sub-apertures, the stated air;
    the input's metric in the report."""
    rep = AutofocusReport(metric=o.metric, methods=list(o.methods))
    temp0 = np.broadcast_to(np.asarray(ds.temperature_c, float), (ds.n_meas,)).copy()
    rel = 0.5 * o.temperature_range_c / (273.15 + float(temp0.min()) - o.temperature_range_c) \
        if "temperature" in o.methods else 0.0
    eopt = dict(margin_s=o.max_delay_s + 1e-4, rel_margin=rel, metric=o.metric, force=o.force)
    engine = FocusEngine(ds, grid, backend=o.backend, device=o.device, **eopt)
    rep.backend, rep.device = engine.backend, engine.device
    stop, t_stop, xy = stops_of(ds)
    state = FocusState(ds, grid, o, engine, eopt, rep, progress, temp0, ds.c_per_meas, stop, t_stop, xy, splits=())
    rep.metric_before = state.image_metric(np.zeros(ds.n_meas), state.c_stated, "input")
    splits = tuple(hs for hs in (split_halves(ds, grid, stop, xy, how, backend=engine.selection, **eopt)
                                 for how in SPLIT_NAMES) if hs is not None)
    state = replace(state, splits=splits)
    if state.halves is None:
        rep.notes.append("fewer than 8 stops: no halves to check with; only what the direct sound gives is applied")
    return state


def find_direct(state: FocusState) -> DirectPath | None:
    """The direct sound's arrivals, where found, noted in the report."""
    ds, rep, max_delay_s = state.ds, state.rep, state.options.max_delay_s
    t = time.perf_counter()
    direct = direct_arrivals(ds, max_delay_s=max(max_delay_s, 1e-4))
    rep.direct_snr_db = float(np.median(direct.snr_db[np.isfinite(direct.snr_db)])) \
        if np.isfinite(direct.snr_db).any() else float("nan")
    if direct.found:
        fit = direct.fit_c()
        if fit is not None:
            rep.notes.append(f"direct sound: speaker-to-microphone distances differ, c = {fit[0]:.2f} m/s "
                             "from the direct arrivals alone")
        rep.notes.append(f"direct sound found in {int(direct.detected.sum())} of {ds.n_meas} recordings "
                         f"(median {rep.direct_snr_db:.0f} dB above the filter's RMS)")
    else:
        rep.notes.append(f"direct sound not found (detected in {int(direct.detected.sum())} of {ds.n_meas} "
                         "recordings): delays not estimated from it")
        direct = None
    rep.stages.append({"step": "direct", "found": direct is not None, "time_s": time.perf_counter() - t})
    return direct


def delay_parameters(state: FocusState, direct: DirectPath | None) -> Delays:
    """The group delay and per-stop timing (into the report): from the direct sound, else
    (``"delay"``) the two halves' sharpest delays where they agree, else not determined (0);
    returned, the delays to apply."""
    o, rep = state.options, state.rep
    gd = ParameterEstimate("group_delay", "s", 0.0, float("nan"), False, False,
                           "no direct sound: a delay mostly shifts the image in range, which no focus "
                           "metric sees; left at 0")
    timing = ParameterEstimate("timing", "s RMS", 0.0, float("nan"), False, False, "no direct sound")
    delays = Delays(direct)
    if direct is not None:
        gd, timing = _direct_delays(state, direct)
        delays = Delays(direct, "per_stop" if timing.determined else "median" if gd.determined else "none")
    elif "delay" in o.methods and o.max_delay_s > 0 and state.halves is not None:
        gd, extra_s = _delay_search(state, o.max_delay_s, o.delay_tolerance_s)
        delays = Delays(None, extra_s=extra_s)
    rep.parameters["group_delay"], rep.parameters["timing"] = gd, timing
    return delays


def _direct_delays(state: FocusState, direct: DirectPath) -> tuple[ParameterEstimate, ParameterEstimate]:
    """The group delay (the recordings' median) and the timing (their scatter) from the direct
    sound's arrivals, each applied only where :func:`.significance.judge` says so."""
    ds, floor = state.ds, delay_floor_s(state.ds)
    diff = (ds.t0_s - direct.t0_s(state.c_stated, ds.t0_s))[direct.detected]
    median = float(np.median(diff))
    mad = 1.4826 * float(np.median(np.abs(diff - median)))
    sigma = mad / np.sqrt(len(diff))
    v_gd = judge(median * 1e6, sigma * 1e6, len(diff) - 1, abs(median), floor, "us")
    gd = ParameterEstimate("group_delay", "s", median, sigma, v_gd.apply, False,
                           f"direct sound's arrival per recording, median (at the stated c); {v_gd.why}")
    if not state.options.per_stop_delay:
        timing = ParameterEstimate("timing", "s RMS", mad, float("nan"), False, False,
                                   "per_stop_delay=False: the median delay only")
    else:
        v_t = judge(mad * 1e6, float("nan"), 1, mad, floor, "us")
        timing = ParameterEstimate("timing", "s RMS", mad, float("nan"), v_t.apply, False,
                                   f"each recording's own direct arrival, their scatter; {v_t.why}")
    return gd, timing


def _delay_search(state: FocusState, max_delay_s: float, tolerance_s: float) -> tuple[ParameterEstimate, float]:
    """Without the direct sound: the two halves' sharpest global delays, and the delay to apply
    (where they agree and :func:`.significance.judge` passes it; else 0), s."""
    t = time.perf_counter()
    ds = state.ds
    base = ds.t0_s - ds.t0_s
    found = [_bounded_search(lambda dd, h=h: state.half_metric(h, base + dd, state.c_stated, None, "delay"),
                             -max_delay_s, max_delay_s, step=max_delay_s / 10, tol=2e-7)[0] for h in state.halves]
    ag = agreement(found[0], found[1], -max_delay_s, max_delay_s, tolerance_s)
    state.rep.stages.append({"step": "delay", "halves_s": list(ag["halves"]), "time_s": time.perf_counter() - t})
    how = f"no direct sound: sharpest delay of the two halves {found[0] * 1e6:+.1f} and {found[1] * 1e6:+.1f} us"
    if not ag["determined"]:
        how += "; they disagree (or sit at the edge of the hardware range): not determined, left at 0"
    else:
        verdict = judge(ag["estimate"] * 1e6, ag["uncertainty"] * 1e6, 1, abs(ag["estimate"]),
                        delay_floor_s(ds), "us")
        ag["determined"] = verdict.apply
        how += "; " + verdict.why + ("" if verdict.apply else ": left at 0")
    extra_s = ag["estimate"] if ag["determined"] else 0.0  # a shift dd reads the profile dd later: t0 + dd
    return ParameterEstimate("group_delay", "s", -ag["estimate"], ag["uncertainty"], ag["determined"], False,
                             how), extra_s


def temperature(state: FocusState) -> float:
    """The temperature offset the two halves' sharpest images agree on, °C, where it is beyond
    its uncertainty and changes the image (:func:`.significance.judge`); else 0 (stated kept)."""
    t = time.perf_counter()
    ds, move = state.ds, state.move
    range_c, tolerance_c = state.options.temperature_range_c, state.options.temperature_tolerance_c

    def f_temp(dt, h):
        c = state.c_at(dt)
        return state.half_metric(h, state.t0_at(c) - ds.t0_s, c, move, "temperature")

    found = [_bounded_search(lambda dt, h=h: f_temp(dt, h), -range_c, range_c, step=min(1.0, range_c / 2),
                             tol=0.02)[0] for h in state.halves]
    # each half is half the aperture: the whole one determines c at least sqrt(2) better
    ag = agreement(found[0], found[1], -range_c, range_c, tolerance_c * np.sqrt(2))
    ag["uncertainty"] /= np.sqrt(2)
    how = (f"sharpest image of each half at {found[0]:+.2f} and {found[1]:+.2f} C from the stated "
           f"(search +-{range_c:g} C, the thermometer's stated uncertainty)")
    if ag["determined"]:
        how += _temperature_whole(state, ag, range_c)
    else:
        how += ("; at the edge of the search" if ag["at_edge"] else
                f"; uncertainty over {tolerance_c:g} C") + ": not determined, stated kept"
    state.rep.parameters["temperature"] = ParameterEstimate("temperature", "C offset", ag["estimate"],
                                                            ag["uncertainty"], ag["determined"], False, how)
    state.rep.stages.append({"step": "temperature", "halves_c": found, "determined": ag["determined"],
                             "time_s": time.perf_counter() - t})
    log.info("autofocus temperature: %s", how)
    return ag["estimate"] if ag["determined"] else 0.0


def _temperature_whole(state: FocusState, ag: dict, range_c: float) -> str:
    """Where the halves agree: the whole aperture's sharpest offset near their mean (into
    ``ag["estimate"]``), then judged (``ag["determined"]``); the words for the report."""
    ds, move = state.ds, state.move
    lo, hi = ag["estimate"] - 4 * ag["uncertainty"] - 0.1, ag["estimate"] + 4 * ag["uncertainty"] + 0.1

    def f_whole(dt):
        c = state.c_at(dt)
        return state.image_metric(state.t0_at(c) - ds.t0_s, c, "temperature", ds.tx_positions + move,
                                  ds.rx_positions + move)

    ag["estimate"] = _bounded_search(f_whole, max(lo, -range_c), min(hi, range_c), step=(hi - lo) / 4,
                                     tol=0.01)[0]
    c_new = state.c_at(ag["estimate"])
    effect = delay_spread_s(ds, state.grid, state.t0_at(c_new), c_new)
    verdict = judge(ag["estimate"], ag["uncertainty"], 1, effect, delay_floor_s(ds), "C")
    ag["determined"] = verdict.apply
    return (f"; the whole aperture's sharpest at {ag['estimate']:+.2f} C; " + verdict.why
            + ("" if verdict.apply else ": stated kept"))


def _finish(fo: FocusState, started: float) -> tuple:
    """The check on the whole correction, the report's estimates, and the corrected dataset, or
    the input where nothing determined passed the check."""
    ds, engine, rep = fo.ds, fo.engine, fo.rep
    methods, d_temp, move, stop = fo.options.methods, fo.d_temp, fo.move, fo.stop
    c_est = fo.c_at(d_temp)
    t0_est = fo.t0_at(c_est)
    shift = t0_est - ds.t0_s
    tx, rx = ds.tx_positions + move, ds.rx_positions + move
    rep.metric_after = metric_and_weight(engine.image(shift, c_est, tx, rx), rep.metric)[0]
    rep.history.append(rep.metric_after)
    changed = bool(np.any(shift != 0) or d_temp != 0 or np.any(move != 0))
    if fo.halves is not None:  # judged against the direct sound's delay alone (a measurement, not a focus)
        before = fo.split_agreement(fo.t0_at(fo.c_stated) - ds.t0_s, fo.c_stated, None)
        after = fo.split_agreement(shift, c_est, move)
        for n, b, a in zip(fo.split_names, before, after, strict=True):
            rep.check.update({f"{n}_before": b, f"{n}_after": a})
        rep.check["passed"] = bool(min(a - b for a, b in zip(after, before, strict=True)) >= -FINAL_TOLERANCE)
        why = ("the disjoint sub-apertures' images agree less after the whole correction ("
               + ", ".join(f"{n} {b:.3f} -> {a:.3f}" for n, b, a in zip(fo.split_names, before, after, strict=True))
               + ")")
    else:  # no halves: only the direct sound's delay, which the physics determines, may be applied
        rep.check.update(passed=bool(not np.any(move != 0) and d_temp == 0))
        why = "too few stops to check anything but the direct sound's delay"
    rep.improved = bool(rep.check["passed"] and changed)
    _fill(rep, ds, t0_est, c_est, d_temp, fo.temp0, move, stop, methods, applied=rep.improved)
    rep.time_s = time.perf_counter() - started
    if not rep.improved:
        rep.metric_after = rep.metric_before
        rep.notes.append((why if not rep.check["passed"] else "nothing was determined well enough to apply")
                         + ": the input is returned unchanged; the estimates above are not applied")
        log.warning("autofocus: %s; returning the input", rep.notes[-1])
        if fo.options.consistency_iter:  # what the input leaves unexplained, for the record
            consistency_gate(ds, ds, fo.grid, rep, fo.options.consistency_iter, engine.selection)
            rep.time_s = time.perf_counter() - started
        return ds, rep
    new_temp = fo.temp0 + d_temp
    out = ds.replace(t0_s=t0_est, tx_positions=tx, rx_positions=rx, c_mps=c_est,
                     temperature_c=new_temp if np.ndim(ds.temperature_c) else float(new_temp[0]),
                     provenance=list(ds.provenance) + [{"step": "autofocus", **_record(rep)}])
    if fo.options.consistency_iter:
        out = _consistency_checked(fo, out, started)
    rep.time_s = time.perf_counter() - started
    log.info("%s", rep.summary())
    return out, rep


def _consistency_checked(fo: FocusState, out, started: float):
    """``out`` where the data-consistency gate passes; else the direct sound's delay alone (the
    physics determines it, no focus) where it was found, or the input."""
    ds, rep, stop, methods = fo.ds, fo.rep, fo.stop, fo.options.methods
    base = ds.replace(t0_s=fo.t0_at(fo.c_stated)) if fo.direct is not None else ds
    only_direct = bool(np.array_equal(out.t0_s, base.t0_s) and np.array_equal(out.tx_positions, ds.tx_positions)
                       and np.array_equal(out.c_per_meas, ds.c_per_meas))
    passed = consistency_gate(out if only_direct else base, out, fo.grid, rep, fo.options.consistency_iter,
                              fo.engine.selection)
    if not passed:
        rep.check["consistency_passed"] = False
        rep.metric_after = metric_and_weight(fo.engine.image(base.t0_s - ds.t0_s, fo.c_stated), rep.metric)[0]
        rep.history.append(rep.metric_after)
        rep.improved = fo.direct is not None and bool(np.any(base.t0_s != ds.t0_s))
        _fill(rep, ds, base.t0_s, fo.c_stated, 0.0, fo.temp0, np.zeros((ds.n_meas, 3)), stop, methods,
              applied=rep.improved)
        for p in rep.parameters.values():
            p.applied = bool(p.applied and p.name in ("group_delay", "timing") and fo.direct is not None)
        dropped = [n for n, changed in (("motion", np.any(out.tx_positions != ds.tx_positions)),
                                        ("air", np.any(out.c_per_meas != ds.c_per_meas)),
                                        ("delay", fo.direct is None and np.any(out.t0_s != ds.t0_s))) if changed]
        kept = "the direct sound's delay alone is returned" if rep.improved else "the input is returned unchanged"
        rep.notes.append(f"data consistency: the {', '.join(dropped) or 'correction'} estimate"
                         f"{'s are' if len(dropped) > 1 else ' is'} withdrawn; {kept}")
        log.warning("autofocus: %s (%s)", rep.notes[-1], rep.notes[-2])
    rep.time_s = time.perf_counter() - started
    if not rep.improved:
        rep.metric_after = rep.metric_before
        return ds
    return (out if passed else base).replace(provenance=list(ds.provenance) + [{"step": "autofocus", **_record(rep)}])


def _fill(rep, ds, t0_est, c_est, d_temp, temp0, move, stop, methods, applied: bool) -> None:
    """The report's estimates and each parameter's ``applied``."""
    rep.t0_s = t0_est
    rep.group_delay_s = float(np.median(ds.t0_s - t0_est))
    rep.timing_jitter_rms_s = float(np.sqrt(np.mean((ds.t0_s - t0_est - rep.group_delay_s) ** 2)))
    rep.temperature_offset_c = float(d_temp)
    rep.temperature_c = float(np.mean(temp0) + d_temp)
    rep.c_mps = float(np.mean(c_est))
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    if {"los", "phase", "points", "track", "3d", "pga"} & set(methods) and rep.focus_centre_m is not None:
        rep.los_path_m = _los_path(ds, rep.focus_centre_m, move, first)
    rep.position_correction_m = move
    rep.stop_index = stop
    for name, p in rep.parameters.items():
        p.applied = bool(applied and p.determined and (name != "motion" or np.any(move != 0)))
