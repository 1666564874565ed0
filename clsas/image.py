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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .dataset import json_default
from .geometry import VoxelGrid

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

    def magnitude(self) -> np.ndarray:
        return np.abs(self.values)

    def db(self, floor_db: float = -60.0) -> np.ndarray:
        """Magnitude in dB relative to the maximum, floored at ``floor_db``."""
        mag = self.magnitude()
        peak = mag.max(initial=0.0)
        if peak == 0:
            return np.full(mag.shape, floor_db)
        rel = np.asarray(mag, np.float64) / float(peak)
        return np.maximum(20 * np.log10(np.maximum(rel, 1e-300)), floor_db)

    def peaks(self, k: int = 1, min_separation_m: float = 0.0) -> list[Peak]:
        """The ``k`` strongest local maxima of ``|values|``, strongest first.

        Peaks closer than ``min_separation_m`` to a stronger one are dropped.
        """
        from scipy.ndimage import maximum_filter

        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        mag = self.magnitude()
        local = (mag == maximum_filter(mag, size=3, mode="nearest")) & (mag > 0)
        idx = np.argwhere(local)
        order = np.argsort(-mag[tuple(idx.T)], kind="stable")
        out: list[Peak] = []
        axes = (self.grid.x_m, self.grid.y_m, self.grid.z_m)
        for i in order:
            ix = tuple(int(j) for j in idx[i])
            pos = np.array([a[j] for a, j in zip(axes, ix, strict=True)])
            if any(np.linalg.norm(pos - p.position_m) < min_separation_m for p in out):
                continue
            out.append(Peak(pos, ix, float(mag[ix])))
            if len(out) == k:
                break
        return out

    def plot(self, path: str | Path | None = None, **kwargs) -> Figure:
        """Maximum-intensity projections and slices through the brightest peak, in dB.

        See :func:`clsas.plots.plot_image` for the keyword arguments (``truth_m``, ``scene``,
        ``aperture``, ``dynamic_range_db``, ``title``, ``dpi``). With ``path`` (.png, .svg or
        .pdf) the figure is also written there. The caller's matplotlib backend is left as it is.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from .plots import plot_image

        return plot_image(self, path, **kwargs)

    def describe_provenance(self) -> dict:
        """What made this image: ``provenance`` plus method, formation, grid and device."""
        from . import __version__

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

    def save(self, path: str | Path) -> Path:
        """Write the image to HDF5; see :mod:`clsas.image` for the layout.

        Readable with plain h5py and with ``xarray.open_dataset(path, engine="h5netcdf")``, which
        gets the coordinates ``x_m``, ``y_m``, ``z_m`` (metres) from the HDF5 dimension scales.
        """
        import h5py

        path = Path(path)
        prov = self.describe_provenance()
        with h5py.File(path, "w") as f:
            scales = []
            for name in _AXES:
                d = f.create_dataset(name, data=getattr(self.grid, name))
                d.attrs.update(units="m", long_name=f"{name[0]} (voxel centre)")
                d.make_scale(name)
                scales.append(d)
            d = f.create_dataset("values", data=self.values)
            d.attrs.update(units="arbitrary (complex, backprojected pressure)",
                           long_name="complex image value on the voxel grid")
            for i, s in enumerate(scales):
                d.dims[i].attach_scale(s)
            f.attrs.update(
                format="clsas image", format_version=IMAGE_FORMAT_VERSION, method=self.method,
                formation=str(prov.get("formation", "")), backend=self.backend, device=self.device,
                clsas_version=str(prov["clsas_version"]),
                spacing_m=np.array(self.grid.spacing()),
                provenance_json=json.dumps(prov, default=json_default),
            )
            for key in ("source_sha256", "source_path"):
                if key in prov:
                    f.attrs[key] = str(prov[key])
            if "dataset_provenance" in prov:
                f.attrs["dataset_provenance_json"] = json.dumps(prov["dataset_provenance"], default=json_default)
            for k, val in self.timings_s.items():
                f.attrs[f"time_{k}_s"] = val
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

