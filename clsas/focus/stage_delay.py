"""The first stage of :func:`clsas.autofocus`: the delays (``"direct"``, ``"delay"``).

The delay of each recording from the direct speaker-to-microphone sound (:mod:`.direct`): the
group delay (the recordings' median) and the per-stop timing (their scatter), which the physics
determines; without the direct sound, ``"delay"``: the sharpest global delay of the first and
of the second half of the stops (:mod:`.split`), where they agree. Each is applied only where
:func:`.significance.judge` says it matters; otherwise the delay is *not determined* and stays 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from .direct import DirectPath, direct_arrivals
from .report import ParameterEstimate
from .search import bounded_search
from .significance import delay_floor_s, judge
from .split import agreement
from .state import Delays, FocusState

__all__ = ["DelayEstimate", "DelayStage"]


@dataclass(frozen=True, eq=False)
class DelayEstimate:
    """What the delay stage measured: the direct sound's arrivals (None: not found or not named),
    the group delay and the timing as the report states them, and the global delay the halves
    agree on without the direct sound (``"delay"``; 0 where not searched), s."""

    direct: DirectPath | None
    group_delay: ParameterEstimate
    timing: ParameterEstimate
    search_s: float = 0.0


class DelayStage:
    """The direct sound's delays, else the halves' sharpest delay; always runs (the report states
    the group delay and the timing, determined or not)."""

    name = "delay"

    def runs(self, state: FocusState) -> bool:
        return True

    def estimate(self, state: FocusState) -> DelayEstimate:
        """The direct sound (where ``"direct"`` is named), then the group delay and timing from
        it, else (``"delay"``) from the two halves; into the report's parameters."""
        o, rep = state.options, state.rep
        direct = _find_direct(state) if "direct" in o.methods else None
        gd = ParameterEstimate("group_delay", "s", 0.0, float("nan"), False, False,
                               "no direct sound: a delay mostly shifts the image in range, which no focus "
                               "metric sees; left at 0")
        timing = ParameterEstimate("timing", "s RMS", 0.0, float("nan"), False, False, "no direct sound")
        search_s = 0.0
        if direct is not None:
            gd, timing = _direct_delays(state, direct)
        elif "delay" in o.methods and o.max_delay_s > 0 and state.halves is not None:
            gd, search_s = _delay_search(state, o.max_delay_s, o.delay_tolerance_s)
        rep.parameters["group_delay"], rep.parameters["timing"] = gd, timing
        return DelayEstimate(direct, gd, timing, search_s)

    def check(self, state: FocusState, estimate: DelayEstimate) -> bool:
        """Whether a delay is determined (the halves agree, and the significance test passed it)."""
        return bool(estimate.group_delay.determined or estimate.timing.determined)

    def update(self, state: FocusState, estimate: DelayEstimate, passed: bool) -> FocusState:
        """The state with the delays to apply: of the direct sound each recording's own (the timing
        determined) or their median (the group delay alone), else the halves' delay; where
        nothing passed, none (the direct sound's arrivals kept, for the final check)."""
        direct = estimate.direct
        if not passed:
            return replace(state, delays=Delays(direct))
        if direct is not None:
            return replace(state, delays=Delays(direct, "per_stop" if estimate.timing.determined else "median"))
        # a shift dd reads the profile dd later: t0 + dd
        return replace(state, delays=Delays(None, extra_s=estimate.search_s))


def _find_direct(state: FocusState) -> DirectPath | None:
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
    """Without the direct sound: the two halves' sharpest global delays (the group delay,
    determined where they agree and :func:`.significance.judge` passes it), and the delay they
    agree on, s."""
    t = time.perf_counter()
    ds = state.ds
    base = ds.t0_s - ds.t0_s
    found = [bounded_search(lambda dd, h=h: state.half_metric(h, base + dd, state.c_stated, None, "delay"),
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
    return ParameterEstimate("group_delay", "s", -ag["estimate"], ag["uncertainty"], ag["determined"], False,
                             how), ag["estimate"]
