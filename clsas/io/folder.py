"""Import a folder of recordings with a positions table (any rig that writes WAV or CSV files).

Layout
------
::

    scan/
      positions.csv        which file is which measurement, and where (required)
      import.toml          sample rate, chirp, delays, air (optional; or clsas-import.toml)
      waveform.wav         the transmitted signal (or waveform.csv; not needed with [chirp])
      stop-000.wav ...     the recordings, any names: WAV or CSV, mono or multi-channel

**Recordings.** A WAV file (int16, int32, 8-bit or float; integer samples are scaled to full
scale 1) or a CSV file with one column per channel and one row per sample; a CSV header naming
the channels is optional, and a column named ``time_s`` is the time axis, not a channel (it
gives the sample rate when nothing else does). A mono file is one measurement; a file with k
channels is k measurements, one per microphone (one bistatic pair per measurement), except the
loopback channel (see ``loopback_channel``). Recordings of different lengths are padded with
zeros at the end to the longest (with a log warning).

**positions.csv** (the name can be changed with ``positions=``): a header, then one row per
recording file; column names are case-insensitive, positions are in metres in one fixed frame::

    file,tx_x,tx_y,tx_z,rx_x,rx_y,rx_z,rx2_x,rx2_y,rx2_z,temperature_c
    stop-000.wav,0.00,0.0,0.0,0.05,0.0,0.0,-0.05,0.0,0.0,21.3
    stop-001.wav,0.01,0.0,0.0,0.06,0.0,0.0,-0.04,0.0,0.0,21.3

==============================  ============================================================
``file``                        the recording, relative to the folder (required)
``tx_x``, ``tx_y``, ``tx_z``    speaker, m (required)
``rx_x``, ``rx_y``, ``rx_z``    microphone of channel 1, m (required; also ``rx1_x`` ...)
``rxK_x``, ``rxK_y``, ``rxK_z`` microphone of channel K of a multi-channel file, m
``t0_s``                        time of sample 0 after the transmit start, s (default 0)
``temperature_c``               air temperature during this recording, degC
``humidity_pct``                relative humidity, % (default 50, assumed: see :class:`clsas.Dataset`)
``c_mps``                       speed of sound, m/s (default: from the temperature and humidity)
``timestamp_s``                 when, s since the Unix epoch
==============================  ============================================================

Optional cells may be left empty (the default of ``import.toml`` or clsas then applies);
other columns are refused (a misspelt name is not silently ignored). Measurements come in the
order of the rows, channel by channel within a file.

**import.toml** (optional; every table and key is optional, unknown ones are refused)::

    [recording]
    fs_hz = 96000.0              # needed for CSV recordings; must agree with the WAV headers
    positions = "positions.csv"
    waveform = "waveform.wav"    # the transmitted signal, WAV or CSV at fs_hz
    loopback_channel = 3         # this channel is the loopback reference (-> Dataset.loopback)

    [chirp]                      # the transmitted LFM chirp, instead of a waveform file
    f_start_hz = 20000.0
    f_stop_hz = 30000.0
    duration_s = 0.005
    taper = 0.1                  # Tukey fraction (clsas.lfm_chirp)

    [delay]
    t0_s = 0.0                   # for rows without a t0_s cell
    group_delay_samples = 62.33  # or group_delay_s: subtracted from every t0_s

    [air]                        # for rows without the corresponding cell
    temperature_c = 20.0
    humidity_pct = 50.0
    c_mps = 343.2

Arguments of :func:`import_folder` override the file. The waveform is, in this order: the
``waveform=`` argument, ``[chirp]``, ``[recording] waveform``, ``waveform.wav`` or
``waveform.csv`` in the folder.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..physics.signals import lfm_chirp
from ..physics.sound import ASSUMED_HUMIDITY_PCT, speed_of_sound
from ..types.dataset import Dataset
from ..validate import cell_number
from ._common import attach_background, read_numbers, read_settings, read_wav, sniff_delimiter, stack_padded
from .registry import IMPORTERS, Importer

__all__ = ["SETTINGS_FILES", "import_folder"]

log = logging.getLogger("clsas.io")

#: names of the optional settings file, looked for in this order
SETTINGS_FILES = ("import.toml", "clsas-import.toml")

_SCHEMA: dict[str, dict[str, type]] = {
    "recording": {"fs_hz": float, "positions": str, "waveform": str, "loopback_channel": int},
    "chirp": {"f_start_hz": float, "f_stop_hz": float, "duration_s": float, "taper": float, "fs_hz": float},
    "delay": {"t0_s": float, "group_delay_samples": float, "group_delay_s": float},
    "air": {"temperature_c": float, "humidity_pct": float, "c_mps": float},
}
_CHIRP_KEYS = ("f_start_hz", "f_stop_hz", "duration_s", "taper")
_OPTIONAL = ("t0_s", "temperature_c", "humidity_pct", "c_mps", "timestamp_s")
_FILE_NAMES = ("file", "filename", "recording")
_RX = re.compile(r"^rx(\d*)_([xyz])$")
_TIME_NAMES = ("time_s", "t_s", "time")


@dataclass
class _Row:
    lineno: int
    file: str
    tx: np.ndarray
    rx: dict[int, np.ndarray]  # channel (1-based) -> position
    extra: dict[str, float] = field(default_factory=dict)  # optional columns given in this row


def _recordings_and_rate(folder: Path, table: Path, rows, cfg: dict, cfg_path, fs_hz):
    """The recordings, the loopback takes and the sample rate (given, from the settings, else the files')."""
    loopback_ch = cfg["recording"].get("loopback_channel")
    if loopback_ch is not None and loopback_ch < 1:
        raise ValueError(f"{cfg_path}: [recording] loopback_channel must be >= 1, got {loopback_ch}")
    fs = _given_fs(fs_hz, cfg, cfg_path)
    meas, loop, file_fs = _read_recordings(folder, table, rows, loopback_ch, fs)
    fs = fs if fs is not None else file_fs
    if fs is None:
        raise ValueError(f"{folder}: the sample rate is not known (CSV recordings without a time_s column): "
                         "give fs_hz= or set [recording] fs_hz in import.toml")
    return meas, loop, fs


def _rows(takes: list, width: int) -> np.ndarray:
    """The loopback takes as rows of ``width`` samples, zero-padded at the end."""
    out = np.zeros((len(takes), width))
    for i, x in enumerate(takes):
        out[i, : len(x)] = x
    return out


def _per_measurement(table: Path, src, cfg: dict, group_delay_s: float):
    """(t0_s, temperature_c, humidity_pct, c_mps or None, timestamps or None), one per measurement: the
    table's column where it has one, else the settings file's value."""
    air, delay = cfg["air"], cfg["delay"]
    t0 = _column(table, src, "t0_s", delay.get("t0_s", 0.0)) - group_delay_s
    temperature = _column(table, src, "temperature_c", air.get("temperature_c", 20.0))
    humidity = _column(table, src, "humidity_pct", air.get("humidity_pct"), partial=True)  # None: not logged
    if humidity is not None and np.any(np.isnan(humidity)):  # cells left empty: the Dataset's assumed air
        humidity = np.where(np.isnan(humidity), ASSUMED_HUMIDITY_PCT, humidity)
    c = _column(table, src, "c_mps", air.get("c_mps"), partial=True)
    if c is not None and np.any(np.isnan(c)):  # cells left empty: from that row's temperature and humidity
        c = np.where(np.isnan(c), speed_of_sound(temperature, ASSUMED_HUMIDITY_PCT if humidity is None else humidity),
                     c)
    return t0, temperature, humidity, c, _column(table, src, "timestamp_s", None)


def import_folder(
    folder: str | Path, *, positions: str | Path | None = None, waveform: str | Path | np.ndarray | dict | None = None,
    fs_hz: float | None = None, settings: str | Path | None = None, group_delay_samples: float | None = None,
    background: str | Path | None = None,
) -> Dataset:
    """Read a folder of recordings and its positions table into a :class:`~clsas.Dataset` (layout:
    :mod:`clsas.io.folder`).

    Parameters
    ----------
    folder : path
        The folder.
    positions : path, optional
        The positions table, relative to the folder (default: the settings' ``[recording]
        positions``, else ``positions.csv``).
    waveform : path, (n_wave,) array or dict, optional
        The transmitted signal: a WAV or CSV file (relative to the folder, or any path), the
        samples at ``fs_hz``, or chirp parameters ``{"f_start_hz", "f_stop_hz",
        "duration_s", "taper"}`` (Hz, s, Tukey fraction) for :func:`clsas.lfm_chirp`.
    fs_hz : float, optional
        Sample rate, Hz (default: the settings', else the WAV headers', else CSV ``time_s``'s).
    settings : path, optional
        The TOML settings file (default: the folder's ``import.toml`` or ``clsas-import.toml``).
    group_delay_samples : float, optional
        Delay of the transducer chain, in samples: ``t0_s`` is lowered by
        ``group_delay_samples / fs_hz`` (default: the settings file's ``[delay]``, else 0).
    background : path, optional
        The empty-scene scan's folder (same layout, stop for stop) -> ``Dataset.background``.

    Returns
    -------
    Dataset
        ``signals`` (n_meas, n_samples), positions (n_meas, 3) m, per-measurement ``t0_s`` and air;
        ``provenance``: one ``{"step": "import", "format": "folder", ...}``; ``config``: the settings.

    Raises
    ------
    FileNotFoundError
        No folder, positions table, recording or waveform file; the message names it.
    ValueError
        A malformed table or settings file (named, with line and column or table and key),
        inconsistent sample rates, a background that does not match.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder {folder} (import_folder: folder)")
    cfg, cfg_text, cfg_path = _settings(folder, settings)
    table = folder / (positions if positions is not None else cfg["recording"].get("positions", "positions.csv"))
    rows = _read_positions(table)
    meas, loop, fs = _recordings_and_rate(folder, table, rows, cfg, cfg_path, fs_hz)
    sig, padded = _signals(meas, table)
    wave, chirp, wave_src = _waveform(folder, waveform, cfg, cfg_path, fs)
    gd = _group_delay(group_delay_samples, cfg, cfg_path, fs)
    air = _per_measurement(table, [rows[m.row] for m in meas], cfg, gd / fs)
    prov = _provenance(folder, table, len(rows), fs, wave_src, gd, padded, cfg_path, background)
    ds = _dataset(table, rows, meas, sig, loop, air, fs_hz=fs, waveform=wave, chirp=chirp, config=cfg_text,
                  provenance=[prov])
    if background is not None:
        ds = _with_background(ds, folder, background, positions=positions, waveform=wave, fs_hz=fs,
                              settings=settings, group_delay_samples=gd)
    log.info("imported %s: %d measurements x %d samples at %g Hz", folder, ds.n_meas, ds.n_samples, fs)
    return ds


def _signals(meas: list[_Meas], table: Path) -> tuple[np.ndarray, bool]:
    """(n_meas, n_samples) the recordings, zero-padded at the end to the longest, and whether any was."""
    padded = len({len(m.samples) for m in meas}) > 1
    return stack_padded([m.samples for m in meas], [m.name for m in meas], str(table)), padded


def _with_background(ds: Dataset, folder: Path, background: str | Path, **read) -> Dataset:
    """``ds`` with the empty-scene scan in ``background`` read as the scan was (``read``: the
    arguments of :func:`import_folder`) and checked stop for stop."""
    bg = import_folder(background, **read)
    return ds.replace(background=attach_background(ds, bg, str(folder), str(background)))


def _provenance(folder: Path, table: Path, n_files: int, fs: float, wave_src: str, gd: float, padded: bool,
                cfg_path: Path | None, background: str | Path | None) -> dict[str, Any]:
    """The import's provenance entry: where the scan came from and what was assumed in reading it."""
    return {
        "step": "import", "source": str(folder), "format": "folder", "positions": table.name, "files": n_files,
        "fs_hz": fs, "waveform": wave_src, "group_delay_samples": gd, "padded": padded,
        "settings": None if cfg_path is None else cfg_path.name,
        **({"background": str(background)} if background is not None else {})}


def _dataset(table: Path, rows: list[_Row], meas: list[_Meas], signals: np.ndarray, loop: list[np.ndarray],
             air: tuple, **fields) -> Dataset:
    """The :class:`~clsas.Dataset` of the measurements ``meas`` (positions from their ``rows``, the
    per-measurement ``air`` of :func:`_per_measurement`, the loopback takes ``loop``) and ``fields``;
    a value the Dataset refuses (e.g. a humidity above 100 %) is reported with the table it came from."""
    t0, temperature, humidity, c, stamps = air
    loopback = _rows(loop, signals.shape[1]) if loop else None
    try:
        return Dataset(
            signals=signals,
            tx_positions=np.array([rows[m.row].tx for m in meas]),
            rx_positions=np.array([rows[m.row].rx[m.channel] for m in meas]),
            t0_s=t0, c_mps=c, temperature_c=temperature, humidity_pct=humidity, timestamps=stamps,
            loopback=loopback, **fields,
        )
    except ValueError as exc:
        raise ValueError(f"{table}: {exc}") from None


@dataclass
class _Meas:
    samples: np.ndarray  # (n,)
    name: str  # file, channel: for messages
    row: int  # index into the positions rows
    channel: int  # 1-based


def _settings(folder: Path, settings: str | Path | None) -> tuple[dict, str, Path | None]:
    if settings is not None:
        path = Path(settings)
        if not path.is_absolute() and not path.exists() and (folder / path).exists():
            path = folder / path
        if not path.is_file():
            raise FileNotFoundError(f"no settings file {path} (import_folder: settings)")
    else:
        path = next((folder / n for n in SETTINGS_FILES if (folder / n).is_file()), None)
        if path is None:
            return {t: {} for t in _SCHEMA}, "", None
    cfg, text = read_settings(path, _SCHEMA)
    return cfg, text, path


def _given_fs(fs_hz: float | None, cfg: dict, cfg_path: Path | None) -> float | None:
    if fs_hz is not None:
        fs = float(fs_hz)
        if not (math.isfinite(fs) and fs > 0):
            raise ValueError(f"fs_hz must be a finite number > 0, got {fs_hz!r}")
        return fs
    a, b = cfg["recording"].get("fs_hz"), cfg["chirp"].get("fs_hz")
    if a is not None and b is not None and a != b:
        raise ValueError(f"{cfg_path}: [recording] fs_hz = {a:g} and [chirp] fs_hz = {b:g} disagree")
    fs = a if a is not None else b
    if fs is not None and fs <= 0:
        raise ValueError(f"{cfg_path}: fs_hz must be > 0, got {fs:g}")
    return fs


def _read_positions(path: Path) -> list[_Row]:
    """The rows of the positions table (see the module docstring)."""
    if not path.is_file():
        raise FileNotFoundError(f"no positions table {path} (import_folder: positions)")
    text = path.read_text(encoding="utf-8-sig")
    lines = [(i + 1, s) for i, s in enumerate(text.splitlines()) if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path} is empty: it needs a header (file,tx_x,tx_y,tx_z,rx_x,rx_y,rx_z) and rows")
    delimiter = sniff_delimiter(lines[0][1]) or ","
    parsed = list(csv.reader([s for _, s in lines], delimiter=delimiter))
    header = [h.strip().lower() for h in parsed[0]]
    cols = _header_columns(path, header)
    rows, seen = [], {}
    for (lineno, _), cells in zip(lines[1:], parsed[1:], strict=True):
        cells = [c.strip() for c in cells]
        if len(cells) != len(header):
            raise ValueError(f"{path}, line {lineno}: {len(cells)} cells, the header has {len(header)}")

        def num(name: str, idx: int, optional: bool = False, *, _cells=cells, _line=lineno) -> float | None:
            cell = _cells[idx]
            if cell == "" and optional:
                return None
            return cell_number(cell, f"{path}, line {_line}, column {name!r}")

        name = cells[cols["file"]]
        if not name:
            raise ValueError(f"{path}, line {lineno}, column 'file': an empty cell")
        if name in seen:
            raise ValueError(f"{path}, line {lineno}: {name} is listed twice (also on line {seen[name]})")
        seen[name] = lineno
        tx = np.array([num(f"tx_{a}", cols[f"tx_{a}"]) for a in "xyz"])
        rx = {}
        for ch, axes in cols["rx"].items():
            vals = [num(f"rx{ch}_{a}", axes[a], optional=ch > 1) for a in "xyz"]
            if all(v is None for v in vals):
                continue
            if any(v is None for v in vals):
                raise ValueError(f"{path}, line {lineno}: rx{ch}_x, rx{ch}_y, rx{ch}_z must all be given or all empty")
            rx[ch] = np.array(vals)
        extra = {k: num(k, cols[k], optional=True) for k in _OPTIONAL if k in cols}
        rows.append(_Row(lineno, name, tx, rx, {k: v for k, v in extra.items() if v is not None}))
    if not rows:
        raise ValueError(f"{path} has a header but no rows")
    return rows


def _header_columns(path: Path, header: list[str]) -> dict:
    cols: dict[str, Any] = {"rx": {}}
    for i, h in enumerate(header):
        m = _RX.match(h)
        key = "file" if h in _FILE_NAMES else h
        if key in cols or (m and m.group(2) in cols["rx"].get(int(m.group(1) or 1), {})):
            raise ValueError(f"{path}, line 1: column {h!r} appears twice")
        if m:
            cols["rx"].setdefault(int(m.group(1) or 1), {})[m.group(2)] = i
        elif key in ("file", "tx_x", "tx_y", "tx_z", *_OPTIONAL):
            cols[key] = i
        else:
            known = "file, tx_x, tx_y, tx_z, rx_x, rx_y, rx_z, rxK_x/y/z, " + ", ".join(_OPTIONAL)
            raise ValueError(f"{path}, line 1: unknown column {h!r} (known: {known})")
    missing = [k for k in ("file", "tx_x", "tx_y", "tx_z") if k not in cols]
    missing += [f"rx_{a}" for a in "xyz" if a not in cols["rx"].get(1, {})]
    for ch, axes in cols["rx"].items():
        missing += [f"rx{ch}_{a}" for a in "xyz" if ch > 1 and a not in axes]
    if missing:
        raise ValueError(f"{path}, line 1: missing column(s) {', '.join(missing)}")
    return cols


def _read_recordings(folder: Path, table: Path, rows: list[_Row], loopback_ch: int | None,
                     fs: float | None) -> tuple[list[_Meas], list[np.ndarray], float | None]:
    """Every measurement (one per microphone channel of each file), the loopback channels,
    and the sample rate the files say (checked against ``fs`` and each other)."""
    meas: list[_Meas] = []
    loop: list[np.ndarray] = []
    file_fs: float | None = None
    first_fs_file = ""
    for r_i, row in enumerate(rows):
        path = folder / row.file
        if not path.is_file():
            raise FileNotFoundError(f"no recording {path} (named in {table}, line {row.lineno})")
        rate, data = _read_recording(path)
        tol = 1e-6 if path.suffix.lower() == ".wav" else 1e-3  # a CSV time column is rounded
        if rate is not None:
            if fs is not None and not math.isclose(rate, fs, rel_tol=tol):
                raise ValueError(f"{path} is sampled at {rate:g} Hz, but fs_hz is {fs:g} Hz")
            if file_fs is not None and not math.isclose(rate, file_fs, rel_tol=tol):
                raise ValueError(f"{path} is sampled at {rate:g} Hz, {first_fs_file} at {file_fs:g} Hz")
            if file_fs is None:
                file_fs, first_fs_file = rate, str(path)
        n_ch = data.shape[1]
        if loopback_ch is not None and loopback_ch > n_ch:
            raise ValueError(f"{path} has {n_ch} channel(s); [recording] loopback_channel is {loopback_ch}")
        extra = [ch for ch in row.rx if ch > n_ch]
        if extra:
            raise ValueError(f"{table}, line {row.lineno}: rx{extra[0]}_x/y/z given, but {row.file} has "
                             f"{n_ch} channel(s)")
        for ch in range(1, n_ch + 1):
            if ch == loopback_ch:
                loop.append(data[:, ch - 1])
                continue
            if ch not in row.rx:
                raise ValueError(f"{table}, line {row.lineno}: {row.file} has {n_ch} channels; give the "
                                 f"microphone of channel {ch} in columns rx{ch}_x, rx{ch}_y, rx{ch}_z")
            meas.append(_Meas(data[:, ch - 1], f"{row.file} channel {ch}", r_i, ch))
    if not meas:
        raise ValueError(f"{table}: no microphone channels (only the loopback channel)")
    return meas, loop, file_fs


def _read_recording(path: Path) -> tuple[float | None, np.ndarray]:
    """(sample rate or None, (n_samples, n_channels) samples) of a WAV or CSV recording."""
    suffix = path.suffix.lower()
    if suffix == ".wav":
        return read_wav(path)
    if suffix in (".csv", ".txt"):
        names, values = read_numbers(path)
        rate = None
        if names is not None:
            low = [n.lower() for n in names]
            t = next((i for i, n in enumerate(low) if n in _TIME_NAMES), None)
            if t is not None:
                dt = np.diff(values[:, t])
                if len(dt) == 0 or np.any(dt <= 0) or np.ptp(dt) > 1e-3 * np.mean(dt):
                    raise ValueError(f"{path}: column {names[t]!r} must increase in even steps")
                rate = 1.0 / float(np.mean(dt))
                values = np.delete(values, t, axis=1)
                if values.shape[1] == 0:
                    raise ValueError(f"{path} has a time column but no channel")
        return rate, values
    raise ValueError(f"{path}: unsupported recording type {suffix!r} (WAV or CSV)")


def _column(table: Path, src: list[_Row], name: str, default: float | None, *,
            partial: bool = False) -> np.ndarray | None:
    """A per-measurement optional column: its cells, the default where a cell is empty; None
    where no row gives it and there is no default. ``partial``: NaN where neither is given."""
    vals = [r.extra.get(name, default) for r in src]
    if all(v is None for v in vals):
        return None
    if any(v is None for v in vals) and not partial:
        line = next(r.lineno for r, v in zip(src, vals, strict=True) if v is None)
        raise ValueError(f"{table}, line {line}, column {name!r}: an empty cell (fill every row or none)")
    return np.array([np.nan if v is None else v for v in vals], dtype=float)


def _waveform(folder: Path, waveform: Any, cfg: dict, cfg_path: Path | None,
              fs: float) -> tuple[np.ndarray, dict, str]:
    """(samples, chirp parameters or {}, a description for the provenance)."""
    if isinstance(waveform, dict):
        return _chirp(waveform, fs, "waveform")
    if isinstance(waveform, np.ndarray | list | tuple):
        wave = np.asarray(waveform, dtype=float)
        if wave.ndim != 1 or len(wave) == 0 or not np.all(np.isfinite(wave)):
            raise ValueError(f"waveform must be a 1-D finite array of samples, got shape {wave.shape}")
        return wave, {}, "array"
    if waveform is not None:
        path = Path(waveform)
        if not path.is_absolute() and (folder / path).exists():
            path = folder / path
        return _waveform_file(path, fs), {}, f"file {path.name}"
    if cfg["chirp"]:
        return _chirp({k: v for k, v in cfg["chirp"].items() if k != "fs_hz"}, fs, f"{cfg_path} [chirp]")
    named = cfg["recording"].get("waveform")
    if named is not None:
        path = folder / named
        if not path.is_file():
            raise FileNotFoundError(f"no waveform file {path} (named in {cfg_path}, [recording] waveform)")
        return _waveform_file(path, fs), {}, f"file {named}"
    for name in ("waveform.wav", "waveform.csv"):
        if (folder / name).is_file():
            return _waveform_file(folder / name, fs), {}, f"file {name}"
    raise FileNotFoundError(f"{folder}: no transmitted waveform: add waveform.wav or waveform.csv, a [chirp] "
                            "table in import.toml, or pass waveform= (a file, samples or chirp parameters)")


def _chirp(params: dict, fs: float, where: str) -> tuple[np.ndarray, dict, str]:
    unknown = sorted(set(params) - set(_CHIRP_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown chirp parameter {unknown[0]!r} (known: {', '.join(_CHIRP_KEYS)})")
    missing = [k for k in _CHIRP_KEYS[:3] if k not in params]
    if missing:
        raise ValueError(f"{where}: chirp parameters lack {', '.join(missing)}")
    chirp = {k: float(params[k]) for k in _CHIRP_KEYS if k in params}
    chirp.setdefault("taper", 0.0)
    wave = lfm_chirp(chirp["f_start_hz"], chirp["f_stop_hz"], chirp["duration_s"], fs, chirp["taper"])
    return wave, chirp, "chirp"


def _waveform_file(path: Path, fs: float) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"no waveform file {path} (import_folder: waveform)")
    rate, data = _read_recording(path)
    if rate is not None and not math.isclose(rate, fs, rel_tol=1e-3):
        raise ValueError(f"{path} is sampled at {rate:g} Hz, the recordings at {fs:g} Hz")
    if data.shape[1] > 1:
        log.warning("%s has %d channels: the first is taken as the transmitted waveform", path, data.shape[1])
    return data[:, 0].copy()


def _group_delay(given: float | None, cfg: dict, cfg_path: Path | None, fs: float) -> float:
    """Group delay in samples (0 if none is given)."""
    if given is not None:
        gd = float(given)
        if not math.isfinite(gd):
            raise ValueError(f"group_delay_samples must be finite, got {given!r}")
        return gd
    d = cfg["delay"]
    if "group_delay_samples" in d and "group_delay_s" in d:
        raise ValueError(f"{cfg_path}: [delay] has both group_delay_samples and group_delay_s: give one")
    if "group_delay_s" in d:
        return d["group_delay_s"] * fs
    return d.get("group_delay_samples", 0.0)


def is_folder_scan(folder: str | Path) -> bool:
    """Whether ``folder`` holds a ``positions.csv`` or a settings file (:data:`SETTINGS_FILES`)."""
    folder = Path(folder)
    return folder.is_dir() and any((folder / n).is_file() for n in ("positions.csv", *SETTINGS_FILES))


IMPORTERS.register("folder", Importer(read=import_folder, detect=is_folder_scan,
                                      summary="a folder of WAV or CSV recordings with positions.csv"))
