"""The autofocus pipeline behind :func:`clsas.autofocus` (inputs already checked there)."""

from __future__ import annotations

import logging
import time

import numpy as np

from ..physics import speed_of_sound
from .direct import direct_arrivals
from .engine import FocusEngine
from .metrics import metric_and_weight
from .motion import default_basis_size, los_directions, motion_basis, optimise_los, optimise_xyz, stops_of
from .pga import pga_refine
from .phases import PHASE_MIN_GAIN, phase_to_path, stop_phase_search
from .report import AutofocusReport

log = logging.getLogger("clsas.autofocus")


def _bounded_search(f, lo: float, hi: float, step: float, tol: float) -> tuple[float, float, int]:
    """Maximise a 1-D ``f`` on ``[lo, hi]``: a scan at ``step``, then golden-section search
    in the bracket around the best point, to ``tol``. Returns ``(x, f(x), evaluations)``."""
    n = max(3, int(np.ceil((hi - lo) / step)) + 1)
    xs = np.linspace(lo, hi, n)
    fs = np.array([f(x) for x in xs])
    k = int(np.argmax(fs))
    a, b = xs[max(k - 1, 0)], xs[min(k + 1, n - 1)]
    best_x, best_f = float(xs[k]), float(fs[k])
    g = (np.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    evals = n + 2
    while b - a > tol:
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
        evals += 1
    for x, fx in ((c, fc), (d, fd)):
        if fx > best_f:
            best_x, best_f = float(x), float(fx)
    return best_x, best_f, evals


def run(ds, grid, *, methods, metric, n_basis, bandwidth_hz, temperature_range_c, max_delay_s, per_stop_delay,
        max_iter, backend, device, progress, force, started, phase_sweeps=4, max_stop_bytes=1 << 30,
        smooth_start=True, pga_options=None) -> tuple:
    """The stages of :func:`clsas.autofocus` in turn: the direct sound, the temperature, a
    global delay, per-stop phases, line-of-sight motion, 3-D motion, PGA; then the corrected
    dataset (or the input, where the image did not get sharper) and the report."""
    rep = AutofocusReport(metric=metric, methods=list(methods))
    temp0 = np.broadcast_to(np.asarray(ds.temperature_c, float), (ds.n_meas,)).copy()
    # profiles reach past the grid's gate by the largest delay change searched: the delay, the
    # motion (0.1 ms: 34 mm of path) and c (|dc / c| <= dT / (2 (273.15 + T)))
    rel = 0.5 * temperature_range_c / (273.15 + float(temp0.min()) - temperature_range_c) if "temperature" in methods \
        else 0.0
    engine = FocusEngine(ds, grid, margin_s=max_delay_s + 1e-4, rel_margin=rel, metric=metric, backend=backend,
                         device=device, force=force)
    rep.backend, rep.device = engine.backend, engine.device
    fo = _Focus(ds, engine, rep, metric, progress, temp0, per_stop_delay)
    m0 = fo.image_metric(np.zeros(ds.n_meas), fo.c_stated, "input")
    rep.metric_before = m0
    stop, t_stop, xy = stops_of(ds)
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]  # each stop's first measurement
    if "direct" in methods:  # 1. the direct sound: each recording's t0 at a given c
        fo.find_direct(max_delay_s)
    d_temp = 0.0  # 2. temperature (c) from sharpness; the direct-path delays follow c
    if "temperature" in methods and temperature_range_c > 0:
        d_temp = fo.temperature(temperature_range_c)
    c_est = fo.c_at(d_temp)
    t0_est = fo.t0_at(c_est)
    if "delay" in methods and fo.direct is None and max_delay_s > 0:  # 3. a global delay, where no direct sound
        t0_est = fo.global_delay(t0_est, c_est, max_delay_s)
    # 4. per-stop phases by coordinate ascent: the global start for large motion
    shift = t0_est - ds.t0_s
    p_stop = np.zeros(len(t_stop))
    if "phase" in methods:
        p_stop = _phase_step(engine, ds, grid, shift, c_est, stop, phase_sweeps, max_stop_bytes, fo.image_metric,
                             rep.history, progress, rep)
    if "los" in methods:  # 5. line-of-sight motion
        p_stop = fo.line_of_sight(shift, c_est, stop, t_stop, xy, p_stop, n_basis, bandwidth_hz, max_iter)
    # the corrected dataset: t0 and air as estimated, positions moved along the line of sight
    centre = _focus_centre(engine, grid, shift - p_stop[stop] / c_est, c_est)
    rep.focus_centre_m = centre
    move = (-0.5 * p_stop[stop])[:, None] * los_directions(ds, centre)  # a path shorter by p: the pair was p/2 nearer
    if "3d" in methods:  # 6. the carriage's 3-D displacement per stop, from the line of sight on
        move = fo.carriage_3d(t0_est - ds.t0_s, c_est, stop, t_stop, xy, move, n_basis, bandwidth_hz, max_iter,
                              smooth_start)
        p_stop = _los_path(ds, centre, move, first)
    if "pga" in methods:  # 7. phase-gradient autofocus on strong points: per-stop 3-D refinement
        move, changed = _pga_step(engine, ds, t0_est - ds.t0_s, c_est, stop, xy, move, pga_options or {},
                                  fo.image_metric, rep)
        if changed:
            p_stop = _los_path(ds, centre, move, first)
    return _finish(ds, engine, rep, methods, m0, t0_est, c_est, d_temp, temp0, p_stop, move, stop, started)


class _Focus:
    """What the stages of :func:`run` share: the dataset, the engine, the report (its history of
    metrics), the stated air, and the direct sound once found; the scalar stages as methods."""

    def __init__(self, ds, engine, rep, metric, progress, temp0, per_stop_delay):
        self.ds, self.engine, self.rep, self.metric, self.progress = ds, engine, rep, metric, progress
        self.temp0, self.per_stop_delay = temp0, per_stop_delay
        self.c_stated = ds.c_per_meas
        self.direct = None

    def c_at(self, dt):  # the stated c scaled as a temperature offset dt scales it
        temp0 = self.temp0
        return self.c_stated * np.asarray(speed_of_sound(temp0 + dt), float) / np.asarray(speed_of_sound(temp0), float)

    def image_metric(self, shift, c, step, tx=None, rx=None):
        m = metric_and_weight(self.engine.image(shift, c, tx, rx), self.metric)[0]
        self.rep.history.append(m)
        if self.progress is not None:
            self.progress(step, len(self.rep.history), m)
        return m

    def t0_at(self, c):
        ds = self.ds
        if self.direct is None:
            return ds.t0_s.copy()
        t0 = self.direct.t0_s(c, ds.t0_s)
        if not self.per_stop_delay:
            t0 = ds.t0_s + float(np.median(t0 - ds.t0_s))
        return t0

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

    def temperature(self, temperature_range_c: float) -> float:
        """The temperature offset from the stated one that gives the sharpest image, °C (0 where
        that is at the edge of the search)."""
        t = time.perf_counter()

        def f_temp(dt):
            c = self.c_at(dt)
            return self.image_metric(self.t0_at(c) - self.ds.t0_s, c, "temperature")

        d_temp, m_t, n_ev = _bounded_search(f_temp, -temperature_range_c, temperature_range_c,
                                            step=min(1.0, temperature_range_c / 2), tol=0.01)
        if abs(d_temp) >= temperature_range_c - 0.05 * temperature_range_c:
            self.rep.notes.append(f"temperature: the sharpest image is at the edge of the search ({d_temp:+.2f} C): "
                                  "not determined by this scan and grid (a narrow aperture for its range?); "
                                  "stated kept")
            d_temp = 0.0
        self.rep.stages.append({"step": "temperature", "metric": m_t, "evaluations": n_ev,
                                "offset_c": d_temp, "time_s": time.perf_counter() - t})
        log.info("autofocus temperature: %+.3f C from the stated one (metric %.5g, %d images)", d_temp, m_t, n_ev)
        return d_temp

    def global_delay(self, t0_est, c_est, max_delay_s: float):
        """``t0_est`` plus the one delay that gives the sharpest image, s."""
        t = time.perf_counter()
        base = t0_est - self.ds.t0_s

        def f_delay(dd):
            return self.image_metric(base + dd, c_est, "delay")

        dd, m_d, n_ev = _bounded_search(f_delay, -max_delay_s, max_delay_s, step=max_delay_s / 10, tol=2e-7)
        self.rep.notes.append(f"group delay from sharpness alone (weakly determined: it mostly shifts the image): "
                              f"{-dd * 1e6:+.1f} us")  # the summary's sign: t0_s lowered by it
        self.rep.stages.append({"step": "delay", "metric": m_d, "evaluations": n_ev, "delay_s": dd,
                                "time_s": time.perf_counter() - t})
        return t0_est + dd

    def line_of_sight(self, shift, c_est, stop, t_stop, xy, p_stop, n_basis, bandwidth_hz, max_iter):
        """``p_stop`` plus the line-of-sight path changes per stop (a smooth motion basis), m."""
        rep = self.rep
        t = time.perf_counter()
        k = n_basis or default_basis_size(t_stop, len(t_stop), bandwidth_hz, self.ds.timestamps is not None)
        k = min(k, max(len(t_stop) - 3, 1))
        basis = motion_basis(t_stop, xy, k)
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

    def carriage_3d(self, shift, c_est, stop, t_stop, xy, move, n_basis, bandwidth_hz, max_iter, smooth_start):
        """The carriage's 3-D displacement per measurement (n_meas, 3), m, started from ``move``."""
        t = time.perf_counter()
        start = _per_stop_mean(move, stop)
        k = n_basis or default_basis_size(t_stop, len(t_stop), bandwidth_hz, self.ds.timestamps is not None)
        basis = motion_basis(t_stop, xy, min(k, max(len(t_stop) - 3, 1))) if k < len(t_stop) else None
        if basis is not None and smooth_start:
            # the carriage moves smoothly: the start keeps the line-of-sight move's part in the basis
            # and in the unseen constant and tilt; what is left is the per-stop estimates' noise
            # and the line of sight's own turn from stop to stop, not motion
            nuis, _ = np.linalg.qr(np.c_[np.ones(len(t_stop)), xy - xy.mean(axis=0)])
            start = basis @ (basis.T @ start) + nuis @ (nuis.T @ start)
        d, info = optimise_xyz(self.engine, shift, c_est, stop, start, max_iter, self.rep.history,
                               callback=self.progress, basis=basis)
        self.rep.n_basis = info["functions"]
        self.rep.stages.append({"step": "3d", "metric": info["metric"], "evaluations": info["evaluations"],
                                "time_s": time.perf_counter() - t})
        return d[stop]


def _focus_centre(engine, grid, shift, c) -> np.ndarray:
    """The image's centre of energy (|value|^2), m."""
    values = engine.image(shift, c)
    mag2 = np.abs(values) ** 2
    pts = grid.points()
    return (pts * mag2[:, None]).sum(axis=0) / max(mag2.sum(), 1e-300)


def _finish(ds, engine, rep, methods, m0, t0_est, c_est, d_temp, temp0, p_stop, move, stop, started) -> tuple:
    """The final image's metric, the report's estimates, and the corrected dataset, or the input
    where the image did not get sharper."""
    metric = rep.metric
    tx, rx = ds.tx_positions + move, ds.rx_positions + move
    m_final = metric_and_weight(engine.image(t0_est - ds.t0_s, c_est, tx, rx), metric)[0]
    rep.history.append(m_final)
    rep.t0_s = t0_est
    rep.group_delay_s = float(np.median(ds.t0_s - t0_est))
    rep.timing_jitter_rms_s = float(np.sqrt(np.mean((ds.t0_s - t0_est - rep.group_delay_s) ** 2)))
    rep.temperature_offset_c = float(d_temp)
    rep.temperature_c = float(np.mean(temp0) + d_temp)
    rep.c_mps = float(np.mean(c_est))
    rep.los_path_m = p_stop if {"los", "phase", "3d", "pga"} & set(methods) else None
    rep.position_correction_m = move
    rep.stop_index = stop
    rep.metric_after = m_final
    rep.improved = bool(m_final > m0)
    rep.time_s = time.perf_counter() - started
    if not rep.improved:
        rep.metric_after = m0
        rep.notes.append(f"the image did not get sharper ({metric} {m_final:.5g} against {m0:.5g} as given): "
                         "the input is returned unchanged; the estimates above are not applied")
        log.warning("autofocus: no improvement (%s %.5g <= %.5g); returning the input", metric, m_final, m0)
        return ds, rep
    new_temp = temp0 + d_temp
    out = ds.replace(t0_s=t0_est, tx_positions=tx, rx_positions=rx, c_mps=c_est,
                     temperature_c=new_temp if np.ndim(ds.temperature_c) else float(new_temp[0]),
                     provenance=list(ds.provenance) + [{"step": "autofocus", **_record(rep)}])
    log.info("%s", rep.summary())
    return out, rep


def _phase_step(engine, ds, grid, shift, c, stop, sweeps, max_bytes, image_metric, history, progress, rep):
    """Per-stop phases (:mod:`.phases`) read as line-of-sight paths; zero if the image does not agree."""
    t = time.perf_counter()
    n_stops = int(stop.max()) + 1
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
    zero = np.zeros(n_stops)
    if n_stops < 3:
        rep.notes.append("phase: fewer than 3 stops; not estimated")
        return zero
    voxels = None
    if n_stops * grid.size * 8 > max_bytes:  # complex64 stop images: keep the brightest voxels
        keep = max(int(max_bytes // (8 * n_stops)), 1)
        values = engine.image(shift, c)
        voxels = np.sort(np.argsort(np.abs(values))[-keep:])
        rep.notes.append(f"phase: stop images on the {keep} brightest of {grid.size} voxels (memory)")
    a = engine.stop_images(shift, c, stop, voxels)
    phi, info = stop_phase_search(a, sweeps=sweeps, history=history, callback=progress)
    del a
    p = phase_to_path(phi, c[first], engine.prof.fc_hz)
    m_before = image_metric(shift, c, "phase")
    m_after = image_metric(shift - p[stop] / c, c, "phase")
    kept = m_after > m_before + PHASE_MIN_GAIN
    rep.stages.append({"step": "phase", "metric": m_after, "sweeps": info["sweeps"], "kept": kept,
                       "time_s": time.perf_counter() - t})
    if not kept:
        rep.notes.append(f"phase: the per-stop phases did not sharpen the image by more than fitting the noise "
                         f"does ({m_after:.5g} against {m_before:.5g}); not used")
        return zero
    log.info("autofocus phase: %d sweeps, %.2f mm RMS of path, metric %.5g", info["sweeps"],
             float(np.sqrt(np.mean(p**2))) * 1e3, m_after)
    return p


def _per_stop_mean(move, stop) -> np.ndarray:
    """(n_stops, 3): the mean of ``move`` (n_meas, 3) over each stop's measurements."""
    n = np.bincount(stop)
    return np.stack([np.bincount(stop, move[:, k], len(n)) / n for k in range(3)], axis=1)


def _los_path(ds, centre, move, first) -> np.ndarray:
    """The bistatic path change at ``centre`` that the displacement ``move`` makes, per stop, m."""
    path = np.linalg.norm(centre - ds.tx_positions, axis=1) + np.linalg.norm(centre - ds.rx_positions, axis=1)
    moved = np.linalg.norm(centre - ds.tx_positions - move, axis=1) \
        + np.linalg.norm(centre - ds.rx_positions - move, axis=1)
    return (moved - path)[first]


def _pga_step(engine, ds, shift, c, stop, xy, move, options, image_metric, rep) -> tuple[np.ndarray, bool]:
    """PGA from the displacement ``move`` (n_meas, 3); kept where the image gets sharper."""
    t = time.perf_counter()
    start = _per_stop_mean(move, stop)
    d, info = pga_refine(engine, shift, c, stop, start, xy, **options)
    stage = {"step": "pga", "points": info["points"], "candidates": info["candidates"],
             "iterations": info["iterations"], "kept": False, "coherence": info["coherence"],
             "coherence_after": info.get("coherence_after", [])}
    if info["reason"]:
        rep.notes.append(f"pga: no strong isolated points ({info['reason']}): not used")
        rep.stages.append({**stage, "time_s": time.perf_counter() - t})
        return move, False
    tx, rx = ds.tx_positions + move, ds.rx_positions + move
    m_before = image_metric(shift, c, "pga", tx, rx)
    m_after = image_metric(shift, c, "pga", ds.tx_positions + d[stop], ds.rx_positions + d[stop])
    stage.update(metric=m_after, kept=bool(m_after > m_before), time_s=time.perf_counter() - t)
    rep.stages.append(stage)
    if not stage["kept"]:
        rep.notes.append(f"pga: {info['points']} strong points, but their per-stop phases did not sharpen the image "
                         f"({m_after:.5g} against {m_before:.5g}); not used")
        return move, False
    rep.notes.append(f"pga: {info['points']} strong points (coherence after {max(info['coherence_after']):.2f} "
                     f"at best), {info['iterations']} iterations, per-stop 3-D moves "
                     f"{np.sqrt(np.mean(np.sum((d - start) ** 2, axis=1))) * 1e3:.3f} mm RMS")
    log.info("autofocus pga: %d points, metric %.5g -> %.5g", info["points"], m_before, m_after)
    return d[stop], True


def _record(rep) -> dict:
    d = rep.as_dict()
    d.pop("stages", None)
    return d
