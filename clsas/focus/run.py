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

import numpy as np

from ..physics import speed_of_sound
from .consistency_gate import consistency_gate
from .direct import direct_arrivals
from .engine import FocusEngine
from .metrics import metric_and_weight
from .motion import default_basis_size, motion_basis, optimise_los, stops_of
from .options import AutofocusOptions
from .report import AutofocusReport, ParameterEstimate
from .significance import delay_floor_s, delay_spread_s, judge
from .split import agreement, magnitude_correlation, split_halves
from .steps import _bounded_search, _los_path, _record

__all__ = ["run"]

log = logging.getLogger("clsas.autofocus")

FINAL_TOLERANCE = 0.005  # the returned correction may lower a sub-aperture pair's agreement by at most this


def run(ds, grid, options: AutofocusOptions, *, progress, started) -> tuple:
    """The stages of :func:`clsas.autofocus` in turn: the direct sound, a delay, the motion, the
    temperature; then the check and the corrected dataset (or the input) and the report."""
    o, methods = options, options.methods
    rep = AutofocusReport(metric=o.metric, methods=list(methods))
    temp0 = np.broadcast_to(np.asarray(ds.temperature_c, float), (ds.n_meas,)).copy()
    rel = 0.5 * o.temperature_range_c / (273.15 + float(temp0.min()) - o.temperature_range_c) \
        if "temperature" in methods else 0.0
    eopt = dict(margin_s=o.max_delay_s + 1e-4, rel_margin=rel, metric=o.metric, force=o.force)
    engine = FocusEngine(ds, grid, backend=o.backend, device=o.device, **eopt)
    rep.backend, rep.device = engine.backend, engine.device
    fo = _Focus(ds, engine, rep, o.metric, progress, temp0, o.per_stop_delay)
    fo.phase_region_m, fo.engine_options, fo.heldout_gain = o.phase_region_m, eopt, o.heldout_gain
    fo.track_tolerance_m, fo.grid, fo.consistency_iter = o.track_tolerance_m, grid, o.consistency_iter
    rep.metric_before = fo.image_metric(np.zeros(ds.n_meas), fo.c_stated, "input")
    stop, t_stop, xy = stops_of(ds)
    fo.splits = [hs for hs in (split_halves(ds, grid, stop, xy, how, backend=engine.selection, **eopt)
                               for how in fo.split_names) if hs is not None]
    fo.halves = fo.splits[0] if len(fo.splits) == len(fo.split_names) else None
    if fo.halves is None:
        rep.notes.append("fewer than 8 stops: no halves to check with; only what the direct sound gives is applied")
    if "direct" in methods:  # the direct sound: each recording's t0 at a given c
        fo.find_direct(o.max_delay_s)
    fo.delay_parameters("delay" in methods, o.max_delay_s, o.delay_tolerance_s)
    zero3 = np.zeros((ds.n_meas, 3))
    move, motion_ok = zero3, False
    if o.motion and fo.halves is not None:
        move, motion_ok = fo.motion(methods, stop, t_stop, xy, o.n_basis, o.motion_bandwidth_hz, o.max_iter,
                                    o.phase_sweeps, o.max_stop_bytes, True, o.pga_options, o.check_margin)
    d_temp = 0.0
    if "temperature" in methods and o.temperature_range_c > 0 and fo.halves is not None:
        d_temp = fo.temperature(o.temperature_range_c, o.temperature_tolerance_c, move if motion_ok else zero3)
    return _finish(fo, methods, d_temp, move if motion_ok else zero3, stop, started)


class _Focus:
    """What the stages of :func:`run` share: the dataset, the engine and the sub-apertures' engines,
    the report, the stated air, the direct sound once found, the delay found without it."""

    def __init__(self, ds, engine, rep, metric, progress, temp0, per_stop_delay):
        self.ds, self.engine, self.rep, self.metric, self.progress = ds, engine, rep, metric, progress
        self.temp0, self.per_stop_delay = temp0, per_stop_delay
        self.c_stated = ds.c_per_meas
        self.direct = None
        self.direct_use = "none"  # what of the direct sound's t0 is applied: "none", "median" or "per_stop"
        self.halves = None
        self.extra_delay = 0.0  # a global delay determined without the direct sound, s
        self.grid, self.consistency_iter = engine.grid, 0

    def c_at(self, dt):  # the stated c scaled as a temperature offset dt scales it (at the dataset's humidity)
        temp0, hum = self.temp0, self.ds.humidity_pct
        return self.c_stated * (np.asarray(speed_of_sound(temp0 + dt, hum), float)
                                / np.asarray(speed_of_sound(temp0, hum), float))

    def image_metric(self, shift, c, step, tx=None, rx=None):
        m = metric_and_weight(self.engine.image(shift, c, tx, rx), self.metric)[0]
        self.rep.history.append(m)
        if self.progress is not None:
            self.progress(step, len(self.rep.history), m)
        return m

    def metric_of(self, values, step):
        m = metric_and_weight(values, self.metric)[0]
        self.rep.history.append(m)
        if self.progress is not None:
            self.progress(step, len(self.rep.history), m)
        return m

    def half_metric(self, h, shift, c, move, step):
        m = metric_and_weight(h.image(shift, c, move), self.metric)[0]
        self.rep.history.append(m)
        if self.progress is not None:
            self.progress(step, len(self.rep.history), m)
        return m

    def t0_at(self, c):
        ds = self.ds
        if self.direct is None:
            return ds.t0_s + self.extra_delay
        if self.direct_use == "none":
            return ds.t0_s.copy()
        t0 = self.direct.t0_s(c, ds.t0_s)
        if self.direct_use == "median":
            t0 = ds.t0_s + float(np.median(t0 - ds.t0_s))
        return t0

    split_names = ("time", "x")

    def split_agreement(self, shift, c, move) -> list[float]:
        """Per pair of sub-apertures (``split_names``): their images' magnitude correlation."""
        return [magnitude_correlation(a.image(shift, c, move), b.image(shift, c, move)) for a, b in self.splits]

    def find_direct(self, max_delay_s: float) -> None:
        """The direct sound's arrivals (kept in ``self.direct`` where found), noted in the report."""
        ds, rep = self.ds, self.rep
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
        self.direct = direct
        rep.stages.append({"step": "direct", "found": direct is not None, "time_s": time.perf_counter() - t})

    def delay_parameters(self, search: bool, max_delay_s: float, tolerance_s: float) -> None:
        """The group delay and per-stop timing: from the direct sound, else (``search``) the
        two halves' sharpest delays where they agree, else not determined (0)."""
        rep = self.rep
        gd = ParameterEstimate("group_delay", "s", 0.0, float("nan"), False, False,
                               "no direct sound: a delay mostly shifts the image in range, which no focus "
                               "metric sees; left at 0")
        timing = ParameterEstimate("timing", "s RMS", 0.0, float("nan"), False, False, "no direct sound")
        if self.direct is not None:
            gd, timing = self._direct_delays()
        elif search and max_delay_s > 0 and self.halves is not None:
            gd = self._delay_search(max_delay_s, tolerance_s)
        rep.parameters["group_delay"], rep.parameters["timing"] = gd, timing

    def _direct_delays(self) -> tuple[ParameterEstimate, ParameterEstimate]:
        """The group delay (the recordings' median) and the timing (their scatter) from the direct
        sound's arrivals, each applied only where :func:`.significance.judge` says so; sets
        ``direct_use`` accordingly."""
        ds, floor = self.ds, delay_floor_s(self.ds)
        diff = (ds.t0_s - self.direct.t0_s(self.c_stated, ds.t0_s))[self.direct.detected]
        median = float(np.median(diff))
        mad = 1.4826 * float(np.median(np.abs(diff - median)))
        sigma = mad / np.sqrt(len(diff))
        v_gd = judge(median * 1e6, sigma * 1e6, len(diff) - 1, abs(median), floor, "us")
        gd = ParameterEstimate("group_delay", "s", median, sigma, v_gd.apply, False,
                               f"direct sound's arrival per recording, median (at the stated c); {v_gd.why}")
        if not self.per_stop_delay:
            timing = ParameterEstimate("timing", "s RMS", mad, float("nan"), False, False,
                                       "per_stop_delay=False: the median delay only")
        else:
            v_t = judge(mad * 1e6, float("nan"), 1, mad, floor, "us")
            timing = ParameterEstimate("timing", "s RMS", mad, float("nan"), v_t.apply, False,
                                       f"each recording's own direct arrival, their scatter; {v_t.why}")
        self.direct_use = "per_stop" if timing.determined else "median" if gd.determined else "none"
        return gd, timing

    def _delay_search(self, max_delay_s: float, tolerance_s: float) -> ParameterEstimate:
        t = time.perf_counter()
        base = self.ds.t0_s - self.ds.t0_s
        found = [_bounded_search(lambda dd, h=h: self.half_metric(h, base + dd, self.c_stated, None, "delay"),
                                 -max_delay_s, max_delay_s, step=max_delay_s / 10, tol=2e-7)[0] for h in self.halves]
        ag = agreement(found[0], found[1], -max_delay_s, max_delay_s, tolerance_s)
        self.rep.stages.append({"step": "delay", "halves_s": list(ag["halves"]), "time_s": time.perf_counter() - t})
        how = f"no direct sound: sharpest delay of the two halves {found[0] * 1e6:+.1f} and {found[1] * 1e6:+.1f} us"
        if not ag["determined"]:
            how += "; they disagree (or sit at the edge of the hardware range): not determined, left at 0"
        else:
            verdict = judge(ag["estimate"] * 1e6, ag["uncertainty"] * 1e6, 1, abs(ag["estimate"]),
                            delay_floor_s(self.ds), "us")
            ag["determined"] = verdict.apply
            how += "; " + verdict.why + ("" if verdict.apply else ": left at 0")
        if ag["determined"]:
            self.extra_delay = ag["estimate"]  # a shift dd reads the profile dd later: t0 + dd
        return ParameterEstimate("group_delay", "s", -ag["estimate"], ag["uncertainty"], ag["determined"], False, how)

    def temperature(self, range_c: float, tolerance_c: float, move) -> float:
        """The temperature offset the two halves' sharpest images agree on, °C, where it is beyond
        its uncertainty and changes the image (:func:`.significance.judge`); else 0 (stated kept)."""
        t = time.perf_counter()

        def f_temp(dt, h):
            c = self.c_at(dt)
            return self.half_metric(h, self.t0_at(c) - self.ds.t0_s, c, move, "temperature")

        found = [_bounded_search(lambda dt, h=h: f_temp(dt, h), -range_c, range_c, step=min(1.0, range_c / 2),
                                 tol=0.02)[0] for h in self.halves]
        # each half is half the aperture: the whole one determines c at least sqrt(2) better
        ag = agreement(found[0], found[1], -range_c, range_c, tolerance_c * np.sqrt(2))
        ag["uncertainty"] /= np.sqrt(2)
        how = (f"sharpest image of each half at {found[0]:+.2f} and {found[1]:+.2f} C from the stated "
               f"(search +-{range_c:g} C, the thermometer's stated uncertainty)")
        if ag["determined"]:
            how += self._temperature_whole(ag, range_c, move)
        else:
            how += ("; at the edge of the search" if ag["at_edge"] else
                    f"; uncertainty over {tolerance_c:g} C") + ": not determined, stated kept"
        self.rep.parameters["temperature"] = ParameterEstimate("temperature", "C offset", ag["estimate"],
                                                               ag["uncertainty"], ag["determined"], False, how)
        self.rep.stages.append({"step": "temperature", "halves_c": found, "determined": ag["determined"],
                                "time_s": time.perf_counter() - t})
        log.info("autofocus temperature: %s", how)
        return ag["estimate"] if ag["determined"] else 0.0

    def _temperature_whole(self, ag: dict, range_c: float, move) -> str:
        """Where the halves agree: the whole aperture's sharpest offset near their mean (into
        ``ag["estimate"]``), then judged (``ag["determined"]``); the words for the report."""
        lo, hi = ag["estimate"] - 4 * ag["uncertainty"] - 0.1, ag["estimate"] + 4 * ag["uncertainty"] + 0.1

        def f_whole(dt):
            c = self.c_at(dt)
            return self.image_metric(self.t0_at(c) - self.ds.t0_s, c, "temperature",
                                     self.ds.tx_positions + move, self.ds.rx_positions + move)

        ag["estimate"] = _bounded_search(f_whole, max(lo, -range_c), min(hi, range_c), step=(hi - lo) / 4,
                                         tol=0.01)[0]
        c_new = self.c_at(ag["estimate"])
        effect = delay_spread_s(self.ds, self.grid, self.t0_at(c_new), c_new)
        verdict = judge(ag["estimate"], ag["uncertainty"], 1, effect, delay_floor_s(self.ds), "C")
        ag["determined"] = verdict.apply
        return (f"; the whole aperture's sharpest at {ag['estimate']:+.2f} C; " + verdict.why
                + ("" if verdict.apply else ": stated kept"))

    def motion(self, methods, stop, t_stop, xy, n_basis, bandwidth_hz, max_iter, sweeps, max_bytes, smooth_start,
               pga_options, margin) -> tuple[np.ndarray, bool]:
        """The carriage's displacement (n_meas, 3), m, and whether it passed the held-out check."""
        from .motion_steps import estimate_motion

        return estimate_motion(self, methods, stop, t_stop, xy, n_basis, bandwidth_hz, max_iter, sweeps, max_bytes,
                               smooth_start, pga_options, margin)

    def line_of_sight(self, shift, c_est, stop, t_stop, xy, p_stop, n_basis, bandwidth_hz, max_iter):
        """``p_stop`` plus the line-of-sight path changes per stop (a smooth motion basis), m."""
        rep = self.rep
        t = time.perf_counter()
        k = n_basis or default_basis_size(t_stop, len(t_stop), bandwidth_hz, self.ds.timestamps is not None)
        basis = motion_basis(t_stop, xy, min(k, max(len(t_stop) - 3, 1)))
        rep.n_basis = basis.shape[1]
        if rep.n_basis == 0:
            rep.notes.append("line of sight: too few stops for a motion basis; not estimated")
            return p_stop
        stages = sorted({min(s, rep.n_basis) for s in (4, 12, rep.n_basis // 2, rep.n_basis) if s > 0})
        dp, info = optimise_los(self.engine, shift - p_stop[stop] / c_est, c_est, stop, basis, stages, max_iter,
                                rep.history, callback=self.progress)
        rep.stages.append({"step": "los", "metric": info["stages"][-1]["metric"],
                           "evaluations": info["evaluations"], "stages": info["stages"],
                           "time_s": time.perf_counter() - t})
        return p_stop + dp


def _finish(fo, methods, d_temp, move, stop, started) -> tuple:
    """The check on the whole correction, the report's estimates, and the corrected dataset, or
    the input where nothing determined passed the check."""
    ds, engine, rep = fo.ds, fo.engine, fo.rep
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
        if fo.consistency_iter:  # what the input leaves unexplained, for the record
            consistency_gate(ds, ds, fo.grid, rep, fo.consistency_iter, engine.selection)
            rep.time_s = time.perf_counter() - started
        return ds, rep
    new_temp = fo.temp0 + d_temp
    out = ds.replace(t0_s=t0_est, tx_positions=tx, rx_positions=rx, c_mps=c_est,
                     temperature_c=new_temp if np.ndim(ds.temperature_c) else float(new_temp[0]),
                     provenance=list(ds.provenance) + [{"step": "autofocus", **_record(rep)}])
    if fo.consistency_iter:
        out = _consistency_checked(fo, out, stop, methods, started)
    rep.time_s = time.perf_counter() - started
    log.info("%s", rep.summary())
    return out, rep


def _consistency_checked(fo, out, stop, methods, started):
    """``out`` where the data-consistency gate passes; else the direct sound's delay alone (the
    physics determines it, no focus) where it was found, or the input."""
    ds, rep = fo.ds, fo.rep
    base = ds.replace(t0_s=fo.t0_at(fo.c_stated)) if fo.direct is not None else ds
    only_direct = bool(np.array_equal(out.t0_s, base.t0_s) and np.array_equal(out.tx_positions, ds.tx_positions)
                       and np.array_equal(out.c_per_meas, ds.c_per_meas))
    passed = consistency_gate(out if only_direct else base, out, fo.grid, rep, fo.consistency_iter,
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
