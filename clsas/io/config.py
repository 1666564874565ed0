"""One configuration layer for scene files (``clsas simulate``) and rig files (``clsas acquire``).

Both kinds are TOML. This module reads the text, refuses unknown tables and keys (with a
suggestion when one is close), checks every value's type and range, and builds the pieces the
two kinds share: the chirp, the reflectors and walls, and the imaging grid. Every error is a
:class:`ConfigError` (a ``ValueError``) whose message names the file, the table and the key,
e.g. ``scene.toml: [aperture] unknown key 'n_x' (did you mean 'nx'?)``.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..physics.geometry import Scene, VoxelGrid, Wall
from ..physics.signals import lfm_chirp

__all__ = [
    "ConfigError", "Table", "SCENE_TABLES", "RIG_TABLES", "read_text", "read_toml", "kind_of", "suggestion",
    "chirp_table", "points_table", "walls_table", "grid_table", "preprocess_table", "build_scene",
    "CHIRP_KEYS", "POINT_KEYS", "WALL_KEYS", "GRID_KEYS", "BEAM_KEYS", "beams_table",
]

T = TypeVar("T")

#: top-level tables of a scene file and of a rig file
SCENE_TABLES = ("chirp", "aperture", "air", "noise", "points", "walls", "grid", "preprocess", "beams")
RIG_TABLES = ("stage", "scan", "aperture", "audio", "recorder", "chirp", "air", "grid", "simulate", "preprocess",
              "beams")
BEAM_KEYS = ("speaker", "microphone", "boresight", "normal", "axis_point_m", "axis_dir")
CHIRP_KEYS = ("f_start_hz", "f_stop_hz", "duration_s", "taper")
POINT_KEYS = ("position_m", "amplitude", "visible")
WALL_KEYS = ("point_m", "normal", "reflectivity")
GRID_KEYS = ("x_m", "y_m", "z_m", "spacing_m")

_REQUIRED: Any = object()
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_RIG_ONLY = ("stage", "scan", "audio", "recorder", "simulate")
_SCENE_ONLY = ("points", "walls", "noise")


class ConfigError(ValueError):
    """A scene or rig configuration that cannot be used; the message names file, table and key."""


def suggestion(name: str, options: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``options`` to ``name``, or an empty string."""
    close = difflib.get_close_matches(name, list(options), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _show(value: Any) -> str:
    """A value as the user wrote it (no ``np.float64(...)``)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list) and any(isinstance(x, dict) for x in value):
        return "an array of tables ([[...]])"
    return str(value)


class Table:
    """One table of a configuration file, checked against its known keys.

    Parameters
    ----------
    data : dict
        The table as ``tomllib`` read it.
    source : str
        The file (or a description of the text) the table came from, prefixed to every error.
    label : str
        How the table is named in messages, e.g. ``"[aperture]"`` or ``"[[points]] #2"``.
    keys : iterable of str
        The keys the table may hold; any other key is refused with a suggestion.
    prefix : str, optional
        How a key is named in messages about its value: ``prefix + key``, e.g. ``"audio.repeats"``
        or ``"points[2].position_m"``; default: the label without brackets and a dot.
    hints : dict, optional
        ``{key: text}``: what to say instead of a suggestion when ``key`` is found here (a key
        that belongs in another table).
    """

    def __init__(self, data: Any, source: str, label: str, keys: Iterable[str], prefix: str | None = None,
                 hints: dict[str, str] | None = None) -> None:
        self.source, self.label, self.keys = source, label, tuple(keys)
        self.prefix = _dotted(label) + "." if prefix is None else prefix
        if not isinstance(data, dict):
            raise self.error(f"{label} must be a table, got {_show(data)}")
        self.data = data
        for key in data:
            if key in (hints or {}):
                raise self.error(f"{label} unknown key {key!r}: {hints[key]}")
            if key not in self.keys:
                raise self.error(f"{label} unknown key {key!r}{suggestion(key, self.keys)}; "
                                 f"known keys: {', '.join(self.keys)}")

    def error(self, message: str) -> ConfigError:
        """A :class:`ConfigError` for ``message``, prefixed with the file."""
        return ConfigError(f"{self.source}: {message}")

    def name(self, key: str) -> str:
        """``table.key``, the way messages about a value name its key."""
        return f"{self.prefix}{key}"

    def __contains__(self, key: str) -> bool:
        return key in self.data

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _REQUIRED:
            raise self.error(f"{self.label} has no {key!r}: {self.name(key)} is required")
        return default

    def _bad(self, key: str, want: str, value: Any) -> ConfigError:
        return self.error(f"{self.name(key)} must be {want}, got {_show(value)}")

    def number(self, key: str, default: Any = _REQUIRED, *, low: float | None = None,
               high: float | None = None, above: float | None = None) -> Any:
        """A finite number (int or float, not a string or boolean) within the given bounds:
        ``low <= x <= high`` and ``x > above``. A default is returned unchecked."""
        value = self._get(key, default)
        if key not in self.data:
            return value
        return self._check_number(key, value, low, high, above)

    def _check_number(self, key: str, value: Any, low, high, above) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self._bad(key, "a number", value)
        if not math.isfinite(value):
            raise self._bad(key, "finite", value)
        if above is not None and not value > above:
            raise self._bad(key, f"> {above:g}", value)
        if low is not None and value < low:
            raise self._bad(key, f">= {low:g}", value)
        if high is not None and value > high:
            raise self._bad(key, f"<= {high:g}", value)
        return float(value)

    def integer(self, key: str, default: Any = _REQUIRED, *, low: int | None = None,
                high: int | None = None) -> Any:
        """An integer (not a float or boolean) with ``low <= n <= high``."""
        value = self._get(key, default)
        if key not in self.data:
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            raise self._bad(key, "an integer", value)
        if low is not None and value < low:
            raise self._bad(key, f">= {low}", value)
        if high is not None and value > high:
            raise self._bad(key, f"<= {high}", value)
        return value

    def boolean(self, key: str, default: Any = _REQUIRED) -> Any:
        """``true`` or ``false``."""
        value = self._get(key, default)
        if key in self.data and not isinstance(value, bool):
            raise self._bad(key, "true or false", value)
        return value

    def string(self, key: str, default: Any = _REQUIRED, *, choices: tuple[str, ...] | None = None) -> Any:
        """A string, one of ``choices`` if given."""
        value = self._get(key, default)
        if key not in self.data:
            return value
        if not isinstance(value, str):
            raise self._bad(key, "a string", value)
        if choices is not None and value not in choices:
            raise self.error(f"{self.name(key)} must be one of {', '.join(map(repr, choices))}, got "
                             f"{value!r}{suggestion(value, choices)}")
        return value

    def vector(self, key: str, default: Any = _REQUIRED, *, shape: tuple[int | None, ...] = (3,)) -> Any:
        """An array of finite numbers with the given shape (``None``: any length)."""
        value = self._get(key, default)
        if key not in self.data:
            return value if value is None else np.asarray(value, float)
        want = "[" + ", ".join("n" if s is None else str(s) for s in shape) + "]"
        text = f"an array of numbers of shape {want}" if len(shape) > 1 else (
            "a list of numbers" if shape[0] is None else f"a list of {shape[0]} numbers")
        flat = np.asarray(value, dtype=object).ravel() if _nested_lists(value) else None
        if flat is None or any(isinstance(x, bool) or not isinstance(x, int | float) for x in flat):
            raise self._bad(key, text, value)
        arr = np.asarray(value, float)
        if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape, strict=False)):
            raise self._bad(key, text, value)
        if arr.size == 0 or not np.all(np.isfinite(arr)):
            raise self._bad(key, f"{text} (finite, not empty)", value)
        return arr

    def raw(self, key: str, default: Any = None) -> Any:
        """The value as read, unchecked."""
        return self._get(key, default)

    def build(self, func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Call ``func`` and turn its ``ValueError`` or ``TypeError`` into a ``ConfigError``
        that names this table."""
        try:
            return func(*args, **kwargs)
        except (ValueError, TypeError) as exc:
            raise self.error(f"{self.label} {exc}") from None


def _dotted(label: str) -> str:
    """``[aperture]`` -> ``aperture``; ``[simulate] points`` -> ``simulate.points``."""
    return label.replace("[", "").replace("]", "").replace(" ", ".")


def _nested_lists(value: Any) -> bool:
    """True for a (possibly nested) rectangular list of scalars."""
    if not isinstance(value, list):
        return False
    try:
        arr = np.asarray(value, dtype=object)
    except ValueError:
        return False
    return all(not isinstance(x, list | dict) for x in arr.ravel())


def kind_of(cfg: dict) -> str:
    """``"rig"``, ``"scene"`` or ``"other"`` (e.g. an ``import.toml``), from the top-level tables."""
    if any(t in cfg for t in ("stage", "scan", "audio", "recorder")):
        return "rig"
    if any(t in cfg for t in _SCENE_ONLY):
        return "scene"
    if "simulate" in cfg:
        return "rig"
    if any(t in cfg for t in ("recording", "delay")):
        return "other"
    return "scene"


def read_text(path: Path, kind: str) -> str:
    """The text of the ``kind`` (``"scene"`` or ``"rig"``) file at ``path``, which exists;
    a folder, an HDF5 file or another binary file is refused, saying what it is."""
    if path.is_dir():
        raise ConfigError(f"{path} is a folder, not a {kind} file (TOML)")
    data = path.read_bytes()
    if data.startswith(_HDF5_SIGNATURE):
        raise ConfigError(f"{path} is an HDF5 file (a dataset or an image), not a {kind} file (TOML): "
                          "`clsas reconstruct` reads datasets")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is not a text (TOML) {kind} file") from None


def read_toml(text: str, source: str, kind: str, keys: dict[str, tuple[str, ...]] | None = None) -> dict:
    """Parse ``text`` as a ``kind`` (``"scene"`` or ``"rig"``) configuration.

    Refuses invalid TOML, a file of another kind (saying which command reads it), and
    unknown top-level tables or keys (with a suggestion). ``keys`` ({table: its keys}) lets a
    key written outside its table be told where it belongs.
    """
    if not isinstance(text, str):
        raise TypeError(f"a {kind} configuration must be TOML text (str), got {type(text).__name__}")
    try:
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source} is not valid TOML: {exc}") from None
    found = kind_of(cfg)
    if kind == "scene" and found == "rig":
        tables = ", ".join(f"[{t}]" for t in _RIG_ONLY if t in cfg)
        raise ConfigError(f"{source} is a rig configuration ({tables}), not a scene file: scan it with "
                          "`clsas acquire RIG.toml OUT.h5` (add --simulate to hear its [simulate] scene), "
                          "or give `clsas simulate` a scene file (docs/guide/command-line.md: 'A scene file')")
    if kind == "rig" and found == "scene":
        tables = ", ".join(f"[[{t}]]" if t in ("points", "walls") else f"[{t}]" for t in _SCENE_ONLY if t in cfg)
        raise ConfigError(f"{source} is a scene configuration ({tables}), not a rig file: simulate it with "
                          "`clsas simulate SCENE.toml OUT.h5`, or write a rig file with "
                          "`clsas acquire --sample-config > rig.toml`")
    if found == "other":
        raise ConfigError(f"{source} holds import settings ([recording], [delay]) for `clsas import`, "
                          f"not a {kind} file")
    known = SCENE_TABLES if kind == "scene" else RIG_TABLES
    for name, value in cfg.items():
        if name in known:
            continue
        if not isinstance(value, dict | list):
            home = [t for t, k in (keys or {}).items() if name in k]
            if home:
                raise ConfigError(f"{source}: key {name!r} is outside any table: put it under [{home[0]}]")
        what = "table" if isinstance(value, dict | list) else "key"
        raise ConfigError(f"{source}: unknown {what} {name!r}{suggestion(name, known)} in a {kind} "
                          f"configuration; known tables: {', '.join(known)}")
    return cfg


def chirp_table(tab: Table, fs_hz: float) -> tuple[dict, np.ndarray]:
    """The ``[chirp]`` parameters (``f_start_hz``, ``f_stop_hz``, ``duration_s``, ``taper``) and
    the unit-peak waveform sampled at ``fs_hz``."""
    chirp = {
        "f_start_hz": tab.number("f_start_hz", 20e3, above=0),
        "f_stop_hz": tab.number("f_stop_hz", 30e3, above=0),
        "duration_s": tab.number("duration_s", 5e-3, above=0),
        "taper": tab.number("taper", 0.1, low=0, high=1),
    }
    chirp = {k: float(x) for k, x in chirp.items()}
    wave = tab.build(lfm_chirp, chirp["f_start_hz"], chirp["f_stop_hz"], chirp["duration_s"], fs_hz, chirp["taper"])
    return chirp, wave


def _array_of_tables(value: Any, source: str, label: str) -> list:
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list):
        raise ConfigError(f"{source}: {label} must be a list of tables, got {_show(value)}")
    return value


def points_table(value: Any, source: str, label: str = "[[points]]") -> list[dict]:
    """Reflectors from an array of tables (``position_m``, required; ``amplitude``; ``visible``).

    Returns a list of ``{"position_m": (3,) array, "amplitude": float, "visible": bool}``.
    """
    out = []
    for i, p in enumerate(_array_of_tables(value, source, label), 1):
        tab = Table(p, source, f"{label} #{i}", POINT_KEYS, f"{_dotted(label)}[{i}].")
        out.append({"position_m": tab.vector("position_m"),
                    "amplitude": float(tab.number("amplitude", 1.0)),
                    "visible": tab.boolean("visible", True)})
    return out


def walls_table(value: Any, source: str, label: str = "[[walls]]") -> list[Wall]:
    """Walls from an array of tables (``point_m`` and ``normal``, required; ``reflectivity``)."""
    out = []
    for i, w in enumerate(_array_of_tables(value, source, label), 1):
        tab = Table(w, source, f"{label} #{i}", WALL_KEYS, f"{_dotted(label)}[{i}].")
        point, normal = tab.vector("point_m"), tab.vector("normal")
        refl = tab.number("reflectivity", 0.9, low=-1, high=1)
        out.append(tab.build(Wall, tuple(point), tuple(normal), float(refl)))
    return out


def build_scene(points: list[dict], walls: list[Wall], temperature_c: float, humidity_pct: float,
                wall_echo: bool = False) -> Scene:
    """A :class:`clsas.Scene` from checked points and walls."""
    return Scene(np.array([p["position_m"] for p in points], float).reshape(-1, 3),
                 np.array([p["amplitude"] for p in points], float),
                 np.array([p["visible"] for p in points], bool), tuple(walls),
                 temperature_c=temperature_c, humidity_pct=humidity_pct, wall_echo=wall_echo)


def grid_table(cfg: dict, source: str) -> VoxelGrid | None:
    """The ``[grid]`` table (``x_m``, ``y_m``, ``z_m`` as ``[lo, hi]``; ``spacing_m``), if any."""
    if "grid" not in cfg:
        return None
    tab = Table(cfg["grid"], source, "[grid]", GRID_KEYS)
    bounds = []
    for key in ("x_m", "y_m", "z_m"):
        lo, hi = tab.vector(key, shape=(2,))
        if hi < lo:
            raise tab.error(f"{tab.name(key)} must be [low, high], got {_show([float(lo), float(hi)])}")
        bounds.append((float(lo), float(hi)))
    spacing = tab.raw("spacing_m", 0.01)
    if isinstance(spacing, list):
        spacing = tab.vector("spacing_m", shape=(3,))
        if np.any(spacing <= 0):
            raise tab.error(f"{tab.name('spacing_m')} must be > 0, got {_show(spacing.tolist())}")
        spacing = tuple(spacing)
    else:
        spacing = tab.number("spacing_m", 0.01, above=0)
    return tab.build(VoxelGrid.from_bounds, *bounds, spacing)


#: the keys of a ``[preprocess]`` table, one per step of :func:`clsas.preprocess.apply`
PREPROCESS_KEYS = ("group_delay_s", "group_delay_samples", "direct_clock", "dc", "bandpass", "background",
                   "common", "blank_direct")


def preprocess_table(cfg: dict, source: str) -> dict:
    """The ``[preprocess]`` table, passed through (``clsas.preprocess.from_table`` checks its
    values); only its keys are checked here."""
    if "preprocess" not in cfg:
        return {}
    return dict(Table(cfg["preprocess"], source, "[preprocess]", PREPROCESS_KEYS).data)


def beams_table(cfg: dict, source: str, tx_positions: np.ndarray, rx_positions: np.ndarray):
    """The ``[beams]`` table as :class:`clsas.physics.beam.Beams` for these positions, or None (absent:
    omnidirectional). Keys: ``speaker`` and ``microphone`` (inline tables such as
    ``{ model = "piston", diameter_m = 0.006 }``; models omni, piston, cone, table; default
    omni), ``boresight`` (``"normal"``: every transducer faces ``normal``, default
    ``[0, 0, 1]``; ``"axis"``: toward the rotation axis through ``axis_point_m`` along
    ``axis_dir``; or a fixed ``[x, y, z]``)."""
    from ..physics.beam import Beams, axis_boresights, beam_from_spec, planar_boresights

    if "beams" not in cfg:
        return None
    tab = Table(cfg["beams"], source, "[beams]", BEAM_KEYS)
    specs = {}
    for key in ("speaker", "microphone"):
        raw = tab.raw(key, {"model": "omni"})
        specs[key] = tab.build(beam_from_spec, raw, f"beams.{key}")
    n = len(tx_positions)
    how = tab.raw("boresight", "normal")
    if isinstance(how, str):
        how = tab.string("boresight", "normal", choices=("normal", "axis"))
        if how == "normal":
            tx_dir = rx_dir = tab.build(planar_boresights, n, tab.vector("normal", (0.0, 0.0, 1.0)))
        else:
            point, axis = tab.vector("axis_point_m", (0.0, 0.0, 0.0)), tab.vector("axis_dir", (0.0, 0.0, 1.0))
            tx_dir = tab.build(axis_boresights, tx_positions, point, axis)
            rx_dir = tab.build(axis_boresights, rx_positions, point, axis)
    else:
        tx_dir = rx_dir = tab.vector("boresight")
    return tab.build(Beams, specs["speaker"], specs["microphone"], tx_dir, rx_dir, n)
