"""Transducer beams in ω-k: the two-way pattern as a weight per plane-wave angle, and the share
of the grid in the aperture's well-sampled cone (within the beams' edge)."""

from __future__ import annotations

import logging

import numpy as np

from ..physics.beam import angular_weights, beam_weights, facing
from ..physics.geometry import VoxelGrid
from ..types.profiles import Profiles
from .planar import cone_of

__all__ = ["beam_angular", "beam_edge_sine", "plane_wave_beam", "warn_outside_cone"]

log = logging.getLogger("clsas.formation.omega_k")


def plane_wave_beam(weights, ku: np.ndarray, kv: np.ndarray, k: np.ndarray):
    """(columns, n_f) two-way beam weight of each plane wave (1 without beams)."""
    if weights is None:
        return 1.0
    return angular_weights(weights, np.hypot(ku, kv)[:, None] / np.abs(k))


def beam_angular(profiles: Profiles, o: dict, fc: float, c, ap, grid: VoxelGrid):
    """The profiles' beams as weights of plane-wave angles (``beam`` option as in bp: default
    ``"limited"`` for directional beams), or None; refused unless every boresight is the
    aperture plane's normal toward the grid."""
    beams = profiles.beams
    mode = o["beam"] or ("limited" if beams is not None and not beams.is_omni else "none")
    weights = beam_weights(beams, mode, fc, c, o["beam_floor_db"])
    if weights is None:
        return None
    normal = np.zeros(3)
    normal[ap.axis] = 1.0 if [grid.x_m, grid.y_m, grid.z_m][ap.axis].mean() > ap.w_m else -1.0
    if not facing(weights, normal):
        raise ValueError(f"beam={mode!r}: omega-k weights plane waves by angle from the aperture's normal, and "
                         "needs every boresight along it; use formation='bp' (any boresight) or beam='none'")
    return weights


def beam_edge_sine(weights) -> float:
    """The sine of the steepest angle from the normal that the beams' angular weights keep (1
    without beams): where a weight first stays under 1e-3 of its peak."""
    if weights is None:
        return 1.0
    s = np.linspace(0.0, 1.0, 2001)
    w = angular_weights(weights, s)
    kept = np.flatnonzero(w > 1e-3 * max(float(w.max()), 1e-300))
    return float(s[kept[-1]]) if len(kept) else 0.0


def warn_outside_cone(ap, grid: VoxelGrid, f_top: float, c_ref: float, weights=None) -> float:
    """The share of the grid in the aperture's well-sampled cone (within the beams' edge, where the
    profiles carry beams), with a warning where it is under half."""
    frac = float(cone_of(ap, grid, f_top, c_ref, max_sine=beam_edge_sine(weights)).mean())
    if frac < 0.5:
        log.warning("omega-k: the aperture's lattice samples only %.0f %% of the grid unaliased at %.0f kHz "
                    "(its well-sampled cone); elsewhere backprojection also forms aliased angles (grating "
                    "lobes), which omega-k leaves out: formation_options={'upsample': 'auto'} forms them, "
                    "or use formation='bp'", 100 * frac, f_top / 1e3)
    return frac
