"""A seeded family of hand-held scans for testing autofocus on scenes nobody tuned it on.

:func:`family_scene` draws one scene from a seed: a raster aperture of 13-28 stops a side over
0.24-1.0 m, a target at 0.5-1.8 m, 6-15 cm across (2-12 point reflectors, a rough tilted plane of about 120
scatterers, or a sphere cap of about 160), a 20-30 kHz chirp of 1-5 ms at 96 kHz, an SNR of
15-35 dB and :class:`~clsas.scan_errors.HandMotion` of a given RMS (0.2-5 Hz). In half the seeds
(odd ones) the scan also has a 10-50 us group delay, a 0.5-3 C air temperature error and the
direct speaker-to-microphone sound; in the other half none of these.

The seeds are split once, and for good: :data:`TUNING_SEEDS` (and :data:`TUNING_2_SEEDS`) are
the ones autofocus may be developed and tuned on; :data:`HELD_OUT_SEEDS` and
:data:`HELD_OUT_2_SEEDS` (disjoint, 30 scenes each) are for reports only
(``python -m bench --autofocus held-out`` / ``held-out-2``). :data:`SEED_SETS` names them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import validate as v
from ..physics.geometry import Scene, VoxelGrid, raster_aperture
from ..physics.scan_errors import HandMotion
from ..physics.signals import lfm_chirp
from ..types.dataset import Dataset
from .simulation import simulate

__all__ = ["FamilyScene", "family_scene", "TUNING_SEEDS", "HELD_OUT_SEEDS", "TUNING_2_SEEDS", "HELD_OUT_2_SEEDS",
           "SEED_SETS", "KINDS", "FS_HZ"]

TUNING_SEEDS = tuple(range(0, 12))
HELD_OUT_SEEDS = tuple(range(1000, 1030))
#: A second tuning set (``"track"``'s check was tuned on it too).
TUNING_2_SEEDS = tuple(range(2000, 2030))
#: A second held-out set, for reports once :data:`HELD_OUT_SEEDS` has been reported several
#: times; never for tuning.
HELD_OUT_2_SEEDS = tuple(range(3000, 3030))
SEED_SETS = {"tuning": TUNING_SEEDS, "tuning-2": TUNING_2_SEEDS, "held-out": HELD_OUT_SEEDS,
             "held-out-2": HELD_OUT_2_SEEDS}
KINDS = ("points", "plane", "sphere")
FS_HZ = 96e3
MAX_VOXELS = 120_000


@dataclass
class FamilyScene:
    """One drawn scene: the scan with its errors, the same scan without them, and the grid.

    Attributes
    ----------
    seed : int
    kind : {"points", "plane", "sphere"}
    dataset : Dataset
        The scan as recorded (errors applied, the truth in ``dataset.truth``).
    clean : Dataset
        The same scan with no motion, delay or air error (the same noise draw), the reference.
    grid : VoxelGrid
        The scene's box plus 2 cm, at a spacing of a third of the shortest wavelength (coarser
        only past :data:`MAX_VOXELS` voxels: a coarser grid aliases the carrier's fringes, and
        the focus metrics with it).
    scene : Scene
    params : dict
        What was drawn (aperture, range, chirp, SNR, errors).
    """

    seed: int
    kind: str
    dataset: Dataset
    clean: Dataset
    grid: VoxelGrid
    scene: Scene
    params: dict = field(default_factory=dict)


def _target(rng: np.random.Generator, kind: str, range_m: float, extent_m: float) -> np.ndarray:
    """(k, 3) scatterers of the target, centred on (x0, y0, range_m), m."""
    centre = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), range_m])
    half = 0.5 * extent_m
    if kind == "points":
        k = int(rng.integers(2, 13))
        pts = np.c_[rng.uniform(-half, half, (k, 2)), rng.uniform(-0.4 * half, 0.4 * half, k)]
    elif kind == "plane":
        k = 120
        uv = rng.uniform(-half, half, (k, 2))
        tilt = rng.uniform(-0.35, 0.35, 2)  # slopes dz/dx, dz/dy
        rough = rng.normal(0.0, 0.003, k)
        pts = np.c_[uv, uv @ tilt + rough]
    else:  # a cap of a sphere facing the aperture (the part within 50 degrees of its axis)
        k = 161
        radius = half / np.sin(np.deg2rad(50))
        cos_t = rng.uniform(np.cos(np.deg2rad(50)), 1.0, k)
        phi = rng.uniform(0, 2 * np.pi, k)
        sin_t = np.sqrt(1 - cos_t**2)
        pts = np.c_[radius * sin_t * np.cos(phi), radius * sin_t * np.sin(phi), radius * (1 - cos_t)]
    return pts + centre


def family_scene(seed: int, *, rms_m: float = 3e-3, kind: str | None = None) -> FamilyScene:
    """Draw the scene of ``seed`` (see the module docstring).

    Parameters
    ----------
    seed : int
        Non-negative; the same seed always gives the same scene (and the same motion shape:
        ``rms_m`` only scales it).
    rms_m : float
        RMS of the hand motion's 3-D displacement, m.
    kind : {"points", "plane", "sphere"}, optional
        Force the target kind (default drawn from the seed).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    rms = v.non_negative("rms_m", rms_m)
    rng = np.random.default_rng([26, int(seed)])
    drawn_kind = KINDS[int(rng.integers(0, 3))]
    kind = drawn_kind if kind is None else v.choice("kind", kind, KINDS)
    nx, ny = (int(n) for n in rng.integers(13, 29, 2))
    width, height = (float(s) for s in rng.uniform(0.24, 1.0, 2))
    range_m = float(rng.uniform(0.5, 1.8))
    extent = float(rng.uniform(0.06, 0.15))
    duration = float(rng.uniform(1e-3, 5e-3))
    up = bool(rng.integers(0, 2))
    snr = float(rng.uniform(15, 35))
    errors = seed % 2 == 1
    delay = float(rng.uniform(10e-6, 50e-6))
    temp_err = float(rng.uniform(0.5, 3.0) * rng.choice([-1, 1]))
    pts = _target(rng, kind, range_m, extent)
    amps = rng.uniform(0.5, 1.0, len(pts)) if kind == "points" else rng.uniform(0.2, 1.0, len(pts))
    scene = Scene(pts, amps)
    f0, f1 = (20e3, 30e3) if up else (30e3, 20e3)
    wave = lfm_chirp(f0, f1, duration, FS_HZ, taper=0.1)
    chirp = {"f_start_hz": f0, "f_stop_hz": f1, "duration_s": duration, "taper": 0.1}
    ap = raster_aperture(nx, ny, width, height)
    common = dict(snr_db=snr, seed=int(seed), chirp=chirp, direct_gain=1.0 if errors else None,
                  config=f"scene_family seed {seed}")
    motion = HandMotion(rms, band_hz=(0.2, 5.0), seed=int(seed))
    err = {"position_error": motion}
    if errors:
        err.update(group_delay_s=delay, temperature_error_c=temp_err)
    ds = simulate(scene, ap, wave, FS_HZ, **common, **err)
    clean = simulate(scene, ap, wave, FS_HZ, **common, position_error=HandMotion(0.0, seed=int(seed)))
    params = {"nx": nx, "ny": ny, "width_m": width, "height_m": height, "range_m": range_m, "extent_m": extent,
              "n_scatterers": len(pts), "duration_s": duration, "f_start_hz": f0, "f_stop_hz": f1, "snr_db": snr,
              "rms_m": rms, "direct": errors, "group_delay_s": delay if errors else 0.0,
              "temperature_error_c": temp_err if errors else 0.0}
    return FamilyScene(int(seed), kind, ds, clean, _grid(pts), scene, params)


def _grid(pts: np.ndarray, pad_m: float = 0.02, max_voxels: int = MAX_VOXELS) -> VoxelGrid:
    """The box around ``pts`` plus ``pad_m``, at a third of 30 kHz's wavelength or coarser."""
    lo, hi = pts.min(axis=0) - pad_m, pts.max(axis=0) + pad_m
    spacing = max(343.0 / 30e3 / 3, float(np.prod(hi - lo) / max_voxels) ** (1 / 3))
    return VoxelGrid.from_bounds(*zip(lo, hi, strict=True), spacing)
