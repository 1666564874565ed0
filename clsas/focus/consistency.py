"""Does any target in the grid explain the scan at its stated geometry? The data-consistency test.

A static target anywhere in ``grid``, seen from the stated positions with the stated clock and air,
predicts the recordings. :func:`data_consistency` fits the best such target by least squares (CGLS
on :class:`clsas.inverse.ImagingOperator`, the compressed pulse included) and reports what is left
unexplained, next to what the scan's noise alone leaves under the same fit (one pure-noise draw
at the scan's noise level, fitted with as many iterations). What is left beyond the noise, the
*excess*, measures errors in the geometry (motion, timing, air) and in the model, without any
focus metric: a sharper image does not lower it unless the data agree with it.

It answers two questions that a focus metric cannot:

- *Does the scan determine its motion?* Where the stated geometry already explains the data
  to the noise (excess near the model's own), no motion can be found from the data: a target in
  the grid explains them without one.
- *Is a correction complete?* The corrected dataset's excess against the input's: a correction
  that removes the motion takes the excess to the model's floor; one that sharpens a wrong image
  leaves it (or raises it).

Where the grid is large for the target (a few points in a big box), a target in the grid can
absorb the motion, and the data cannot see it. At a fixed ``max_iter`` the excess also holds what
the fit has not converged to: compare scans at the same ``max_iter``. The scene family's figures
(what the recorded and the true geometries leave unexplained, how often the data determine the
errors) are on the consistency pages of ``bench/results``.

The fit costs ``2 max_iter`` projections and as many backprojections (the scan's and the noise
draw's fits): tens of seconds to minutes on a CPU for the family's scans; an estimate is logged
before it starts.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset

__all__ = ["Consistency", "data_consistency"]

log = logging.getLogger("clsas.autofocus")


@dataclass
class Consistency:
    """What a least-squares target in the grid leaves of a scan (see the module docstring).

    Attributes
    ----------
    residual : float
        ``||b - A x|| / ||b||`` after the fit (the profiles ``b`` over the grid's delay gate).
    floor : float
        What the noise draw leaves under the same fit, relative to ``||b||``.
    excess : float
        ``sqrt(residual**2 - floor**2)`` (0 where the residual is at or below the floor): the
        part of the data that neither the target nor the noise explains.
    history, floor_history : list of float
        ``residual`` and ``floor`` after each iteration (index 0: before the fit); shorter than
        ``max_iter + 1`` where CGLS converged early.
    noise_sigma : float
        The profiles' per-sample noise standard deviation used for the draw.
    scale : float
        ``||b||``, what ``residual`` and ``floor`` are relative to.
    iterations : int
        The CGLS iterations the scan's fit ran (at most ``max_iter``).
    max_iter : int
        The iterations asked for (what ``floor_of`` must match).
    grid_shape : tuple of int
    n_meas : int
    backend, device : str
    time_s : float
    """

    residual: float
    floor: float
    excess: float
    history: list = field(default_factory=list)
    floor_history: list = field(default_factory=list)
    noise_sigma: float = float("nan")
    scale: float = float("nan")
    iterations: int = 0
    max_iter: int = 0
    grid_shape: tuple = ()
    n_meas: int = 0
    backend: str = ""
    device: str = ""
    time_s: float = 0.0

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("residual", "floor", "excess", "noise_sigma", "iterations", "backend",
                                              "device", "time_s")}

    def line(self) -> str:
        return (f"data consistency: {self.residual:.3g} of the data unexplained after {self.iterations} "
                f"iterations, noise alone {self.floor:.3g}, excess {self.excess:.3g}")


def data_consistency(dataset: Dataset, grid: VoxelGrid, *, max_iter: int = 60, seed: int = 0,
                     floor_of: Consistency | None = None, backend: str | None = None, device: Any = None,
                     progress: Callable[[str, int, int], None] | None = None) -> Consistency:
    """Fit a target in ``grid`` to ``dataset`` at its stated geometry; report what is left.

    Parameters
    ----------
    dataset : Dataset
        Recordings (not range profiles: the noise draw needs the waveform).
    grid : VoxelGrid
        Where targets may be: the scene's box (the fit's freedom grows with it), at a third of
        the wavelength or finer.
    max_iter : int
        CGLS iterations of each fit (1 to 10000). The excess falls as the fit converges; compare
        scans at the same ``max_iter``.
    seed : int
        Seed of the noise draw.
    floor_of : Consistency, optional
        An earlier result on the same grid and nearly the same geometry (the same scan before a
        correction): its noise floor is taken instead of fitting a noise draw again (half the
        cost). Its ``iterations`` must equal ``max_iter``.
    backend, device : as for :func:`clsas.reconstruct`.
    progress : callable(step, done, total), optional
        Called after each iteration; ``step`` is ``"fit"`` or ``"noise"``.

    Returns
    -------
    Consistency
    """
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    n_iter = v.positive_int("max_iter", max_iter)
    if n_iter > 10_000:
        raise ValueError(f"max_iter must be at most 10000, got {n_iter}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    if floor_of is not None:
        if not isinstance(floor_of, Consistency):
            raise TypeError(f"floor_of must be a Consistency, got {type(floor_of).__name__}")
        if floor_of.max_iter != n_iter:
            raise ValueError(f"floor_of was fitted with max_iter {floor_of.max_iter}, max_iter is {n_iter}")
        if tuple(floor_of.grid_shape) != tuple(grid.shape) or floor_of.n_meas != dataset.n_meas:
            raise ValueError(f"floor_of is of another grid or scan ({floor_of.grid_shape}, {floor_of.n_meas} "
                             f"measurements; here {grid.shape}, {dataset.n_meas})")
    if progress is not None and not callable(progress):
        raise TypeError(f"progress must be callable, got {type(progress).__name__}")
    return _fit_both(dataset, grid, n_iter, int(seed), floor_of, _cl.select(backend, device), progress)


def _fit_both(dataset, grid, n_iter, seed, floor_of, selection, progress) -> Consistency:
    from ..compression import compress
    from ..inverse import solvers
    from ..inverse.methods import noise_sigma, operator_for
    from ..types.rangegate import plan_reconstruction

    t0 = time.perf_counter()
    prof = compress(dataset, gate_s=plan_reconstruction(dataset, grid).gate_s, backend=selection)
    A = operator_for(dataset, prof, grid, selection)
    log.info("data consistency: %d fit(s) of %d iterations, %d voxels x %d measurements each, on %s",
             1 if floor_of else 2, n_iter, grid.size, dataset.n_meas, A.backend)
    b = A.data
    scale = float(np.linalg.norm(b))
    if not scale > 0:
        raise ValueError("dataset has no signal within the grid's delay gate")
    if floor_of is None:
        sigma, unit = noise_sigma(dataset, prof, None, np.random.default_rng(seed), A.selection)
        rhs = {"fit": b, "noise": sigma * unit.ravel()}
    else:
        sigma, rhs = floor_of.noise_sigma, {"fit": b}
    out = {}
    for step, y in rhs.items():
        say = None if progress is None else (lambda done, total, s=step: progress(s, done, total))
        res = solvers.cgls(A, y, None, max_iter=n_iter, tol=1e-12, progress=say)
        out[step] = [float(np.sqrt(2.0 * f)) / scale for f in res.objective]
    hist = out["fit"]
    if floor_of is None:
        floor_hist = out["noise"]
    else:  # the same noise, relative to this scan's norm
        floor_hist = [f * floor_of.scale / scale for f in floor_of.floor_history]
    r, f = hist[-1], floor_hist[-1]
    excess = float(np.sqrt(max(r * r - f * f, 0.0)))
    return Consistency(r, f, excess, hist, floor_hist, float(sigma), scale, len(hist) - 1, n_iter, tuple(grid.shape),
                       dataset.n_meas, A.backend, A.selection.device, time.perf_counter() - t0)
