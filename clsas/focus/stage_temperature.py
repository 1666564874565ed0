"""The third stage of :func:`clsas.autofocus`: the air temperature (``"temperature"``).

The sharpest air temperature of each half of the stops (the motion applied), within the
thermometer's ± ``temperature_range_c``; where the halves agree (their uncertainty within
``temperature_tolerance_c``, neither at the search's edge), the whole aperture's sharpest near
their mean, applied only where :func:`.significance.judge` says it matters; else the stated
temperature is kept.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from .report import ParameterEstimate
from .search import bounded_search
from .significance import delay_floor_s, delay_spread_s, judge
from .split import agreement
from .state import FocusState

__all__ = ["TemperatureEstimate", "TemperatureStage"]

log = logging.getLogger("clsas.autofocus")


@dataclass(frozen=True)
class TemperatureEstimate:
    """The offset from the stated temperature, °C, its uncertainty, and whether it is determined
    (the halves agree and the significance test passed it)."""

    offset_c: float
    uncertainty_c: float
    determined: bool


class TemperatureStage:
    """The air temperature from the two halves of the stops, with the motion the motion stage applied."""

    name = "temperature"

    def runs(self, state: FocusState) -> bool:
        o = state.options
        return "temperature" in o.methods and o.temperature_range_c > 0 and state.halves is not None

    def estimate(self, state: FocusState) -> TemperatureEstimate:
        """The offset the two halves' sharpest images agree on, refined on the whole aperture and
        judged (:func:`.significance.judge`); into the report's parameters."""
        t = time.perf_counter()
        ds, move = state.ds, state.move
        range_c, tolerance_c = state.options.temperature_range_c, state.options.temperature_tolerance_c

        def f_temp(dt, h):
            c = state.c_at(dt)
            return state.half_metric(h, state.t0_at(c) - ds.t0_s, c, move, "temperature")

        found = [bounded_search(lambda dt, h=h: f_temp(dt, h), -range_c, range_c, step=min(1.0, range_c / 2),
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
        return TemperatureEstimate(ag["estimate"], ag["uncertainty"], bool(ag["determined"]))

    def check(self, state: FocusState, estimate: TemperatureEstimate) -> bool:
        """Whether the offset is determined: applied (else the stated temperature is kept)."""
        return estimate.determined

    def update(self, state: FocusState, estimate: TemperatureEstimate, passed: bool) -> FocusState:
        return replace(state, d_temp=estimate.offset_c) if passed else state


def _temperature_whole(state: FocusState, ag: dict, range_c: float) -> str:
    """Where the halves agree: the whole aperture's sharpest offset near their mean (into
    ``ag["estimate"]``), then judged (``ag["determined"]``); the words for the report."""
    ds, move = state.ds, state.move
    lo, hi = ag["estimate"] - 4 * ag["uncertainty"] - 0.1, ag["estimate"] + 4 * ag["uncertainty"] + 0.1

    def f_whole(dt):
        c = state.c_at(dt)
        return state.image_metric(state.t0_at(c) - ds.t0_s, c, "temperature", ds.tx_positions + move,
                                  ds.rx_positions + move)

    ag["estimate"] = bounded_search(f_whole, max(lo, -range_c), min(hi, range_c), step=(hi - lo) / 4,
                                    tol=0.01)[0]
    c_new = state.c_at(ag["estimate"])
    effect = delay_spread_s(ds, state.grid, state.t0_at(c_new), c_new)
    verdict = judge(ag["estimate"], ag["uncertainty"], 1, effect, delay_floor_s(ds), "C")
    ag["determined"] = verdict.apply
    return (f"; the whole aperture's sharpest at {ag['estimate']:+.2f} C; " + verdict.why
            + ("" if verdict.apply else ": stated kept"))
