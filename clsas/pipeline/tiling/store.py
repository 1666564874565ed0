"""The file an out-of-core reconstruction streams its tiles into, and resumes from.

An image file in :mod:`clsas.types.image`'s layout (so :meth:`clsas.Image.load` and
:meth:`clsas.Image.open` read it) whose ``values`` are chunked complex64, plus:

- ``tiles_done``: (n_tiles,) uint8, 1 for each tile written (set only after its values are flushed
  and synced to the disk);
- attributes ``tile_shape`` (3,), ``request_sha256`` (what was asked: profiles, grid, formation,
  options, backend kind and tile shape) and ``complete`` (False until the last tile and the
  image's attributes are written).

Crash safety (HDF5): every chunk of ``values`` is allocated when the file is made (no fill is
written), so writing a tile changes no HDF5 metadata, only the tile's own bytes and then its
byte in ``tiles_done``. A process killed at any moment of a tile (mid-write included) leaves a
file that opens, whose marked tiles are whole, and the run started again forms the unmarked
tiles and only those (``tests/unit/tiling/test_tiles_crash.py`` kills a writer process mid-run).

A ``.zarr`` store (Zarr v3, :class:`ZarrTileFile`) holds the same arrays, with the attributes as
JSON; a tile is marked after its values too, but whether a kill mid-write leaves the store
readable is the store's (not tested by killing a writer).

Opening an unfinished file with the same request resumes it: the tiles already written are not
formed again. A file made by another request is refused, not overwritten.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from ...physics.geometry import VoxelGrid
from ...types.image import attach_values, write_axes
from ...types.profiles import Profiles
from .tiles import Tile, chunk_shape

__all__ = ["TileFile", "ZarrTileFile", "open_store", "request_digest", "SUFFIXES"]

log = logging.getLogger(__name__)

SUFFIXES = (".h5", ".hdf5", ".zarr")


def request_digest(profiles: Profiles, grid: VoxelGrid, formation: str, options: dict, kind: str,
                   tile_shape: tuple[int, int, int]) -> str:
    """SHA-256 of everything that decides a tile's values (the profiles' data and geometry, the grid,
    the formation and its options, the backend kind, the tile shape)."""
    h = hashlib.sha256()
    for arr in (profiles.data, profiles.tau0_s, profiles.tx_positions, profiles.rx_positions,
                np.asarray(profiles.c_mps, float), grid.x_m, grid.y_m, grid.z_m):
        a = np.ascontiguousarray(arr)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    h.update(json.dumps([profiles.dtau_s, profiles.fc_hz, formation, options, kind, list(tile_shape)],
                        sort_keys=True, default=str).encode())
    return h.hexdigest()


class TileFile:
    """A chunked image file being filled tile by tile (see the module notes).

    Parameters
    ----------
    path : str or Path
        ``.h5`` or ``.hdf5``.
    grid : VoxelGrid
    tiles : list of Tile
        The tiles, as :func:`clsas.pipeline.tiling.tiles.tile_grid` made them.
    tile_shape : (int, int, int)
    digest : str
        :func:`request_digest` of the request.
    """

    def __init__(self, path: str | Path, grid: VoxelGrid, tiles: list[Tile], tile_shape: tuple[int, int, int],
                 digest: str):
        import h5py

        self.path = Path(path)
        self.n_tiles = len(tiles)
        if self.path.exists():
            self._f = h5py.File(self.path, "r+")
            self._check(digest)
        else:  # made under another name and renamed once whole: a kill while making it leaves no file here
            part = self.path.with_name(self.path.name + ".part")
            self._f = h5py.File(part, "w")
            self._create(grid, tile_shape, digest)
            self._sync()
            os.replace(part, self.path)
        self.done = self._f["tiles_done"][()].astype(bool)
        if self.done.any():
            log.info("%s: resuming, %d of %d tiles already written", self.path, int(self.done.sum()), self.n_tiles)

    def _create(self, grid, tile_shape, digest) -> None:
        f = self._f
        scales = write_axes(f, grid)
        import h5py

        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)  # every chunk placed now: a tile's write is data only
        d = f.create_dataset("values", shape=grid.shape, dtype=np.complex64, chunks=chunk_shape(tile_shape),
                             fillvalue=np.complex64(0), fill_time="never", dcpl=dcpl)
        attach_values(d, scales)
        f.create_dataset("tiles_done", data=np.zeros(self.n_tiles, np.uint8))
        f.attrs.update(format="clsas image", tile_shape=np.asarray(tile_shape), request_sha256=digest,
                       complete=False)
        f.flush()

    def _check(self, digest) -> None:
        a = self._f.attrs
        if "request_sha256" not in a or "tiles_done" not in self._f:
            self._f.close()
            raise ValueError(f"out: {self.path} exists and is not a tiled clsas image; remove it or choose another "
                             "file")
        if a["request_sha256"] != digest or self._f["tiles_done"].shape != (self.n_tiles,):
            self._f.close()
            raise ValueError(f"out: {self.path} holds tiles of another request (other data, grid, formation, "
                             "backend or tile shape); remove it or choose another file")

    @property
    def pending(self) -> list[int]:
        """Numbers of the tiles not yet written."""
        return [int(i) for i in np.flatnonzero(~self.done)]

    def write(self, tile: Tile, values: np.ndarray) -> None:
        """Write one tile's values, flush and sync them to the disk, and only then mark the tile done
        (a crash at any point loses at most this tile, which the next run forms again)."""
        self._f["values"][tile.slices] = np.asarray(values, np.complex64).reshape(tile.grid.shape)
        self._sync()
        self._f["tiles_done"][tile.index] = 1
        self._f.flush()
        self.done[tile.index] = True

    def _sync(self) -> None:
        """Flush HDF5's buffers to the file and the file to the disk (fsync where the driver has a
        file descriptor)."""
        self._f.flush()
        try:
            fd = self._f.id.get_vfd_handle()
        except (AttributeError, ValueError, RuntimeError):  # a driver without one (in-memory, family)
            return
        if isinstance(fd, int) and fd >= 0:
            os.fsync(fd)

    def close(self) -> None:
        self._f.close()


class ZarrTileFile(TileFile):
    """The same as :class:`TileFile` in a Zarr v3 store (a folder ending in ``.zarr``)."""

    def __init__(self, path: str | Path, grid: VoxelGrid, tiles: list[Tile], tile_shape: tuple[int, int, int],
                 digest: str):
        from ...types.zarrstore import import_zarr

        zarr = import_zarr()
        self.path = Path(path)
        self.n_tiles = len(tiles)
        if self.path.exists():
            self._g = zarr.open_group(str(self.path), mode="r+")
            a = dict(self._g.attrs)
            if "request_sha256" not in a or "tiles_done" not in set(self._g.array_keys()):
                raise ValueError(f"out: {self.path} exists and is not a tiled clsas image; remove it or choose "
                                 "another store")
            if a["request_sha256"] != digest or self._g["tiles_done"].shape != (self.n_tiles,):
                raise ValueError(f"out: {self.path} holds tiles of another request (other data, grid, formation, "
                                 "backend or tile shape); remove it or choose another store")
        else:
            g = self._g = zarr.open_group(str(self.path), mode="w")
            for name in ("x_m", "y_m", "z_m"):
                g.create_array(name, data=getattr(grid, name), attributes={"units": "m"})
            g.create_array("values", shape=grid.shape, dtype=np.complex64, chunks=chunk_shape(tile_shape),
                           fill_value=0, attributes={"dims": ["x_m", "y_m", "z_m"]})
            g.create_array("tiles_done", data=np.zeros(self.n_tiles, np.uint8))
            g.attrs.update(format="clsas image", tile_shape=list(tile_shape), request_sha256=digest, complete=False)
        self.done = self._g["tiles_done"][:].astype(bool)

    def write(self, tile: Tile, values: np.ndarray) -> None:
        self._g["values"][tile.slices] = np.asarray(values, np.complex64).reshape(tile.grid.shape)
        self._g["tiles_done"][tile.index] = 1
        self.done[tile.index] = True

    def close(self) -> None:
        pass  # every write went to the store


def open_store(path, grid: VoxelGrid, tiles: list[Tile], tile_shape, digest: str) -> TileFile:
    """The tiled file for ``path``: Zarr for ``.zarr``, else HDF5."""
    cls = ZarrTileFile if Path(path).suffix.lower() == ".zarr" else TileFile
    return cls(path, grid, tiles, tile_shape, digest)
