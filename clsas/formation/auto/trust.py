"""Which of ``formation="auto"``'s predictions it trusts, and what it forms and measures in turn.

:func:`.choice.choose` ranks the formations by their predicted time and error (:mod:`.predict`);
the rules here turn that ranking into :attr:`.rules.Choice.steps`: a formation predicted at most
``target - MARGIN_DB`` by a model it trusts is taken as it is; one predicted near the target, or by
a model it does not trust (:attr:`Estimate.unpredicted`), is formed and its error measured
(:mod:`.measure`) where that pays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles
from .timing import _seconds

__all__ = ["CHECK_ABOVE_DB", "CHECK_IF_UNDER", "CHECK_SHARE", "CHECK_UNPREDICTED_SHARE", "MARGIN_DB",
           "Estimate", "bp_options", "check_seconds"]

MARGIN_DB = 3.0  # a formation is chosen only where its predicted error is this far under the target
# Measuring instead of predicting (clsas.formation.auto.measure: exact bp on a sub-lattice, within 0.6 dB of the
# whole grid's error on the 31 fit requests 500-530, where ω-k's prediction was off by -7 to +10 dB).
# A formation predicted between the target less MARGIN_DB and the target plus CHECK_ABOVE_DB is formed
# and measured where it and its check together take under CHECK_IF_UNDER of the best predicted to meet
# the target with the margin; that one is measured too where its check costs at most CHECK_SHARE of it.
# A formation whose measured error (its bootstrap upper bound) misses the target gives way to the next.
CHECK_ABOVE_DB = 2.0
# Plain ω-k where any voxel-stop pair is sampled aliased (lattice_aliases) is never taken unmeasured
# (Estimate.unpredicted): on the 42 planar fit requests 500-599 every such request but two small
# lattices measured 1-10 dB worse than predicted (three whose aliased share rounds to 0 measured -32 to
# -37 dB against -42), while on the crossover scans the same model over-predicts by up to 3 dB. Where its
# check would cost more than this share of it (the 96 x 96-stop crossover scan: 0.29 s on 0.10 s, 2.5x
# auto's time), the prediction and the margin are trusted as before
CHECK_UNPREDICTED_SHARE = 1.0
CHECK_IF_UNDER = 0.5
CHECK_SHARE = 0.1


@dataclass(frozen=True)
class Estimate:
    """One formation's prediction for a request."""

    formation: str
    time_s: float  # predicted run time, s (inf where it cannot run)
    error_db: float  # predicted error against bp, dB (-inf: exact)
    options: dict = field(default_factory=dict)  # formation options it would run with
    note: str = ""  # why it cannot run, or what the error estimate rests on
    # the prediction is not trusted: taken only once its error is measured (clsas.formation.auto.measure)
    unpredicted: bool = False

    @property
    def feasible(self) -> bool:
        return math.isfinite(self.time_s)


def bp_options(max_error_db: float | None) -> dict:
    """The options auto forms bp with under the target ``max_error_db`` the caller gave: its kernel
    may take a variant whose stated error against the float64 twin (per voxel, relative to the
    peak) is at most the target less :data:`MARGIN_DB` (:class:`clsas.formation.bp.Backprojector`;
    the exact float kernels where the device has none, or none is faster). None (no target given:
    auto's default): none, bp stays exact. The image's ``provenance["bp"]`` names what ran."""
    return {} if max_error_db is None else {"max_error_db": max_error_db - MARGIN_DB}


def check_seconds(profiles: Profiles, grid: VoxelGrid, selection, factors: dict) -> float:
    """Predicted time of measuring a formed image's error (:func:`.measure.measure_error`:
    bp on the grid's sub-lattice)."""
    from .measure import stride_for

    s = stride_for(grid.shape)
    n_sub = math.prod(-(-n // s) for n in grid.shape)  # at most this many voxels, whatever the offsets
    return _seconds("bp", {"fixed": 1, "meas": float(profiles.n_meas), "pairs": float(profiles.n_meas) * n_sub},
                    selection, factors)


def _measurable(e: Estimate, check_s: float) -> bool:
    """An unpredicted formation whose check costs at most :data:`CHECK_UNPREDICTED_SHARE` of it."""
    return e.unpredicted and check_s <= CHECK_UNPREDICTED_SHARE * e.time_s


def _safe(e: Estimate, target: float, check_s: float) -> bool:
    """Predicted to meet ``target`` with the margin, by a trusted model or one whose check would cost
    more than the formation itself (then the prediction and the margin are all there is)."""
    ok = e.feasible and e.error_db <= target - MARGIN_DB  # NaN (not planned) is not
    return ok and not _measurable(e, check_s)


def _near(e: Estimate, target: float, check_s: float) -> bool:
    """A fast formation auto may form and measure: predicted within the margin of ``target`` (or up to
    :data:`CHECK_ABOVE_DB` over it), or predicted to meet it by a model it does not trust."""
    if not e.feasible or e.formation == "bp" or e.error_db > target + CHECK_ABOVE_DB:
        return False
    return _measurable(e, check_s) or e.error_db > target - MARGIN_DB


def _steps(ests: list[Estimate], target: float, check_s: float) -> tuple[tuple[Estimate, bool], ...]:
    """What auto forms in turn, and which it measures (:data:`CHECK_ABOVE_DB`, :data:`CHECK_IF_UNDER`,
    :data:`CHECK_SHARE`): ends at the first one kept unmeasured, or at bp."""
    ok = sorted((e for e in ests if _safe(e, target, check_s)), key=lambda e: e.time_s)
    steps: list[tuple[Estimate, bool]] = []
    near = sorted((e for e in ests if _near(e, target, check_s)), key=lambda e: e.time_s)
    if near and near[0].time_s + check_s < CHECK_IF_UNDER * ok[0].time_s:
        steps.append((near[0], True))
    for e in ok:  # bp is among them, exact
        measured = e.formation != "bp" and check_s <= CHECK_SHARE * e.time_s
        steps.append((e, measured))
        if not measured:
            break
    return tuple(steps)
