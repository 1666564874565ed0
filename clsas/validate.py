"""Input checks shared by the public functions across the packages: every error names the parameter."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _show(value: Any) -> str:
    """A value as a user wrote it: ``-0.01``, not ``np.float64(-0.01)``."""
    if isinstance(value, np.generic):
        value = value.item()
    return repr(value)


def positive(name: str, value: Any) -> float:
    """Return ``value`` as a finite float > 0, or raise ``ValueError`` naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {_show(value)}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {_show(value)}")
    return v


def finite(name: str, value: Any) -> float:
    """Return ``value`` as a finite float, or raise naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {_show(value)}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {_show(value)}")
    return v


def non_negative(name: str, value: Any) -> float:
    v = finite(name, value)
    if v < 0:
        raise ValueError(f"{name} must be >= 0, got {_show(value)}")
    return v


def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name} must be an integer, got {_show(value)}")
    if value <= 0:
        raise ValueError(f"{name} must be >= 1, got {_show(value)}")
    return int(value)


def array(
    name: str,
    value: Any,
    *,
    ndim: int | None = None,
    shape: tuple[int | None, ...] | None = None,
    dtype: Any = np.float64,
    allow_complex: bool = False,
) -> np.ndarray:
    """Convert ``value`` to an array and check dimensions, shape and finiteness."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be array-like, got {type(value).__name__}") from exc
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
    ):
        raise TypeError(f"{name} must be numeric, got dtype {arr.dtype}")
    if np.iscomplexobj(arr) and not allow_complex:
        raise TypeError(f"{name} must be real, got complex dtype {arr.dtype}")
    if dtype is not None:
        if np.iscomplexobj(arr):
            dtype = np.result_type(dtype, np.complex64)
        arr = arr.astype(dtype, copy=False)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    if shape is not None:
        ok = arr.ndim == len(shape) and all(
            s is None or s == a for s, a in zip(shape, arr.shape, strict=False)
        )
        if not ok:
            want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} must not be empty, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name} contains {bad} NaN or Inf value(s)")
    return arr


def choice(name: str, value: Any, options: tuple[str, ...]) -> str:
    if value not in options:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, options))}, got {_show(value)}")
    return value


def speeds(name: str, value: Any, n: int) -> float | np.ndarray:
    """A speed of sound: a float > 0, or an (n,) array of them (one per measurement)."""
    if np.ndim(value) == 0:
        return positive(name, value)
    arr = array(name, value, shape=(n,))
    if np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0, got min {arr.min():g}")
    return arr


def install_hint(extra: str) -> str:
    """How to install an optional extra: from the source checkout when clsas runs from one
    (``pip install 'clsas[rig]'`` would look for clsas on PyPI), else the package's name."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    if (root / "pyproject.toml").is_file():
        return f"pip install -e '{root}[{extra}]'"
    return f"pip install 'clsas[{extra}]'"


def cell_number(text: str, where: str) -> float:
    """A table cell read as a finite number; ``where`` ("file, line L, column 'c'") leads the
    error (an empty cell, not a number, NaN or infinite)."""
    s = text.strip()
    if not s:
        raise ValueError(f"{where}: the field is empty")
    try:
        x = float(s)
    except ValueError:
        raise ValueError(f"{where}: {s!r} is not a number") from None
    if not math.isfinite(x):
        raise ValueError(f"{where}: {s!r} is NaN or infinite")
    return x


def unit_rows(name: str, value: Any, n: int) -> np.ndarray:
    """(n, 3) unit vectors from one (3,) vector or (n, 3) rows, refusing a zero row (naming it)."""
    arr = np.asarray(value, float)
    if arr.shape == (3,):
        arr = np.broadcast_to(arr, (n, 3))
    arr = array(name, arr, shape=(n, 3))
    norm = np.linalg.norm(arr, axis=1)
    if np.any(norm == 0):
        raise ValueError(f"{name}: a direction must not be the zero vector (row {int(np.argmin(norm))})")
    return arr / norm[:, None]


#: below these an audio or ultrasound rate or band is most likely given in kHz, a duration in ms
LEAST_FS_HZ = 1000.0
LEAST_BAND_HZ = 100.0


def sampling_rate(name: str, fs_hz) -> float:
    """A positive sampling rate, Hz; one under :data:`LEAST_FS_HZ` is logged as a likely kHz value
    (``96`` for 96 kHz), since the recordings' times and delays are then 1000x too long."""
    fs = positive(name, fs_hz)
    if fs < LEAST_FS_HZ:
        import logging

        logging.getLogger("clsas").warning("%s=%g Hz: a sampling rate in kHz? clsas takes Hz (96 kHz is %s=96e3); "
                                           "every time and delay is otherwise 1000x too long", name, fs, name)
    return fs

