"""Sweeps and large volumes on a Dask cluster (a local one by default).

A sweep is split into one task per trial (method x setting x seed); the results come back in
the serial order, so a sweep on Dask equals the same sweep run serially, field for field (run
times aside). A volume is split into tiles along x; runs of tiles are backprojected on the workers
(on their OpenCL device where they have one) and the tiles are joined into the image a single call
would give.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager

import numpy as np

from clsas.physics.geometry import VoxelGrid

__all__ = ["dask_client", "sweep_dask", "grid_sweep_dask", "backproject_tiled", "tiles"]

log = logging.getLogger(__name__)


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise ImportError("the Dask runs need dask.distributed: pip install 'clsas[bench]'") from exc
    return distributed


@contextmanager
def dask_client(scheduler: str | None = None, n_workers: int = 2):
    """A client of the cluster at ``scheduler``, or of a local cluster of ``n_workers`` processes."""
    distributed = _import_distributed()
    quiet = logging.getLogger("distributed")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # its INFO lines would bury the report's progress
    try:
        with _client(distributed, scheduler, n_workers) as client:
            yield client
    finally:
        quiet.setLevel(level)


@contextmanager
def _client(distributed, scheduler, n_workers):
    if scheduler:
        client = distributed.Client(scheduler, timeout="20s")
        log.info("dask: connected to %s (%d workers)", scheduler, len(client.scheduler_info()["workers"]))
        try:
            yield client
        finally:
            client.close()
        return
    with distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                  dashboard_address=None, silence_logs=logging.ERROR) as cluster, \
            distributed.Client(cluster) as client:
        log.info("dask: local cluster of %d workers", n_workers)
        yield client


def sweep_dask(client, task, methods, separations_b, snrs_db, trials: int, *, seed0: int = 0, **kwargs) -> list[dict]:
    """:func:`bench.trials.sweep` with one Dask task per trial; same rows, same order."""
    from .trials import run_trial

    futures = [client.submit(run_trial, task, m, sep, snr, seed0 + k, pure=False, **kwargs)
               for sep in separations_b for snr in snrs_db for k in range(trials) for m in methods]
    return client.gather(futures)


def grid_sweep_dask(client, methods, deltas, lam_fracs) -> list[dict]:
    """:func:`bench.trials.grid_sweep` with one Dask task per cell; same rows, same order."""
    from .trials import grid_cell

    futures = [client.submit(grid_cell, m, d, lf, pure=False) for d in deltas for lf in lam_fracs for m in methods]
    return client.gather(futures)


def tiles(grid: VoxelGrid, n_tiles: int) -> list[tuple[slice, VoxelGrid]]:
    """Split ``grid`` along x into ``n_tiles`` contiguous sub-grids: (x slice, sub-grid)."""
    nx = grid.shape[0]
    if not 1 <= n_tiles <= nx:
        raise ValueError(f"n_tiles must be between 1 and the grid's {nx} x-planes, got {n_tiles}")
    edges = np.linspace(0, nx, n_tiles + 1).round().astype(int)
    return [(slice(a, b), VoxelGrid(grid.x_m[a:b], grid.y_m, grid.z_m)) for a, b in zip(edges[:-1], edges[1:],
                                                                                       strict=True)]


def backproject_tiled(client, profiles, grid: VoxelGrid, n_tiles: int, backend: str | None = "auto"):
    """Backproject ``profiles`` onto ``grid`` in ``n_tiles`` tiles on the cluster, through the library's
    tiling (:func:`clsas.pipeline.tiling.dask.run_on_cluster`: the profiles scattered once, one task per run
    of a few tiles, each formed in turn with the next tile's kernels beside the last one's read back).

    Returns ``(values (nx, ny, nz) complex, devices)``: the joined image and the device each tile ran on.
    """
    from clsas.pipeline.tiling import Tile
    from clsas.pipeline.tiling.dask import run_on_cluster

    parts = [Tile(i, (sl, slice(None), slice(None)), sub) for i, (sl, sub) in enumerate(tiles(grid, n_tiles))]
    out = None
    devices = [""] * len(parts)
    for tile, vals, device, *_ in run_on_cluster(client, profiles, parts, list(range(len(parts))), "bp", {},
                                                backend or "auto", False):
        out = np.zeros(grid.shape, vals.dtype) if out is None else out
        out[tile.slices] = vals
        devices[tile.index] = device
    return out, devices
