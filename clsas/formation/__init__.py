"""Image formation: how range profiles become an image.

``"bp"`` is exact bistatic backprojection (:mod:`clsas.formation.bp`), the reference every fast
formation is measured against. The fast ones trade a stated error for run time:

- ``"omega-k"``: wavenumber-domain range migration for planar, uniform apertures
  (:mod:`clsas.formation.omega_k`);
- ``"ffbp"``: 3-D fast factorized backprojection for any trajectory (:mod:`clsas.formation.ffbp`).

``"auto"`` (:mod:`clsas.formation.auto`) forms by the fastest of them whose error meets a target.

Each formation is a function ``form(profiles, grid, *, backend, device, progress, force, **options)
-> Image`` that registers itself in :data:`FORMATIONS` (a :class:`clsas.registry.Registry`) where it is
defined; this package imports each formation module once (one line each, below). A formation
declares its options as keyword-only parameters (:func:`declared_options`), and :func:`form`
refuses any other before work (:func:`check_options`). One that forms by another registered
formation (``auto``) records that one as ``provenance["formation"]``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from ..physics.geometry import VoxelGrid
from ..types.profiles import Profiles
from . import auto, bp, ffbp, omega_k  # noqa: F401 - each registers its formation
from .registry import FORMATIONS

__all__ = ["FORMATIONS", "check_options", "declared_options", "error_to_signal_db", "form"]


def form(profiles: Profiles, grid: VoxelGrid, formation: str = "bp", *, backend: str | None = None,
         device: Any = None, progress: Callable[[int, int], None] | None = None, force: bool = False,
         **options):
    """Form an image of ``profiles`` on ``grid`` with ``formation`` (see :data:`FORMATIONS`)."""
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    fn = FORMATIONS.choose(formation)
    check_options(formation, fn, options)
    image = fn(profiles, grid, backend=backend, device=device, progress=progress, force=force, **options)
    if "formation" in image.provenance:  # formed by another registered formation, which it names
        return image
    provenance = {**image.provenance, "formation": formation}
    if options:
        provenance["formation_options"] = dict(options)
    return replace(image, provenance=provenance)


_COMMON = ("backend", "device", "progress", "force")


def declared_options(fn: Callable) -> tuple[str, ...] | None:
    """The options a formation function declares (its keyword-only parameters besides the common
    ones), or None where it takes ``**options`` and checks them itself."""
    params = inspect.signature(fn).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return tuple(p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in _COMMON)


def check_options(formation: str, fn: Callable, options: dict) -> None:
    """Refuse options ``fn`` does not declare, naming them and the ones it takes (before any work)."""
    known = declared_options(fn)
    if known is None:
        return
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(f"formation_options: unknown option(s) {unknown} for {formation!r}; known: {sorted(known)}")


def error_to_signal_db(image, reference, mask: np.ndarray | None = None) -> float:
    """Complex error of ``image`` against ``reference``: 20·log10(‖a − b‖ / ‖b‖), in dB.

    Parameters
    ----------
    image, reference : Image or ndarray
        Same shape; values compared as they are (no rescaling).
    mask : ndarray of bool, optional
        Voxels to compare (e.g. the aperture's well-sampled cone); default all.
    """
    a = np.asarray(getattr(image, "values", image))
    b = np.asarray(getattr(reference, "values", reference))
    if a.shape != b.shape:
        raise ValueError(f"image: shape {a.shape} differs from reference's {b.shape}")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != b.shape:
            raise ValueError(f"mask: shape {mask.shape} differs from the images' {b.shape}")
        if not mask.any():
            raise ValueError("mask: selects no voxel")
        a, b = a[mask], b[mask]
    a = a.astype(np.complex128).ravel()
    b = b.astype(np.complex128).ravel()
    ref = float(np.linalg.norm(b))
    if ref == 0:
        raise ValueError("reference: all zero, the ratio is undefined")
    err = float(np.linalg.norm(a - b))
    return 20 * np.log10(max(err / ref, 1e-300))
