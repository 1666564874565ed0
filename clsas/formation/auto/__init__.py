"""``formation="auto"``: the fastest formation whose error against exact backprojection meets a target.

A formation like the others (registered in :data:`clsas.formation.FORMATIONS` as ``"auto"``; its one
option is ``max_error_db``, the target in dB, default :data:`DEFAULT_MAX_ERROR_DB`) that forms the
image by another registered one. Its stages, one module each, in the order they run:

1. :mod:`.rules`: bp whatever the predictions for a sparse method's rendered profiles, a grid formed
   in tiles or directional beams; the :class:`Choice` record;
2. :mod:`.timing` and :mod:`.predict`: each formation's predicted time (counted work times seconds
   per unit on the device) and error against bp;
3. :mod:`.trust` and :mod:`.choice`: which predictions are trusted, the choice, and what is formed
   and measured in turn where a prediction is near the target or not trusted;
4. :mod:`.measure`: a formed image's error measured against bp on a sub-lattice, and the steps
   formed until one is kept (:func:`form_choice`);
5. :mod:`.calibrate`: the time model's factors measured on a device and kept (``clsas calibrate``).

The choice, its reason and any measurement are logged and kept in the image's provenance
(``provenance["formation_auto"]``); ``provenance["formation"]`` names the formation kept.

Where auto forms by bp, it gives bp its target less :data:`MARGIN_DB` (:func:`.trust.bp_options`,
in the choice's options): bp's kernel may then take a variant whose stated error against the
float64 twin is within it (half-precision records on devices with ``cl_khr_fp16``), and the image's
``provenance["bp"]`` names the variant that ran. The bp that measures a formed image's error
(:mod:`.measure`) stays exact.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from ... import cl
from ...physics.geometry import VoxelGrid
from ...types.image import Image
from ...types.profiles import Profiles
from ..registry import FORMATIONS
from .calibrate import calibrate_auto
from .choice import choose, resolve
from .measure import Check, form_choice, measure_error
from .predict import alias_fraction, estimate, predict_time
from .rules import DEFAULT_MAX_ERROR_DB, Choice, by_rule, check_max_error_db, rule_reason
from .timing import BUILTIN, calibration_path, load_calibration, store_calibration
from .trust import MARGIN_DB, Estimate, bp_options

__all__ = [
    "BUILTIN", "DEFAULT_MAX_ERROR_DB", "MARGIN_DB", "Check", "Choice", "Estimate", "alias_fraction", "bp_options",
    "by_rule",
    "calibrate_auto", "calibration_path", "check_max_error_db", "choose", "estimate", "form", "form_choice",
    "load_calibration", "measure_error", "predict_time", "resolve", "rule_reason", "store_calibration",
]


@FORMATIONS.register("auto")
def form(profiles: Profiles, grid: VoxelGrid, *, backend: str | cl.Selection | None = None, device: Any = None,
         progress: Callable[[int, int], None] | None = None, force: bool = False,
         max_error_db: float | None = None) -> Image:
    """Image ``profiles`` on ``grid`` with the fastest formation that meets ``max_error_db``.

    Parameters
    ----------
    profiles : Profiles
    grid : VoxelGrid
    backend, device
        As :func:`clsas.formation.form`; resolved once, and the same device predicts, forms and
        measures.
    progress : callable(done, total), optional
        Passed to the formation chosen.
    force : bool
        Passed to the formation chosen.
    max_error_db : float, optional
        The largest error against exact bp (error-to-signal over the grid, dB). None:
        :data:`DEFAULT_MAX_ERROR_DB` (-30), and bp, where formed, stays exact. Given: where bp is
        formed, its kernel may take a variant stated within ``max_error_db - MARGIN_DB`` of the
        peak per voxel (:func:`.trust.bp_options`).

    Returns
    -------
    Image
        The kept formation's image; ``provenance["formation"]`` and ``["formation_options"]`` are
        that formation's, ``provenance["formation_auto"]`` the :class:`Choice` (``as_dict``) with
        any measurement (``checks``).
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    given = None if max_error_db is None else check_max_error_db(max_error_db)
    selection = cl.select(backend, device)
    choice = resolve(profiles, grid, selection, max_error_db=given)
    image, record = form_choice(profiles, grid, choice, backend=selection, progress=progress, force=force)
    return replace(image, provenance={**image.provenance, "formation_auto": record})


def for_tiles(profiles: Profiles, grid: VoxelGrid, *, backend: Any = None, device: Any = None,
              max_error_db: float | None = None) -> tuple[str, dict, dict]:
    """What the tiles of a grid formed in tiles are formed by: (formation, its options, the
    provenance to add), bp by rule (:func:`.rules.by_rule`)."""
    choice = resolve(profiles, grid, cl.select(backend, device), max_error_db=max_error_db, tiled=True)
    return choice.formation, dict(choice.options), {"formation_auto": choice.as_dict()}


form.for_tiles = for_tiles  # a formation that forms by another names the one its tiles are formed by
