"""Import a scan in the AirSAS layout (the in-air circular SAS of Penn State ARL / Arizona State).

AirSAS (Reed, Blanford, Brown, Jayasuriya, "Neural volumetric reconstruction for coherent
synthetic aperture sonar", SIGGRAPH 2023; and the earlier SINR work) is a turntable rig: the
target rotates about the vertical axis while a speaker and one or two microphones stay fixed
(a vertical stage may raise them between turns). Its LabVIEW software writes one folder per
scan, and the empty-scene scan (background) is a second folder in the same layout.

Layout
------
The layout below is what the dataset authors' own readers read: ``airsas/utils.py`` and
``airsas/reconstruct_airsas_scene.py`` of github.com/awreed/
Neural-Volumetric-Reconstruction-for-Coherent-SAS, and ``airsas_deconv_pipeline/
airsas_utils.py`` of github.com/awreed/CSAS_Deconvolution_INR (SINR). No specification was
published and no sample file was found; where those readers are silent the choice made here
is said. File names are matched without regard to case::

    scan/
      Coordinates.csv      one row per ping, after a header row
      SysParams.csv        "name,value" rows
      WaveformParams.csv   one row per transmitted waveform
      Waveforms.csv        the transmitted waveforms, one column each (optional here)
      Flight-000001.csv    the recording of ping 1: one sample per row, no header
      Flight-000002.csv    ...

``Coordinates.csv``: columns *flight number* (1-based; ping N is ``Flight-NNNNNN.csv``, any
zero padding), *angle* of the turntable (degrees), *height* of the transducers' vertical
stage (millimetres, added to their z), *temperature* (degC, logged per ping), and optionally
*waveform* (0-based index into ``WaveformParams.csv`` rows and ``Waveforms.csv`` columns,
when a scan interleaves several waveforms). Columns are found by header words (``flight``,
``angle``, ``height``, ``temp``, ``wave``/``wfm``; a header ``(rad)`` or ``(m)`` changes the
unit), else taken in that order.

``SysParams.csv``: rows ``Speaker x``, ``Speaker y``, ``Speaker z``, ``Mic1 x`` ... ``Mic1 z``
(and ``Mic2 ...`` on two-microphone rigs), ``Center x`` ... ``Center z`` (metres, the rig's
frame: the turntable centre), ``Fs`` (Hz) and ``Group Delay`` (samples); other rows are
ignored. Names are matched without regard to case, spaces, underscores or a ``(unit)``.

``WaveformParams.csv``: the first cell of row *i* names waveform *i*, fields separated by
``_``: field 1 the start frequency (``...Hz``), field 2 the stop frequency, field 3 the
duration (``...s``), field 6 the Tukey taper ratio, numbers as MATLAB writes them
(``3.000000E+4Hz``); fields 0, 4 and 5 are not used. The measured set published with the
paper is reported to sweep 30 -> 10 kHz at ``Fs`` = 100 kHz, with a group delay of 62.33
samples and 360 pings (one per degree).

``Flight-*.csv``: the samples of column 1 (microphone 1); further columns, if any, are read
only with ``microphones="all"`` (assumed: column k is microphone k).

Geometry
--------
The dataset is returned in the target's frame, origin on the turntable axis at the height of
``Center``, z up: for a ping at turntable angle a and stage height h, a transducer at p in the
rig's frame is at ``R_z(s (a + a0)) (p - Center) + (0, 0, h)``, with ``s = angle_sign`` and
``a0 = zero_angle_deg``. The defaults (``s = +1``, ``a0 = 0``) keep the rig's frame at angle
0 (the transducers where ``SysParams.csv`` puts them, at -y on the published scans) and were
checked on the published measured scans (``bench/airsas_compare.py``), against the photo of
the object published with them:

- the owners' figure (``20k_scene/fig-a.PNG``) shows the photo beside their delay-and-sum
  image; that image is their ``scene.npy`` drawn with row 0 (their y = -0.3 m) at the top
  (``bench/airsas_compare.py`` measures this: the figure's panel correlates with
  ``scene.npy`` drawn that way, not with it flipped);
- a photo taken from above shows the object as seen from +z; a picture with y growing
  downward shows a right-handed (x, y, z up) frame as seen from below. So the object seen
  from above is the owners' image mirrored in y (y -> -y);
- the owners' own geometry puts the transducers at ``(0.85 cos(90 - a), 0.85 sin(90 - a))``
  (``sim_csas_package``'s ``theta_start=90, theta_step=-1``): mirrored in y, that is
  ``-90 + a``, which is this importer's default (the speaker at -y at angle 0, turning
  counter-clockwise in the target's frame as the angle grows). The default image, drawn
  with y up (``clsas.types.pictures``), has the photo's handedness.

``angle_sign=-1, zero_angle_deg=180`` gives the owners' frame exactly (their image's pixels,
their handedness). ``angle_sign=-1`` alone gives the owners' image turned by 180 degrees.

Timing: sample 0 is recorded ``Group Delay`` samples before the sound leaves the speaker,
so ``t0_s = -group_delay / fs`` (negative). The speed of sound follows each ping's
temperature (``Dataset.temperature_c`` per measurement) at 50 % relative humidity, assumed:
the scans log no humidity (:class:`clsas.Dataset`; the provenance says so).
"""

from __future__ import annotations

import csv
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..physics.signals import lfm_chirp
from ..types.dataset import Dataset
from ..validate import cell_number
from ._common import attach_background, is_number, read_numbers, stack_padded
from .registry import IMPORTERS, Importer

__all__ = ["import_airsas", "is_airsas"]

log = logging.getLogger("clsas.io")

_FLIGHT = re.compile(r"^flight\D*(\d+)\.csv$", re.IGNORECASE)
_COORD_WORDS = (("flight", ("flight",)), ("angle", ("angle", "theta")), ("height", ("height",)),
                ("temp", ("temp",)), ("wave", ("wave", "wfm")))


def is_airsas(folder: str | Path) -> bool:
    """Whether ``folder`` looks like an AirSAS scan (``Coordinates.csv`` and ``SysParams.csv``)."""
    folder = Path(folder)
    return folder.is_dir() and all(_find(folder, n) is not None for n in ("coordinates.csv", "sysparams.csv"))


def import_airsas(folder: str | Path, *, background: str | Path | None = None, waveform: str = "chirp",
                  waveform_index: int | None = None, microphones: str = "first", angle_sign: float = 1.0,
                  zero_angle_deg: float = 0.0, radius_m: float | None = None) -> Dataset:
    """Read an AirSAS scan folder into a :class:`~clsas.Dataset` (layout: :mod:`clsas.io.airsas`).

    Parameters
    ----------
    folder : path
        The scan's folder.
    background : path, optional
        The empty-scene scan's folder (same layout, same pings): its recordings become
        ``Dataset.background``, aligned ping by ping.
    waveform : {"chirp", "recorded"}
        ``"chirp"``: the LFM of ``WaveformParams.csv`` (:func:`clsas.lfm_chirp`, Tukey taper);
        ``"recorded"``: the column of ``Waveforms.csv``.
    waveform_index : int, optional
        Which waveform (0-based) when ``Coordinates.csv`` interleaves several (then needed): only
        its pings are read.
    microphones : {"first", "all"}
        ``"first"``: microphone 1 (column 1 of each flight file), one measurement per ping;
        ``"all"``: every column, microphone k at ``Mick`` of ``SysParams.csv``, k measurements
        per ping (ping-major order).
    angle_sign : {1, -1}
        Direction of the turntable angle (module docstring, "Geometry"); ``-1`` mirrors the image.
    zero_angle_deg : float
        Added to every angle before the rotation (degrees): turns the image about the axis.
    radius_m : float, optional
        The transducers' horizontal distance from the turntable axis (directions and heights
        kept) instead of ``SysParams.csv``'s (0.8485 m speaker, 0.8615 m microphones in the
        published scans; the owners' code assumes 0.85 m). :func:`clsas.focus.calibrate.calibrate`
        estimates it.

    Returns
    -------
    Dataset
        ``signals`` (n_pings * n_mics, n_samples); positions (n, 3) in metres in the target's
        frame; ``t0_s = -group_delay / fs``; ``temperature_c`` per ping (50 % RH assumed for c);
        ``chirp``; ``provenance`` = ``[{"step": "import", ...}, {"step": "speed_of_sound", ...}]``.

    Raises
    ------
    FileNotFoundError
        A missing folder or file (named).
    ValueError
        A malformed file (named, with the line), a missing parameter, a background whose pings
        or lengths differ from the scan's.
    """
    folder = Path(folder)
    _check_options(folder, waveform, microphones, angle_sign, zero_angle_deg, radius_m)
    sys_path = _need(folder, "SysParams.csv")
    sysp, fs, gd, center, speaker = _system(sys_path)
    coord_path = _need(folder, "Coordinates.csv")
    pings, index = _pings_of_waveform(coord_path, waveform_index)
    recs, names, n_ch = _read_flights(folder, coord_path, pings, microphones)
    tx, rx = _ping_positions(sysp, sys_path, speaker, center, pings, n_ch, angle_sign, zero_angle_deg, radius_m)
    wave, chirp = _waveform(folder, waveform, index, fs)
    prov = _provenance(folder, pings, n_ch, fs, gd, center, background, waveform=waveform, waveform_index=int(index),
                       angle_sign=int(angle_sign), zero_angle_deg=float(zero_angle_deg), radius_m=radius_m)
    ds = _dataset(folder, stack_padded(recs, names, str(folder)), tx, rx, fs, wave, np.full(len(recs), -gd / fs),
                  np.repeat(pings["temp_c"], n_ch), chirp, prov)
    if background is not None:
        ds = _with_background(ds, folder, background, waveform=waveform, waveform_index=waveform_index,
                              microphones=microphones, angle_sign=angle_sign, zero_angle_deg=zero_angle_deg,
                              radius_m=radius_m)
    log.info("imported AirSAS %s: %d pings x %d microphone(s), %d samples at %g Hz; c_mps from the logged temperature, "
             "%s", folder, len(pings["flight"]), n_ch, ds.n_samples, fs, ds.provenance[-1]["c_mps_source"])
    return ds


def _with_background(ds: Dataset, folder: Path, background: str | Path, **read) -> Dataset:
    """``ds`` with the empty-scene scan in ``background`` read as the scan was (``read``: the
    arguments of :func:`import_airsas`) and aligned ping by ping."""
    bg = import_airsas(background, **read)
    return ds.replace(background=attach_background(ds, bg, str(folder), str(background)))


def _ping_positions(sysp: dict, sys_path: Path, speaker: np.ndarray, center: np.ndarray, pings: dict, n_ch: int,
                    angle_sign: float, zero_angle_deg: float, radius_m: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The speaker's and the first ``n_ch`` microphones' positions (``SysParams.csv``) turned by
    each ping's turntable angle into the target's frame: ``(tx (n, 3), rx (n, 3))`` m, ping-major."""
    mics = np.array([[_param(sysp, sys_path, f"mic{k + 1} {a}") for a in "xyz"] for k in range(n_ch)])
    a = np.deg2rad(pings["angle_deg"] + zero_angle_deg) * angle_sign
    return _bistatic_pairs(speaker, mics, center, a, pings["height_m"], radius_m, sys_path)


def _provenance(folder: Path, pings: dict, n_ch: int, fs: float, gd: float, center: np.ndarray,
                background: str | Path | None, **options) -> dict[str, Any]:
    """The import's provenance entry: the scan, its rig's numbers and the reading ``options``
    (waveform, waveform_index, angle_sign, zero_angle_deg, radius_m)."""
    return {
        "step": "import", "source": str(folder), "format": "airsas", "pings": int(len(pings["flight"])),
        "microphones": int(n_ch), "fs_hz": fs, "group_delay_samples": gd, **options,
        "angle_deg": [float(pings["angle_deg"].min()), float(pings["angle_deg"].max())],
        "center_m": center.tolist(), **({"background": str(background)} if background is not None else {})}


def _system(sys_path: Path) -> tuple[dict, float, float, np.ndarray, np.ndarray]:
    """``SysParams.csv``: (its table, sample rate Hz, group delay samples, centre (3,) m, speaker (3,) m)."""
    sysp = _read_sysparams(sys_path)
    fs = _param(sysp, sys_path, "fs")
    if fs <= 0:
        raise ValueError(f"{sys_path}: Fs must be > 0, got {fs:g}")
    gd = _param(sysp, sys_path, "group delay")
    center = np.array([_param(sysp, sys_path, f"center {a}") for a in "xyz"])
    speaker = np.array([_param(sysp, sys_path, f"speaker {a}") for a in "xyz"])
    return sysp, fs, gd, center, speaker


def _bistatic_pairs(speaker, mics, center, angle_rad, height_m, radius_m, sys_path) -> tuple[np.ndarray, np.ndarray]:
    """Speaker and microphone positions in the target's frame, one pair per ping and microphone
    (ping-major): ``(tx (n, 3), rx (n, 3))`` in metres."""
    n_ch = len(mics)
    tx = np.repeat(_to_target(speaker, center, angle_rad, height_m, radius_m, sys_path), n_ch, axis=0)
    rx = np.stack([_to_target(m, center, angle_rad, height_m, radius_m, sys_path) for m in mics],
                  axis=1).reshape(-1, 3)
    return tx, rx


def _dataset(folder: Path, signals, tx, rx, fs, wave, t0, temperature, chirp, prov) -> Dataset:
    """The Dataset, its own refusals (e.g. a temperature that gives no speed of sound) naming the folder."""
    try:
        return Dataset(signals=signals, tx_positions=tx, rx_positions=rx, fs_hz=fs, waveform=wave, t0_s=t0,
                       temperature_c=temperature, chirp=chirp, provenance=[prov])
    except ValueError as exc:
        raise ValueError(f"{folder}: {exc}") from None


def _pings_of_waveform(coord_path: Path, waveform_index: int | None) -> tuple[dict, int]:
    """The pings of ``Coordinates.csv`` that use one waveform, and its index (the only one the file
    has, else ``waveform_index``, which a file interleaving several needs)."""
    pings = _read_coordinates(coord_path)
    kinds = sorted({int(w) for w in pings["wave"]}) if pings["wave"] is not None else []
    if waveform_index is None and len(kinds) > 1:
        raise ValueError(f"{coord_path} interleaves waveforms {kinds}: choose one with waveform_index=")
    index = waveform_index if waveform_index is not None else (kinds[0] if kinds else 0)
    keep = np.ones(len(pings["flight"]), bool) if pings["wave"] is None else pings["wave"] == index
    if not keep.any():
        raise ValueError(f"{coord_path}: no ping uses waveform {index} (the file has {kinds})")
    return {k: (None if v is None else v[keep]) for k, v in pings.items()}, index


def _check_options(folder: Path, waveform: str, microphones: str, angle_sign: float, zero_angle_deg: float,
                   radius_m: float | None) -> None:
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder {folder} (import_airsas: folder)")
    if waveform not in ("chirp", "recorded"):
        raise ValueError(f"waveform must be 'chirp' or 'recorded', got {waveform!r}")
    if microphones not in ("first", "all"):
        raise ValueError(f"microphones must be 'first' or 'all', got {microphones!r}")
    if angle_sign not in (1, -1):
        raise ValueError(f"angle_sign must be 1 or -1, got {angle_sign!r}")
    if not isinstance(zero_angle_deg, int | float) or not math.isfinite(zero_angle_deg):
        raise ValueError(f"zero_angle_deg must be a finite number of degrees, got {zero_angle_deg!r}")
    if radius_m is not None and (not isinstance(radius_m, int | float) or not math.isfinite(radius_m)
                                 or radius_m <= 0):
        raise ValueError(f"radius_m must be a finite number of metres > 0, got {radius_m!r}")


def _read_flights(folder: Path, coord_path: Path, pings: dict, microphones: str
                  ) -> tuple[list[np.ndarray], list[str], int]:
    """The recordings of the listed pings (ping-major), their names, and the channels per ping."""
    flights = _flight_files(folder)
    recs, names = [], []
    n_ch = None
    for number, line in zip(pings["flight"], pings["line"], strict=True):
        path = flights.get(int(number))
        if path is None:
            raise FileNotFoundError(f"no flight file for ping {int(number)} in {folder} "
                                    f"(Flight-{int(number):06d}.csv, listed in {coord_path}, line {line})")
        _, data = read_numbers(path)
        cols = data.shape[1] if microphones == "all" else 1
        if n_ch is not None and cols != n_ch:
            raise ValueError(f"{path} has {data.shape[1]} columns, earlier flight files {n_ch}")
        n_ch = cols
        for k in range(cols):
            recs.append(data[:, k])
            names.append(f"{path.name} column {k + 1}")
    if len(flights) > len(pings["flight"]):
        log.info("%s: %d flight files, %d pings read", folder, len(flights), len(pings["flight"]))
    return recs, names, int(n_ch)


def _to_target(p: np.ndarray, center: np.ndarray, angle_rad: np.ndarray, height_m: np.ndarray,
               radius_m: float | None, sys_path: Path) -> np.ndarray:
    """The rig point ``p`` (3,) in the target's frame at each ping: (n_pings, 3)."""
    d = p - center
    if radius_m is not None:
        r = math.hypot(d[0], d[1])
        if r == 0:
            raise ValueError(f"{sys_path}: a transducer is on the turntable axis; radius_m cannot move it")
        d = np.array([d[0] * radius_m / r, d[1] * radius_m / r, d[2]])
    cos, sin = np.cos(angle_rad), np.sin(angle_rad)
    return np.stack([cos * d[0] - sin * d[1], sin * d[0] + cos * d[1], d[2] + height_m], axis=1)


def _find(folder: Path, name: str) -> Path | None:
    """The file called ``name`` in ``folder``, without regard to case."""
    exact = folder / name
    if exact.is_file():
        return exact
    low = name.lower()
    return next((p for p in folder.iterdir() if p.name.lower() == low and p.is_file()), None)


def _need(folder: Path, name: str) -> Path:
    path = _find(folder, name)
    if path is None:
        raise FileNotFoundError(f"no {name} in {folder} (an AirSAS scan folder has Coordinates.csv, "
                                "SysParams.csv, WaveformParams.csv and Flight-NNNNNN.csv files)")
    return path


def _rows(path: Path) -> list[tuple[int, list[str]]]:
    """(1-based line number, cells) of the non-blank lines of a CSV file."""
    text = path.read_text(encoding="utf-8-sig")
    lines = [(i + 1, s) for i, s in enumerate(text.splitlines()) if s.strip()]
    return [(n, [c.strip() for c in cells]) for (n, _), cells in
            zip(lines, csv.reader([s for _, s in lines]), strict=True)]


def _key(name: str) -> str:
    """'Mic 1_X (m)' -> 'mic1 x'."""
    k = re.sub(r"\(.*?\)|\[.*?\]", " ", name.lower()).replace("_", " ")
    k = re.sub(r"\bmic\s+(\d)", r"mic\1", " ".join(k.split()))
    return {"gd": "group delay", "sample rate": "fs", "sampling rate": "fs", "fs hz": "fs",
            "mic x": "mic1 x", "mic y": "mic1 y", "mic z": "mic1 z"}.get(k, k)


def _read_sysparams(path: Path) -> dict[str, tuple[str, int]]:
    """{normalised name: (value text, line)} of SysParams.csv."""
    out: dict[str, tuple[str, int]] = {}
    for line, cells in _rows(path):
        if len(cells) >= 2 and cells[0]:
            out.setdefault(_key(cells[0]), (cells[1], line))
    return out


def _param(sysp: dict, path: Path, key: str) -> float:
    if key not in sysp:
        raise ValueError(f"{path}: no {key!r} row (import_airsas needs Speaker, "
                         "Mic1 and Center x/y/z in metres, Fs in Hz and Group Delay in samples)")
    text, line = sysp[key]
    try:
        val = float(text)
    except ValueError:
        raise ValueError(f"{path}, line {line}: {key} = {text!r} is not a number") from None
    if not math.isfinite(val):
        raise ValueError(f"{path}, line {line}: {key} = {text!r} is not a finite number")
    return val


def _read_coordinates(path: Path) -> dict[str, np.ndarray | None]:
    """Flight numbers, angles (deg), heights (m), temperatures (degC), waveform indices."""
    rows = _rows(path)
    if not rows:
        raise ValueError(f"{path} is empty")
    head = rows[0][1]
    has_header = not all(is_number(c) for c in head if c)
    cols: dict[str, int] = {}
    units = {"angle": 1.0, "height": 1e-3}
    if has_header:
        for i, h in enumerate(head):
            hl = h.lower()
            for name, words in _COORD_WORDS:
                if name not in cols and any(w in hl for w in words):
                    cols[name] = i
                    if name == "angle" and "rad" in hl:
                        units["angle"] = 180.0 / math.pi
                    if name == "height" and re.search(r"\(\s*m\s*\)|\[\s*m\s*\]", hl):
                        units["height"] = 1.0
                    break
    if not all(k in cols for k in ("flight", "angle", "height", "temp")):
        if has_header:
            log.warning("%s: header %s not understood; taking the columns as flight, angle, height, "
                        "temperature, waveform", path, head)
        cols = {name: i for i, (name, _) in enumerate(_COORD_WORDS) if i < len(head)}
    body = rows[1:] if has_header else rows
    if not body:
        raise ValueError(f"{path} lists no pings")
    labels = head if has_header else [name for name, _ in _COORD_WORDS]
    values: dict[str, list[float]] = {k: [] for k in cols}
    for line, cells in body:
        for name, i in cols.items():
            if i >= len(cells):
                raise ValueError(f"{path}, line {line}: {len(cells)} cells, no {labels[i]!r} column")
            values[name].append(cell_number(cells[i], f"{path}, line {line}, column {labels[i]!r}"))
    missing = [k for k in ("flight", "angle", "height", "temp") if k not in values]
    if missing:
        raise ValueError(f"{path}: needs the columns flight, angle, height, temperature; lacks {missing}")
    return {
        "flight": np.array(values["flight"]),
        "line": np.array([line for line, _ in body]),
        "angle_deg": np.array(values["angle"]) * units["angle"],
        "height_m": np.array(values["height"]) * units["height"],
        "temp_c": np.array(values["temp"]),
        "wave": np.array(values["wave"]) if "wave" in values else None,
    }


def _flight_files(folder: Path) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in folder.iterdir():
        m = _FLIGHT.match(p.name)
        if m and p.is_file():
            out[int(m.group(1))] = p
    if not out:
        raise FileNotFoundError(f"no Flight-NNNNNN.csv files in {folder}")
    return out


def _number(token: str, unit: str, path: Path, line: int) -> float:
    t = token.strip()
    if unit and t.lower().endswith(unit.lower()):
        t = t[: -len(unit)]
    try:
        return float(t)
    except ValueError:
        raise ValueError(f"{path}, line {line}: cannot read a number from {token!r}") from None


def _waveform(folder: Path, kind: str, index: int, fs: float) -> tuple[np.ndarray, dict]:
    if kind == "recorded":
        path = _need(folder, "Waveforms.csv")
        _, data = read_numbers(path, header=None)
        if index >= data.shape[1]:
            raise ValueError(f"{path} has {data.shape[1]} column(s), no waveform {index}")
        return data[:, index].copy(), {}
    path = _need(folder, "WaveformParams.csv")
    rows = _rows(path)
    if index >= len(rows):
        raise ValueError(f"{path} has {len(rows)} row(s), no waveform {index}")
    line, cells = rows[index]
    fields = cells[0].split("_")
    if len(fields) < 4:
        raise ValueError(f"{path}, line {line}: {cells[0]!r} is not a waveform name like "
                         "LFM_3.0E+4Hz_1.0E+4Hz_1.0E-3s_..._..._1.0E-1")
    chirp = {
        "f_start_hz": _number(fields[1], "Hz", path, line),
        "f_stop_hz": _number(fields[2], "Hz", path, line),
        "duration_s": _number(fields[3], "s", path, line),
        "taper": _number(fields[6], "", path, line) if len(fields) > 6 else 0.0,
    }
    if len(fields) <= 6:
        log.warning("%s, line %d: no taper field in %r; using no taper", path, line, cells[0])
    try:
        wave = lfm_chirp(chirp["f_start_hz"], chirp["f_stop_hz"], chirp["duration_s"], fs, chirp["taper"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}, line {line}: {exc}") from None
    return wave, chirp


IMPORTERS.register("airsas", Importer(
    read=import_airsas, detect=is_airsas,
    summary="the AirSAS turntable layout (Coordinates.csv, SysParams.csv, Flight-*.csv)"))
