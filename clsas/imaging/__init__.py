"""Backprojection (NumPy twin and OpenCL plan behind one dispatcher) and ``reconstruct``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from .. import _validate as v
from .. import cl as _cl
from ..compress import Profiles, compress
from ..dataset import Dataset
from ..geometry import VoxelGrid
from . import numpy as twin
from .image import Image, Peak
from .plan import ReconstructionPlan, path_bounds, plan_reconstruction

__all__ = ["Image", "Peak", "ReconstructionPlan", "backproject", "reconstruct", "path_bounds"]

log = logging.getLogger(__name__)

METHODS = ("bp", "bpdn", "cbp-taylor", "cbp-polar")


def backproject(
    profiles: Profiles,
    grid: VoxelGrid,
    *,
    tx_positions: np.ndarray | None = None,
    rx_positions: np.ndarray | None = None,
    c_mps: float | None = None,
    backend: str | None = "auto",
    chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Image:
    """Bistatic delay-and-sum of complex baseband profiles onto ``grid``.

    For each voxel and measurement the profile is linearly interpolated at the bistatic
    delay ``(|v - tx| + |v - rx|) / c`` and the carrier phase restored; samples outside the
    profile window contribute nothing. Positions and ``c`` default to those the profiles
    carry (from a Dataset).

    Returns
    -------
    Image
        complex64 values (OpenCL) or complex128 (NumPy), shape ``grid.shape``.
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    n = profiles.n_meas
    tx = v.array("tx_positions", profiles.tx_positions if tx_positions is None else tx_positions, shape=(n, 3))
    rx = v.array("rx_positions", profiles.rx_positions if rx_positions is None else rx_positions, shape=(n, 3))
    c = v.positive("c_mps", profiles.c_mps if c_mps is None else c_mps)
    data = v.array("profiles.data", profiles.data, ndim=2, dtype=None, allow_complex=True)
    backend = _cl.resolve_backend(backend)
    t_start = time.perf_counter()
    timings = {}
    if backend == "opencl":
        from .opencl import BackprojectPlan

        plan = BackprojectPlan(grid, n, data.shape[1], chunk=chunk)
        values = plan(data, profiles.tau0_s, profiles.dtau_s, profiles.fc_hz, tx, rx, c, progress)
        timings["backproject_kernel"] = plan.last_kernel_s
        device = _cl.device_info()
    else:
        values = twin.backproject(
            data.astype(np.complex128), profiles.tau0_s, profiles.dtau_s, profiles.fc_hz, tx, rx, c,
            grid.points(), progress,
        )
        device = "NumPy (float64)"
    timings["backproject"] = time.perf_counter() - t_start
    return Image(values.reshape(grid.shape), grid, "bp", backend, device, timings)


def reconstruct(
    dataset: Dataset,
    grid: VoxelGrid,
    method: str = "bp",
    *,
    compression: str = "matched",
    backend: str | None = "auto",
    progress: Callable[[int, int], None] | None = None,
    sparse: dict | None = None,
) -> Image:
    """Image a dataset on a grid.

    The plan computes only what the grid needs: range profiles over the exact delay gate of
    the grid (min and max bistatic path over all voxels and stops), and only the kernels
    the pipeline uses. ``plan.describe()`` on the result says what was skipped.

    Parameters
    ----------
    dataset : Dataset
    grid : VoxelGrid
    method : {"bp", "bpdn", "cbp-taylor", "cbp-polar"}
        ``"bp"``: pulse compression + backprojection. The sparse methods super-resolve each
        recording within its own range gate (complex amplitudes: echoes of unknown phase),
        render each echo as a pulse much narrower than the matched filter's, and backproject
        those profiles (see :func:`clsas.imaging.sparse.superres_profiles`).
    compression : {"matched", "fmcw"}
    backend : {"auto", "opencl", "numpy"}
    progress : callable(done, total), optional
    sparse : dict, optional
        Options for the sparse methods: ``delta_s``, ``lam``, ``lam_frac``, ``render_width_s``.
    """
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    v.choice("method", method, METHODS)
    backend = _cl.resolve_backend(backend)
    if method != "bp":
        return _reconstruct_sparse(dataset, grid, method, backend, progress, sparse or {})
    compress_kernel = "matched_filter" if compression == "matched" else "fmcw_dechirp"
    kernels = [f"compress.cl:{compress_kernel}", "backproject.cl:backproject"] if backend == "opencl" else []
    plan = plan_reconstruction(dataset, grid, kernels)
    if compression == "fmcw":
        plan.notes.append("fmcw: delays are gated; the mixed window is the whole chirp overlap")
    t_start = time.perf_counter()
    prof = compress(dataset, method=compression, gate_s=plan.gate_s, backend=backend)
    plan.lags = prof.n_lags
    plan.lag_step = int(round(prof.dtau_s * dataset.fs_hz))
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    image = backproject(prof, grid, backend=backend, progress=progress)
    image.method = method
    image.plan = plan
    image.timings_s = {**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start}
    return image


def _reconstruct_sparse(dataset, grid, method, backend, progress, options) -> Image:
    from .sparse import superres_profiles

    unknown = set(options) - {"delta_s", "lam", "lam_frac", "render_width_s"}
    if unknown:
        raise ValueError(f"sparse: unknown option(s) {sorted(unknown)}")
    kernels = ["backproject.cl:backproject"] if backend == "opencl" else []
    plan = plan_reconstruction(dataset, grid, kernels)
    b = grid.bounds()
    pmin, pmax = path_bounds(b[:, 0], b[:, 1], dataset.tx_positions, dataset.rx_positions)
    gates = np.stack([pmin, pmax], axis=1) / dataset.c_mps
    plan.notes.append(f"{method}: each recording super-resolved within its own gate, echoes rendered as pulses")
    t_start = time.perf_counter()
    prof, echoes = superres_profiles(dataset, gates, method, progress=progress, **options)
    plan.lags = prof.n_lags
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    image = backproject(prof, grid, backend=backend, progress=progress)
    image.method = method
    image.plan = plan
    image.echoes = echoes
    image.timings_s = {**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start}
    return image
