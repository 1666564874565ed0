"""The registry of image formations (:data:`FORMATIONS`), apart from the formations themselves so
that each formation module can register itself without importing its package."""

from __future__ import annotations

from collections.abc import Callable

from ..registry import Registry

__all__ = ["FORMATIONS"]

# name -> form(profiles, grid, *, backend, device, progress, force, **options) -> Image
FORMATIONS: Registry[Callable] = Registry("formation", "formation")
