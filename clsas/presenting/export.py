"""Images in forms other programs open: VTK image data (ParaView) and NumPy + JSON (napari).

- :func:`to_vti` writes a VTK XML ImageData file (``.vti``): the grid's origin and spacing, and
  two point-data arrays, ``magnitude`` (|values|, float32) and ``db`` (dB re the peak, float32,
  floored). Written with NumPy alone (base64-encoded binary, uncompressed), readable by ParaView,
  VTK, pyvista and meshio.
- :func:`to_npy` writes the magnitude as ``.npy`` (axes x, y, z) and a JSON sidecar with ``scale``
  and ``translate`` in metres (napari's layer arguments), the axis names and units:
  ``napari.view_image(np.load(p), **{k: meta[k] for k in ("scale", "translate")})``.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..types.image import Image

__all__ = ["to_vti", "to_npy", "read_vti", "export"]

_FLOOR_DB = -120.0


def _origin_spacing(image: Image) -> tuple[list[float], list[float]]:
    g = image.grid
    origin = [float(a[0]) for a in (g.x_m, g.y_m, g.z_m)]
    return origin, [float(s) for s in g.spacing()]


def _encode(arr: np.ndarray) -> str:
    """VTK's base64 'binary' inline encoding: a UInt32 byte count, then the little-endian data."""
    raw = np.ascontiguousarray(arr, dtype="<f4").tobytes()
    return base64.b64encode(np.uint32(len(raw)).astype("<u4").tobytes() + raw).decode("ascii")


def to_vti(image: Image, path: str | Path, floor_db: float = _FLOOR_DB) -> Path:
    """Write ``image`` as VTK XML image data (``.vti``) for ParaView.

    Parameters
    ----------
    image : Image
        The image; its grid gives the origin (first voxel centre) and spacing, metres.
    path : str or Path
        Output file.
    floor_db : float
        The floor of the ``db`` array, dB below the peak.

    Returns
    -------
    Path
    """
    path = Path(path)
    nx, ny, nz = image.grid.shape
    origin, spacing = _origin_spacing(image)
    # VTK point data run with x fastest: (nx, ny, nz) C order -> transpose to (nz, ny, nx)
    mag = np.abs(image.values).transpose(2, 1, 0)
    db = image.db(floor_db).transpose(2, 1, 0)
    extent = f"0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"
    arrays = "\n".join(
        f'        <DataArray type="Float32" Name="{name}" NumberOfComponents="1" format="binary">'
        f"{_encode(a)}</DataArray>"
        for name, a in (("magnitude", mag), ("db", db))
    )
    text = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt32">\n'
        f'  <ImageData WholeExtent="{extent}" Origin="{" ".join(map(repr, origin))}" '
        f'Spacing="{" ".join(map(repr, spacing))}">\n'
        f'    <Piece Extent="{extent}">\n'
        '      <PointData Scalars="magnitude">\n'
        f"{arrays}\n"
        "      </PointData>\n"
        "      <CellData/>\n"
        "    </Piece>\n"
        "  </ImageData>\n"
        "</VTKFile>\n"
    )
    path.write_text(text, encoding="ascii")
    return path


def read_vti(path: str | Path) -> dict:
    """Read a ``.vti`` written by :func:`to_vti`: arrays (nx, ny, nz), origin and spacing."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    img = root.find("ImageData")
    if root.get("type") != "ImageData" or img is None:
        raise ValueError(f"{path} is not VTK ImageData")
    ext = [int(e) for e in img.get("WholeExtent").split()]
    shape = (ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1)
    out: dict = {
        "origin": np.array(img.get("Origin").split(), float),
        "spacing": np.array(img.get("Spacing").split(), float),
    }
    for da in img.iter("DataArray"):
        raw = base64.b64decode(da.text.strip())
        n = int(np.frombuffer(raw[:4], "<u4")[0])
        data = np.frombuffer(raw[4:4 + n], "<f4")
        out[da.get("Name")] = data.reshape(shape[::-1]).transpose(2, 1, 0)
    return out


def to_npy(image: Image, path: str | Path) -> tuple[Path, Path]:
    """Write ``|values|`` as ``.npy`` (axes x, y, z) and a ``.json`` sidecar for napari.

    Returns
    -------
    (npy path, json path)
    """
    path = Path(path).with_suffix(".npy")
    origin, spacing = _origin_spacing(image)
    np.save(path, np.abs(image.values).astype(np.float32))
    meta = {
        "axes": ["x", "y", "z"],
        "units": "m",
        "scale": spacing,
        "translate": origin,
        "shape": list(image.grid.shape),
        "method": image.method,
        "provenance": image.provenance,
    }
    side = path.with_suffix(".json")
    side.write_text(json.dumps(meta, indent=2, default=str))
    return path, side


def export(image: Image, path: str | Path) -> list[Path]:
    """Write ``image`` in the format its suffix names: ``.vti`` (ParaView) or ``.npy`` (napari)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".vti":
        return [to_vti(image, path)]
    if suffix == ".npy":
        return list(to_npy(image, path))
    raise ValueError(f"export: unknown format {suffix!r} in {str(path)!r}; use .vti (ParaView) or .npy (napari)")
