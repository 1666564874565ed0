"""Scene configurations (TOML) and the paper's two demo scenes.

A configuration holds the chirp, the aperture, the air, the reflectors and walls, the noise
and the imaging grid; ``clsas simulate`` reads it and stores it in the dataset, so that
``clsas reconstruct`` finds the grid again. Parsing and checking is :mod:`clsas.io.config`'s:
unknown tables and keys are refused, and errors name the file, the table and the key.
"""

from __future__ import annotations

import logging
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from ..io import config as c
from ..physics.geometry import Aperture, Scene, VoxelGrid, Wall, raster_aperture

__all__ = ["SceneConfig", "load_config", "parse_config", "mannequin_points", "demo_configs", "stored_grid_and_truth",
           "stored_scene"]

log = logging.getLogger(__name__)
_STORED = "the dataset's stored configuration"

APERTURE_KEYS = ("nx", "ny", "width_m", "height_m", "center_m", "tx_offset_m", "rx_offset_m", "pattern")
AIR_KEYS = ("temperature_c", "humidity_pct", "wall_echo")
NOISE_KEYS = ("snr_db", "seed")


@dataclass
class SceneConfig:
    """A parsed scene file; ``text`` is stored verbatim in the dataset."""

    scene: Scene
    aperture: Aperture
    waveform: np.ndarray
    fs_hz: float
    chirp: dict
    grid: VoxelGrid | None
    snr_db: float | None
    seed: int
    text: str
    preprocess: dict = field(default_factory=dict)
    beams: Any = None  # clsas.physics.beam.Beams from [beams], None: omnidirectional


def parse_config(text: str, source: str = "scene configuration") -> SceneConfig:
    """Build the scene, aperture, waveform and grid described by TOML ``text``.

    Parameters
    ----------
    text : str
        The scene file's text.
    source : str
        What to call the text in error messages (the file name).

    Raises
    ------
    clsas.config.ConfigError
        (a ``ValueError``) naming the file, the table and the key: invalid TOML, a rig file,
        an unknown table or key, a value of the wrong type or out of range, or no reflector.
    """
    cfg = c.read_toml(text, source, "scene", {"chirp": (*c.CHIRP_KEYS, "fs_hz"), "aperture": APERTURE_KEYS,
                                               "air": AIR_KEYS, "noise": NOISE_KEYS, "grid": c.GRID_KEYS})
    ch = c.Table(cfg.get("chirp", {}), source, "[chirp]", (*c.CHIRP_KEYS, "fs_hz"))
    fs = float(ch.number("fs_hz", 96e3, above=0))
    chirp, waveform = c.chirp_table(ch, fs)
    ap = c.Table(cfg.get("aperture", {}), source, "[aperture]", APERTURE_KEYS)
    aperture = ap.build(
        raster_aperture, ap.integer("nx", 18, low=1), ap.integer("ny", 12, low=1),
        float(ap.number("width_m", 1.0, low=0)), float(ap.number("height_m", 1.0, low=0)),
        center_m=tuple(ap.vector("center_m", (0.0, 0.0, 0.0))),
        tx_offset_m=tuple(ap.vector("tx_offset_m", (-0.02, 0.0, 0.0))),
        rx_offset_m=tuple(ap.vector("rx_offset_m", (0.02, 0.0, 0.0))),
        pattern=ap.string("pattern", "serpentine", choices=("serpentine", "raster")),
    )
    air = c.Table(cfg.get("air", {}), source, "[air]", AIR_KEYS)
    if "points" not in cfg:
        raise c.ConfigError(f"{source}: the scene has no reflector: add one [[points]] table per reflector "
                            "with position_m = [x, y, z]")
    points = c.points_table(cfg["points"], source)
    if not points:
        raise c.ConfigError(f"{source}: [[points]] is empty: give at least one reflector")
    walls = c.walls_table(cfg.get("walls", []), source)
    scene = air.build(c.build_scene, points, walls, float(air.number("temperature_c", 20.0, low=-273.15)),
                      float(air.number("humidity_pct", 50.0, low=0, high=100)), air.boolean("wall_echo", False))
    grid = c.grid_table(cfg, source)
    noise = c.Table(cfg.get("noise", {}), source, "[noise]", NOISE_KEYS)
    snr = noise.number("snr_db", None)
    seed = noise.integer("seed", 0, low=0)
    beams = c.beams_table(cfg, source, aperture.tx_positions, aperture.rx_positions)
    return SceneConfig(scene, aperture, waveform, fs, chirp, grid, None if snr is None else float(snr), seed, text,
                       c.preprocess_table(cfg, source), beams)


def _stored(text: str) -> tuple[dict, str]:
    """The tables of a configuration stored in a dataset and its kind (see :func:`clsas.config.kind_of`)."""
    if not text.strip():
        return {}, "other"
    try:
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise c.ConfigError(f"{_STORED} is not valid TOML: {exc}") from None
    return cfg, c.kind_of(cfg)


def stored_scene(text: str) -> Scene | None:
    """The scene (reflectors and walls) of a configuration stored in a dataset, or None.

    A scene file gives its ``[[points]]`` and ``[[walls]]`` in its ``[air]``; a rig file its
    ``[simulate]`` points and walls (20 C, 50 %); anything else (no reflectors, an
    ``import.toml``, a text that today's checks refuse: logged as a warning) gives None.
    """
    cfg, kind = _stored(text)
    table = cfg if kind == "scene" else cfg.get("simulate", {}) if kind == "rig" else {}
    if not isinstance(table, dict) or not table.get("points"):
        return None
    label = "[[{}]]" if kind == "scene" else "[simulate] {}"
    # the file was checked when the dataset was written; a stored text that the checks of this
    # version refuse costs the truth markers, with a warning, not the image
    try:
        points = c.points_table(table["points"], _STORED, label.format("points"))
        walls = c.walls_table(table.get("walls", []), _STORED, label.format("walls"))
        air = cfg.get("air", {}) if kind == "scene" else {}
        air = c.Table(air, _STORED, "[air]", AIR_KEYS if kind == "scene" else ())
        return c.build_scene(points, walls, float(air.number("temperature_c", 20.0, low=-273.15)),
                             float(air.number("humidity_pct", 50.0, low=0, high=100)),
                             air.boolean("wall_echo", False))
    except ValueError as exc:
        log.warning("%s; no true positions", exc)
        return None


def stored_grid_and_truth(text: str) -> tuple[VoxelGrid | None, np.ndarray | None]:
    """The ``[grid]`` and the true reflector (image) positions of a configuration stored in a dataset.

    Works for scene files (``clsas simulate``) and rig files (``clsas acquire``; the truth is its
    ``[simulate]`` scene, if any); other stored settings (e.g. an ``import.toml``) give
    ``(None, None)``. A stored ``[grid]`` that today's checks refuse gives no grid, with a
    warning.
    """
    cfg, kind = _stored(text)
    if kind not in ("scene", "rig"):
        return None, None
    try:
        grid = c.grid_table(cfg, _STORED)
    except c.ConfigError as exc:
        log.warning("%s; no stored grid", exc)
        grid = None
    scene = stored_scene(text)
    return grid, None if scene is None else scene.image_sources()[0]


def load_config(path: str | Path) -> SceneConfig:
    """Read and check a scene file; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no scene configuration at {path}")
    return parse_config(c.read_text(path, "scene"), str(path))


def mannequin_points(center_m=(0.0, 0.0, 1.5), seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A mannequin-like cluster of point scatterers (head, shoulders, torso, arms).

    Returns ``(points (n, 3), amplitudes (n,))``; the figure faces -z (the aperture).
    """
    rng = np.random.default_rng(seed)
    pts = []
    for a in np.linspace(0, 2 * np.pi, 6, endpoint=False):  # head
        pts.append((0.08 * np.cos(a), 0.50 + 0.09 * np.sin(a), -0.03 * abs(np.cos(a))))
    pts += [(0.0, 0.38, 0.0), (-0.20, 0.30, 0.02), (0.20, 0.30, 0.02)]  # neck, shoulders
    for x in (-0.14, 0.0, 0.14):  # torso
        for y in (0.18, 0.0, -0.18, -0.36):
            pts.append((x, y, -0.05 + 2.0 * x**2))
    for s in (-1, 1):  # arms
        for y in (0.15, -0.05, -0.25):
            pts.append((s * 0.27, y, 0.03))
    p = np.asarray(pts) + np.asarray(center_m)
    amps = rng.uniform(0.5, 1.0, len(p))
    return p, amps


def _config_text(points, amps, visible, walls, grid, snr_db=20.0) -> str:
    cfg = {
        "chirp": {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 5e-3, "fs_hz": 96e3, "taper": 0.1},
        "aperture": {"nx": 18, "ny": 12, "width_m": 1.0, "height_m": 1.0, "pattern": "serpentine"},
        "air": {"temperature_c": 20.0, "humidity_pct": 50.0},
        "noise": {"snr_db": snr_db, "seed": 0},
        "points": [
            {"position_m": [round(float(c), 6) for c in p], "amplitude": round(float(a), 6), "visible": bool(v)}
            for p, a, v in zip(points, amps, visible, strict=True)
        ],
        "walls": walls,
        "grid": grid,
    }
    return tomli_w.dumps(cfg)


def demo_configs(spacing_m: float = 0.01) -> dict[str, str]:
    """TOML text of the paper's two scenes: a mannequin in front, and one around a corner.

    Around the corner, the mannequin is hidden from the aperture (``visible = false``) and is
    heard only through a wall at 45 degrees; its mirror image lies behind the wall, in front
    of the aperture, at about (0, 0, 2.6) m.
    """
    front, amps = mannequin_points((0.0, 0.0, 1.5))
    front_grid = {"x_m": [-0.45, 0.45], "y_m": [-0.55, 0.7], "z_m": [1.3, 1.65], "spacing_m": spacing_m}
    wall = {"point_m": [0.0, 0.0, 2.0], "normal": [0.70710678, 0.0, -0.70710678], "reflectivity": 0.9}
    w = Wall(tuple(wall["point_m"]), tuple(wall["normal"]))
    hidden = w.mirror(mannequin_points((0.0, 0.0, 2.6))[0])  # placed so its image is at z = 2.6
    corner_grid = {"x_m": [-0.45, 0.45], "y_m": [-0.55, 0.7], "z_m": [2.35, 2.8], "spacing_m": spacing_m}
    return {
        "front": _config_text(front, amps, [True] * len(front), [], front_grid),
        "corner": _config_text(hidden, amps, [False] * len(hidden), [wall], corner_grid),
    }
