"""Circular and helical apertures (turntable or arc) and apertures read from CSV tables.

The frames (z up and the rotation axis for circles, the rig's local frame for the offsets) and
the order of the measurements with several microphones per ping are described in
:mod:`clsas.physics.geometry`.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .. import validate as v
from .geometry import BISTATIC_COLUMNS, STAGE_COLUMNS, TX_OFFSET_M, Aperture, aperture_from_stops, mic_offsets

__all__ = ["circular_aperture", "helical_aperture", "aperture_from_csv"]


def _ring(azimuth_rad: np.ndarray, radius: float, z_m: np.ndarray, center: np.ndarray,
          txo: np.ndarray, rxo: np.ndarray) -> Aperture:
    """Rig at ``azimuth_rad`` on a circle about the vertical axis through ``center``, looking in."""
    cs, sn = np.cos(azimuth_rad), np.sin(azimuth_rad)
    zero, one = np.zeros_like(cs), np.ones_like(cs)
    stage = center + np.stack([radius * cs, radius * sn, z_m], axis=1)
    frame = np.stack([np.stack([sn, -cs, zero], 1),      # local x: tangential, clockwise
                      np.stack([zero, zero, one], 1),    # local y: up
                      np.stack([-cs, -sn, zero], 1)], 1)  # local z: towards the axis
    tx = stage + np.einsum("c,ncd->nd", txo, frame)
    rx = stage[:, None, :] + np.einsum("kc,ncd->nkd", rxo, frame)
    return aperture_from_stops(stage, tx, rx)


def _ring_args(radius_m, center_m, height_m, mode, tx_offset_m, rx_offset_m, rx_offsets_m):
    r = v.positive("radius_m", radius_m)
    c = v.array("center_m", center_m, shape=(3,))
    h = v.finite("height_m", height_m)
    v.choice("mode", mode, ("turntable", "arc"))
    txo = v.array("tx_offset_m", tx_offset_m, shape=(3,))
    return r, c, h, (-1.0 if mode == "turntable" else 1.0), txo, mic_offsets(rx_offset_m, rx_offsets_m)


def circular_aperture(n: int, radius_m: float, *, center_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
                      height_m: float = 0.0, start_deg: float = 0.0, stop_deg: float | None = None,
                      mode: str = "turntable", tx_offset_m: tuple[float, float, float] = TX_OFFSET_M,
                      rx_offset_m: tuple[float, float, float] | None = None,
                      rx_offsets_m: np.ndarray | None = None) -> Aperture:
    """Stops on a circle (or an arc of it) about the vertical axis through ``center_m``.

    The rotation axis is parallel to z (up) through ``center_m``; the rig stays at
    ``z = center_m[2] + height_m``, ``radius_m`` from the axis, looking horizontally at it.
    Positions are returned in the scene (target) frame; see the module notes for the rig's
    local frame, in which the offsets are given.

    Parameters
    ----------
    n : int
        Number of stops (pings).
    radius_m : float
        Distance of the rig's reference point from the axis, metres (> 0).
    center_m : tuple of float
        A point on the rotation axis, metres.
    height_m : float
        Height of the rig above ``center_m[2]``, metres.
    start_deg, stop_deg : float
        Angles of the first and last stop, degrees counterclockwise seen from +z; ``stop_deg``
        defaults to ``start_deg + 360``. A full turn (``|stop_deg - start_deg| == 360``) has
        ``n`` stops ``360 / n`` apart, the endpoint excluded (it is the start again); a partial
        arc includes both ends. A negative span turns the other way.
    mode : {"turntable", "arc"}
        ``"arc"``: the rig moves on the circle, stop i at azimuth ``angle_i``. ``"turntable"``:
        the target turns by ``angle_i`` (counterclockwise seen from +z) in front of a fixed rig
        that stands at azimuth 0 (on the +x side of the axis) in the room; the scene frame is
        the target's, equal to the room's at turntable angle 0. Imaging in the target's frame
        is equivalent to the rig moving by ``-angle_i``: stop i is at azimuth ``-angle_i``.
        Reconstruct with the scene (the target) as it stands at turntable angle 0.
    tx_offset_m, rx_offset_m : tuple of float
        Speaker and microphone offsets from the reference point in the rig's local frame
        (x tangential, y up, z towards the axis), metres; ``rx_offset_m`` defaults to
        ``(0.02, 0, 0)``.
    rx_offsets_m : (k, 3) array, optional
        Several microphones per ping (local frame), replacing ``rx_offset_m``.

    Returns
    -------
    Aperture
        ``n * k`` measurements, stop-major.

    Examples
    --------
    A turntable turned in 2-degree steps, the rig 0.8 m from its axis:

    >>> import clsas
    >>> clsas.circular_aperture(180, 0.8).tx_positions.shape
    (180, 3)
    """
    n = v.positive_int("n", n)
    r, c, h, sign, txo, rxo = _ring_args(radius_m, center_m, height_m, mode, tx_offset_m, rx_offset_m,
                                         rx_offsets_m)
    angles = _arc_angles(n, start_deg, stop_deg)
    return _ring(np.deg2rad(sign * angles), r, np.full(n, h), c, txo, rxo)


def _arc_angles(n: int, start_deg: float, stop_deg: float | None) -> np.ndarray:
    """The ``n`` stops' angles, degrees: a full turn ``360 / n`` apart without its endpoint, or a
    partial arc with both ends (see :func:`circular_aperture`)."""
    start = v.finite("start_deg", start_deg)
    span = 360.0 if stop_deg is None else v.finite("stop_deg", stop_deg) - start
    if abs(span) > 360.0 + 1e-9:
        raise ValueError(f"stop_deg - start_deg must be within [-360, 360] degrees, got {span:g} "
                         "(use helical_aperture for more than one turn)")
    if n > 1 and span == 0:
        raise ValueError(f"stop_deg must differ from start_deg for n > 1 stops, both are {start:g}")
    if np.isclose(abs(span), 360.0):
        return start + span * np.arange(n) / n
    return start + span * (np.arange(n) / (n - 1) if n > 1 else np.zeros(1))


def helical_aperture(
    n_per_turn: int,
    turns: float,
    radius_m: float,
    pitch_m: float,
    *,
    center_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    height_m: float = 0.0,
    start_deg: float = 0.0,
    mode: str = "turntable",
    tx_offset_m: tuple[float, float, float] = TX_OFFSET_M,
    rx_offset_m: tuple[float, float, float] | None = None,
    rx_offsets_m: np.ndarray | None = None,
) -> Aperture:
    """A circular aperture whose height rises by ``pitch_m`` per turn.

    Stop i (of ``round(n_per_turn * turns)``) is at angle ``start_deg + 360 i / n_per_turn``
    and height ``center_m[2] + height_m + pitch_m * i / n_per_turn``; ``mode``, the frames and
    the offsets are those of :func:`circular_aperture` (a turntable that turns while the rig,
    or the table, moves vertically).

    Parameters
    ----------
    n_per_turn : int
        Stops per full turn.
    turns : float
        Number of turns (> 0; fractional turns allowed).
    radius_m : float
        Distance from the axis, metres (> 0).
    pitch_m : float
        Height gained per turn, metres (negative: descending).
    center_m, height_m, start_deg, mode, tx_offset_m, rx_offset_m, rx_offsets_m
        As in :func:`circular_aperture`; ``height_m`` is the height of the first stop.

    Returns
    -------
    Aperture
        ``round(n_per_turn * turns) * k`` measurements, stop-major.

    Examples
    --------
    >>> import clsas
    >>> clsas.helical_aperture(36, 2, 0.8, 0.1).tx_positions.shape       # two turns, 10 cm per turn
    (72, 3)
    """
    npt = v.positive_int("n_per_turn", n_per_turn)
    t = v.positive("turns", turns)
    pitch = v.finite("pitch_m", pitch_m)
    start = v.finite("start_deg", start_deg)
    r, c, h, sign, txo, rxo = _ring_args(radius_m, center_m, height_m, mode, tx_offset_m, rx_offset_m,
                                         rx_offsets_m)
    n = int(round(npt * t))
    if n < 1:
        raise ValueError(f"n_per_turn * turns must give at least one stop, got {npt} * {t:g}")
    frac = np.arange(n) / npt
    return _ring(np.deg2rad(sign * (start + 360.0 * frac)), r, h + pitch * frac, c, txo, rxo)


def aperture_from_csv(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    units: str = "m",
    tx_offset_m: tuple[float, float, float] | None = None,
    rx_offset_m: tuple[float, float, float] | None = None,
    rx_offsets_m: np.ndarray | None = None,
) -> Aperture:
    """Read an aperture from a CSV table of positions (a header row, then one row per position).

    Two layouts are accepted, recognised from the header:

    - ``tx_x, tx_y, tx_z, rx_x, rx_y, rx_z``: one measurement per row (several microphones of
      one ping are several rows). Optional ``x, y, z`` columns give the stage positions,
      otherwise the speaker position is used. The offsets must not be given.
    - ``x, y, z``: one stop per row (the carriage); the speaker is at ``x + tx_offset_m`` and
      each microphone at ``x + rx_offset_m`` (or each of ``rx_offsets_m``), offsets in the scene
      frame as for :func:`raster_aperture` (defaults ``(-0.02, 0, 0)`` and ``(0.02, 0, 0)``).

    Header names are matched without case and surrounding spaces; other columns are ignored;
    empty lines and lines starting with ``#`` are skipped; fields are comma-separated.

    Parameters
    ----------
    path : str or Path
        The CSV file (UTF-8, a byte-order mark is allowed).
    columns : mapping, optional
        Header names for the standard ones, e.g. ``{"x": "X [mm]", "y": "Y [mm]", "z": "Z"}``.
    units : {"m", "mm"}
        Unit of the positions in the file. The offsets are always in metres.
    tx_offset_m, rx_offset_m, rx_offsets_m
        Speaker and microphone offsets for the ``x, y, z`` layout, metres.

    Returns
    -------
    Aperture
        Positions in metres, in the order of the rows.

    Raises
    ------
    ValueError
        Naming the file, the line and the column: a missing column, a field that is not a
        number, NaN or Inf, a short row, no data rows.

    Examples
    --------
    >>> from pathlib import Path
    >>> import clsas
    >>> _ = Path("stops.csv").write_text("x,y,z\\n0,0,0\\n0.01,0,0\\n0.02,0,0\\n")
    >>> clsas.aperture_from_csv("stops.csv").tx_positions.shape
    (3, 3)
    """
    v.choice("units", units, ("m", "mm"))
    scale = 1e-3 if units == "mm" else 1.0
    names = _column_names(columns)
    path = Path(path)
    rows = list(_csv_rows(path))
    col, keys, bistatic, has_stage = _csv_layout(path, rows, names)
    table = _csv_table(path, rows, col, keys, names) * scale
    if bistatic:
        if tx_offset_m is not None or rx_offset_m is not None or rx_offsets_m is not None:
            raise ValueError(f"{path} gives speaker and microphone positions (tx_x..rx_z): "
                             "tx_offset_m, rx_offset_m and rx_offsets_m apply only to the x,y,z layout")
        tx, rx = table[:, 0:3], table[:, 3:6]
        return Aperture(tx, rx, table[:, 6:9] if has_stage else tx)
    txo = v.array("tx_offset_m", TX_OFFSET_M if tx_offset_m is None else tx_offset_m, shape=(3,))
    rxo = mic_offsets(rx_offset_m, rx_offsets_m)
    return aperture_from_stops(table, table + txo, table[:, None, :] + rxo[None])


def _column_names(columns: Mapping[str, str] | None) -> dict[str, str]:
    """The header name of each standard column: its own name, or the one ``columns`` gives."""
    names = {k: k for k in BISTATIC_COLUMNS + STAGE_COLUMNS}
    for key, header in (columns or {}).items():
        if key not in names:
            raise ValueError(f"columns has an unknown key {key!r}; the keys are {', '.join(names)}")
        if not isinstance(header, str):
            raise TypeError(f"columns[{key!r}] must be a header name (str), got {header!r}")
        names[key] = header
    return names


def _csv_layout(path: Path, rows: list, names: dict[str, str]):
    """From the header row: (field index of each column or None, the columns to read in order,
    whether the layout is bistatic, whether stage columns are there)."""
    if not rows:
        raise ValueError(f"{path}: no header row (the file is empty)")
    hline, header = rows[0]
    where = {h.strip().lower(): i for i, h in enumerate(header)}
    col = {k: where.get(h.strip().lower()) for k, h in names.items()}
    bistatic = any(col[k] is not None for k in BISTATIC_COLUMNS)
    need = BISTATIC_COLUMNS if bistatic else STAGE_COLUMNS
    missing = [names[k] for k in need if col[k] is None]
    if missing:
        raise ValueError(
            f"{path}, line {hline}: missing column(s) {', '.join(missing)} (the header has "
            f"{', '.join(h.strip() for h in header)}); expected tx_x,tx_y,tx_z,rx_x,rx_y,rx_z (one "
            "measurement per row) or x,y,z (one stop per row, with tx_offset_m and rx_offset_m)")
    has_stage = all(col[k] is not None for k in STAGE_COLUMNS)
    keys = need + (STAGE_COLUMNS if bistatic and has_stage else ())
    if len(rows) < 2:
        raise ValueError(f"{path}: no data rows after the header on line {hline}")
    return col, keys, bistatic, has_stage


def _csv_table(path: Path, rows: list, col: dict, keys: tuple[str, ...], names: dict[str, str]) -> np.ndarray:
    """(n_rows, len(keys)) the numbers of the data rows, in the file's unit."""
    table = np.empty((len(rows) - 1, len(keys)))
    for r, (line, row) in enumerate(rows[1:]):
        for j, key in enumerate(keys):
            i = col[key]
            if i >= len(row):
                raise ValueError(f"{path}, line {line}: {len(row)} field(s), but column {names[key]!r} "
                                 f"is field {i + 1} of the header")
            table[r, j] = _number(path, line, names[key], row[i])
    return table


def _csv_rows(path: Path):
    """(line number, fields) of the non-empty, non-comment rows of a CSV file."""
    text = path.read_text(encoding="utf-8-sig")
    reader = csv.reader(io.StringIO(text))
    start = 1
    for row in reader:
        line, start = start, reader.line_num + 1
        if not row or all(not f.strip() for f in row) or row[0].lstrip().startswith("#"):
            continue
        yield line, row


def _number(path: Path, line: int, column: str, text: str) -> float:
    return v.cell_number(text, f"{path}, line {line}, column {column!r}")

