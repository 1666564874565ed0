"""The last stage of :func:`clsas.autofocus`: the check on the whole correction, and what comes back.

The correction that the stages applied (delays, motion, temperature) must not make the disjoint
sub-apertures agree less than the direct sound's delay alone does (by more than
:data:`FINAL_TOLERANCE`); without them only the direct sound's delay may be applied. Where it
passes and something changed, the corrected dataset comes back, else the input (a note says
why). With ``consistency_iter``, the data-consistency check (:mod:`.final_consistency`) may
still withdraw all but the direct sound's delay.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from .final_consistency import consistency_gate
from .metrics import metric_and_weight
from .state import FocusState

__all__ = ["FINAL_TOLERANCE", "Correction", "FinalCheck"]

log = logging.getLogger("clsas.autofocus")

FINAL_TOLERANCE = 0.005  # the returned correction may lower a sub-aperture pair's agreement by at most this


@dataclass(frozen=True, eq=False)
class Correction:
    """The whole correction the stages applied, and the sub-apertures' agreement before it (with
    the direct sound's delay alone) and after it, per pair (None: no sub-apertures).

    ``t0_s`` and ``c_mps`` (n_meas,), s and m/s; ``move`` (n_meas, 3), m; ``d_temp``, °C;
    ``changed``: any of them differs from the input.
    """

    t0_s: np.ndarray
    c_mps: np.ndarray
    move: np.ndarray
    d_temp: float
    changed: bool
    before: list[float] | None
    after: list[float] | None


class FinalCheck:
    """The check on the whole correction; :meth:`result` runs it and returns the dataset and report."""

    name = "check"

    def estimate(self, state: FocusState) -> Correction:
        """The correction, its image's metric (the report's ``metric_after``), and the
        sub-apertures' agreement before and after it."""
        ds, rep, d_temp, move = state.ds, state.rep, state.d_temp, state.move
        c_est = state.c_at(d_temp)
        t0_est = state.t0_at(c_est)
        shift = t0_est - ds.t0_s
        rep.metric_after = metric_and_weight(state.engine.image(shift, c_est, ds.tx_positions + move,
                                                                ds.rx_positions + move), rep.metric)[0]
        rep.history.append(rep.metric_after)
        changed = bool(np.any(shift != 0) or d_temp != 0 or np.any(move != 0))
        before = after = None
        if state.halves is not None:  # judged against the direct sound's delay alone (a measurement, not a focus)
            before = state.split_agreement(state.t0_at(state.c_stated) - ds.t0_s, state.c_stated, None)
            after = state.split_agreement(shift, c_est, move)
        return Correction(t0_est, c_est, move, d_temp, changed, before, after)

    def check(self, state: FocusState, estimate: Correction) -> bool:
        """No pair of sub-apertures agrees less after the correction (by more than
        :data:`FINAL_TOLERANCE`); without them, nothing but the direct sound's delay is applied.
        Into ``rep.check``."""
        rep, before, after = state.rep, estimate.before, estimate.after
        if before is not None:
            for n, b, a in zip(state.split_names, before, after, strict=True):
                rep.check.update({f"{n}_before": b, f"{n}_after": a})
            rep.check["passed"] = bool(min(a - b for a, b in zip(after, before, strict=True)) >= -FINAL_TOLERANCE)
        else:  # no halves: only the direct sound's delay, which the physics determines, may be applied
            rep.check.update(passed=bool(not np.any(estimate.move != 0) and estimate.d_temp == 0))
        return rep.check["passed"]

    def result(self, state: FocusState, started: float) -> tuple:
        """The report's estimates, and the corrected dataset, or the input where nothing
        determined passed the check."""
        ds, rep, o = state.ds, state.rep, state.options
        corr = self.estimate(state)
        passed = self.check(state, corr)
        rep.improved = bool(passed and corr.changed)
        _fill(rep, ds, corr.t0_s, corr.c_mps, corr.d_temp, state.temp0, corr.move, state.stop, o.methods,
              applied=rep.improved)
        rep.time_s = time.perf_counter() - started
        if not rep.improved:
            rep.metric_after = rep.metric_before
            rep.notes.append((_why(state, corr) if not passed else "nothing was determined well enough to apply")
                             + ": the input is returned unchanged; the estimates above are not applied")
            log.warning("autofocus: %s; returning the input", rep.notes[-1])
            if o.consistency_iter:  # what the input leaves unexplained, for the record
                consistency_gate(ds, ds, state.grid, rep, o.consistency_iter, state.engine.selection)
                rep.time_s = time.perf_counter() - started
            return ds, rep
        new_temp = state.temp0 + corr.d_temp
        out = ds.replace(t0_s=corr.t0_s, tx_positions=ds.tx_positions + corr.move,
                         rx_positions=ds.rx_positions + corr.move, c_mps=corr.c_mps,
                         temperature_c=new_temp if np.ndim(ds.temperature_c) else float(new_temp[0]),
                         provenance=list(ds.provenance) + [{"step": "autofocus", **record(rep)}])
        if o.consistency_iter:
            out = _consistency_checked(state, out, started)
        rep.time_s = time.perf_counter() - started
        log.info("%s", rep.summary())
        return out, rep


def _why(state: FocusState, corr: Correction) -> str:
    """Why the check failed, for the report's note."""
    if corr.before is None:
        return "too few stops to check anything but the direct sound's delay"
    return ("the disjoint sub-apertures' images agree less after the whole correction ("
            + ", ".join(f"{n} {b:.3f} -> {a:.3f}"
                        for n, b, a in zip(state.split_names, corr.before, corr.after, strict=True)) + ")")


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
    return (out if passed else base).replace(provenance=list(ds.provenance) + [{"step": "autofocus", **record(rep)}])


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
        rep.los_path_m = los_path(ds, rep.focus_centre_m, move, first)
    rep.position_correction_m = move
    rep.stop_index = stop
    for name, p in rep.parameters.items():
        p.applied = bool(applied and p.determined and (name != "motion" or np.any(move != 0)))


def los_path(ds, centre, move, first) -> np.ndarray:
    """The bistatic path change at ``centre`` that the displacement ``move`` makes, per stop, m."""
    path = np.linalg.norm(centre - ds.tx_positions, axis=1) + np.linalg.norm(centre - ds.rx_positions, axis=1)
    moved = np.linalg.norm(centre - ds.tx_positions - move, axis=1) \
        + np.linalg.norm(centre - ds.rx_positions - move, axis=1)
    return (moved - path)[first]


def record(rep) -> dict:
    """The report as the provenance record keeps it (without the stages)."""
    d = rep.as_dict()
    d.pop("stages", None)
    return d
