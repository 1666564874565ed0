"""Import channel data in UFF, the ultrasound file format of USTB, in HDF5 (``.uff``).

UFF (the UltraSound ToolBox's format, version 0.0.1 as USTB writes it and as the
``pyuff-ustb`` package reads it) keeps a scan as one ``uff.channel_data`` object: a probe of
fixed elements, a sequence of transmitted waves, and the recordings as an array
``[time x channel x wave x frame]``. This reader and the writer (:mod:`clsas.io.uff_export`)
use h5py alone; ``tests/unit/io/test_uff.py`` checks both against ``pyuff-ustb``.

Layout
------
Each UFF object is an HDF5 group whose attribute ``class`` names its type
(``uff.channel_data``, ``uff.probe``, ``uff.wave``, ``uff.point``, ``uff.pulse``); a number is
a dataset (``class`` ``single``; a complex one a group with ``real`` and ``imag``); MATLAB
wrote the arrays, so their axes are reversed in HDF5 (the recordings are stored
``(frame, wave, channel, time)``). A list of objects (the sequence of waves) is a group with
``array = 1``, ``size = [1, n]`` and members ``sequence_0001``, ``sequence_0002``, ...

- ``channel_data``: ``sampling_frequency`` (Hz), ``initial_time`` (s, time of the first
  sample), ``sound_speed`` (m/s), ``modulation_frequency`` (Hz; 0 for RF), ``probe``,
  ``sequence``, ``data``, optional ``pulse`` (``waveform``: the transmitted signal).
- ``probe``: ``geometry``, one row per element ``[x, y, z, azimuth, elevation, width,
  height]`` (metres, radians); its subclasses (linear array, ...) store it as well.
- ``wave``: ``wavefront`` (0 plane, 1 spherical, 2 photoacoustic), ``source`` (a point:
  ``distance``, ``azimuth``, ``elevation``; ``x = d sin(az) cos(el)``, ``y = d sin(el)``,
  ``z = d cos(az) cos(el)``), ``delay`` (s), ``sound_speed`` (m/s).

Timing
------
USTB's delay-and-sum (``midprocess.das``) puts the echo of a point p of the wave w, received
on element e, at ``t = (|s - p| + k |s|) / c_w - delay_w + |p - e| / c`` on the axis
``initial_time + n / fs``, where s is the wave's source, ``k = -1`` for a source behind the
probe (``z < -1 mm``, a diverging wave) and ``+1`` otherwise (a source on or in front of it:
an element firing alone, or a focus treated as a virtual source past it). A point source that
fires at ``k |s| / c_w - delay_w`` on that axis gives exactly these times, so each
(wave, element) pair is one bistatic measurement: speaker at s, microphone at e, and
``t0_s = initial_time - (k |s| / c_w - delay_w)``. Plane and photoacoustic waves have no
point source and are refused; so are demodulated (IQ) recordings.

Files written by :func:`clsas.io.export_uff` also carry a ``clsas`` group: which
(wave, element) pairs were measured (the others hold zeros), each measurement's speed of
sound and air, the chirp and the dataset's provenance. Other readers ignore it; this reader
then returns exactly the measured pairs.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..types.dataset import Dataset
from ._common import attach_background
from .registry import IMPORTERS, Importer

__all__ = ["import_uff", "is_uff", "CLSAS_GROUP", "DIVERGING_Z_M"]

log = logging.getLogger("clsas.io")

CLSAS_GROUP = "clsas"
"""The group that :func:`clsas.io.export_uff` adds beside the UFF objects."""

DIVERGING_Z_M = -1e-3
"""A source below this z is behind the probe (USTB's diverging wave, ``k = -1``), metres."""

_SUFFIXES = (".uff", ".h5", ".hdf5", ".hdf", ".mat")


def _class(obj) -> str:
    c = obj.attrs.get("class", b"")
    if isinstance(c, np.ndarray):
        c = c.flat[0] if c.size else b""
    return c.decode("utf-8", "replace") if isinstance(c, bytes) else str(c)


def _channel_data_groups(f) -> list[str]:
    """Names of the top-level groups of class ``uff.channel_data``."""
    import h5py

    return [k for k, v in f.items() if isinstance(v, h5py.Group) and _class(v) == "uff.channel_data"]


def is_uff(source: str | Path) -> bool:
    """Whether ``source`` is an HDF5 file with a top-level ``uff.channel_data`` group."""
    source = Path(source)
    if not source.is_file() or source.suffix.lower() not in _SUFFIXES:
        return False
    import h5py

    try:
        if not h5py.is_hdf5(source):
            return False
        with h5py.File(source, "r") as f:
            return bool(_channel_data_groups(f))
    except OSError:
        return False


def import_uff(
    path: str | Path, *, background: str | Path | None = None, location: str | None = None,
    frame: int = 0, waveform: np.ndarray | None = None,
) -> Dataset:
    """Read the channel data of a UFF file into a :class:`~clsas.Dataset` (layout: :mod:`clsas.io.uff`).

    Parameters
    ----------
    path : path
        The ``.uff`` (HDF5) file.
    background : path, optional
        The empty-scene scan, a UFF file with the same probe, waves and samples: its recordings
        become ``Dataset.background``, pair by pair.
    location : str, optional
        The channel data's group; needed when the file holds several (``None``: the one the
        ``clsas`` group names, else the only ``uff.channel_data`` group).
    frame : int
        Which frame (0-based) of a file with several.
    waveform : (n,) array, optional
        The transmitted signal at the file's sample rate, when the file has no
        ``pulse/waveform`` (or to replace it).

    Returns
    -------
    Dataset
        One measurement per (wave, element) pair, wave by wave (or the measured pairs of a file
        written by :func:`clsas.io.export_uff`); positions in metres in the file's frame;
        ``t0_s`` per measurement (module docstring, "Timing"); ``c_mps`` the file's
        ``sound_speed``; ``provenance`` = ``[{"step": "import", "format": "uff", ...}]``.

    Raises
    ------
    FileNotFoundError
        No file at ``path``.
    ValueError
        Not a UFF file, a missing or malformed field (named with its location in the file), a
        plane or photoacoustic wave, demodulated (IQ) data, NaN or Inf samples, no waveform, a
        background whose shape differs.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no file {path} (import_uff: path)")
    if not isinstance(frame, int | np.integer) or isinstance(frame, bool) or frame < 0:
        raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
    if not h5py.is_hdf5(path):
        raise ValueError(f"{path} is not an HDF5 file (UFF files are HDF5)")
    with h5py.File(path, "r") as f:
        loc = _location(f, path, location)
        extra = _read_clsas_group(f, path, loc)
        cd = _Reader(f[loc], f"{path}:/{loc}")
        parts = _read_channel_data(cd, int(frame), waveform, None if extra is None else extra["pairs"])
        bg_loc = None if extra is None or background is not None else extra.get("background_location")
        stored_bg = None
        if bg_loc is not None and bg_loc in f:
            stored_bg = _pair_recordings(_Reader(f[bg_loc], f"{path}:/{bg_loc}"), int(frame), parts["pairs"])
    ds = _dataset(path, loc, int(frame), parts, extra)
    if stored_bg is not None:
        ds = ds.replace(background=stored_bg)
    if background is not None:
        bg = import_uff(background, frame=frame, waveform=ds.waveform,
                        location=None if extra is None else extra.get("background_location"))
        ds = ds.replace(background=attach_background(ds, bg, str(path), str(background)))
        ds.provenance[0]["background"] = str(background)
    log.info("imported UFF %s:/%s: %d waves x %d elements -> %d measurements, %d samples at %g Hz", path, loc,
             parts["n_waves"], parts["n_elements"], ds.n_meas, ds.n_samples, ds.fs_hz)
    return ds


def _location(f, path: Path, location: str | None) -> str:
    found = _channel_data_groups(f)
    if location is not None:
        loc = location.strip("/")
        if loc not in f or _class(f[loc]) != "uff.channel_data":
            raise ValueError(f"{path}: no uff.channel_data group at {location!r} (location); "
                             f"the file has {found or 'none'}")
        return loc
    if CLSAS_GROUP in f and "location" in f[CLSAS_GROUP].attrs:
        return str(f[CLSAS_GROUP].attrs["location"])
    if not found:
        raise ValueError(f"{path} holds no uff.channel_data group (top-level groups: {list(f)})")
    if len(found) > 1:
        raise ValueError(f"{path} holds several channel data groups {found}: choose one with location=")
    return found[0]


class _Reader:
    """One UFF object (an HDF5 group), with errors that name the file and the field."""

    def __init__(self, group, where: str) -> None:
        self.g, self.where = group, where

    def has(self, key: str) -> bool:
        return key in self.g

    def child(self, key: str) -> _Reader:
        if key not in self.g:
            raise ValueError(f"{self.where}: no {key!r} field (UFF {_class(self.g) or 'object'})")
        return _Reader(self.g[key], f"{self.where}/{key}")

    def array(self, key: str) -> np.ndarray:
        """A numeric field as stored (complex from ``real``/``imag``), axes as in HDF5."""
        import h5py

        node = self.child(key).g
        if isinstance(node, h5py.Group):
            if "real" not in node:
                raise ValueError(f"{self.where}/{key}: a group, not a number")
            real = np.asarray(node["real"][()])
            return real + 1j * np.asarray(node["imag"][()]) if "imag" in node else real
        value = np.asarray(node[()])
        if not np.issubdtype(value.dtype, np.number):
            raise ValueError(f"{self.where}/{key}: not a number (dtype {value.dtype})")
        return value

    def scalar(self, key: str, default: float | None = None, *, finite: bool = True) -> float:
        if default is not None and key not in self.g:
            return default
        value = self.array(key)
        if value.size != 1 or np.iscomplexobj(value) or np.isnan(value).any() or (
                finite and not np.isfinite(value).all()):
            raise ValueError(f"{self.where}/{key}: expected one finite real number, got {value!r}")
        return float(value.reshape(()))


def _data_shape(cd: _Reader) -> tuple[int, int, int, int]:
    """``(time, channel, wave, frame)`` of ``data`` (MATLAB's order; HDF5 holds it reversed), unread."""
    import h5py

    node = cd.child("data").g
    shape = node["real"].shape if isinstance(node, h5py.Group) and "real" in node else getattr(node, "shape", ())
    if not 1 <= len(shape) <= 4:
        raise ValueError(f"{cd.where}/data: expected 1 to 4 axes, got shape {shape}")
    t, ch, w, f = tuple(reversed(shape)) + (1,) * (4 - len(shape))
    return t, ch, w, f


def _pair_recordings(cd: _Reader, frame: int, pairs: np.ndarray) -> np.ndarray:
    """The recordings of the (wave, element) ``pairs`` of one frame: ``(n_pairs, n_samples)`` real.

    A (wave, element, time) dataset (what :func:`clsas.io.export_uff` writes) is read wave by
    wave, only the listed elements: a moving rig's matrix is mostly unwritten chunks."""
    import h5py

    node = cd.child("data").g
    n_t, _, _, n_f = _data_shape(cd)
    if frame >= n_f:
        raise ValueError(f"frame must be < {n_f} (the frames of {cd.where}/data), got {frame}")
    if isinstance(node, h5py.Dataset) and node.ndim == 3:
        out = np.empty((len(pairs), n_t))
        for w in np.unique(pairs[:, 0]):
            rows = np.flatnonzero(pairs[:, 0] == w)
            rows = rows[np.argsort(pairs[rows, 1])]
            e = pairs[rows, 1]
            out[rows] = node[int(w), int(e[0]), :] if len(rows) == 1 else node[int(w), e.tolist(), :]
    else:
        raw = cd.array("data")
        data = raw.T.reshape((n_t, *raw.T.shape[1:], *(1,) * (4 - raw.ndim)))[..., frame]
        if n_f > 1:
            log.info("%s/data: %d frames, frame %d read", cd.where, n_f, frame)
        if np.iscomplexobj(data):
            log.info("%s/data: complex RF (modulation frequency 0): its real part read", cd.where)
            data = data.real
        out = data[:, pairs[:, 1], pairs[:, 0]].T
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{cd.where}/data holds NaN or Inf samples")
    return np.ascontiguousarray(out)


def _elements(cd: _Reader, n_channels: int) -> np.ndarray:
    """The probe's element centres, (n_channels, 3) metres."""
    probe = cd.child("probe")
    geo = probe.array("geometry").astype(float)
    if geo.ndim == 2 and geo.shape[1] == n_channels and 3 <= geo.shape[0] <= 7:
        xyz = geo[:3].T
    elif geo.ndim == 2 and geo.shape[0] == n_channels and 3 <= geo.shape[1] <= 7:
        xyz = geo[:, :3]
    else:
        raise ValueError(f"{probe.where}/geometry: expected (7, {n_channels}) (one column per channel of "
                         f"the data), got shape {geo.shape}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"{probe.where}/geometry holds NaN or Inf positions")
    return xyz


def _waves(cd: _Reader) -> list[_Reader]:
    """The sequence's waves in order: one wave object, or a list (members ``sequence_0001``, ...)."""
    seq = cd.child("sequence")
    if "source" in seq.g or "wavefront" in seq.g:
        return [seq]

    def number(key: str) -> tuple[int, str]:
        tail = key.rsplit("_", 1)[-1]
        return (int(tail) if tail.isdigit() else 0, key)

    return [seq.child(k) for k in sorted(seq.g, key=number)]


def _point(p: _Reader) -> np.ndarray:
    d, az, el = (p.scalar(k, 0.0) for k in ("distance", "azimuth", "elevation"))
    return np.array([d * np.sin(az) * np.cos(el), d * np.sin(el), d * np.cos(az) * np.cos(el)])


def _read_wave(w: _Reader, c_default: float) -> tuple[np.ndarray, float, float]:
    """A point-source wave: (source (3,) m, emission time on the data's axis s, its sound speed m/s)."""
    front = int(w.scalar("wavefront", 1.0))
    source = w.child("source") if w.has("source") else None
    distance = source.scalar("distance", 0.0, finite=False) if source is not None else 0.0
    if front == 1 and source is None:
        raise ValueError(f"{w.where}: no 'source' field (a spherical wave needs its source point)")
    if front == 0 or not np.isfinite(distance):
        raise ValueError(f"{w.where}: a plane wave (no point source); clsas images point-source "
                         "(speaker, microphone) pairs and cannot read it")
    if front != 1:
        raise ValueError(f"{w.where}: wavefront {front} (photoacoustic or unknown) has no transmitted "
                         "point source; clsas reads spherical waves only")
    src = _point(source)
    c = w.scalar("sound_speed", c_default)
    if c <= 0:
        raise ValueError(f"{w.where}/sound_speed must be > 0, got {c:g}")
    k = -1.0 if src[2] < DIVERGING_Z_M else 1.0
    return src, k * float(np.linalg.norm(src)) / c - w.scalar("delay", 0.0), c


def _read_channel_data(cd: _Reader, frame: int, waveform: np.ndarray | None,
                       pairs: np.ndarray | None) -> dict[str, Any]:
    """The fields of the channel data and the recordings of ``pairs`` (``None``: every
    (wave, element) pair, wave by wave)."""
    fs = cd.scalar("sampling_frequency")
    c = cd.scalar("sound_speed")
    if fs <= 0 or c <= 0:
        raise ValueError(f"{cd.where}: sampling_frequency and sound_speed must be > 0, got {fs:g} and {c:g}")
    fmod = cd.scalar("modulation_frequency", 0.0)
    if fmod != 0:
        raise ValueError(f"{cd.where}: demodulated (IQ) data at {fmod:g} Hz; clsas reads RF recordings "
                         "(modulation_frequency 0)")
    t_first = cd.scalar("initial_time")
    _, n_ch, n_w, _ = _data_shape(cd)
    elements = _elements(cd, n_ch)
    waves = [_read_wave(w, c) for w in _waves(cd)]
    if len(waves) != n_w:
        raise ValueError(f"{cd.where}: the sequence has {len(waves)} waves, data has {n_w}")
    pulse = _pulse_waveform(cd) if waveform is None else np.asarray(waveform, float)
    if pulse is None:
        raise ValueError(f"{cd.where}: no pulse/waveform (the transmitted signal); give it with waveform=")
    if pairs is None:
        pairs = np.array([(w, e) for w in range(n_w) for e in range(n_ch)], dtype=np.int64).reshape(-1, 2)
    pairs = pairs.astype(np.int64)
    if np.any(pairs < 0) or np.any(pairs[:, 0] >= n_w) or np.any(pairs[:, 1] >= n_ch):
        raise ValueError(f"{cd.where}: a measured pair ({CLSAS_GROUP}/pairs) outside the {n_w} waves x "
                         f"{n_ch} elements")
    return {"signals": _pair_recordings(cd, frame, pairs), "fs": fs, "c": c, "t_first": t_first,
            "elements": elements, "waves": waves, "waveform": pulse, "pairs": pairs, "n_waves": n_w, "n_elements": n_ch}


def _pulse_waveform(cd: _Reader) -> np.ndarray | None:
    if not cd.has("pulse") or not cd.child("pulse").has("waveform"):
        return None
    wave = cd.child("pulse").array("waveform")
    if np.iscomplexobj(wave):
        wave = wave.real
    wave = np.asarray(wave, float).ravel()
    return wave if wave.size > 1 and np.any(wave) else None


def _read_clsas_group(f, path: Path, loc: str) -> dict | None:
    """What :func:`clsas.io.export_uff` adds (measured pairs, air, chirp, provenance), if present."""
    if CLSAS_GROUP not in f or str(f[CLSAS_GROUP].attrs.get("location", loc)) != loc:
        return None
    g = f[CLSAS_GROUP]
    out: dict[str, Any] = {k: np.asarray(g[k][()]) for k in g}
    for k in ("chirp", "provenance"):
        out[k] = json.loads(g.attrs.get(k, "{}" if k == "chirp" else "[]"))
    if "background_location" in g.attrs:
        out["background_location"] = str(g.attrs["background_location"])
    pairs = out.get("pairs")
    if pairs is None or pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ValueError(f"{path}:/{CLSAS_GROUP}/pairs: expected (n, 2) wave and element indices")
    return out


def _dataset(path: Path, loc: str, frame: int, parts: dict, extra: dict | None) -> Dataset:
    waves, elements, pairs = parts["waves"], parts["elements"], parts["pairs"]
    n_w, n_ch = parts["n_waves"], parts["n_elements"]
    w, e = pairs[:, 0], pairs[:, 1]
    src = np.array([s for s, _, _ in waves]).reshape(-1, 3)
    emit = np.array([t for _, t, _ in waves])
    air: dict[str, Any] = {"c_mps": parts["c"]}
    if extra is None and any(abs(cw - parts["c"]) > 1e-6 * parts["c"] for _, _, cw in waves):
        log.warning("%s:/%s: a wave's sound_speed differs from the channel data's %g m/s; clsas uses one "
                    "speed per measurement, the channel data's", path, loc, parts["c"])
    if extra is not None:
        air = {k: extra[k] for k in ("c_mps", "temperature_c", "humidity_pct") if k in extra}
    prov = {"step": "import", "source": str(path), "format": "uff", "location": loc, "frame": frame,
            "waves": int(n_w), "elements": int(n_ch), "fs_hz": parts["fs"], "initial_time_s": parts["t_first"],
            "sound_speed_mps": parts["c"]}
    if extra is not None and extra["provenance"]:
        prov["history"] = extra["provenance"]
    try:
        return Dataset(signals=parts["signals"], tx_positions=src[w], rx_positions=elements[e],
                       fs_hz=parts["fs"], waveform=parts["waveform"], t0_s=parts["t_first"] - emit[w],
                       chirp={} if extra is None else extra["chirp"], provenance=[prov], **air)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}:/{loc}: {exc}") from None


IMPORTERS.register("uff", Importer(
    read=import_uff, detect=is_uff,
    summary="UFF channel data in HDF5 (USTB's ultrasound file format, .uff): spherical waves, RF"))
