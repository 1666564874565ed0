"""A fast formation's error measured, not predicted: exact bp on a sub-lattice of the grid.

``formation="auto"`` predicts each formation's error (:mod:`.predict`), and the
prediction is a model: on the formation family's requests ω-k's aliased share was off by up to
10 dB either way. Where a prediction is close to the target, or where measuring costs little
against the formation itself, auto forms the image and then measures its error here:

- exact backprojection on a regular sub-lattice of the grid (every ``stride``-th voxel along
  each axis, from an offset drawn from the grid's shape), on the same device, so the check
  costs ``1 / stride**3`` of bp;
- the error-to-signal ratio over the whole grid is estimated as the sub-lattice's error energy,
  scaled by the share of the grid it covers, over the whole image's energy (the formed image's:
  within ``2 sqrt(ratio)`` of bp's, 0.3 dB at -30 dB);
- its upper bound is the 95th percentile of that estimate over 200 bootstrap draws of the
  sub-lattice's voxels. An error concentrated in voxels no sample falls on is not seen: a
  stride of at most :data:`MAX_STRIDE` bounds how sparse the sub-lattice gets.

On the 31 requests of the formation family's fit seeds 500-530 (strides 1-7) the estimate was
within 0.6 dB of the error over the whole grid, for ω-k, ω-k upsampled and FFBP, where ω-k's
predicted error had been off by -7 to +10 dB; on the 128 x 128-stop dense case (stride 8 and 12)
-32.3 and -32.4 dB against -32.5 dB.

Auto keeps the image where the upper bound is within the target and forms the next candidate
otherwise (:func:`clsas.pipeline.reconstruction.reconstruct` records both).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles

__all__ = ["CHECK_VOXELS", "MAX_STRIDE", "Check", "form_choice", "measure_error", "sublattice"]

log = logging.getLogger(__name__)

CHECK_VOXELS = 4096  # voxels on the sub-lattice the check aims for
MAX_STRIDE = 16  # never sparser than every 16th voxel along an axis
BOOTSTRAP = 200
UPPER_QUANTILE = 0.95


@dataclass(frozen=True)
class Check:
    """The measured error of a formed image against exact bp on a sub-lattice."""

    error_db: float  # the estimate over the whole grid, dB
    upper_db: float  # its bootstrap upper bound (UPPER_QUANTILE), dB
    voxels: int  # voxels bp formed
    stride: int
    time_s: float

    def as_dict(self) -> dict:
        """JSON-friendly form (infinities as strings, as :meth:`.rules.Choice.as_dict`)."""
        def num(x: float):
            return x if math.isfinite(x) else ("inf" if x > 0 else "-inf")

        return {"error_db": num(self.error_db), "upper_db": num(self.upper_db), "voxels": self.voxels,
                "stride": self.stride, "time_s": self.time_s}


def stride_for(shape: tuple[int, int, int]) -> int:
    """The sub-lattice's stride for a grid of ``shape``: about :data:`CHECK_VOXELS` voxels, at most
    :data:`MAX_STRIDE` (over the axes longer than one voxel: a plane's stride thins two axes)."""
    n = int(np.prod(shape))
    dims = max(1, sum(k > 1 for k in shape))
    return int(min(MAX_STRIDE, max(1, math.floor((n / CHECK_VOXELS) ** (1 / dims)))))


def sublattice(grid: VoxelGrid) -> tuple[VoxelGrid, tuple[slice, slice, slice], int]:
    """The sub-grid bp forms, the slices that pick it out of an image on ``grid``, and the stride.

    The offset along each axis is drawn from a generator seeded by the grid's shape, so the same
    request is checked on the same voxels."""
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    s = stride_for(grid.shape)
    rng = np.random.default_rng(list(grid.shape))
    sl = tuple(slice(int(rng.integers(0, min(s, n))), None, s) for n in grid.shape)
    sub = VoxelGrid(grid.x_m[sl[0]], grid.y_m[sl[1]], grid.z_m[sl[2]])
    return sub, sl, s


def measure_error(profiles: Profiles, grid: VoxelGrid, values: np.ndarray, *, backend=None) -> Check:
    """The error of ``values`` (an image on ``grid``) against exact bp, measured on a sub-lattice.

    Parameters
    ----------
    profiles : Profiles
        The profiles the image was formed from.
    grid : VoxelGrid
    values : ndarray, complex, ``grid.shape``
    backend : str or clsas.cl.Selection, optional
        Where bp runs (as :func:`clsas.formation.form`).
    """
    from .. import form

    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles, got {type(profiles).__name__}")
    values = np.asarray(values)
    if values.shape != tuple(grid.shape):
        raise ValueError(f"values: shape {values.shape} differs from the grid's {tuple(grid.shape)}")
    if not np.all(np.isfinite(values)):
        raise ValueError("values: contains NaN or Inf")
    t = time.perf_counter()
    sub, sl, stride = sublattice(grid)
    ref = np.asarray(form(profiles, sub, "bp", backend=backend).values).ravel()
    err = np.abs(values[sl].ravel() - ref) ** 2
    flat = values.ravel()
    total = float(np.vdot(flat, flat).real)  # no temporary the size of the grid
    scale = values.size / err.size
    if total == 0.0:
        db = 0.0 if float(err.sum()) > 0 else -math.inf
        return Check(db, db, err.size, stride, time.perf_counter() - t)
    rng = np.random.default_rng(0)
    draws = np.concatenate([err[rng.integers(0, err.size, (min(10, BOOTSTRAP - i), err.size))].sum(axis=1)
                            for i in range(0, BOOTSTRAP, 10)])  # in chunks: a flat grid's sub-lattice can be large
    with np.errstate(divide="ignore"):
        est = 10 * math.log10(max(scale * float(err.sum()) / total, 1e-300))
        upper = 10 * math.log10(max(scale * float(np.quantile(draws, UPPER_QUANTILE)) / total, 1e-300))
    return Check(est, upper, err.size, stride, time.perf_counter() - t)


def form_choice(profiles: Profiles, grid: VoxelGrid, choice, *, backend=None,
                progress: Callable[[int, int], None] | None = None, force: bool = False) -> tuple[Any, dict]:
    """Form what ``formation="auto"`` chose (:func:`.choice.choose`): its steps in turn,
    each one that is to be measured checked by :func:`measure_error` against the target, until one is
    kept.

    Returns
    -------
    image : Image
    record : dict
        ``choice.as_dict()`` with the formation kept (``formation``, ``options``) and ``checks``: per
        step measured, its formation, options, the :class:`Check` and whether it was kept. A step that
        missed the target is logged at WARNING with what is formed instead.
    """
    from .. import form

    steps = choice.steps or ((None, False),)
    record = choice.as_dict()
    record["checks"] = []
    for i, (est, measured) in enumerate(steps):
        name, opts = (choice.formation, dict(choice.options)) if est is None else (est.formation, dict(est.options))
        image = None  # the image a step let go is not kept while the next one forms
        image = form(profiles, grid, name, backend=backend, progress=progress, force=force, **opts)
        last = i == len(steps) - 1
        if measured and not last:
            values = np.asarray(image.values)
            if np.all(np.isfinite(values)):
                chk = measure_error(profiles, grid, values, backend=backend)
            else:  # a formation that came out with NaN or Inf misses any target
                chk = Check(math.inf, math.inf, 0, 0, 0.0)
            values = None
            kept = chk.upper_db <= choice.max_error_db
            record["checks"].append({"formation": name, "options": opts, **chk.as_dict(), "kept": kept})
            if not kept:
                nxt = steps[i + 1][0]
                log.warning("formation auto: %s measured %.1f dB against bp on a sub-lattice (a stride of %d; "
                            "upper bound %.1f dB), over the %g dB target: forming %s instead", name, chk.error_db,
                            chk.stride, chk.upper_db, choice.max_error_db, nxt.formation)
                continue
            log.info("formation auto: %s measured %.1f dB against bp on a sub-lattice (upper bound %.1f dB): kept",
                     name, chk.error_db, chk.upper_db)
        record.update(formation=name, options=opts)
        return image, record
    raise AssertionError("unreachable: the last step is always kept")
