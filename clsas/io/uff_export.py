"""Write a :class:`~clsas.Dataset` as UFF channel data (USTB's ultrasound file format, HDF5).

The layout and the timing convention are those :mod:`clsas.io.uff` reads. A dataset is a
list of bistatic (speaker, microphone) pairs; UFF holds a matrix of waves (transmit events,
each from a point source) by probe elements (fixed receivers). :func:`export_uff` makes one
wave per distinct (speaker position, ``t0_s``) and one element per distinct microphone
position, in the order they first appear, and writes the recordings into that matrix. A
fixed array fired element by element (full matrix capture) fills it; a moving rig (a speaker
and a microphone on one stage) fills only its diagonal: the pairs not measured read as zeros,
which USTB's delay-and-sum adds as nothing. They take no room in the file (one HDF5 chunk per
recording; unwritten chunks are the fill value), but readers that load the whole array
(USTB, ``pyuff-ustb``) hold the full matrix in memory. The file's ``clsas`` group lists the
measured pairs, so :func:`clsas.io.import_uff` reads exactly the dataset's measurements.

What the file keeps: the recordings (float32), positions, ``t0_s``, the sample rate, the
transmitted waveform (``pulse``), the speed of sound (``sound_speed``: the mean; each
measurement's in the ``clsas`` group, with its air), the chirp and the provenance, and the
empty-scene recordings as a second channel data group. What it does not: ``loopback``,
``stage_positions``, ``timestamps``, ``truth`` and ``config`` (a log line names those present).

USTB's beamformer images points beyond the sources (larger z): with clsas's planar scans
(aperture at z = 0, scene at z > 0) that is the same frame. A turntable scan in its target's
frame (z up) is written as it is; a reader that assumes depth along z will not image it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..types.dataset import Dataset, json_default
from .uff import CLSAS_GROUP, DIVERGING_Z_M

__all__ = ["export_uff"]

log = logging.getLogger("clsas.io")

_MAX_BYTES = 2 ** 31


def export_uff(dataset: Dataset, path: str | Path, *, location: str = "channel_data",
               overwrite: bool = False, max_bytes: int = _MAX_BYTES) -> Path:
    """Write ``dataset`` as UFF channel data (``.uff``, HDF5) that USTB and ``pyuff-ustb`` read.

    Parameters
    ----------
    dataset : Dataset
        The scan (one recording per bistatic pair).
    path : str or Path
        The file to write (``.uff`` by convention).
    location : str
        The channel data group's name (USTB's examples use ``channel_data``); the background,
        if any, goes to ``<location>_background``.
    overwrite : bool
        Replace an existing file (otherwise an existing file is refused).
    max_bytes : int
        Refuse a recording matrix (waves x elements x samples, float32) larger than this
        (default 2 GiB): the file stores only the measured recordings, but USTB and
        ``pyuff-ustb`` load the whole matrix, which for a moving rig grows with the square of
        its stops.

    Returns
    -------
    Path

    Raises
    ------
    TypeError
        ``dataset`` is not a Dataset.
    ValueError
        Two measurements with the same speaker, microphone and ``t0_s`` (one matrix cell), a
        matrix over ``max_bytes``, an existing file without ``overwrite``, a bad ``location``.

    Examples
    --------
    >>> import clsas, clsas.io
    >>> ds = clsas.synthetic.turntable_scan(12).dataset                  # doctest: +SKIP
    >>> clsas.io.export_uff(ds, "scan.uff")                              # doctest: +SKIP
    >>> clsas.io.import_uff("scan.uff").n_meas == ds.n_meas              # doctest: +SKIP
    True
    """
    import h5py

    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    if not isinstance(location, str) or not location.strip("/") or "/" in location.strip("/"):
        raise ValueError(f"location must be a group name like 'channel_data', got {location!r}")
    location = location.strip("/")
    path = Path(path)
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists (export_uff: pass overwrite=True to replace it)")
    layout = _layout(dataset, max_bytes)
    dropped = [k for k in ("loopback", "stage_positions", "timestamps") if getattr(dataset, k) is not None]
    dropped += [k for k in ("truth", "config") if getattr(dataset, k)]
    if dropped:
        log.info("export_uff %s: not written (UFF has no place for them): %s", path, ", ".join(dropped))
    with h5py.File(path, "w") as f:
        _write_channel_data(f, location, dataset, dataset.signals, layout)
        g = f.create_group(CLSAS_GROUP)
        if dataset.background is not None:
            _write_channel_data(f, f"{location}_background", dataset, dataset.background, layout)
            g.attrs["background_location"] = f"{location}_background"
        _write_clsas_group(g, location, dataset, layout)
    log.info("wrote UFF %s: %d waves x %d elements (%d measured pairs), %d samples", path,
             len(layout["sources"]), len(layout["elements"]), dataset.n_meas, dataset.n_samples)
    return path


def _first_order_unique(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows in order of first appearance, and each row's index among them."""
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rows[np.sort(first)], rank[inverse.ravel()]


def _layout(ds: Dataset, max_bytes: int) -> dict:
    """Waves (distinct speaker position and t0), elements (distinct microphone positions) and
    each measurement's (wave, element) cell, with the per-wave sound speed and emission time."""
    keys, wave = _first_order_unique(np.column_stack([ds.tx_positions, ds.t0_s]))
    elements, element = _first_order_unique(ds.rx_positions)
    pairs = np.column_stack([wave, element]).astype(np.int64)
    cells = pairs[:, 0] * len(elements) + pairs[:, 1]
    if len(np.unique(cells)) != len(cells):
        i = next(i for i in range(len(cells)) if np.count_nonzero(cells == cells[i]) > 1)
        raise ValueError(f"measurements with the same speaker, microphone and t0_s (measurement {i} and "
                         "another): UFF holds one recording per (wave, element); export them separately "
                         "(Dataset.subset)")
    size = len(keys) * len(elements) * ds.n_samples * 4
    if size > max_bytes:
        raise ValueError(f"the UFF recording matrix would be {len(keys)} waves x {len(elements)} elements x "
                         f"{ds.n_samples} samples = {size / 2**30:.2f} GiB, over max_bytes = {max_bytes} "
                         f"({ds.n_meas} measurements: a moving rig fills only its diagonal); raise max_bytes "
                         "or export a subset")
    c = ds.c_per_meas
    c_wave = np.array([c[wave == w].mean() for w in range(len(keys))])
    t_first = float(ds.t0_s[0])
    return {"sources": keys[:, :3], "t0": keys[:, 3], "elements": elements, "pairs": pairs,
            "c_wave": c_wave, "c": float(c.mean()), "t_first": t_first}


def _attrs(obj, cls: str, name: str, **extra) -> None:
    obj.attrs["class"] = np.bytes_(cls)
    obj.attrs["name"] = np.bytes_(name)
    for k, v in extra.items():
        obj.attrs[k] = v


def _number(g, name: str, value) -> None:
    """A real number or array, as MATLAB writes them (scalars as 1 x 1)."""
    arr = np.asarray(value, dtype=np.float64)
    d = g.create_dataset(name, data=arr.reshape(1, 1) if arr.ndim == 0 else arr)
    _attrs(d, "single", name, complex=np.array([0]), imaginary=np.array([0]))


def _text(g, name: str, text: str) -> None:
    d = g.create_dataset(name, data=np.array([ord(ch) for ch in text], dtype=np.uint16)[:, None])
    _attrs(d, "char", name)


def _group(parent, name: str, cls: str):
    g = parent.create_group(name)
    _attrs(g, cls, name, array=np.array([0]), size=np.array([1, 1]))
    return g


def _point(parent, name: str, xyz: np.ndarray) -> None:
    """A ``uff.point`` at ``xyz`` (3,) metres, in USTB's spherical coordinates."""
    x, y, z = (float(a) for a in xyz)
    d = float(np.sqrt(x * x + y * y + z * z))
    g = _group(parent, name, "uff.point")
    _number(g, "distance", d)
    _number(g, "azimuth", np.arctan2(x, z))
    _number(g, "elevation", np.arcsin(np.clip(y / d, -1.0, 1.0)) if d > 0 else 0.0)


def _write_channel_data(f, location: str, ds: Dataset, signals: np.ndarray, layout: dict) -> None:
    n_w, n_e = len(layout["sources"]), len(layout["elements"])
    cd = _group(f, location, "uff.channel_data")
    _number(cd, "sampling_frequency", ds.fs_hz)
    _number(cd, "initial_time", layout["t_first"])
    _number(cd, "sound_speed", layout["c"])
    _number(cd, "modulation_frequency", 0.0)
    _text(cd, "info", "written by clsas (clsas.io.export_uff): in-air bistatic recordings, positions in m")
    # MATLAB's [time, channel, wave] reversed; one chunk per recording, so the cells a moving rig
    # never measured are not stored (HDF5 reads them as the fill value, 0)
    d = cd.create_dataset("data", shape=(n_w, n_e, ds.n_samples), dtype=np.float32, chunks=(1, 1, ds.n_samples),
                          fillvalue=np.float32(0))
    pairs = layout["pairs"]
    for w in np.unique(pairs[:, 0]):
        rows = np.flatnonzero(pairs[:, 0] == w)
        rows = rows[np.argsort(pairs[rows, 1])]
        block = np.asarray(signals[rows], np.float32)
        if len(rows) == 1:  # a moving rig: one recording per wave (a plain slice is much faster)
            d[int(w), int(pairs[rows[0], 1]), :] = block[0]
        else:
            d[int(w), pairs[rows, 1].tolist(), :] = block
    _attrs(d, "single", "data", complex=np.array([0]), imaginary=np.array([0]))
    probe = _group(cd, "probe", "uff.probe")
    geometry = np.zeros((7, n_e))
    geometry[:3] = layout["elements"].T
    _number(probe, "geometry", geometry)
    _point(probe, "origin", np.zeros(3))
    _sequence(cd, layout)
    _pulse(cd, ds)


def _sequence(cd, layout: dict) -> None:
    sources, c_wave = layout["sources"], layout["c_wave"]
    seq = cd.create_group("sequence")
    _attrs(seq, "uff.wave", "sequence", array=np.array([1]), size=np.array([1, len(sources)]))
    for i, (src, t0, c) in enumerate(zip(sources, layout["t0"], c_wave, strict=True)):
        w = _group(seq, f"sequence_{i + 1:04d}", "uff.wave")
        front = w.create_dataset("wavefront", data=np.array([[1]], dtype=np.float64))
        _attrs(front, "uff.wavefront", "wavefront")
        _point(w, "source", src)
        _point(w, "origin", np.zeros(3))
        k = -1.0 if src[2] < DIVERGING_Z_M else 1.0
        emit = layout["t_first"] - t0  # when the speaker fires, on the data's time axis
        _number(w, "delay", k * float(np.linalg.norm(src)) / c - emit)
        _number(w, "sound_speed", c)


def _pulse(cd, ds: Dataset) -> None:
    ch = ds.chirp
    if {"f_start_hz", "f_stop_hz"} <= set(ch):
        fc = 0.5 * (ch["f_start_hz"] + ch["f_stop_hz"])
        bw = abs(ch["f_stop_hz"] - ch["f_start_hz"]) / fc
    else:
        spec = np.abs(np.fft.rfft(ds.waveform)) ** 2
        f = np.fft.rfftfreq(len(ds.waveform), 1.0 / ds.fs_hz)
        fc = float(np.sum(f * spec) / np.sum(spec)) if np.any(spec) else 0.0
        bw = 2.0 * float(np.sqrt(np.sum((f - fc) ** 2 * spec) / np.sum(spec))) / fc if fc > 0 else 0.0
    p = _group(cd, "pulse", "uff.pulse")
    _number(p, "center_frequency", fc)
    _number(p, "fractional_bandwidth", bw)
    _number(p, "phase", 0.0)
    _number(p, "waveform", ds.waveform[None, :])


def _write_clsas_group(g, location: str, ds: Dataset, layout: dict) -> None:
    from ..version import __version__

    g.attrs["location"] = location
    g.attrs["clsas_version"] = __version__
    g.attrs["chirp"] = json.dumps(ds.chirp, default=json_default)
    g.attrs["provenance"] = json.dumps(ds.provenance, default=json_default)
    g.create_dataset("pairs", data=layout["pairs"])
    for k in ("c_mps", "temperature_c", "humidity_pct"):
        g.create_dataset(k, data=np.broadcast_to(np.asarray(getattr(ds, k), float), (ds.n_meas,)))
