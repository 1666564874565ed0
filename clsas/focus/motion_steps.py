"""The motion stages of :mod:`.run`: from two halves of the stops (``"3d"``, the default), or on
the whole scan (``"phase"``, ``"los"``, ``"pga"`` without ``"3d"``); each behind a check.

With ``"3d"`` each half of the stops (:mod:`.split`) estimates the carriage motion in the same
smooth basis over stop time (constant and tilt projected out: the gauge no focus metric sees),
from its own per-stop phases where ``"phase"`` is asked; the coefficients are shrunk by how
well the halves agree, and the motion is applied only where each half's image, corrected with
the *other* half's estimate, agrees with it better than uncorrected (by ``check_margin`` in
coherence). On the whole scan there is nothing held out: the check then compares the halves'
images both corrected with the same estimate.
"""

from __future__ import annotations

import time

import numpy as np

from .motion import default_basis_size, los_directions, motion_basis
from .report import ParameterEstimate
from .split import combine, fit_half_motion
from .steps import _focus_centre, _pga_step, _phase_step

__all__ = ["split_motion", "full_motion"]


def _centre(engine, shift, c, move) -> np.ndarray:
    ds = engine.ds
    values = engine.image(shift, c, ds.tx_positions + move, ds.rx_positions + move)
    mag2 = np.abs(values) ** 2
    return (engine.grid.points() * mag2[:, None]).sum(axis=0) / max(mag2.sum(), 1e-300)


def split_motion(fo, methods, stop, t_stop, xy, n_basis, bandwidth_hz, max_iter, sweeps, max_bytes, margin
                 ) -> tuple[np.ndarray, bool]:
    """The motion from the two halves, and whether it passed the held-out check."""
    t = time.perf_counter()
    ds, rep = fo.ds, fo.rep
    zero = np.zeros((ds.n_meas, 3))
    c = fo.c_stated
    shift = fo.t0_at(c) - ds.t0_s
    k = n_basis or default_basis_size(t_stop, len(t_stop), bandwidth_hz, ds.timestamps is not None)
    basis = motion_basis(t_stop, xy, min(k, max(len(t_stop) // 2 - 3, 1)))
    rep.n_basis = basis.shape[1]
    rep.focus_centre_m = _centre(fo.engine, shift, c, zero)
    if rep.n_basis == 0:
        rep.notes.append("motion: too few stops for a motion basis; not estimated")
        return zero, False
    coefs, infos = [], []
    for h in fo.halves:
        coef, info = fit_half_motion(h, shift, c, basis, use_phase="phase" in methods, use_3d=True, sweeps=sweeps,
                                     max_bytes=max_bytes, max_iter=max_iter, history=rep.history,
                                     progress=fo.progress)
        coefs.append(coef)
        infos.append(info)

    def move_of(coef):
        return (basis @ coef)[stop]

    base = fo.halves_coherence(shift, c)
    held = fo.halves_coherence(shift, c, (move_of(coefs[1]), move_of(coefs[0])))
    applied, sigma, det = combine(*coefs)
    passed = bool(held > base + margin and det.any())
    rms = float(np.sqrt(np.mean(np.sum((basis @ applied) ** 2, axis=1))))
    unc = float(np.sqrt(np.mean(np.sum((basis @ sigma) ** 2, axis=1))))
    how = (f"{rep.n_basis} smooth functions x 3 axes from each half of the stops (phase start kept: "
           f"{[i['phase_kept'] for i in infos]}); {int(det.sum())} of {det.size} coefficients agree between the halves;"
           f" each half corrected with the other's estimate: coherence {base:.3f} -> {held:.3f}")
    rep.check.update(coherence_motion_base=base, coherence_heldout=held, motion_passed=passed)
    rep.parameters["motion"] = ParameterEstimate("motion", "m RMS", rms, unc, passed, False, how)
    rep.stages.append({"step": "3d", "halves": infos, "determined": int(det.sum()), "coefficients": int(det.size),
                       "coherence_base": base, "coherence_heldout": held, "time_s": time.perf_counter() - t})
    if not passed:
        rep.notes.append(f"motion: the halves' images corrected with each other's estimate agree "
                         f"{'less' if held <= base else 'not enough'} better (coherence {base:.3f} -> {held:.3f}, "
                         f"margin {margin:g}): not determined by this scan (the sharpness over-fits); not applied")
        return zero, False
    move = move_of(applied)
    rep.focus_centre_m = _centre(fo.engine, shift, c, move)
    return move, True


def full_motion(fo, methods, stop, t_stop, xy, n_basis, bandwidth_hz, max_iter, sweeps, max_bytes, smooth_start,
                pga_options, margin) -> tuple[np.ndarray, bool]:
    """``"phase"``, ``"los"``, ``"pga"`` on the whole scan; kept where the halves' images, both
    corrected with it, agree better by ``margin`` (not held out)."""
    ds, rep, engine = fo.ds, fo.rep, fo.engine
    c = fo.c_stated
    shift = fo.t0_at(c) - ds.t0_s
    p_stop = np.zeros(len(t_stop))
    if "phase" in methods:
        p_stop = _phase_step(engine, ds, engine.grid, shift, c, stop, sweeps, max_bytes, fo.image_metric,
                             rep.history, fo.progress, rep)
    if "los" in methods:
        p_stop = fo.line_of_sight(shift, c, stop, t_stop, xy, p_stop, n_basis, bandwidth_hz, max_iter)
    centre = _focus_centre(engine, engine.grid, shift - p_stop[stop] / c, c)
    rep.focus_centre_m = centre
    move = (-0.5 * p_stop[stop])[:, None] * los_directions(ds, centre)
    if "pga" in methods:
        move, _ = _pga_step(engine, ds, shift, c, stop, xy, move, pga_options, fo.image_metric, rep)
    base = fo.halves_coherence(shift, c)
    after = fo.halves_coherence(shift, c, (move, move))
    passed = bool(after > base + margin)
    rms = float(np.sqrt(np.mean(np.sum(move**2, axis=1))))
    rep.check.update(coherence_motion_base=base, coherence_motion=after, motion_passed=passed)
    rep.parameters["motion"] = ParameterEstimate(
        "motion", "m RMS", rms, float("nan"), passed, False,
        f"{'+'.join(m for m in methods if m in ('phase', 'los', 'pga'))} on all stops; the halves both corrected "
        f"with it: coherence {base:.3f} -> {after:.3f} (not held out)")
    if not passed:
        rep.notes.append(f"motion: the halves' images agree not enough better after it (coherence {base:.3f} -> "
                         f"{after:.3f}, margin {margin:g}): not applied")
        return np.zeros((ds.n_meas, 3)), False
    return move, True
