"""Shared pieces of the importers: number tables in text files, WAV files, TOML settings,
padding to a common length and the empty-scene background.

Every error names the file (and, for text files, the line and the column).
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..types.dataset import Dataset

log = logging.getLogger("clsas.io")

_DELIMITERS = (",", ";", "\t")


def is_number(cell: str) -> bool:
    """Whether a text cell reads as a number (``nan`` and ``inf`` included)."""
    try:
        float(cell)
    except ValueError:
        return False
    return True


def sniff_delimiter(line: str) -> str | None:
    """The first of ``,``, ``;``, tab found in ``line``; ``None`` (whitespace) otherwise."""
    for d in _DELIMITERS:
        if d in line:
            return d
    return None


def split_cells(line: str, delimiter: str | None) -> list[str]:
    return [c.strip() for c in (line.split(delimiter) if delimiter else line.split())]


def _content_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, text) of the lines that are neither blank nor ``#`` comments."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a text (CSV) file") from None
    return [(i + 1, s) for i, s in enumerate(text.splitlines()) if s.strip() and not s.lstrip().startswith("#")]


def read_numbers(path: Path, *, header: bool | None = None) -> tuple[list[str] | None, np.ndarray]:
    """The numbers of a delimited text file (CSV), and its header's column names.

    Parameters
    ----------
    path : Path
    header : bool, optional
        Whether the first line names the columns; ``None``: yes if any of its cells is not a
        number.

    Returns
    -------
    names : list of str or None
        The header's cells (``None`` without a header).
    values : (n_rows, n_columns) float64 array

    Raises
    ------
    FileNotFoundError
        No file at ``path``.
    ValueError
        A cell that is not a number, a row with another number of cells, a NaN or Inf, or no
        rows: the message names the file, the line and the column.
    """
    if not path.is_file():
        raise FileNotFoundError(f"no file {path}")
    lines = _content_lines(path)
    if not lines:
        raise ValueError(f"{path} holds no numbers (empty file)")
    delimiter = sniff_delimiter(lines[0][1])
    first = split_cells(lines[0][1], delimiter)
    if header is None:
        header = not all(is_number(c) for c in first)
    names = first if header else None
    body = lines[1:] if header else lines
    if not body:
        raise ValueError(f"{path} has a header but no rows of numbers")
    try:
        values = np.loadtxt([s for _, s in body], delimiter=delimiter, ndmin=2, dtype=float, comments=None)
    except ValueError:
        _raise_bad_cell(path, body, delimiter, names)
        raise  # not reached: _raise_bad_cell found the cell or raised its own error
    if names is not None and len(names) != values.shape[1]:
        raise ValueError(f"{path}: the header names {len(names)} columns, the rows have {values.shape[1]} cells")
    if not np.all(np.isfinite(values)):
        r, c = np.argwhere(~np.isfinite(values))[0]
        raise ValueError(f"{path}, line {body[r][0]}, {_column(names, c)}: {values[r, c]} is not a finite number")
    return names, values


def _column(names: Sequence[str] | None, c: int) -> str:
    return f"column {c + 1}" + (f" ({names[c]!r})" if names is not None and c < len(names) else "")


def _raise_bad_cell(path: Path, body: list[tuple[int, str]], delimiter: str | None,
                    names: Sequence[str] | None) -> None:
    """Find the first row that numpy could not read and say why (file, line, column)."""
    n_cols = None
    for lineno, text in body:
        cells = split_cells(text, delimiter)
        if n_cols is None:
            n_cols = len(cells)
        if len(cells) != n_cols:
            raise ValueError(f"{path}, line {lineno}: {len(cells)} cells, earlier rows have {n_cols}")
        for c, cell in enumerate(cells):
            if not is_number(cell):
                what = "an empty cell" if cell == "" else f"{cell!r} is not a number"
                raise ValueError(f"{path}, line {lineno}, {_column(names, c)}: {what}")
    raise ValueError(f"{path} could not be read as a table of numbers")


def read_wav(path: Path) -> tuple[float, np.ndarray]:
    """Sample rate (Hz) and samples, ``(n_samples, n_channels)`` float64, of a WAV file.

    Integer samples are scaled to full scale 1 (int16 / 2**15, int32 / 2**31, 8-bit unsigned
    centred on 128); float samples are kept as they are.
    """
    import warnings

    import scipy.io.wavfile

    if not path.is_file():
        raise FileNotFoundError(f"no file {path}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", scipy.io.wavfile.WavFileWarning)
        try:
            rate, data = scipy.io.wavfile.read(path)
        except (ValueError, EOFError, OSError) as exc:
            raise ValueError(f"{path} is not a readable WAV file: {exc}") from None
    for w in caught:
        log.warning("%s: %s", path, w.message)
    data = np.asarray(data)
    if data.dtype == np.uint8:
        x = (data.astype(np.float64) - 128.0) / 128.0
    elif np.issubdtype(data.dtype, np.integer):
        x = data.astype(np.float64) / float(2 ** (8 * data.dtype.itemsize - 1))
    else:
        x = data.astype(np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.shape[0] == 0:
        raise ValueError(f"{path} holds no samples")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{path} holds NaN or Inf samples")
    return float(rate), x


_TYPE_NAMES = {float: "a number", int: "an integer", str: "a string"}


def read_settings(path: Path, schema: dict[str, dict[str, type]]) -> tuple[dict, str]:
    """A TOML settings file checked against ``schema`` ({table: {key: type}}).

    Unknown tables and keys are refused, naming the file, the table and the key; so is a
    value of the wrong type. Returns the tables (each a dict, absent ones empty) and the text.
    """
    try:
        text = path.read_text(encoding="utf-8")
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path} is not valid TOML: {exc}") from None
    tables = ", ".join(f"[{t}]" for t in schema)
    out: dict[str, dict] = {t: {} for t in schema}
    for name, table in cfg.items():
        if name not in schema:
            raise ValueError(f"{path}: unknown table or key {name!r} (known tables: {tables})")
        if not isinstance(table, dict):
            raise ValueError(f"{path}: {name!r} must be a table [{name}], got a value")
        for key, value in table.items():
            want = schema[name].get(key)
            if want is None:
                known = ", ".join(schema[name])
                raise ValueError(f"{path}: unknown key {key!r} in table [{name}] (known: {known})")
            ok = (isinstance(value, int | float) and not isinstance(value, bool)) if want is float else (
                isinstance(value, want) and not isinstance(value, bool))
            if not ok or (want is float and not math.isfinite(value)):
                raise ValueError(f"{path}: [{name}] {key} must be {_TYPE_NAMES[want]}, got {value!r}")
            out[name][key] = float(value) if want is float else value
    return out, text


def stack_padded(recordings: Sequence[np.ndarray], names: Sequence[str], where: str) -> np.ndarray:
    """Stack 1-D recordings as rows, padding the shorter ones with zeros at the end (and
    saying so in a log warning that names the shortest and longest)."""
    lengths = np.array([len(r) for r in recordings])
    n = int(lengths.max())
    if np.any(lengths != n):
        short = int(np.argmin(lengths))
        log.warning("%s: recordings have different lengths (%d to %d samples; shortest %s): "
                    "%d padded with zeros to %d samples", where, lengths.min(), n, names[short],
                    int(np.sum(lengths != n)), n)
    out = np.zeros((len(recordings), n))
    for i, r in enumerate(recordings):
        out[i, : len(r)] = r
    return out


def attach_background(ds: Dataset, bg: Dataset, source: str, bg_source: str) -> np.ndarray:
    """The background's recordings, checked against the scan's: same number of measurements
    (aligned stop by stop), same length and sample rate. Raises ``ValueError`` naming both."""
    if bg.n_meas != ds.n_meas:
        raise ValueError(f"background {bg_source} has {bg.n_meas} measurements, the scan {source} has "
                         f"{ds.n_meas}: the empty-scene scan must have the same stops, in the same order")
    if bg.n_samples != ds.n_samples:
        raise ValueError(f"background {bg_source} has {bg.n_samples} samples per recording, the scan "
                         f"{source} has {ds.n_samples}")
    if not math.isclose(bg.fs_hz, ds.fs_hz, rel_tol=1e-9):
        raise ValueError(f"background {bg_source} is sampled at {bg.fs_hz:g} Hz, the scan {source} at "
                         f"{ds.fs_hz:g} Hz")
    moved = max(float(np.max(np.abs(bg.tx_positions - ds.tx_positions))),
                float(np.max(np.abs(bg.rx_positions - ds.rx_positions))))
    if moved > 1e-3:
        log.warning("background %s: its positions differ from the scan's by up to %.1f mm", bg_source,
                    moved * 1e3)
    return bg.signals
