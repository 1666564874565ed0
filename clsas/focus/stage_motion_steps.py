"""The motion stage's steps on the whole scan (:mod:`.stage_motion`): per-stop phases and their
held-out check, PGA, the focus centre, per-stop means."""

from __future__ import annotations

import logging
import time

import numpy as np

from .pga import pga_refine
from .phases import PHASE_MIN_GAIN, phase_to_path, stop_phase_search

log = logging.getLogger("clsas.autofocus")


def _focus_centre(engine, grid, shift, c) -> np.ndarray:
    """The image's centre of energy (|value|^2), m."""
    values = engine.image(shift, c)
    mag2 = np.abs(values) ** 2
    pts = grid.points()
    return (pts * mag2[:, None]).sum(axis=0) / max(mag2.sum(), 1e-300)


def _phase_step(engine, ds, grid, shift, c, stop, sweeps, max_bytes, image_metric, history, progress, rep,
                margin=None):
    """Per-stop phases (:mod:`.phases`) read as line-of-sight paths; zero if the image does not agree.

    With ``margin``, the held-out check (:func:`_held_out_phases`) runs on the same stop images;
    its result goes to ``rep.check["phase_heldout"]``.
    """
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
    if margin is not None:
        rep.check["phase_heldout"] = _held_out_phases(a, sweeps, margin)
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


def _held_out_phases(a: np.ndarray, sweeps: int, margin: float = 0.01) -> dict:
    """Each half of the stops (even and odd in time) searched on its own, and judged on the other.

    The two halves interleave: each stop's neighbours in time belong to the other half, and hand
    motion is smooth, so a half's phases predict the other's (the mean phasor of the two
    neighbours). Returned, per direction: the held-out half's log-sharpness as given and with
    the predicted phases, and the agreement (magnitude correlation) of its image with the
    predicting half's own corrected image, as given and after (reported only: two interleaved
    halves blurred by the same smooth motion agree well before any correction). Noise or
    speckle fitted by one half does not sharpen the other; ``passed`` where both directions
    gain more than ``margin`` in sharpness.
    """
    from .phases import _log_sharpness
    from .split import magnitude_correlation

    n = a.shape[0]
    idx = [np.arange(0, n, 2), np.arange(1, n, 2)]
    phis = [stop_phase_search(a[i], sweeps=sweeps)[0] for i in idx]
    full = np.zeros((2, n), np.complex128)  # each half's phasors on its own stops, 0 elsewhere
    for h in (0, 1):
        full[h, idx[h]] = np.exp(1j * phis[h])
    out = {"passed": True}
    for h in (0, 1):  # half h predicts half 1 - h
        other = idx[1 - h]
        pred = np.zeros(len(other), np.complex128)
        for d in (-1, 1):
            nb = other + d
            ok = (nb >= 0) & (nb < n)
            pred[ok] += full[h, nb[ok]]
        pred = np.where(np.abs(pred) > 0, pred / np.maximum(np.abs(pred), 1e-300), 1.0)
        own = (full[h, idx[h]][:, None] * a[idx[h]]).sum(axis=0)
        given = a[other].sum(axis=0, dtype=np.complex128)
        held = (pred[:, None] * a[other]).sum(axis=0)
        r = {"sharpness_before": _log_sharpness(given), "sharpness_after": _log_sharpness(held),
             "agreement_before": magnitude_correlation(a[idx[h]].sum(axis=0, dtype=np.complex128), given),
             "agreement_after": magnitude_correlation(own, held)}
        out[f"from_{'even' if h == 0 else 'odd'}"] = r
        out["passed"] &= bool(r["sharpness_after"] > r["sharpness_before"] + margin)
    return out


def _per_stop_mean(move, stop) -> np.ndarray:
    """(n_stops, 3): the mean of ``move`` (n_meas, 3) over each stop's measurements."""
    n = np.bincount(stop)
    return np.stack([np.bincount(stop, move[:, k], len(n)) / n for k in range(3)], axis=1)


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
