"""Steps 3-6 of ω-k (:mod:`clsas.formation.omega_k`) for one lattice group: the spatial FFT, the
Stolt step over the spatial-frequency columns (on the OpenCL device or its twin, by the path
chosen for the device) and the inverse transform onto the grid; the groups' images summed."""

from __future__ import annotations

import math
import time

import numpy as np

from .. import cl as _cl
from . import stolt_numpy as stolt
from .omega_k_beams import plane_wave_beam
from .omega_k_layout import group_terms, layout
from .omega_k_transforms import dft_axis
from .stolt_opencl import StoltDepthsPlan, StoltPlan

__all__ = ["choose_stolt_step", "form_group", "form_lattices", "stolt_columns"]


def choose_stolt_step(o: dict, backend, device, ap, k: np.ndarray, depth: np.ndarray):
    """(path, OpenCL plan or None, selection) of the Stolt step: the way to the depths chosen for
    the device it runs on (the twins' after a fallback)."""
    u_max = 0.5 * (1.0 / depth[0] - 1.0 / depth[-1])
    terms = max(group_terms(g, k, u_max, o) for g in ap.groups)
    sel = _cl.select(backend, device)
    path = stolt.depth_path(o["depths"], len(k), len(depth), o["kernel_width"], terms, sel.opencl)
    cls = StoltDepthsPlan if path == "direct" else StoltPlan
    runner, sel = sel.plan(lambda q: cls(queue=q))  # None: the twin (NumPy after a fallback, logged)
    if runner is None:
        path = stolt.depth_path(o["depths"], len(k), len(depth), o["kernel_width"], terms, False)
    return path, runner, sel


def form_lattices(ap, spec, k, axes, flip: bool, o: dict, workers: int, stolt_step, k_top: float, progress,
                   records: list) -> tuple[np.ndarray, float]:
    """Each lattice group's image, summed, depths in the grid's order: (values in the aperture's axis
    order, the Stolt step's seconds); each group's record appended to ``records``."""
    pu, pv, depth_inc = axes
    values = np.zeros((len(pu), len(pv), len(depth_inc)), np.complex64)
    t_stolt = 0.0
    for g in ap.groups:
        img, ginfo, dt_stolt = form_group(g, spec[g.index], k, pu, pv, depth_inc, o, workers, stolt_step, k_top,
                                           progress)
        values += img[:, :, ::-1] if flip else img
        records.append(ginfo)
        t_stolt += dt_stolt
    return values, t_stolt


def form_group(g, spec, k, pu, pv, depth, o, workers, stolt_step, k_top, progress):
    """Image one lattice group on the (u, v, depth) grid (depth increasing); ``stolt_step`` is
    (path, OpenCL plan or None for the twin)."""
    import scipy.fft

    nu, nv = g.shape
    du, dv = g.spacing_uv
    z0, z1 = float(depth[0]), float(depth[-1])
    nz = len(depth)
    dz = (z1 - z0) / (nz - 1) if nz > 1 else 2 * np.pi / (2 * np.abs(k).max())
    zc = z0 + (nz // 2) * dz
    zref = 2.0 / (1.0 / z0 + 1.0 / z1)
    u_max = 0.5 * (1.0 / z0 - 1.0 / z1)
    lay = layout(g, k, pu, pv, depth, o, k_top)
    mu, mv, up, s1, s2, cols = lay["mu"], lay["mv"], lay["up"], lay["s1"], lay["s2"], lay["cols"]
    ku_all, kv_all, wu, wv, n_cells = lay["ku"], lay["kv"], lay["wu"], lay["wv"], lay["n_cells"]
    # single precision from the lattice on (relative error ~1e-7, far below the method's); the
    # zero padding of u is transformed only along the nv columns that hold stops
    lattice = np.zeros((nu, nv, len(k)), np.complex64)
    lattice[g.iu, g.iv] = spec
    dspec = scipy.fft.fft(scipy.fft.fft(lattice, mu, axis=0, workers=workers), mv, axis=1, workers=workers)
    del lattice
    n_terms = group_terms(g, k, u_max, o)
    b = tuple(g.baseline_uvw[:2]) if o["bistatic"] else (0.0, 0.0)
    params = stolt.StoltParams(dz, zc, zref, b, n_cells, o["kernel_width"], n_terms, s1, s2)
    u_z = 1.0 / depth - 1.0 / zref
    factors = np.array([(1j * u_z) ** p / math.factorial(p) for p in range(n_terms)])  # (terms, nz)
    T = np.zeros((up * mu, up * mv, nz), np.complex64)
    t_stolt = 0.0
    # chunks of at most o["chunk"] columns, of about equal length (no launch for a short remainder)
    step = -(-len(cols) // max(1, -(-len(cols) // o["chunk"]))) if len(cols) else 1
    for c0 in range(0, len(cols), step):
        cc = cols[c0: c0 + step]
        iu_, iv_ = cc[:, 0], cc[:, 1]
        block = dspec[iu_ % mu, iv_ % mv] * (wu[iu_] * wv[iv_]).astype(np.float32)[:, None]
        block *= plane_wave_beam(o["angular"], ku_all[iu_], kv_all[iv_], k)  # the beam weights: 1 without beams
        t = time.perf_counter()
        T[iu_, iv_] = stolt_columns(stolt_step, block, k, ku_all[iu_], kv_all[iv_], params, factors, workers)
        t_stolt += time.perf_counter() - t
        if progress is not None:
            progress(min(len(cols), c0 + step), len(cols))
    del dspec
    T *= (1j * depth[None, None, :]).astype(np.complex64)
    img = dft_axis(T, ku_all, pu - g.origin_uv[0], workers)
    img = np.moveaxis(dft_axis(np.moveaxis(img, 1, 0), kv_all, pv - g.origin_uv[1], workers), 0, 1)
    img /= (4 * np.pi**2) / ((2 * np.pi / (mu * du)) * (2 * np.pi / (mv * dv)))
    info = {"shape": (nu, nv), "spacing_m": (du, dv), "padded": (mu, mv), "upsample": up, "columns": len(cols),
            "terms": n_terms, "z_ref_m": zref, "look_sine": (s1, s2), "cells": n_cells}
    return img, info, t_stolt


def stolt_columns(stolt_step, block, k, ku, kv, params, factors, workers) -> np.ndarray:
    """(cols, nz) the Stolt sum of ``block``'s columns at the depths, by the step's path."""
    path, runner = stolt_step
    nz = factors.shape[1]
    if path == "direct":
        return (runner or stolt.direct)(block, k, ku, kv, params, nz, factors)
    cells = (runner or stolt.spread)(block, k, ku, kv, params)
    return stolt.terms_to_depths(cells, nz, params, factors, workers, overwrite=True)
