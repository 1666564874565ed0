"""What the stages of :func:`clsas.autofocus` share, in one place: :class:`FocusState`, and
what a stage is: :class:`Stage`.

The state is frozen: a stage reads it and returns its estimate, its check says whether the
estimate is applied, and the stage makes the next state from that (``dataclasses.replace``);
:func:`.run.run` takes the stages in turn. What each stage adds:

========================  =====================================================================
field                     set by
========================  =====================================================================
``delays``                the delay stage: the direct sound (``Delays.direct``), which of its
                          arrivals are applied (``Delays.use``), a delay found without it
                          (``Delays.extra_s``)
``move``                  the motion stage: the carriage's displacement that passed its check
``d_temp``                the temperature stage: the offset from the stated air that passed
========================  =====================================================================

Everything else is fixed when the run starts: the dataset, the grid, the options, the engine
and its options, the stops, the disjoint sub-apertures (``splits``) and the stated air. The
report (``rep``) is the record every stage appends to (its ``notes``, ``stages``, ``check``,
``parameters``, ``history``; the motion stage sets ``focus_centre_m``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numpy as np

from ..physics.geometry import VoxelGrid
from ..physics.sound import speed_of_sound
from ..types.dataset import Dataset
from .direct import DirectPath
from .engine import FocusEngine
from .metrics import metric_and_weight
from .options import AutofocusOptions
from .report import AutofocusReport
from .split import Half, magnitude_correlation

__all__ = ["Delays", "FocusState", "SPLIT_NAMES", "Stage"]

#: The pairs of disjoint sub-apertures the checks compare: first and second half of the stops in
#: time, and the left and right half of the carriage's x.
SPLIT_NAMES = ("time", "x")


@dataclass(frozen=True, eq=False)
class Delays:
    """The delays the delay stage applies.

    Attributes
    ----------
    direct : DirectPath or None
        The direct sound's arrivals, where found (None: not found, or ``"direct"`` not named).
    use : {"none", "median", "per_stop"}
        What of the direct sound's ``t0`` is applied: nothing, the recordings' median, or each
        recording's own.
    extra_s : float
        A global delay determined without the direct sound (``"delay"``), s; a shift ``dd``
        reads the profile ``dd`` later: ``t0 + dd``.
    """

    direct: DirectPath | None = None
    use: str = "none"
    extra_s: float = 0.0


@dataclass(frozen=True, eq=False)
class FocusState:
    """The run's data, engines and sub-apertures, and what the stages have applied so far.

    Attributes
    ----------
    ds, grid, options : Dataset, VoxelGrid, AutofocusOptions
        The request (checked).
    engine : FocusEngine
        Images of the whole scan on ``grid``; ``engine_options`` built it (and the splits).
    rep : AutofocusReport
        The report the stages fill.
    progress : callable or None
        Called after every image formed: ``progress(step, n_images, metric)``.
    temp0, c_stated : (n_meas,) arrays
        The stated air temperature, °C, and speed of sound, m/s.
    stop, t_stop, xy : arrays
        Each measurement's stop (n_meas,), each stop's time (n_stops,) and carriage x, y
        (n_stops, 2) (:func:`.motion.stops_of`).
    splits : tuple of (Half, Half)
        The disjoint sub-apertures, one pair per name of :data:`SPLIT_NAMES` that has them.
    delays, move, d_temp
        What the delay, motion and temperature stages applied (see the module docstring);
        ``move`` (n_meas, 3), m, zeros until the motion stage passes.
    """

    ds: Dataset
    grid: VoxelGrid
    options: AutofocusOptions
    engine: FocusEngine
    engine_options: dict
    rep: AutofocusReport
    progress: Callable[[str, int, float], None] | None
    temp0: np.ndarray
    c_stated: np.ndarray
    stop: np.ndarray
    t_stop: np.ndarray
    xy: np.ndarray
    splits: tuple[tuple[Half, Half], ...]
    delays: Delays = field(default_factory=Delays)
    move: np.ndarray | None = None
    d_temp: float = 0.0

    split_names: ClassVar[tuple[str, ...]] = SPLIT_NAMES

    def __post_init__(self) -> None:
        if self.move is None:
            object.__setattr__(self, "move", np.zeros((self.ds.n_meas, 3)))

    @property
    def halves(self) -> tuple[Half, Half] | None:
        """The first and second half of the stops in time, where every pair of sub-apertures exists."""
        return self.splits[0] if len(self.splits) == len(SPLIT_NAMES) else None

    @property
    def direct(self) -> DirectPath | None:
        return self.delays.direct

    def c_at(self, dt) -> np.ndarray:
        """The stated c scaled as a temperature offset ``dt`` (°C) scales it (at the dataset's humidity), m/s."""
        temp0, hum = self.temp0, self.ds.humidity_pct
        return self.c_stated * (np.asarray(speed_of_sound(temp0 + dt, hum), float)
                                / np.asarray(speed_of_sound(temp0, hum), float))

    def t0_at(self, c) -> np.ndarray:
        """Each measurement's ``t0`` with the delays applied, at the speed of sound ``c``, s."""
        ds, delays = self.ds, self.delays
        if delays.direct is None:
            return ds.t0_s + delays.extra_s
        if delays.use == "none":
            return ds.t0_s.copy()
        t0 = delays.direct.t0_s(c, ds.t0_s)
        if delays.use == "median":
            t0 = ds.t0_s + float(np.median(t0 - ds.t0_s))
        return t0

    def metric_of(self, values, step: str) -> float:
        """The focus metric of an image, recorded in the report's history and reported to ``progress``."""
        m = metric_and_weight(values, self.options.metric)[0]
        self.rep.history.append(m)
        if self.progress is not None:
            self.progress(step, len(self.rep.history), m)
        return m

    def image_metric(self, shift, c, step: str, tx=None, rx=None) -> float:
        """:meth:`metric_of` the whole scan's image."""
        return self.metric_of(self.engine.image(shift, c, tx, rx), step)

    def half_metric(self, h: Half, shift, c, move, step: str) -> float:
        """:meth:`metric_of` a sub-aperture's image."""
        return self.metric_of(h.image(shift, c, move), step)

    def split_agreement(self, shift, c, move) -> list[float]:
        """Per pair of sub-apertures (``split_names``): their images' magnitude correlation."""
        return [magnitude_correlation(a.image(shift, c, move), b.image(shift, c, move)) for a, b in self.splits]


class Stage(Protocol):
    """One stage of the autofocus, in the order :func:`.run.run` takes them.

    ``runs`` says whether the options name it and the scan allows it; ``estimate`` measures
    what the stage estimates from the state (and records it in the report); ``check`` says
    whether that estimate is applied; ``update`` returns the next state: the estimate where the
    check passed, else what the stage learnt without applying anything.
    """

    name: str

    def runs(self, state: FocusState) -> bool: ...

    def estimate(self, state: FocusState) -> Any: ...

    def check(self, state: FocusState, estimate: Any) -> bool: ...

    def update(self, state: FocusState, estimate: Any, passed: bool) -> FocusState: ...
