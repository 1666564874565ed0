"""The options of :func:`clsas.autofocus`, checked once: :class:`AutofocusOptions`.

:func:`clsas.autofocus` builds one from its keywords (each error names the keyword), and
:func:`.run.run` and its stages read it whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import validate as v
from .metrics import METRICS

__all__ = ["AutofocusOptions", "DEFAULT_METHODS", "FOCUS_METHODS", "METHODS", "MOTION_METHODS"]

METHODS = ("direct", "temperature", "delay", "phase", "points", "track", "los", "3d", "pga")
# only what the physics determines by default: on held-out scenes "phase" and "temperature" made
# a third of the scenes worse; the focus steps run when named
DEFAULT_METHODS = ("direct",)
FOCUS_METHODS = ("direct", "phase", "temperature")
#: The methods that estimate the carriage's motion (the motion stage runs where one is named).
MOTION_METHODS = frozenset({"phase", "points", "track", "los", "3d", "pga"})


@dataclass(frozen=True)
class AutofocusOptions:
    """Every option of :func:`clsas.autofocus` beyond the dataset and the grid, checked.

    The fields are :func:`clsas.autofocus`'s keywords (see its docstring for their meaning),
    except ``progress``, which travels beside them. Built with a bad value, it raises the
    ``TypeError`` or ``ValueError`` that names the keyword; the checked values are kept
    (``methods`` as a tuple, numbers as ``float`` or ``int``).
    """

    methods: tuple[str, ...] = DEFAULT_METHODS
    metric: str = "sharpness"
    n_basis: int | None = None
    motion_bandwidth_hz: float = 5.0
    temperature_range_c: float = 5.0
    max_delay_s: float = 5e-4
    per_stop_delay: bool = True
    max_iter: int = 40
    phase_sweeps: int = 4
    max_stop_bytes: int = 1 << 30
    pga_min_coherence: float | None = None
    pga_max_points: int = 32
    temperature_tolerance_c: float = 0.35
    delay_tolerance_s: float = 1e-6
    check_margin: float = 0.01
    phase_region_m: float | None = None
    heldout_gain: float = 0.2
    track_tolerance_m: float = 2.5e-3
    consistency_iter: int = 0
    backend: str | None = None
    device: Any = None
    force: bool = False

    def __post_init__(self) -> None:
        for name, value in {**_checked_steps(self), **_checked_determination(self)}.items():
            object.__setattr__(self, name, value)

    @property
    def pga_options(self) -> dict:
        """The keywords of :func:`.pga.pga_refine` these options set."""
        out: dict = {"max_points": self.pga_max_points}
        if self.pga_min_coherence is not None:
            out["min_coherence"] = self.pga_min_coherence
        return out

    @property
    def motion(self) -> bool:
        """Whether a motion method is named."""
        return bool(MOTION_METHODS & set(self.methods))


def _checked_steps(o: AutofocusOptions) -> dict:
    """The options of the steps and their searches, checked (by keyword)."""
    methods = o.methods
    if isinstance(methods, str) or not all(isinstance(m, str) for m in methods):
        raise TypeError(f"methods must be a sequence of names from {METHODS}, got {methods!r}")
    for m in methods:
        v.choice("methods", m, METHODS)
    if not methods:
        raise ValueError(f"methods must name at least one of {METHODS}")
    v.choice("metric", o.metric, METRICS)
    out = {"methods": tuple(methods), "per_stop_delay": bool(o.per_stop_delay),
           "n_basis": None if o.n_basis is None else v.positive_int("n_basis", o.n_basis),
           "motion_bandwidth_hz": v.positive("motion_bandwidth_hz", o.motion_bandwidth_hz),
           "temperature_range_c": v.non_negative("temperature_range_c", o.temperature_range_c),
           "max_delay_s": v.non_negative("max_delay_s", o.max_delay_s),
           "max_iter": v.positive_int("max_iter", o.max_iter),
           "phase_sweeps": v.positive_int("phase_sweeps", o.phase_sweeps),
           "max_stop_bytes": v.positive_int("max_stop_bytes", o.max_stop_bytes),
           "pga_max_points": v.positive_int("pga_max_points", o.pga_max_points)}
    if o.pga_min_coherence is not None:
        coh = v.non_negative("pga_min_coherence", o.pga_min_coherence)
        if coh > 1:
            raise ValueError(f"pga_min_coherence must be in [0, 1], got {o.pga_min_coherence!r}")
        out["pga_min_coherence"] = coh
    return out


def _checked_determination(o: AutofocusOptions) -> dict:
    """The options of what counts as determined, and of the checks, checked (by keyword)."""
    margin = v.non_negative("check_margin", o.check_margin)
    if margin >= 1:
        raise ValueError(f"check_margin must be in [0, 1), got {o.check_margin!r}")
    n_iter = o.consistency_iter
    if isinstance(n_iter, bool) or not isinstance(n_iter, int | np.integer) or not 0 <= n_iter <= 10_000:
        raise ValueError(f"consistency_iter must be an int from 0 (off) to 10000, got {n_iter!r}")
    return {"temperature_tolerance_c": v.positive("temperature_tolerance_c", o.temperature_tolerance_c),
            "delay_tolerance_s": v.positive("delay_tolerance_s", o.delay_tolerance_s), "check_margin": margin,
            "heldout_gain": v.positive("heldout_gain", o.heldout_gain),
            "track_tolerance_m": v.positive("track_tolerance_m", o.track_tolerance_m),
            "consistency_iter": int(n_iter),
            "phase_region_m": None if o.phase_region_m is None else v.positive("phase_region_m", o.phase_region_m)}
