"""The autofocus pipeline behind :func:`clsas.autofocus` (options already checked there).

:func:`run` starts a :class:`.state.FocusState` and takes the stages (:class:`.state.Stage`) in
turn, each estimating, checking and handing on the next state, then the final check:

1. :class:`.stage_delay.DelayStage`: the direct sound's delays (none without it: not determined,
   0), else the halves' sharpest delay where they agree;
2. :class:`.stage_motion.MotionStage`: the motion on all stops, applied only where disjoint
   sub-apertures' images agree better after it;
3. :class:`.stage_temperature.TemperatureStage`: the temperature from the first and second half
   of the stops, kept only where the two agree;
4. :class:`.final_check.FinalCheck`: the check on the whole correction, which decides what comes
   back.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .engine import FocusEngine
from .final_check import FinalCheck
from .motion import stops_of
from .options import AutofocusOptions
from .report import AutofocusReport
from .split import split_halves
from .stage_delay import DelayStage
from .stage_motion import MotionStage
from .stage_temperature import TemperatureStage
from .state import SPLIT_NAMES, FocusState, Stage

__all__ = ["STAGES", "run"]

#: The stages in the order they run; :class:`.final_check.FinalCheck` follows them.
STAGES: tuple[Stage, ...] = (DelayStage(), MotionStage(), TemperatureStage())


def run(ds, grid, options: AutofocusOptions, *, progress, started) -> tuple:
    """The stages of :func:`clsas.autofocus` in turn (:data:`STAGES`), each applied where its
    check passes; then the final check, and the corrected dataset (or the input) and the report."""
    state = _start(ds, grid, options, progress)
    for stage in STAGES:
        if stage.runs(state):
            estimate = stage.estimate(state)
            state = stage.update(state, estimate, stage.check(state, estimate))
    return FinalCheck().result(state, started)


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
