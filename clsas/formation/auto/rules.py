"""The rules ``formation="auto"`` keeps whatever the predictions say, and the record of its choice.

The error target is a finite number of dB below 0 (:func:`check_max_error_db`, default
:data:`DEFAULT_MAX_ERROR_DB`). Exact backprojection is taken by rule (:func:`by_rule`), before
anything is predicted, for

- profiles a sparse method rendered from its echoes: the fast formations do not match bp on
  rendered pulses;
- a grid formed in tiles: each tile of bp's image equals the whole image's;
- directional beams: bp alone applies them exactly (FFBP interpolates beam-weighted sub-images,
  which need finer sampling, and cannot match bp's gate; ω-k's angular weighting differs from
  bp's beam gate by more than the target).

Otherwise :func:`.choice.choose` weighs the predictions. Either way the result is a
:class:`Choice`, logged and kept in the image's provenance (``formation_auto``); bp is formed
with :func:`.trust.bp_options` (its kernel may take a variant stated within the target less the
margin).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from ...types.profiles import Profiles
from .trust import Estimate, bp_options

__all__ = ["DEFAULT_MAX_ERROR_DB", "Choice", "by_rule", "check_max_error_db", "rule_reason"]

log = logging.getLogger(__name__)

DEFAULT_MAX_ERROR_DB = -30.0


@dataclass(frozen=True)
class Choice:
    """What ``formation="auto"`` chose, and why (recorded in the image's provenance)."""

    formation: str
    options: dict
    reason: str
    max_error_db: float
    model: str  # "built-in" or where the calibration came from
    estimates: tuple[Estimate, ...]
    # what auto forms, in turn: (estimate, measured?) pairs; the first one formed whose error is not
    # measured, or is measured within the target, is kept (clsas.formation.auto.measure.form_choice)
    steps: tuple[tuple[Estimate, bool], ...] = ()

    def as_dict(self) -> dict:
        """JSON-friendly form (infinities as strings)."""

        def num(x: float):
            if math.isnan(x):
                return None
            return x if math.isfinite(x) else ("inf" if x > 0 else "-inf")

        def est(e: Estimate) -> dict:
            return {**asdict(e), "time_s": num(e.time_s), "error_db": num(e.error_db)}

        return {"formation": self.formation, "options": dict(self.options), "reason": self.reason,
                "max_error_db": self.max_error_db, "model": self.model,
                "estimates": [est(e) for e in self.estimates],
                "steps": [{"formation": e.formation, "options": dict(e.options), "measured": m} for e, m in self.steps]}


def check_max_error_db(max_error_db) -> float:
    """``max_error_db`` validated: a finite number of dB below 0."""
    if isinstance(max_error_db, bool) or not isinstance(max_error_db, int | float | np.floating | np.integer):
        raise TypeError(f"max_error_db must be a number of dB (e.g. -30), got {type(max_error_db).__name__}")
    val = float(max_error_db)
    if not math.isfinite(val) or val >= 0:
        raise ValueError(f"max_error_db must be a finite number of dB below 0 (e.g. -30), got {max_error_db!r}")
    return val


def by_rule(profiles: Profiles, max_error_db: float | None, *, tiled: bool = False) -> Choice | None:
    """The :class:`Choice` of bp where a rule (see the module notes) takes it, logged; else None.

    Parameters
    ----------
    profiles : Profiles
        What would be formed (its ``method`` names a sparse method where one rendered it).
    max_error_db : float or None
        The error target, dB (recorded in the Choice); None: :data:`DEFAULT_MAX_ERROR_DB`, bp exact.
    tiled : bool
        Whether the grid is formed in tiles.
    """
    reason = rule_reason(profiles.method, tiled=tiled, beams=getattr(profiles, "beams", None))
    if reason is None:
        return None
    log.info("formation auto: %s", reason)
    target = check_max_error_db(DEFAULT_MAX_ERROR_DB if max_error_db is None else max_error_db)
    return Choice("bp", bp_options(None if max_error_db is None else target), reason, target, "rule", ())


def rule_reason(method: str, *, tiled: bool = False, beams=None) -> str | None:
    """Why exact backprojection is taken by rule (see the module notes), before any profile is
    formed, else None.

    Parameters
    ----------
    method : str
        What makes the profiles: a compression (``"matched"``, ``"fmcw"``) or a sparse method.
    tiled : bool
        Whether the grid is formed in tiles.
    beams : clsas.physics.beam.Beams or None
        The dataset's beams (None: omnidirectional).
    """
    from ...sparse import SPARSE_METHODS  # imported when auto forms, not by `import clsas`

    if method in SPARSE_METHODS:
        return (f"bp: the {method} profiles are imaged by bp only (the fast formations do not match it on "
                "rendered pulses)")
    if tiled:
        return "bp: a grid formed in tiles is formed by bp (each tile equals the whole image's)"
    if beams is not None and not beams.is_omni:
        return ("bp: directional beams are applied exactly by bp only (FFBP interpolates beam-weighted sub-images, "
                "which need finer sampling, and cannot match bp's gate; omega-k's angular weighting differs from "
                "bp's beam gate by more than the target)")
    return None
