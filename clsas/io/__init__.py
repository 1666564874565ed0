"""Importers: measured scans from other rigs and public datasets into a :class:`~clsas.Dataset`.

Two layouts are read:

- :func:`import_folder` (:mod:`clsas.io.folder`): a folder of WAV or CSV recordings with a
  ``positions.csv`` table (file -> speaker and microphone positions, optional per-recording
  ``t0_s`` and air) and an optional ``import.toml`` (sample rate, chirp, group delay, air).
  Any rig can write it.
- :func:`import_airsas` (:mod:`clsas.io.airsas`): the AirSAS turntable layout
  (``Coordinates.csv``, ``SysParams.csv``, ``WaveformParams.csv``, ``Flight-NNNNNN.csv``),
  returned in the target's frame.

:func:`import_scan` picks the layout (``format="auto"``) and is what ``clsas import`` calls.
Each importer records itself as the first ``provenance`` entry of the dataset
(``{"step": "import", "source": ..., "format": ...}``). ``clsas.io`` is not imported by
``import clsas``: ``import clsas.io``.
"""

from __future__ import annotations

from pathlib import Path

from ..dataset import Dataset
from .airsas import import_airsas, is_airsas
from .folder import SETTINGS_FILES, import_folder

__all__ = ["FORMATS", "detect_format", "import_airsas", "import_folder", "import_scan", "is_airsas"]

#: the layouts :func:`import_scan` reads
FORMATS = ("folder", "airsas")


def detect_format(source: str | Path) -> str:
    """``"airsas"`` or ``"folder"``: the layout of the folder ``source``.

    AirSAS: a ``Coordinates.csv`` and a ``SysParams.csv``; folder: a ``positions.csv`` or a
    settings file (``import.toml``). Raises ``FileNotFoundError`` if there is no such folder
    and ``ValueError`` if it is neither.
    """
    source = Path(source)
    if not source.is_dir():
        raise FileNotFoundError(f"no folder {source} (source)")
    if is_airsas(source):
        return "airsas"
    if any((source / n).is_file() for n in ("positions.csv", *SETTINGS_FILES)):
        return "folder"
    raise ValueError(f"{source}: layout not recognised: expected positions.csv (or import.toml) for "
                     "format 'folder', or Coordinates.csv and SysParams.csv for format 'airsas'")


def import_scan(source: str | Path, *, format: str = "auto", background: str | Path | None = None,
                **options) -> Dataset:
    """Import the scan in the folder ``source``.

    Parameters
    ----------
    source : path
        The scan's folder.
    format : {"auto", "folder", "airsas"}
        The layout; ``"auto"`` decides with :func:`detect_format`.
    background : path, optional
        The empty-scene scan, in the same layout (-> ``Dataset.background``).
    **options
        Passed to :func:`import_folder` or :func:`import_airsas`.
    """
    if format not in ("auto", *FORMATS):
        raise ValueError(f"format must be one of auto, {', '.join(FORMATS)}; got {format!r}")
    fmt = detect_format(source) if format == "auto" else format
    reader = import_airsas if fmt == "airsas" else import_folder
    return reader(source, background=background, **options)
