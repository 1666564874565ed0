"""The registry of importers (:data:`IMPORTERS`), apart from the importers so that each format's
module registers itself without importing its package."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..registry import Registry

__all__ = ["IMPORTERS", "Importer"]


@dataclass(frozen=True)
class Importer:
    """One measured-data format.

    Attributes
    ----------
    read : callable(source, *, background=None, **options) -> Dataset
        Reads the scan at ``source`` (``background``: the empty-scene scan in the same layout).
    detect : callable(source: Path) -> bool
        Whether ``source`` is in this format (for ``format="auto"``; checked in registration order).
    summary : str
        One line for the command line's help.
    """

    read: Callable
    detect: Callable[[Path], bool]
    summary: str = ""


IMPORTERS: Registry[Importer] = Registry("importer", "format")
