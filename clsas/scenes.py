"""Scene configurations (TOML) and the paper's two demo scenes.

A configuration holds the chirp, the aperture, the air, the reflectors and walls, the noise
and the imaging grid; ``clsas simulate`` reads it and stores it in the dataset, so that
``clsas reconstruct`` finds the grid again.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w

from .geometry import Aperture, Scene, VoxelGrid, Wall, raster_aperture
from .signals import lfm_chirp

__all__ = ["SceneConfig", "load_config", "parse_config", "mannequin_points", "demo_configs", "stored_grid_and_truth"]


@dataclass
class SceneConfig:
    scene: Scene
    aperture: Aperture
    waveform: np.ndarray
    fs_hz: float
    chirp: dict
    grid: VoxelGrid | None
    snr_db: float | None
    seed: int
    text: str


def _section(cfg: dict, name: str) -> dict:
    sec = cfg.get(name, {})
    if not isinstance(sec, dict):
        raise ValueError(f"[{name}] must be a table")
    return sec


def _grid(cfg: dict) -> VoxelGrid | None:
    """The ``[grid]`` table of a scene or rig configuration, if any."""
    g = cfg.get("grid")
    if g is None:
        return None
    return VoxelGrid.from_bounds(tuple(g["x_m"]), tuple(g["y_m"]), tuple(g["z_m"]), g.get("spacing_m", 0.01))


def parse_config(text: str) -> SceneConfig:
    """Build the scene, aperture, waveform and grid described by TOML ``text``."""
    try:
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"scene configuration is not valid TOML: {exc}") from None
    ch = _section(cfg, "chirp")
    chirp = {
        "f_start_hz": float(ch.get("f_start_hz", 20e3)),
        "f_stop_hz": float(ch.get("f_stop_hz", 30e3)),
        "duration_s": float(ch.get("duration_s", 5e-3)),
        "taper": float(ch.get("taper", 0.1)),
    }
    fs = float(ch.get("fs_hz", 96e3))
    waveform = lfm_chirp(chirp["f_start_hz"], chirp["f_stop_hz"], chirp["duration_s"], fs, chirp["taper"])
    ap = _section(cfg, "aperture")
    aperture = raster_aperture(
        int(ap.get("nx", 18)), int(ap.get("ny", 12)), float(ap.get("width_m", 1.0)),
        float(ap.get("height_m", 1.0)), center_m=tuple(ap.get("center_m", (0.0, 0.0, 0.0))),
        tx_offset_m=tuple(ap.get("tx_offset_m", (-0.02, 0.0, 0.0))),
        rx_offset_m=tuple(ap.get("rx_offset_m", (0.02, 0.0, 0.0))),
        pattern=str(ap.get("pattern", "serpentine")),
    )
    air = _section(cfg, "air")
    points = cfg.get("points", [])
    if not points:
        raise ValueError("the scene configuration has no [[points]]")
    walls = tuple(
        Wall(tuple(w["point_m"]), tuple(w["normal"]), float(w.get("reflectivity", 0.9)))
        for w in cfg.get("walls", [])
    )
    scene = Scene(
        np.array([p["position_m"] for p in points], float),
        np.array([p.get("amplitude", 1.0) for p in points], float),
        np.array([p.get("visible", True) for p in points], bool),
        walls,
        temperature_c=float(air.get("temperature_c", 20.0)),
        humidity_pct=float(air.get("humidity_pct", 50.0)),
        wall_echo=bool(air.get("wall_echo", False)),
    )
    grid = _grid(cfg)
    noise = _section(cfg, "noise")
    snr = noise.get("snr_db")
    return SceneConfig(scene, aperture, waveform, fs, chirp, grid, None if snr is None else float(snr),
                       int(noise.get("seed", 0)), text)


def stored_grid_and_truth(text: str) -> tuple[VoxelGrid | None, np.ndarray | None]:
    """The ``[grid]`` and the true reflector (image) positions of a configuration stored in a dataset.

    Works for scene files (``clsas simulate``) and rig files (``clsas acquire``; the truth is its
    ``[simulate]`` scene, if any).
    """
    if not text.strip():
        return None, None
    cfg = tomllib.loads(text)
    grid = _grid(cfg)
    if "stage" in cfg or "audio" in cfg:
        from .rig.config import parse_rig_config

        rig = parse_rig_config(text)
        truth = rig.scene().image_sources()[0] if rig.simulate.get("points") else None
        return grid, truth
    return grid, parse_config(text).scene.image_sources()[0]


def load_config(path: str | Path) -> SceneConfig:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no scene configuration at {path}")
    return parse_config(path.read_text())


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
