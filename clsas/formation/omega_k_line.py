"""Wavenumber-domain (ω-k) image formation for 2-D line scans: a 2-D Stolt step.

A line scan has every stop on one straight line along a grid axis (``u``), evenly spaced, the
speaker and microphone together or close: the midpoint is used, and an offset ``b`` whose phase
error ``k b^2 / (4 rho)`` exceeds 0.1 rad at the nearest voxel is refused. Backprojection's image
then depends only on the position along the line and the distance ``rho`` from it (a voxel
sees the line the same from every side), and per frequency it is a 1-D convolution over the
stops with ``h(u) = exp(i k sqrt(u^2 + rho^2))``, ``k = 4 pi f / c``. Its transform along the
line is exact:

    H(q, rho) = -pi rho k / k_rho * H1(rho k_rho),   k_rho = sqrt(k^2 - q^2)

(``H1`` the Hankel function of the first kind), so the image is

    I(x, rho) = 1 / (M du) sum_q exp(i q (x - u0)) sum_f A(q, f) H(q, rho)

with ``A`` the profiles' spectra (step 1-2 of :mod:`clsas.formation.omega_k`, shared:
:mod:`clsas.formation.omega_k_spectra`) FFT'd along the line, zero-padded to ``M`` stops. The
sum over frequency is evaluated directly at each distinct ``rho`` of the grid (no
interpolation: the "Stolt" mapping of the 3-D method becomes exact here), the sum over ``q`` by
a chirp-z transform at the grid's ``x``. As in 3-D, only the unaliased angles (``|q| < pi / du``,
with a raised-cosine ``taper``) and the look angles up to the steepest voxel-stop angle are
formed: backprojection's grating lobes are not.

Costs ``n_q x n_f x n_rho`` Hankel evaluations. Directional beams (``beam`` as in 3-D, every
boresight the same and across the line) weight each plane wave by the two-way pattern at
``cos theta = sqrt(1 - (q / k)^2) cos phi``, ``phi`` the angle around the line between the
boresight and the voxel (so each distinct ``(rho, phi)`` is summed once).
"""

from __future__ import annotations

import logging
import math
import os
import time

import numpy as np

from ..physics.beam import beam_weights, facing, weights_at_cos
from ..physics.geometry import VoxelGrid
from ..types.image import Image
from ..types.profiles import Profiles
from .omega_k_spectra import spectra
from .omega_k_transforms import dft_axis, edge_window
from .planar import NotPlanarUniform, _axis_values

__all__ = ["line_axis", "form_line", "hankel1_1"]

log = logging.getLogger(__name__)


def line_axis(tx: np.ndarray, rx: np.ndarray, tol_m: float) -> int | None:
    """The grid axis the stops' midpoints run along when they lie on one axis-parallel line
    (within ``tol_m``), else None."""
    mid = 0.5 * (tx + rx)
    spread = np.ptp(mid, axis=0)
    along = [a for a in range(3) if spread[a] > 2 * tol_m]
    return along[0] if len(along) == 1 else None


def _rho(grid: VoxelGrid, axis: int, centre: np.ndarray, boresight: np.ndarray | None):
    """The distinct (distance from the line, cos of the angle around it from ``boresight``; 0
    without one) of the voxel columns across the line, (n, 2), and each column's index into them."""
    axes = [grid.x_m, grid.y_m, grid.z_m]
    b, c = (a for a in range(3) if a != axis)
    db, dc = np.meshgrid(axes[b] - centre[b], axes[c] - centre[c], indexing="ij")
    rho = np.hypot(db, dc)
    cos_phi = np.zeros_like(rho) if boresight is None else (
        (db * boresight[b] + dc * boresight[c]) / np.maximum(rho, 1e-30))
    uniq, inverse = np.unique(np.round(np.stack([rho.ravel(), cos_phi.ravel()], axis=1), 12), axis=0,
                              return_inverse=True)
    return uniq, inverse.reshape(rho.shape)


def _line_beams(profiles: Profiles, o: dict, fc: float, c, axis: int):
    """The beams' weights and their common boresight (None, None without directional beams)."""
    beams = profiles.beams
    mode = o["beam"] or ("limited" if beams is not None and not beams.is_omni else "none")
    weights = beam_weights(beams, mode, fc, c, o["beam_floor_db"])
    if weights is None:
        return None, None
    n = weights.tx_dir[0]
    if not (facing(weights, n) and abs(n[axis]) < 1e-3):
        raise ValueError(f"beam={mode!r}: omega-k on a line scan needs every boresight the same and across the "
                         "line; use formation='bp' (any boresight) or beam='none'")
    return weights, n


def hankel1_1(x: np.ndarray) -> np.ndarray:
    """H1 of order 1 at ``x`` > 0: scipy's below 40, else its asymptotic series to four terms
    (relative error < 1e-7 there, at a tenth of the cost)."""
    from scipy.special import hankel1

    x = np.asarray(x, float)
    big = x >= 40.0
    out = np.empty(x.shape, np.complex128)
    out[~big] = hankel1(1, x[~big])
    xb = x[big]
    ix = 1j / xb
    series = 1 + ix * (3 / 8 + ix * (-15 / 128 + ix * (315 / 3072)))
    out[big] = np.sqrt(2 / (np.pi * xb)) * np.exp(1j * (xb - 0.75 * np.pi)) * series
    return out


def _transfer(q: np.ndarray, k: np.ndarray, rho: float, s1: float, s2: float) -> np.ndarray:
    """(n_q, n_f) H(q, rho) for the propagating components, with the look-angle window (the
    sine of the angle from the line's normal ``|q| / k`` kept to ``s1``, falling to 0 at ``s2``)."""
    kk = np.abs(k)[None, :]
    sine = np.abs(q)[:, None] / kk
    keep = sine < s2
    kr = np.sqrt(np.where(keep, kk * kk - q[:, None] ** 2, 1.0))
    h = np.where(keep, -np.pi * rho * kk / kr * hankel1_1(rho * kr), 0.0)
    ramp = np.clip((sine - s1) / max(s2 - s1, 1e-9), 0.0, 1.0)
    h = h * (0.5 * (1 + np.cos(np.pi * ramp)))
    return np.where(k[None, :] < 0, np.conj(h), h)


def form_line(profiles: Profiles, grid: VoxelGrid, axis: int, o: dict, tol: float) -> Image:
    """ω-k image of a line scan along grid ``axis`` (options ``o`` as omega-k's, checked; the
    spectra, the spatial window and the chirp-z shared with the planar step)."""
    import scipy.fft

    if o["upsample"] != 1:
        raise ValueError("upsample: a line scan forms the unaliased angles only (upsample=1)")
    workers = o["workers"] or os.cpu_count() or 1
    data, tau0, dtau, fc, tx, rx, c = profiles.arrays(np.complex128)
    t_start = time.perf_counter()
    mid = 0.5 * (tx + rx)
    iu, u0, du, nu = _axis_values(mid[:, axis], tol, "xyz"[axis])
    if len(np.unique(iu)) != len(iu):
        raise NotPlanarUniform("two measurements share a stop of the line (one per stop: a line scan)")
    centre = mid.mean(axis=0)
    weights, boresight = _line_beams(profiles, o, fc, c, axis)
    keys, inverse = _rho(grid, axis, centre, boresight)
    rho = keys[:, 0]
    if rho.min() < 4 * tol:
        raise ValueError(f"grid: a voxel lies {rho.min():.3g} m from the scan line; omega-k needs the grid off it")
    spec, f, c_ref, f_top = spectra(data, tau0, dtau, fc, c, o["pad_time"], o["band_tol"], workers)
    k = 4 * np.pi * f / c_ref
    base = np.linalg.norm(tx - rx, axis=1).max()
    phase = np.abs(k).max() * base**2 / (4 * rho.min())
    if phase > 0.1:
        raise NotPlanarUniform(f"a line scan is imaged at its speaker-microphone midpoints, and an offset of "
                               f"{base:.3g} m errs there by up to {phase:.2g} rad (0.1 at most)")
    x = [grid.x_m, grid.y_m, grid.z_m][axis]
    lat = max(abs(x[-1] - u0), abs(u0 + du * (nu - 1) - x[0]))
    s_geo = lat / math.hypot(lat, rho.min()) if o["max_sine"] is None else o["max_sine"]
    s1 = min(s_geo + 0.05, 0.97)
    s2 = min(s1 + 0.1, 0.995)
    spread = rho.max() * min(s2, 0.9) / math.sqrt(1 - min(s2, 0.9) ** 2)
    m = scipy.fft.next_fast_len(max(nu, int(math.ceil((lat + spread) / du)) + 4) if o["pad"] is None
                                else int(math.ceil(o["pad"] * nu)))
    line = np.zeros((nu, len(f)), np.complex128)
    line[iu] = spec
    a = scipy.fft.fft(line, m, axis=0, workers=workers)
    q = 2 * np.pi * scipy.fft.fftfreq(m, du)
    a *= edge_window(q, np.pi / du, o["taper"], o["window"])[:, None]
    t = np.empty((m, len(rho)), np.complex128)
    for j, (r, cos_phi) in enumerate(keys):
        h = _transfer(q, k, float(r), s1, s2)
        if weights is not None:  # the plane wave's direction: cos theta = cos(along-line angle) cos phi
            h *= weights_at_cos(weights, np.sqrt(np.clip(1 - (q[:, None] / k[None, :]) ** 2, 0, 1)) * cos_phi)
        t[:, j] = np.einsum("qf,qf->q", a, h)
    img = dft_axis(t, q, x - u0, workers) / (m * du)  # (n_x, n_rho)
    values = np.moveaxis(img[:, inverse], 0, axis).astype(np.complex64)
    total = time.perf_counter() - t_start
    info = {"line_axis": "xyz"[axis], "stops": nu, "spacing_m": du, "padded": m, "n_f": len(f),
            "n_rho": len(rho), "look_sine": (s1, s2), "band_hz": (float(f.min()), float(f.max()))}
    return Image(values, grid, "bp", "numpy", "", {"omega_k": total}, provenance={"omega_k": info})
