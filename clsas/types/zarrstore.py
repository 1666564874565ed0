"""Zarr, imported where used: a missing package says which extra to install."""

from __future__ import annotations

from ..validate import install_hint


def import_zarr():
    """``zarr`` (version 3), or an ImportError naming the extra."""
    try:
        import zarr
    except ImportError as exc:
        raise ImportError(f"Zarr images need zarr >= 3: {install_hint('zarr')}") from exc
    if int(zarr.__version__.split(".")[0]) < 3:
        raise ImportError(f"Zarr images need zarr >= 3, found {zarr.__version__}: {install_hint('zarr')}")
    return zarr
