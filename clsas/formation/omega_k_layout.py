"""The sizes of ω-k's transforms for one lattice group, from the geometry alone (no data touched):
the look-angle window, the spatial padding and upsampling, the spatial-frequency columns kept,
the kz cells and the powers of the bistatic expansion (steps 3-5 of :mod:`clsas.formation.omega_k`).
Both the formation and ``formation="auto"``'s cost model (:func:`clsas.formation.omega_k.plan_sizes`)
read them."""

from __future__ import annotations

import math

import numpy as np

from .omega_k_transforms import edge_window

__all__ = ["expansion_terms", "farthest_offsets", "group_terms", "kz_cells", "layout", "steepest_sine"]


def farthest_offsets(g, pu, pv) -> tuple[float, float]:
    """The largest in-plane offsets ``(du, dv)``, m, between a voxel (axes ``pu``, ``pv``) and a stop
    of the lattice group ``g``."""
    (u0, u1), (v0, v1) = g.extent_uv
    return max(abs(pu[-1] - u0), abs(u1 - pu[0])), max(abs(pv[-1] - v0), abs(v1 - pv[0]))


def steepest_sine(g, pu, pv, depth_min) -> float:
    """Sine of the steepest voxel-stop angle from the plane's normal."""
    lat = math.hypot(*farthest_offsets(g, pu, pv))
    return lat / math.hypot(lat, depth_min)


def kz_cells(n_z: int, width: int) -> int:
    """Cells of the folded kz axis (2x oversampled, at least two kernel widths)."""
    import scipy.fft

    return scipy.fft.next_fast_len(max(2 * n_z, 2 * width))


def group_terms(g, k: np.ndarray, u_max: float, o: dict) -> int:
    """Powers of the bistatic expansion one lattice group needs (``phase_tol`` over its depths)."""
    alpha_max = (g.baseline_uvw[0] ** 2 + g.baseline_uvw[1] ** 2) * np.abs(k).max() / 8
    return expansion_terms(alpha_max, u_max, o["phase_tol"], o["bistatic"])


def expansion_terms(alpha_max: float, u_max: float, tol: float, bistatic: bool) -> int:
    """Powers of ``(1/z - 1/z_ref)`` the bistatic phase ``alpha / z`` needs for its neglected
    term to stay under ``tol`` rad (``alpha_max u_max`` the largest first-order phase; 1 with
    the midpoint approximation)."""
    if not bistatic:
        return 1
    x = alpha_max * u_max
    p = 1
    while x**p / math.factorial(p) > tol and p < 12:
        p += 1
    return p


def layout(g, k, pu, pv, depth, o, k_top) -> dict:
    """Sizes of one lattice group's transforms (no data touched): the padded lattice ``mu x mv``,
    the upsampling, the spatial-frequency columns kept and their windows, the look-angle window."""
    import scipy.fft

    nu, nv = g.shape
    du, dv = g.spacing_uv
    z0, z1 = float(depth[0]), float(depth[-1])
    # look angles: every voxel-stop pair, plus a margin; the window falls from s1 to s2
    s_geo = steepest_sine(g, pu, pv, z0) if o["max_sine"] is None else o["max_sine"]
    s1 = min(s_geo + 0.05, 0.97)
    s2 = min(s1 + 0.1, 0.995)
    # aliased angles: U repeats of the periodic spectrum
    up = o["upsample"]
    if up == "auto":
        need = s2 * np.abs(k).max()
        up = max(1, int(math.ceil(need / (np.pi / min(du, dv)))))
    # spatial zero padding: the longest voxel-stop distance along the axis plus the spread, at
    # the deepest plane, of the angles the lattice samples unaliased at the band's top (the
    # top of its -20 dB band; beyond them the spectrum only tapers) and the look-angle window
    # passes at half weight or more (the middle of its taper: what wraps in from the periodic
    # copies comes through the taper's outer half only; padding to s2 instead cost 1.2-1.3x
    # the columns at 24-32 stops a side and bought 1-3 dB of an error under -36 dB; to s1,
    # the error reached -29.5 dB on a 24 x 24 scan at lambda/4)
    def _spread(d):
        s = min(up * np.pi / (d * k_top), 0.5 * (s1 + s2), 0.9)
        return z1 * s / math.sqrt(1 - s * s)

    lat_u = max(pu[-1] - g.extent_uv[0, 0], g.extent_uv[0, 1] - pu[0]) + _spread(du) + 4 * du
    lat_v = max(pv[-1] - g.extent_uv[1, 0], g.extent_uv[1, 1] - pv[0]) + _spread(dv) + 4 * dv
    if o["pad"] is None:
        mu = scipy.fft.next_fast_len(max(nu, int(math.ceil(lat_u / du))))
        mv = scipy.fft.next_fast_len(max(nv, int(math.ceil(lat_v / dv))))
    else:
        mu = scipy.fft.next_fast_len(int(math.ceil(o["pad"] * nu)))
        mv = scipy.fft.next_fast_len(int(math.ceil(o["pad"] * nv)))
    ku_all = 2 * np.pi * scipy.fft.fftfreq(up * mu, du / up)
    kv_all = 2 * np.pi * scipy.fft.fftfreq(up * mv, dv / up)
    wu = edge_window(ku_all, up * np.pi / du, o["taper"], o["window"])
    wv = edge_window(kv_all, up * np.pi / dv, o["taper"], o["window"])
    # keep only columns with weight, and with any frequency inside the look-angle window
    kp_ok = np.hypot(ku_all[:, None], kv_all[None, :]) < s2 * np.abs(k).max()
    cols = np.argwhere((wu[:, None] * wv[None, :] > 0) & kp_ok)
    n_cells = kz_cells(len(depth), o["kernel_width"])
    return {"mu": mu, "mv": mv, "up": up, "s1": s1, "s2": s2, "ku": ku_all, "kv": kv_all, "wu": wu, "wv": wv,
            "cols": cols, "n_cells": n_cells}
