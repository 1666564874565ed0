"""The choice ``formation="auto"`` makes from the predictions, and the rules before them.

:func:`choose` weighs each formation's predicted time and error (:mod:`.predict`) and what auto
trusts (:mod:`.trust`): the fastest predicted to meet the target with the margin, or one predicted
near it that is formed and measured first (:attr:`.rules.Choice.steps`). :func:`resolve` applies
the rules that take bp whatever the predictions (:func:`.rules.by_rule`) first.
"""

from __future__ import annotations

import logging
import math

from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles
from .predict import estimate
from .rules import DEFAULT_MAX_ERROR_DB, Choice, by_rule, check_max_error_db
from .timing import load_calibration
from .trust import CHECK_ABOVE_DB, MARGIN_DB, Estimate, _steps, check_seconds

__all__ = ["choose", "resolve"]

log = logging.getLogger(__name__)


def resolve(profiles: Profiles, grid: VoxelGrid, selection=None, *, max_error_db: float | None = None,
            tiled: bool = False) -> Choice:
    """What ``formation="auto"`` forms for this request: bp where a rule takes it (:func:`.rules.by_rule`),
    else :func:`choose`'s choice.

    Parameters
    ----------
    profiles : Profiles
    grid : VoxelGrid
    selection : clsas.cl.Selection, optional
        Where the formations would run (None: the NumPy twins).
    max_error_db : float, optional
        Error target against exact backprojection, dB. None: :data:`DEFAULT_MAX_ERROR_DB` (-30),
        and bp, where formed, stays exact (a target given lets its kernel take a variant stated
        within it less the margin, :func:`.trust.bp_options`).
    tiled : bool
        Whether the grid is formed in tiles (then by bp, by rule).
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles, got {type(profiles).__name__}")
    given = None if max_error_db is None else check_max_error_db(max_error_db)
    return by_rule(profiles, given, tiled=tiled) or choose(profiles, grid, selection, max_error_db=given)


def choose(profiles: Profiles, grid: VoxelGrid, selection=None, *, max_error_db: float | None = None,
           formations=("bp", "omega-k", "ffbp")) -> Choice:
    """The fastest formation whose predicted error is at most ``max_error_db - MARGIN_DB``, or one
    predicted near the target whose error is then measured (:attr:`Choice.steps`).

    Parameters
    ----------
    profiles : Profiles
    grid : VoxelGrid
    selection : clsas.cl.Selection, optional
        Where the formations would run (None: the NumPy twins).
    max_error_db : float
        Error target against exact backprojection, dB (default -30).
    formations : tuple of str
        The formations to consider; ``"bp"`` is always among them (it meets any target).

    Returns
    -------
    Choice
        Logged at INFO with its reason.
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles, got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    target = check_max_error_db(DEFAULT_MAX_ERROR_DB if max_error_db is None else max_error_db)
    formations = tuple(dict.fromkeys(("bp", *formations)))
    factors = load_calibration(selection)
    model = "calibrated on this device by python -m bench" if factors else "built-in (not calibrated on this device)"
    ests = estimate(profiles, grid, selection, max_error_db=max_error_db, factors=factors, formations=formations)
    fast = any(e.feasible and e.formation != "bp" and e.error_db <= target + CHECK_ABOVE_DB for e in ests)
    steps = _steps(ests, target, check_seconds(profiles, grid, selection, factors) if fast else math.inf)
    first, measured = steps[0]
    bp = next(e for e in ests if e.formation == "bp")
    others = "; ".join(f"{e.formation}{_opts(e.options)}: {_describe(e, target)}" for e in ests if e is not first)
    if first.formation == "bp":
        reason = (f"bp{_opts(bp.options)} ({_exactness(bp)}, predicted {bp.time_s:.3g} s) is the fastest that "
                  f"meets {target:g} dB; {others}")
    else:
        speedup = bp.time_s / first.time_s
        if first.unpredicted and measured:
            meets = "by a model not trusted here (some voxel-stop pairs aliased), to be measured"
        elif first.error_db > target - MARGIN_DB:
            meets = f"within {target:g} dB + {CHECK_ABOVE_DB:g} dB, to be measured"
        else:
            meets = f"<= {target:g} dB - {MARGIN_DB:g} dB margin"
        then = "; measured on a sub-lattice, then " + ", else ".join(
            f"{e.formation}{_opts(e.options)}" for e, _ in steps[1:]) if measured else ""
        reason = (f"{first.formation}{_opts(first.options)}: predicted {first.time_s:.3g} s ({speedup:.1f}x "
                  f"faster than bp) at {first.error_db:.0f} dB {meets}{then}; {others}")
    log.info("formation auto: %s [cost model %s]", reason, model)
    return Choice(first.formation, dict(first.options), reason, target, model, tuple(ests), steps)


def _opts(options: dict) -> str:
    return "" if not options else " (" + ", ".join(f"{k}={val}" for k, val in options.items()) + ")"


def _exactness(e: Estimate) -> str:
    """How exact a formation predicted exact is: bp formed with an allowance (:func:`.trust.bp_options`)
    may run a kernel variant stated within it."""
    allowed = e.options.get("max_error_db")
    return "exact" if allowed is None else f"exact, or a kernel variant stated within {allowed:g} dB"


def _describe(e: Estimate, target: float) -> str:
    if not e.feasible:
        return f"cannot run ({e.note})"
    if math.isnan(e.error_db):
        return e.note
    err = _exactness(e) if e.error_db == -math.inf else f"{e.error_db:.0f} dB"
    if e.error_db > target - MARGIN_DB:
        over = " (over the target)"
    else:
        over = " (aliased: not trusted unmeasured)" if e.unpredicted else ""
    return f"{e.time_s:.3g} s, {err}{over}"
