"""The Image type: complex values on a voxel grid, peaks, dB, pictures, HDF5.

Image file layout (HDF5, ``format = "clsas image"``, ``format_version = 1``)
----------------------------------------------------------------------------
- ``x_m``, ``y_m``, ``z_m``: (nx,), (ny,), (nz,) float64 voxel centres in metres; each is an HDF5
  dimension scale, so netCDF readers (``xarray.open_dataset(path, engine="h5netcdf")``) see them
  as the coordinates of ``values``. A plane grid has one axis of length 1.
- ``values``: (nx, ny, nz) complex (HDF5 compound of ``r``, ``i``, as h5py writes it), indexed
  ``[ix, iy, iz]``; its three dimensions are attached to the scales above.
- attributes: ``method``, ``formation``, ``backend``, ``device``, ``clsas_version``,
  ``spacing_m`` (3,), ``time_<step>_s``; ``source_sha256`` and ``source_path`` when formed from a
  scan file; ``dataset_provenance_json`` (the scan's preprocessing steps); ``provenance_json``
  (all of the above and any further parameters, as one JSON object).

Files written before the dimension scales (no ``format_version``) still load.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..physics.geometry import VoxelGrid
from .dataset import json_default

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["Image", "Peak", "IMAGE_FORMAT_VERSION", "source_provenance"]

IMAGE_FORMAT_VERSION = 1
_AXES = ("x_m", "y_m", "z_m")


@dataclass(frozen=True)
class Peak:
    position_m: np.ndarray
    index: tuple[int, int, int]
    magnitude: float


@dataclass(frozen=True)
class Image:
    """A reconstruction: complex ``values`` (nx, ny, nz) on ``grid``; immutable once built (derive a
    changed copy with :func:`dataclasses.replace`).

    Parameters
    ----------
    values : numpy.ndarray
        (nx, ny, nz) complex, the image on ``grid`` (linear amplitude).
    grid : VoxelGrid
        Where the values are, metres.
    method, backend, device : str
        How it was made: the imaging method (``"bp"``, ``"cbp-polar"``, ...), ``"opencl"`` or
        ``"numpy"``, and the device's name.
    timings_s : dict
        Seconds per stage.
    plan : ReconstructionPlan, optional
        What the reconstruction computed and skipped (``plan.describe()``).
    echoes : list of Echoes, optional
        The echoes found per recording by a sparse method.
    provenance : dict
        The dataset's provenance and the reconstruction's settings (stored with the image).
    on_device : clsas.cl.DeviceRows, optional
        ``values`` as bp's resident OpenCL path left them on the device (one row of complex64,
        voxels in C order; ``values`` is then read-only), for a next step on the same device
        to read there while it still holds them (:meth:`clsas.cl.DeviceRows.valid`: until
        the plan's next call; autofocus computes its metric there); None: on the host only.
        Not saved.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> image = clsas.reconstruct(data, grid)
    >>> image.values.shape == grid.shape
    True
    >>> top = image.peaks(2, min_separation_m=0.05)             # strongest local maxima, with positions
    >>> _ = image.save("image.h5")
    """

    values: np.ndarray
    grid: VoxelGrid
    method: str = "bp"
    backend: str = "numpy"
    device: str = "NumPy (float64)"
    timings_s: dict = field(default_factory=dict)
    plan: object | None = None
    echoes: list | None = None  # sparse methods: the Echoes found in each recording
    provenance: dict = field(default_factory=dict)  # source scan, parameters (stored as JSON)
    # clsas.cl.DeviceRows: ``values`` as bp's resident path left them on the device (None: host only)
    on_device: object | None = field(default=None, compare=False, repr=False)

    def magnitude(self) -> np.ndarray:
        """``|values|`` (read into memory where the values are on disk: see :meth:`projection`,
        :meth:`section` and :meth:`reduced` for what stays small)."""
        if self.lazy:
            return np.concatenate([np.abs(b) for _, b, _ in _slabs(self.values)], axis=0)
        return np.abs(self.values)

    def db(self, floor_db: float = -60.0) -> np.ndarray:
        """Magnitude in dB relative to the maximum, floored at ``floor_db``."""
        mag = self.magnitude()
        peak = mag.max(initial=0.0)
        if peak == 0:
            return np.full(mag.shape, floor_db)
        rel = np.asarray(mag, np.float64) / float(peak)
        return np.maximum(20 * np.log10(np.maximum(rel, 1e-300)), floor_db)

    @property
    def lazy(self) -> bool:
        """Whether ``values`` stay on disk (an h5py dataset or a dask array, :meth:`open`)."""
        return not isinstance(self.values, np.ndarray)

    def max_magnitude(self) -> float:
        """``max |values|``, read slab by slab where the values are on disk."""
        if not self.lazy:
            return float(np.abs(self.values).max(initial=0.0))
        return max((float(np.abs(b).max(initial=0.0)) for _, b, _ in _slabs(self.values)), default=0.0)

    def peaks(self, k: int = 1, min_separation_m: float = 0.0) -> list[Peak]:
        """The ``k`` strongest local maxima of ``|values|``, strongest first.

        Peaks closer than ``min_separation_m`` to a stronger one are dropped. Values on disk
        are read slab by slab (with one plane either side, so a slab's local maxima are the
        whole image's); each slab gives its strongest ``max(1024, 64 k)`` candidates when
        ``min_separation_m > 0`` (exact unless that many stronger maxima crowd one peak out).
        """
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        if not self.lazy:
            idx, mags = _local_maxima(self.magnitude(), None, k if min_separation_m <= 0 else None)
        else:
            keep = k if min_separation_m <= 0 else max(1024, 64 * k)
            found = [_local_maxima(np.abs(b), (sl, x0), keep) for sl, b, x0 in _slabs(self.values, halo=1)]
            idx = np.concatenate([f[0] for f in found]) if found else np.zeros((0, 3), int)
            mags = np.concatenate([f[1] for f in found]) if found else np.zeros(0)
        return _select_peaks(idx, mags, self.grid, k, min_separation_m)

    def projection(self, axis: str = "z") -> np.ndarray:
        """Maximum of ``|values|`` along ``axis`` ("x", "y" or "z"): a 2-D array of the other two
        axes in order (read slab by slab where the values are on disk)."""
        a = _axis_number(axis)
        if not self.lazy:
            return np.abs(self.values).max(axis=a)
        if a == 0:
            out = None
            for _, b, _ in _slabs(self.values):
                m = np.abs(b).max(axis=0)
                out = m if out is None else np.maximum(out, m)
            return out
        return np.concatenate([np.abs(b).max(axis=a) for _, b, _ in _slabs(self.values)], axis=0)

    def section(self, axis: str, index: int) -> np.ndarray:
        """The complex values of the plane ``axis = axis_m[index]``: a 2-D array of the other two axes."""
        a = _axis_number(axis)
        n = self.grid.shape[a]
        if not -n <= int(index) < n:
            raise ValueError(f"index must be within the grid's {n} planes along {axis}, got {index}")
        sl = [slice(None)] * 3
        sl[a] = int(index) % n
        return np.asarray(self.values[tuple(sl)])

    def in_memory(self) -> Image:
        """This image with its values read into memory (itself if they already are)."""
        if not self.lazy:
            return self
        return replace(self, values=np.asarray(self.values))

    def reduced(self, max_voxels: int = 256**3) -> Image:
        """An in-memory image of at most about ``max_voxels``: each block of ``f`` x ``f`` x ``f``
        voxels replaced by its strongest value (for pictures of volumes larger than memory;
        itself, read into memory, if small enough)."""
        f = max(1, math.ceil((self.grid.size / max(1, int(max_voxels))) ** (1 / 3)))
        if f == 1:
            return self.in_memory()
        fac = tuple(min(f, n) for n in self.grid.shape)
        shape = tuple(-(-n // q) for n, q in zip(self.grid.shape, fac, strict=True))
        out = np.zeros(shape, np.complex64)
        for sl, block, _ in _slabs(self.values, step=fac[0]):
            part = _block_strongest(block, fac)
            out[sl.start // fac[0]: sl.start // fac[0] + part.shape[0]] = part
        axes = [ax[0] + (np.arange(m) * q + (q - 1) / 2) * (ax[1] - ax[0] if len(ax) > 1 else 0.0)
                for ax, m, q in zip((self.grid.x_m, self.grid.y_m, self.grid.z_m), shape, fac, strict=True)]
        note = f"blocks of {fac[0]} x {fac[1]} x {fac[2]} voxels shown by their strongest"
        return replace(self, values=out, grid=VoxelGrid(*axes), provenance={**self.provenance, "reduced": note})

    def plot(self, path: str | Path | None = None, **kwargs) -> Figure:
        """Maximum-intensity projections and slices through the brightest peak, in dB.

        See :func:`clsas.plots.plot_image` for the keyword arguments (``truth_m``, ``scene``,
        ``aperture``, ``dynamic_range_db``, ``title``, ``dpi``). With ``path`` (.png, .svg or
        .pdf) the figure is also written there. The caller's matplotlib backend is left as it is.
        An image on disk (:meth:`open`) is pictured through :meth:`reduced` (at most 256³ voxels).

        Returns
        -------
        matplotlib.figure.Figure
        """
        from .pictures import plot_image

        return plot_image(self.reduced() if self.lazy else self, path, **kwargs)

    def describe_provenance(self) -> dict:
        """What made this image: ``provenance`` plus method, formation, grid and device."""
        from ..version import __version__

        prov = {
            "method": self.method,
            "formation": "bp",
            "spacing_m": [float(s) if len(a) > 1 else None
                          for s, a in zip(self.grid.spacing(), (self.grid.x_m, self.grid.y_m, self.grid.z_m),
                                          strict=True)],
            "shape": list(self.grid.shape),
            "backend": self.backend,
            "device": self.device,
            "clsas_version": __version__,
        }
        prov.update(self.provenance)
        return prov

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the image to HDF5; see :mod:`clsas.types.image` for the layout.

        Readable with plain h5py and with ``xarray.open_dataset(path, engine="h5netcdf")``, which
        gets the coordinates ``x_m``, ``y_m``, ``z_m`` (metres) from the HDF5 dimension scales.
        An existing file is refused (``FileExistsError`` naming it) unless ``overwrite=True``.
        """
        import h5py

        from .dataset import refuse_existing

        path = refuse_existing(path, overwrite, "Image.save")
        with h5py.File(path, "w") as f:
            scales = write_axes(f, self.grid)
            if self.lazy:
                d = f.create_dataset("values", shape=self.grid.shape, dtype=self.values.dtype,
                                     chunks=True)
                for sl, block, _ in _slabs(self.values):
                    d[sl] = block
            else:
                d = f.create_dataset("values", data=self.values)
            attach_values(d, scales)
            write_attrs(f, self)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Image:
        """Read an image written by :meth:`save` (this format or the older one without scales)."""
        import h5py

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no image file at {path}")
        with h5py.File(path, "r") as f:
            missing = [n for n in ("values", *_AXES) if n not in f]
            if missing:
                raise ValueError(f"{path} is not a clsas image (no {', '.join(missing)})")
            a = f.attrs
            version = int(a.get("format_version", 0))
            if version > IMAGE_FORMAT_VERSION:
                raise ValueError(f"{path} has image format_version {version}; "
                                 f"this clsas reads up to {IMAGE_FORMAT_VERSION}")
            grid = VoxelGrid(f["x_m"][()], f["y_m"][()], f["z_m"][()])
            prov = json.loads(a.get("provenance_json", "{}"))
            timings = {k[5:-2]: float(val) for k, val in a.items() if k.startswith("time_") and k.endswith("_s")}
            return cls(f["values"][()], grid, str(a.get("method", "bp")), str(a.get("backend", "numpy")),
                       str(a.get("device", "")), timings_s=timings, provenance=prov)

    @classmethod
    def open(cls, path: str | Path) -> Image:
        """Open an image file lazily: ``values`` is the file's h5py dataset (or, for a ``.zarr``
        store, its Zarr array), read when used.

        For files larger than memory (``reconstruct(..., out=...)``): :meth:`peaks`,
        :meth:`max_magnitude`, :meth:`projection`, :meth:`section`, :meth:`plot` (through
        :meth:`reduced`) and :meth:`save` read the values slab by slab; :meth:`magnitude`,
        :meth:`db` and the exports (:mod:`clsas.presenting.export`) read them whole. The file stays open
        while the image lives. ``dask.array.from_array(image.values, chunks=...)`` gives a dask
        array, and an Image holding a dask array works the same way.
        """
        import h5py

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no image file at {path}")
        if path.suffix.lower() == ".zarr":
            return _open_zarr(cls, path)
        f = h5py.File(path, "r")
        missing = [n for n in ("values", *_AXES) if n not in f]
        if missing:
            f.close()
            raise ValueError(f"{path} is not a clsas image (no {', '.join(missing)})")
        if not bool(f.attrs.get("complete", True)):
            done = f["tiles_done"][()] if "tiles_done" in f else np.zeros(0)
            f.close()
            raise ValueError(f"{path} is an unfinished tiled image ({int(done.sum())} of {done.size} tiles "
                             "written); run the same reconstruct(..., out=...) again to finish it")
        a = f.attrs
        grid = VoxelGrid(f["x_m"][()], f["y_m"][()], f["z_m"][()])
        timings = {k[5:-2]: float(val) for k, val in a.items() if k.startswith("time_") and k.endswith("_s")}
        return cls(f["values"], grid, str(a.get("method", "bp")), str(a.get("backend", "numpy")),
                   str(a.get("device", "")), timings_s=timings, provenance=json.loads(a.get("provenance_json", "{}")))


def write_axes(f, grid: VoxelGrid) -> list:
    """Write the axes ``x_m``, ``y_m``, ``z_m`` of ``grid`` to the open HDF5 file ``f`` as dimension
    scales; returns them (for :func:`attach_values`)."""
    scales = []
    for name in _AXES:
        d = f.create_dataset(name, data=getattr(grid, name))
        d.attrs.update(units="m", long_name=f"{name[0]} (voxel centre)")
        d.make_scale(name)
        scales.append(d)
    return scales


def attach_values(d, scales: list) -> None:
    """Label the ``values`` dataset ``d`` and attach its three dimensions to ``scales``."""
    d.attrs.update(units="arbitrary (complex, backprojected pressure)",
                   long_name="complex image value on the voxel grid")
    for i, s in enumerate(scales):
        d.dims[i].attach_scale(s)


def image_attrs(image: Image) -> dict:
    """``image``'s method, device, provenance and timings as the file's attributes (JSON-able values)."""
    prov = image.describe_provenance()
    out = dict(format="clsas image", format_version=IMAGE_FORMAT_VERSION, method=image.method,
               formation=str(prov.get("formation", "")), backend=image.backend, device=image.device,
               clsas_version=str(prov["clsas_version"]), spacing_m=[float(s) for s in image.grid.spacing()],
               provenance_json=json.dumps(prov, default=json_default))
    for key in ("source_sha256", "source_path"):
        if key in prov:
            out[key] = str(prov[key])
    if "dataset_provenance" in prov:
        out["dataset_provenance_json"] = json.dumps(prov["dataset_provenance"], default=json_default)
    for k, val in image.timings_s.items():
        out[f"time_{k}_s"] = float(val)
    return out


def write_attrs(f, image: Image) -> None:
    """Write :func:`image_attrs` as attributes of ``f`` (an open HDF5 file or a Zarr group)."""
    attrs = image_attrs(image)
    if hasattr(f, "flush"):  # HDF5: the spacing as an array attribute, as Image.save always wrote it
        attrs["spacing_m"] = np.array(attrs["spacing_m"])
    f.attrs.update(attrs)


def _open_zarr(cls, path: Path) -> Image:
    """:meth:`Image.open` of a Zarr store written by ``reconstruct(..., out="image.zarr")``."""
    from .zarrstore import import_zarr

    g = import_zarr().open_group(str(path), mode="r")
    a = dict(g.attrs)
    names = set(g.array_keys())
    missing = [n for n in ("values", *_AXES) if n not in names]
    if missing:
        raise ValueError(f"{path} is not a clsas image (no {', '.join(missing)})")
    if not a.get("complete", True):
        done = g["tiles_done"][:] if "tiles_done" in names else np.zeros(0)
        raise ValueError(f"{path} is an unfinished tiled image ({int(done.sum())} of {done.size} tiles "
                         "written); run the same reconstruct(..., out=...) again to finish it")
    grid = VoxelGrid(g["x_m"][:], g["y_m"][:], g["z_m"][:])
    timings = {k[5:-2]: float(val) for k, val in a.items() if k.startswith("time_") and k.endswith("_s")}
    return cls(g["values"], grid, str(a.get("method", "bp")), str(a.get("backend", "numpy")),
               str(a.get("device", "")), timings_s=timings, provenance=json.loads(a.get("provenance_json", "{}")))


def _axis_number(axis: str) -> int:
    if axis not in ("x", "y", "z"):
        raise ValueError(f"axis must be one of 'x', 'y', 'z', got {axis!r}")
    return "xyz".index(axis)


def _slabs(values, *, halo: int = 0, step: int = 1, max_bytes: int = 64 << 20):
    """Read ``values`` in slabs of whole x-planes (a multiple of ``step`` planes, about
    ``max_bytes`` each): yields ``(x slice of the slab, array of the slab and up to ``halo``
    planes either side, x index of the array's first plane)``."""
    nx = values.shape[0]
    plane = max(1, int(np.prod(values.shape[1:])) * np.dtype(values.dtype).itemsize)
    n = max(step, (max_bytes // plane) // step * step)
    for a in range(0, nx, n):
        b = min(nx, a + n)
        lo, hi = max(0, a - halo), min(nx, b + halo)
        yield slice(a, b), np.asarray(values[lo:hi]), lo


def _local_maxima(mag: np.ndarray, where: tuple[slice, int] | None, keep: int | None):
    """Indices (n, 3) and magnitudes of the local maxima of ``mag`` (3 x 3 x 3 neighbourhood, edges
    repeated), C order; ``where`` = (core x slice, x index of ``mag``'s first plane) restricts them
    to the core planes of a slab read with halos; ``keep``: only the strongest that many."""
    from scipy.ndimage import maximum_filter

    local = (mag == maximum_filter(mag, size=3, mode="nearest")) & (mag > 0)
    idx = np.argwhere(local)
    if where is not None:
        core, x0 = where
        idx[:, 0] += x0
        idx = idx[(idx[:, 0] >= core.start) & (idx[:, 0] < core.stop)]
        mags = mag[idx[:, 0] - x0, idx[:, 1], idx[:, 2]]
    else:
        mags = mag[tuple(idx.T)]
    if keep is not None and len(mags) > keep:
        top = np.sort(np.argsort(-mags, kind="stable")[:keep])  # still in C order
        idx, mags = idx[top], mags[top]
    return idx, mags


def _select_peaks(idx: np.ndarray, mags: np.ndarray, grid: VoxelGrid, k: int, min_sep: float) -> list[Peak]:
    """The strongest ``k`` of the candidates (C order), none within ``min_sep`` of a stronger one."""
    order = np.argsort(-mags, kind="stable")
    out: list[Peak] = []
    axes = (grid.x_m, grid.y_m, grid.z_m)
    for i in order:
        ix = tuple(int(j) for j in idx[i])
        pos = np.array([a[j] for a, j in zip(axes, ix, strict=True)])
        if any(np.linalg.norm(pos - p.position_m) < min_sep for p in out):
            continue
        out.append(Peak(pos, ix, float(mags[i])))
        if len(out) == k:
            break
    return out


def _block_strongest(block: np.ndarray, fac: tuple[int, int, int]) -> np.ndarray:
    """Each ``fac`` block of ``block`` replaced by its value of largest magnitude (edges padded)."""
    pad = [(0, -(-n // q) * q - n) for n, q in zip(block.shape, fac, strict=True)]
    b = np.pad(block, pad)
    m = [n // q for n, q in zip(b.shape, fac, strict=True)]
    b = b.reshape(m[0], fac[0], m[1], fac[1], m[2], fac[2]).transpose(0, 2, 4, 1, 3, 5).reshape(*m, -1)
    pick = np.abs(b).argmax(axis=3)
    return np.take_along_axis(b, pick[..., None], 3)[..., 0]


def source_provenance(dataset, path: str | Path | None = None) -> dict:
    """Provenance of an image's source: the scan file's SHA-256 and the dataset's own steps.

    Parameters
    ----------
    dataset : Dataset
        The scan the image was formed from (its ``provenance`` list is copied).
    path : str or Path, optional
        The scan file it was read from; its SHA-256 and name are recorded.
    """
    out: dict = {"dataset_provenance": list(getattr(dataset, "provenance", []))}
    if path is not None:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        out.update(source_sha256=h.hexdigest(), source_path=Path(path).name)
    return out

