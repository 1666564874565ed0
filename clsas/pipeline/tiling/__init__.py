"""Images past memory and past one machine: tiles, out-of-core files, several devices, Dask.

``reconstruct(dataset, grid, out="image.h5", max_memory="2GB")`` forms the grid tile by tile
into a chunked HDF5 file (resumable: a tile written is not formed again) with the process's
memory held under the budget, and returns an :class:`~clsas.Image` that reads the file lazily
(:meth:`clsas.Image.open`). ``client=`` forms the tiles on a Dask cluster
(:mod:`clsas.pipeline.tiling.dask`); ``device=[...]`` spreads them over several OpenCL devices of this
host (:mod:`clsas.pipeline.tiling.run`).

- :mod:`.tiles`: tiles of a grid, their size from a memory budget, the process's memory.
- :mod:`.store`: the chunked file and its record of the tiles written.
- :mod:`.run`: forming the tiles here (one device or several) or on the cluster.
- :mod:`.dask`: the cluster side (one task per run of a few tiles, profiles scattered once, worker devices).
"""

from __future__ import annotations

import re
from pathlib import Path

from ...physics.geometry import VoxelGrid
from ...types.image import Image
from .run import TiledRequest, form_tiled
from .store import SUFFIXES
from .tiles import Tile, check_tile_shape, peak_rss_bytes, rss_bytes, tile_grid, tile_shape_for

__all__ = ["TiledRequest", "Tile", "check_request", "finish", "form_tiled", "parse_bytes", "peak_rss_bytes",
           "rss_bytes", "tile_grid", "tile_shape_for", "update_attrs"]

_UNITS = {"": 1, "B": 1, "K": 1e3, "KB": 1e3, "M": 1e6, "MB": 1e6, "G": 1e9, "GB": 1e9, "T": 1e12, "TB": 1e12,
          "KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TIB": 2**40}


def parse_bytes(value, name: str = "max_memory") -> float:
    """A memory size: a number of bytes, or a string such as ``"2GB"``, ``"500 MB"``, ``"1.5GiB"``."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be a number of bytes or a string like '2GB', got {value!r}")
    if isinstance(value, (int, float)):
        n = float(value)
    elif isinstance(value, str):
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([A-Za-z]*)\s*", value)
        if not m or m.group(2).upper() not in _UNITS:
            raise ValueError(f"{name} must be a number of bytes or like '2GB', '500MB', '1.5GiB', got {value!r}")
        n = float(m.group(1)) * _UNITS[m.group(2).upper()]
    else:
        raise TypeError(f"{name} must be a number of bytes or a string like '2GB', got {type(value).__name__}")
    if not n > 0 or n == float("inf"):
        raise ValueError(f"{name} must be a positive, finite size, got {value!r}")
    return n


def check_request(grid: VoxelGrid, *, out=None, max_memory=None, client=None, tile_shape=None,
                  device=None) -> TiledRequest | None:
    """Check the tiling arguments of ``reconstruct`` before any work; None where none is asked for."""
    devices = tuple(device) if isinstance(device, (list, tuple)) else ()
    if isinstance(device, (list, tuple)) and not devices:
        raise ValueError("device: an empty list; give one device, several, or None")
    if all(a is None for a in (out, max_memory, client, tile_shape)) and not devices:
        return None
    if out is not None:
        if not isinstance(out, (str, Path)):
            raise TypeError(f"out must be a path (str or Path) ending in .h5 or .zarr, got {type(out).__name__}")
        out = Path(out)
        if out.suffix.lower() == ".zarr":
            from ...types.zarrstore import import_zarr

            import_zarr()  # a missing package is said before any work
        if out.suffix.lower() not in SUFFIXES:
            raise ValueError(f"out must end in {' or '.join(SUFFIXES)}, got {str(out)!r}")
        if not out.parent.is_dir():
            raise ValueError(f"out: the folder {str(out.parent)!r} does not exist")
    budget = None if max_memory is None else parse_bytes(max_memory)
    if client is not None:
        if devices:
            raise ValueError("device: a list of devices is for this host; on a Dask cluster each worker uses its "
                             "own (see clsas.pipeline.tiling.dask.OpenCLDevicePlugin)")
        if not isinstance(client, str) and not (hasattr(client, "submit") and hasattr(client, "scatter")):
            raise TypeError(f"client must be a distributed.Client or a scheduler address, got {type(client).__name__}")
        from .dask import import_distributed

        import_distributed()  # a missing extra is said before any work
    if tile_shape is not None:
        tile_shape = check_tile_shape(grid, tile_shape)
    return TiledRequest(out, budget, client, tile_shape, devices)


def finish(image: Image, out) -> Image:
    """Write ``image``'s attributes into the tiled file ``out``, mark it complete, and open it lazily
    (the plan and echoes, which the file does not hold, are kept)."""
    from dataclasses import replace

    _write_attrs(out, image, complete=True)
    return replace(Image.open(out), plan=image.plan, echoes=image.echoes)


def _write_attrs(path, image: Image, **more) -> None:
    """The image's attributes (and ``more``) into the HDF5 file or Zarr store at ``path``."""
    from ...types.image import write_attrs

    if Path(path).suffix.lower() == ".zarr":
        from ...types.zarrstore import import_zarr

        g = import_zarr().open_group(str(path), mode="r+")
        write_attrs(g, image)
        g.attrs.update(more)
        return
    import h5py

    with h5py.File(path, "r+") as f:
        write_attrs(f, image)
        f.attrs.update(more)


def update_attrs(image: Image, provenance: dict | None = None, **more) -> Image:
    """Add to the provenance of an image opened from a file (:meth:`clsas.Image.open`), in the file
    too; returns the image opened again."""
    from dataclasses import replace

    if hasattr(image.values, "file"):  # h5py: close the read-only handle before writing
        path = image.values.file.filename
        image.values.file.close()
    elif hasattr(image.values, "store_path"):  # a Zarr array
        path = str(image.values.store_path.store.root)
    else:
        raise ValueError("image: not an image opened from a file (Image.open)")
    changed = replace(image, values=None, provenance={**image.provenance, **(provenance or {}), **more})
    _write_attrs(path, changed)
    return replace(Image.open(path), plan=image.plan, echoes=image.echoes)
