"""The Image type: complex values on a voxel grid, peaks, dB, HDF5."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import VoxelGrid

__all__ = ["Image", "Peak"]


@dataclass(frozen=True)
class Peak:
    position_m: np.ndarray
    index: tuple[int, int, int]
    magnitude: float


@dataclass
class Image:
    """A reconstruction: complex ``values`` (nx, ny, nz) on ``grid``."""

    values: np.ndarray
    grid: VoxelGrid
    method: str = "bp"
    backend: str = "numpy"
    device: str = "NumPy (float64)"
    timings_s: dict = field(default_factory=dict)
    plan: object | None = None
    echoes: list | None = None  # sparse methods: the Echoes found in each recording

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

    def save(self, path: str | Path) -> Path:
        """Write values, axes and metadata to HDF5 (readable with plain h5py)."""
        import h5py

        path = Path(path)
        with h5py.File(path, "w") as f:
            d = f.create_dataset("values", data=self.values)
            d.attrs["units"] = "arbitrary (complex, backprojected pressure)"
            for name in ("x_m", "y_m", "z_m"):
                f.create_dataset(name, data=getattr(self.grid, name)).attrs["units"] = "m"
            f.attrs.update(method=self.method, backend=self.backend, device=self.device)
            for k, val in self.timings_s.items():
                f.attrs[f"time_{k}_s"] = val
        return path

    @classmethod
    def load(cls, path: str | Path) -> Image:
        import h5py

        with h5py.File(path, "r") as f:
            grid = VoxelGrid(f["x_m"][()], f["y_m"][()], f["z_m"][()])
            return cls(f["values"][()], grid, str(f.attrs["method"]), str(f.attrs["backend"]), str(f.attrs["device"]))
