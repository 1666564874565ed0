"""Tiles of a voxel grid, sized to a memory budget.

A tile is a box of whole voxels ``[x0:x1, y0:y1, z0:z1]`` and its sub-grid (the grid's own axis
values, sliced, so a voxel has the same centre in a tile as in the whole grid). Tiles are
numbered in C order (x slowest); the file of an out-of-core run records which are done.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from ...formation.bp_numpy import upsample_factor
from ...formation.guard import bytes_per_voxel
from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles

__all__ = ["Tile", "form_in_turn", "form_tile", "read_only", "bp_record", "tile_grid", "tile_shape_for",
           "rss_bytes", "peak_rss_bytes", "profile_bytes"]

# what a tile costs on the host beyond the formation's own bytes per voxel: the values handed
# to the writer (complex64) and the writer's conversion to HDF5's compound (complex64)
_WRITE_BYTES = 16
# the share of the budget a tile may take: the rest is margin for the allocator's fragmentation
_TILE_SHARE = 0.6


@dataclass(frozen=True)
class Tile:
    """One box of the grid: ``index`` (its number), ``slices`` into the grid's values, ``grid``."""

    index: int
    slices: tuple[slice, slice, slice]
    grid: VoxelGrid

    @property
    def size(self) -> int:
        """Voxels in the tile."""
        return self.grid.size


def tile_grid(grid: VoxelGrid, shape: tuple[int, int, int]) -> list[Tile]:
    """Split ``grid`` into boxes of at most ``shape`` voxels (the last along each axis smaller).

    Parameters
    ----------
    grid : VoxelGrid
    shape : (int, int, int)
        Voxels per tile along x, y, z; each between 1 and the grid's length on that axis.
    """
    shape = check_tile_shape(grid, shape)
    axes = (grid.x_m, grid.y_m, grid.z_m)
    starts = [range(0, n, s) for n, s in zip(grid.shape, shape, strict=True)]
    out = []
    for i0 in starts[0]:
        for j0 in starts[1]:
            for k0 in starts[2]:
                sl = tuple(slice(a, min(a + s, n)) for a, s, n in zip((i0, j0, k0), shape, grid.shape, strict=True))
                out.append(Tile(len(out), sl, VoxelGrid(*(ax[s] for ax, s in zip(axes, sl, strict=True)))))
    return out


def check_tile_shape(grid: VoxelGrid, shape) -> tuple[int, int, int]:
    """``shape`` as three ints, each between 1 and the grid's length on that axis (else an error)."""
    try:
        shp = tuple(int(s) for s in shape)
    except (TypeError, ValueError):
        raise TypeError(f"tile_shape must be three integers (x, y, z voxels), got {shape!r}") from None
    if len(shp) != 3 or any(s != t for s, t in zip(shp, shape, strict=False)):
        raise ValueError(f"tile_shape must be three integers (x, y, z voxels), got {shape!r}")
    if any(not 1 <= s <= n for s, n in zip(shp, grid.shape, strict=True)):
        raise ValueError(f"tile_shape must be between 1 and the grid's {grid.shape} on each axis, got {shp}")
    return shp  # type: ignore[return-value]


def profile_bytes(profiles: Profiles) -> int:
    """Host bytes the profiles cost while tiles are formed (on a CPU device, its buffers are host
    memory): the profiles, and the OpenCL path's copy of them and carrier records (complex64
    pairs, upsampled), kept for every tile; at least four times the complex128 data."""
    records = 16 * profiles.n_meas * ((profiles.n_lags - 1) * upsample_factor(profiles.fc_hz, profiles.dtau_s) + 1)
    # complex64 rows still on the device are not read to count them
    data = 8 * profiles.n_meas * profiles.n_lags if profiles.device_rows() is not None else profiles.data.nbytes
    return int(max(4 * data, 2 * data + records) + 64 * profiles.n_meas)


def read_only(profiles: Profiles) -> Profiles:
    """``profiles`` with read-only data (a view where it was writeable): the OpenCL path keeps
    the records it made on the device for the next tile only for an array that cannot change.
    Profiles whose rows are still on the device are returned as they are (not read: their host
    copy, when read, is read-only)."""
    if profiles.device_rows() is not None or not profiles.data.flags.writeable:
        return profiles
    view = profiles.data.view()
    view.flags.writeable = False
    return replace(profiles, data=view)


def tile_shape_for(grid: VoxelGrid, kind: str, *, max_memory: float | None = None, fixed_bytes: int = 0,
                   min_tiles: int = 1, held_tiles: int = 1) -> tuple[int, int, int]:
    """The largest tile shape whose forming fits ``max_memory`` and that gives ``min_tiles`` tiles.

    Whole (y, z) planes of several x-planes where they fit, else planes split along y, then z.

    Parameters
    ----------
    grid : VoxelGrid
    kind : {"opencl", "numpy"}
        Where the tiles are formed (the host bytes per voxel differ, see
        :func:`clsas.formation.guard.bytes_per_voxel`).
    max_memory : float, optional
        Host memory budget of the process, bytes; None: no budget (the tiles only split the
        grid into ``min_tiles``).
    fixed_bytes : int
        What the process holds whatever the tile (its current size, the profiles), bytes.
    min_tiles : int
        At least this many tiles (to spread over workers or devices).
    held_tiles : int
        Tiles whose values the process holds at once (a Dask task returns its run of tiles
        together): each beyond the first costs its values (complex64 on OpenCL, complex128 on
        NumPy) on top of the tile being formed.
    """
    if not isinstance(held_tiles, int) or held_tiles < 1:
        raise ValueError(f"held_tiles must be a positive integer, got {held_tiles!r}")
    per_voxel = bytes_per_voxel(kind) + _WRITE_BYTES + (held_tiles - 1) * (8 if kind == "opencl" else 16)
    cap = grid.size
    if max_memory is not None:
        room = _TILE_SHARE * (float(max_memory) - fixed_bytes)
        cap = int(room // per_voxel)
        if cap < 1:
            raise ValueError(f"max_memory={max_memory:.3g} bytes leaves no room for a tile: the process already "
                             f"holds about {fixed_bytes / 1e6:.0f} MB (code, the dataset and its profiles); give "
                             f"at least {(fixed_bytes + per_voxel * grid.shape[2] / _TILE_SHARE) / 1e6:.0f} MB")
    cap = max(1, min(cap, math.ceil(grid.size / max(1, int(min_tiles)))))
    nx, ny, nz = grid.shape
    plane = ny * nz
    if cap >= plane:
        return (max(1, min(nx, cap // plane)), ny, nz)
    if cap >= nz:
        return (1, max(1, min(ny, cap // nz)), nz)
    return (1, 1, max(1, cap))


def form_tile(profiles: Profiles, grid: VoxelGrid, formation: str, options: dict, selection,
              force: bool = False) -> tuple[np.ndarray, str, float, dict | None]:
    """One tile: ``(values (nx, ny, nz) as the formation gave them, device, seconds, bp)``,
    ``bp`` what bp recorded of it (:func:`bp_record`)."""
    from ...formation import form

    t0 = time.perf_counter()
    image = form(profiles, grid, formation, backend=selection, force=force, **options)
    return np.asarray(image.values), image.device, time.perf_counter() - t0, bp_record(image)


def form_in_turn(profiles: Profiles, grids: Iterable[VoxelGrid], formation: str, options: dict, selection,
                 force: bool = False,
                 overlap: bool = True) -> Iterator[tuple[np.ndarray, str, float, dict | None, bool]]:
    """Each grid of ``grids`` formed in turn: ``(values, device, seconds, bp, overlapped)`` (``bp``:
    :func:`bp_record`).

    A formation that forms tiles itself (``form_tiles``, bp: the next tile's kernels enqueued
    before the last tile's image is read back and handed on) does so on OpenCL, taking each grid
    only as the previous image is handed on, so that it holds at most one grid ahead of the
    caller (a shared queue of tiles stays shared); ``seconds`` is then the tile's share of the
    run's wall time and ``overlapped`` says whether the tile's kernels ran while the previous
    tile's image was read back (with ``overlap``, for every tile of a run but the first, formed
    on the device's resident path: not where the twin took over, nor on records made on the
    host). Elsewhere one :func:`form_tile` after the other (``overlapped`` False).
    """
    from ...formation import FORMATIONS

    form_tiles = getattr(FORMATIONS[formation], "form_tiles", None)
    if form_tiles is None or not selection.opencl:
        for grid in grids:
            yield (*form_tile(profiles, grid, formation, options, selection, force), False)
        return
    t0, previous = time.perf_counter(), False  # whether the previous tile was read back on the resident path
    for image in form_tiles(profiles, grids, backend=selection, force=force, overlap=overlap, **options):
        t1 = time.perf_counter()
        seconds, t0 = t1 - t0, t1
        bp = bp_record(image)
        resident = image.backend == "opencl" and (bp or {}).get("records") not in (None, "host")
        overlapped, previous = overlap and resident and previous, resident
        yield np.asarray(image.values), image.device, seconds, bp, overlapped


def bp_record(image) -> dict | None:
    """What bp recorded of a tile (``image.provenance["bp"]``: the kernel variant and its stated
    error, and on the resident OpenCL path where its carrier records came from: ``"rows"``, the
    compression's device rows, ``"uploaded"``, ``"kept"`` from an earlier tile); None: not bp."""
    return image.provenance.get("bp")


def rss_bytes() -> int:
    """This process's resident memory now, bytes (Linux; 0 where unknown)."""
    return _status_kb("VmRSS:") * 1024


def peak_rss_bytes() -> int:
    """This process's peak resident memory so far, bytes (Linux; 0 where unknown)."""
    return _status_kb("VmHWM:") * 1024


def _status_kb(key: str) -> int:
    try:
        with open(f"/proc/{os.getpid()}/status") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def chunk_shape(tile_shape: tuple[int, int, int], itemsize: int = 8, max_bytes: int = 4 << 20) -> tuple[int, ...]:
    """An HDF5 chunk shape for tiles of ``tile_shape``: the tile halved along x, then y, then z
    until a chunk holds at most ``max_bytes``."""
    c = list(tile_shape)
    for axis in range(3):
        while c[axis] > 1 and int(np.prod(c)) * itemsize > max_bytes:
            c[axis] = -(-c[axis] // 2)
    return tuple(c)
