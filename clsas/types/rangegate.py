"""What a reconstruction needs: the exact range gate of a grid, and what is skipped."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..physics.geometry import VoxelGrid
from .dataset import Dataset

__all__ = ["path_bounds", "ReconstructionPlan", "plan_reconstruction"]


def path_bounds(
    lo_m: np.ndarray, hi_m: np.ndarray, tx: np.ndarray, rx: np.ndarray, iterations: int = 300
) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum bistatic path ``|v - tx| + |v - rx|`` over the box ``[lo, hi]``.

    The maximum of this convex function is at a corner (evaluated exactly). The minimum is
    not, in general: it is found by projected subgradient descent, and what is returned is a
    certified lower bound ``f(x) - gap(x)`` (the Frank-Wolfe duality gap over the box), which
    equals the minimum at convergence and never exceeds it, so a gate built on it never
    cuts a voxel.

    Returns ``(min_path (n,), max_path (n,))`` in metres.
    """
    lo = np.asarray(lo_m, float)
    hi = np.asarray(hi_m, float)
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
    dist = np.linalg.norm(corners[None] - tx[:, None], axis=2) + np.linalg.norm(
        corners[None] - rx[:, None], axis=2
    )
    max_path = dist.max(axis=1)

    def f_and_g(x):
        da, db = x - tx, x - rx
        na = np.linalg.norm(da, axis=1, keepdims=True)
        nb = np.linalg.norm(db, axis=1, keepdims=True)
        g = np.where(na > 0, da / np.where(na > 0, na, 1), 0) + np.where(nb > 0, db / np.where(nb > 0, nb, 1), 0)
        return (na + nb)[:, 0], g

    x = np.clip(0.5 * (tx + rx), lo, hi)
    diag = max(float(np.linalg.norm(hi - lo)), 1e-9)
    lower = np.linalg.norm(tx - rx, axis=1)  # the triangle inequality is always a bound
    best = np.full(len(tx), np.inf)
    for k in range(iterations):
        f, g = f_and_g(x)
        best = np.minimum(best, f)
        gap = np.maximum(g * (x - lo), g * (x - hi)).sum(axis=1)
        lower = np.maximum(lower, f - gap)
        x = np.clip(x - (0.5 * diag / np.sqrt(k + 1)) * g, lo, hi)
        if np.all(best - lower < 1e-9):
            break
    return np.minimum(lower, best), max_path


@dataclass(frozen=True)
class ReconstructionPlan:
    """What a reconstruction computes and what it leaves out (immutable: the pipeline fills the
    profile fields in with :func:`dataclasses.replace`).

    Parameters
    ----------
    grid_shape : tuple of int
        (nx, ny, nz) voxels.
    path_min_m, path_max_m : float
        Shortest and longest bistatic path (speaker -> voxel -> microphone) over the grid, m.
    gate_s : (float, float)
        The delay gate those paths give, s (all measurements together).
    lags_full : int
        Lags of a full-window profile (no gate).
    lags, lag_step : int
        Lags the profiles keep, and recording samples per profile sample (the decimation).
    kernels, notes : list of str
        The kernels run, and what was skipped and why.
    gates_s : numpy.ndarray, optional
        (n_meas, 2) each measurement's own delay gate, s.

    Examples
    --------
    Every image carries the plan that made it:

    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> image = clsas.reconstruct(data, grid)
    >>> text = image.plan.describe()          # the range gate, the lags kept, the kernels run
    >>> image.plan.grid_shape == grid.shape
    True
    """

    grid_shape: tuple[int, int, int]
    path_min_m: float
    path_max_m: float
    gate_s: tuple[float, float]
    lags_full: int
    lags: int = 0  # from the profiles reconstruct() computes
    lag_step: int = 1  # recording samples per profile sample (the profiles' decimation)
    kernels: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    gates_s: np.ndarray | None = None  # (n_meas, 2) each measurement's own delay gate, s

    def describe(self) -> str:
        nx, ny, nz = self.grid_shape
        dims = sum(n > 1 for n in self.grid_shape)
        lines = [
            f"grid {nx} x {ny} x {nz} = {nx * ny * nz} voxels ({dims}-D: computing only these)",
            f"bistatic path over the grid {self.path_min_m:.4f}-{self.path_max_m:.4f} m; "
            f"delay gate {self.gate_s[0] * 1e3:.3f}-{self.gate_s[1] * 1e3:.3f} ms",
            f"range profiles: {self.lags} samples every {self.lag_step} lag(s), covering "
            f"{self.lags * self.lag_step} of {self.lags_full} lags "
            f"({100 * max(0.0, 1 - self.lags * self.lag_step / self.lags_full):.0f} % skipped by the gate)",
            f"kernels built: {', '.join(self.kernels) or 'none (NumPy twins)'}",
        ]
        return "\n".join(lines + self.notes)


def plan_reconstruction(dataset: Dataset, grid: VoxelGrid, kernels: list[str] = ()) -> ReconstructionPlan:
    """Range gate for ``grid``: exact min and max bistatic path over all voxels and stops."""
    b = grid.bounds()
    pmin, pmax = path_bounds(b[:, 0], b[:, 1], dataset.tx_positions, dataset.rx_positions)
    c = dataset.c_per_meas
    gates = np.stack([pmin / c, pmax / c], axis=1)
    gate = (float(gates[:, 0].min()), float(gates[:, 1].max()))
    full = dataset.n_samples + len(dataset.waveform) - 1
    return ReconstructionPlan(grid.shape, float(pmin.min()), float(pmax.max()), gate, full, kernels=list(kernels),
                              gates_s=gates)
