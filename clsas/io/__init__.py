"""Importers: measured scans from other rigs and public datasets into a :class:`~clsas.Dataset`.

Three layouts are read:

- :func:`import_folder` (:mod:`clsas.io.folder`): a folder of WAV or CSV recordings with a
  ``positions.csv`` table (file -> speaker and microphone positions, optional per-recording
  ``t0_s`` and air) and an optional ``import.toml`` (sample rate, chirp, group delay, air).
  Any rig can write it.
- :func:`import_airsas` (:mod:`clsas.io.airsas`): the AirSAS turntable layout
  (``Coordinates.csv``, ``SysParams.csv``, ``WaveformParams.csv``, ``Flight-NNNNNN.csv``),
  returned in the target's frame.
- :func:`import_uff` (:mod:`clsas.io.uff`): channel data in UFF, the ultrasound community's
  HDF5 format written by USTB and ``pyuff-ustb`` (a ``.uff`` file); :func:`export_uff`
  (:mod:`clsas.io.uff_export`) writes a dataset in it.

:func:`import_scan` picks the layout (``format="auto"``) and is what ``clsas import`` calls. Each
format registers itself in :data:`IMPORTERS` (a :class:`clsas.registry.Registry` of
:class:`Importer`) where it is defined; a new format is one module that registers itself.
Each importer records itself as the first ``provenance`` entry of the dataset
(``{"step": "import", "source": ..., "format": ...}``). ``clsas.io`` is not imported by
``import clsas``: ``import clsas.io``.
"""

from __future__ import annotations

from pathlib import Path

from ..types.dataset import Dataset
from .airsas import import_airsas, is_airsas
from .folder import import_folder
from .registry import IMPORTERS, Importer
from .uff import import_uff, is_uff
from .uff_export import export_uff

__all__ = ["IMPORTERS", "Importer", "detect_format", "export_uff", "import_airsas", "import_folder", "import_scan",
           "import_uff", "is_airsas", "is_uff"]


def detect_format(source: str | Path) -> str:
    """The name of the first registered format (:data:`IMPORTERS`) that recognises ``source``.

    AirSAS: a ``Coordinates.csv`` and a ``SysParams.csv``; folder: a ``positions.csv`` or a
    settings file (``import.toml``); UFF: an HDF5 file with a ``uff.channel_data`` group.
    Raises ``FileNotFoundError`` if there is no such file or folder and ``ValueError`` if no
    format recognises it.
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"no file or folder {source} (source)")
    for name, importer in IMPORTERS.items():
        if importer.detect(source):
            return name
    raise ValueError(f"{source}: layout not recognised: expected positions.csv (or import.toml) for "
                     "format 'folder', Coordinates.csv and SysParams.csv for format 'airsas', or an HDF5 "
                     "file with a uff.channel_data group for format 'uff' "
                     f"(formats: {', '.join(IMPORTERS)})")


def import_scan(source: str | Path, *, format: str = "auto", background: str | Path | None = None,
                **options) -> Dataset:
    """Import the scan in the folder (or file) ``source``.

    Parameters
    ----------
    source : path
        The scan's folder (or file, for UFF).
    format : str
        ``"auto"`` (decided by :func:`detect_format`) or a registered format (:data:`IMPORTERS`:
        ``"airsas"``, ``"folder"``, ...).
    background : path, optional
        The empty-scene scan, in the same layout (-> ``Dataset.background``).
    **options
        Passed to the format's reader (:func:`import_folder`, :func:`import_airsas`,
        :func:`import_uff`, ...).

    Returns
    -------
    Dataset
        Positions in metres, the recordings, and a provenance record of the import.

    Examples
    --------
    A scan folder in the AirSAS layout or a folder of WAV/CSV recordings with their positions
    (see the guide's "Your own data"):

    >>> import clsas
    >>> ds = clsas.io.import_scan("airsas-scan/", background="airsas-empty/")   # doctest: +SKIP
    >>> ds.save("scan.h5")                                                       # doctest: +SKIP
    """
    if format != "auto":
        IMPORTERS.check(format)
    fmt = detect_format(source) if format == "auto" else format
    return IMPORTERS[fmt].read(source, background=background, **options)
