"""Wavenumber-domain (ω-k, Stolt) image formation for planar, uniform, bistatic apertures.

``reconstruct(dataset, grid, formation="omega-k")`` gives the image that exact backprojection
(:func:`clsas.backproject`, reference definition in ``clsas/formation/bp_numpy.py``) gives, with the
same complex values and phase convention, at a cost of O(N^3 log N) instead of voxels x
measurements, for apertures whose speakers and microphones lie on one plane normal to a grid
axis, with the pairs' midpoints on a regular lattice and one fixed speaker-microphone offset
(see :mod:`clsas.formation.planar`; several microphones per stop are imaged as one lattice
each and summed). Anything else is refused with a ``ValueError`` naming ``ffbp`` and ``bp``.

Backprojection sums ``s_m(tau_m(v))`` over the measurements, ``s_m`` the analytic profile and
``tau_m(v)`` the bistatic delay. Written per frequency, that is a 2-D convolution over the
lattice with the kernel ``exp(i k r)``, ``k = 4 pi f / c``, which this module evaluates in the
wavenumber domain. The steps, and what each costs in accuracy:

1. **Delay to frequency.** Each profile (complex baseband, row ``m`` at delays
   ``tau0_m + n dtau``) is zero-padded to ``pad_time`` (1.5) times its length and FFT'd, so that
   the delays the grid needs do not wrap; a row's own
   ``tau0`` becomes a phase ramp. Backprojection interpolates profiles linearly; its transfer
   function on the band, ``sinc^2(f_b dtau)`` (``f_b`` the baseband frequency), is applied so
   that amplitudes agree (up to 3.5 % at the band edge otherwise); the interpolation's images
   at ``f_b +- 1/dtau`` are not formed (about -37 dB for 20-30 kHz at 48 kHz profiles).
   A per-measurement speed of sound is **handled**: each profile is then transformed by a
   direct DFT at its own frequencies ``f = kappa c_m / 2 pi`` of one common wavenumber grid
   ``kappa``, so every measurement lands on the same ``k`` samples.
2. **The band used** runs from the lowest to the highest frequency sample whose energy (summed
   over the measurements) is at least ``band_tol^2`` of the strongest sample's (default
   -40 dB); what lies outside is dropped. Frequencies below zero are kept (the sparse methods'
   rendered pulses are wider than their carrier): backprojection forms them too.
3. **Spatial FFT.** Per frequency the lattice is zero-padded to ``M_u x M_v`` (default: enough
   that the spread of the processed angles does not wrap onto the grid, from the geometry) and
   2-D FFT'd (scipy.fft with ``workers``); the padding covers the angles the look-angle window
   (step 4) passes at half weight or more, so only its taper's outer half can wrap. The band's
   outer ``taper`` (default 10 %) of each spatial-frequency axis falls off with a raised cosine;
   ``window="hann"`` windows the whole band instead (lower sidelobes, not backprojection's
   values). ``upsample=U`` repeats the periodic spectrum U times along each axis, which forms
   the aliased angles as well (backprojection's grating lobes), at U^2 the cost; ``"auto"``
   takes the U that covers every voxel-stop angle.
4. **Stolt mapping** ``kz = sqrt(k^2 - ku^2 - kv^2)`` with the exact amplitude of the kernel's
   plane-wave expansion, the bistatic correction and a look-angle window, then the sum over
   frequency onto the grid's depths, one of two ways (option ``depths``): ``"direct"``, the sum
   evaluated at each depth (exact; work ``n_f n_z`` per column), or ``"spread"``, a type-1
   non-uniform FFT (see :mod:`clsas.formation.stolt_numpy`: interpolation by spreading with an
   exponential-of-semicircle kernel of ``kernel_width`` cells on a 2x oversampled ``kz`` axis,
   error ~1e-3 at the default 4 cells, far under the method's own; work about
   ``n_f W + M log M``). ``"auto"`` (default) takes the one a fitted timing model
   (:func:`clsas.formation.stolt_numpy.depth_path`) predicts faster on OpenCL, and the spread on the
   NumPy twins (their direct sum is the slower); on a scan of 32 x 32 stops onto 30 x 30 x 41
   voxels the direct sum took ω-k from 22 to 16 ms. On OpenCL this step runs as
   ``kernels/stolt.cl`` (``stolt_depths``, ``stolt_spread``).
5. **The bistatic offset** is compensated: the path differs from twice the midpoint range by
   ``d^2 (1 - cos^2 psi) / (4 R)`` (0.22 rad at 30 kHz for the default 4 cm baseline at 1 m);
   as ``alpha / z`` per plane-wave component it is expanded about a reference depth in powers
   of ``(1/z - 1/z_ref)``, as many as ``phase_tol`` (default 1e-2 rad: an image error under
   1 %, -40 dB) needs over the grid's depth range (2 for 1.0-1.4 m). The neglected terms are
   of order ``k d^4 / R^3`` (1e-3 rad at 1 m for 4 cm). ``bistatic=False`` uses the midpoint
   approximation (for comparison).
6. **Onto the grid.** The depths come out on the grid's own ``z`` samples (the folded ``kz``
   axis has period ``2 pi / dz``); the lateral axes are an exact inverse DFT evaluated at the
   grid's ``x`` and ``y`` by a chirp-z (Bluestein) transform. Nothing is interpolated in the
   finished image.

Transducer beams: options ``beam`` (``"none"``, ``"limited"``, ``"weighted"``; default
``"limited"`` where the profiles carry directional beams, else ``"none"``) and ``beam_floor_db``
(-12) weight each plane wave by the two-way pattern at its angle ``asin(|k_xy| / k)`` from the
normal (:func:`clsas.physics.beam.angular_weights`, the same tables as bp's), which needs every boresight
along the aperture's normal. A 2-D line scan goes to :mod:`clsas.formation.omega_k_line`.

Where each step lives: steps 1-2 in :mod:`~clsas.formation.omega_k_spectra`; the sizes of steps
3-5 from the geometry in :mod:`~clsas.formation.omega_k_layout`; steps 3-6 per lattice group in
:mod:`~clsas.formation.omega_k_lattice` (the Stolt sum itself in :mod:`~clsas.formation.stolt_numpy` and
``kernels/stolt.cl``); the spatial windows and the chirp-z onto the grid in
:mod:`~clsas.formation.omega_k_transforms`; the beams and the cone in
:mod:`~clsas.formation.omega_k_beams`; this module checks the options and runs the steps.

Where it matches backprojection: inside the aperture's well-sampled cone
(:func:`clsas.formation.planar.well_sampled_cone`) to about -40 dB or better on simulated scans
(see the table in docs/guide/fast-formation.md); outside it, backprojection forms the contributions of stops that see
a voxel at aliased angles, which ω-k leaves out unless ``upsample`` asks for them.
"""

from __future__ import annotations

import inspect
import logging
import math
import os
import time
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.beam import BEAM_MODES
from ..physics.geometry import VoxelGrid
from ..types.image import Image
from ..types.profiles import Profiles
from . import omega_k_line as line
from .omega_k_beams import beam_angular, warn_outside_cone
from .omega_k_lattice import choose_stolt_step, form_lattices
from .omega_k_layout import farthest_offsets, group_terms, layout, steepest_sine
from .omega_k_spectra import spectra
from .planar import NotPlanarUniform, planar_aperture
from .registry import FORMATIONS

__all__ = ["form", "OPTIONS", "NotPlanarUniform", "farthest_offsets", "plan_sizes", "steepest_sine"]

log = logging.getLogger(__name__)

DEPTHS = ("auto", "direct", "spread")


def _options(options: dict) -> dict:
    unknown = set(options) - set(OPTIONS)
    if unknown:
        raise ValueError(f"formation_options: unknown option(s) {sorted(unknown)} for 'omega-k'; "
                         f"known: {sorted(OPTIONS)}")
    o = {**OPTIONS, **options}
    o["pad_time"] = v.positive("pad_time", o["pad_time"])
    if o["pad_time"] < 1:
        raise ValueError(f"pad_time must be >= 1, got {o['pad_time']!r}")
    if o["pad"] is not None:
        o["pad"] = v.positive("pad", o["pad"])
        if o["pad"] < 1:
            raise ValueError(f"pad must be >= 1 (or None: from the geometry), got {o['pad']!r}")
    v.choice("window", o["window"], (None, "hann"))
    o["taper"] = v.non_negative("taper", o["taper"])
    if o["taper"] >= 1:
        raise ValueError(f"taper must be in [0, 1), got {o['taper']!r}")
    if o["upsample"] != "auto":
        o["upsample"] = v.positive_int("upsample", o["upsample"])
    if not isinstance(o["bistatic"], bool):
        raise TypeError(f"bistatic must be True or False, got {o['bistatic']!r}")
    o["phase_tol"] = v.positive("phase_tol", o["phase_tol"])
    o["band_tol"] = v.positive("band_tol", o["band_tol"])
    if o["band_tol"] >= 1:
        raise ValueError(f"band_tol must be < 1, got {o['band_tol']!r}")
    o["kernel_width"] = v.positive_int("kernel_width", o["kernel_width"])
    if not 2 <= o["kernel_width"] <= 16:
        raise ValueError(f"kernel_width must be in 2..16, got {o['kernel_width']!r}")
    if o["tol_m"] is not None:
        o["tol_m"] = v.positive("tol_m", o["tol_m"])
    if o["workers"] is not None:
        o["workers"] = v.positive_int("workers", o["workers"])
    o["chunk"] = v.positive_int("chunk", o["chunk"])
    v.choice("depths", o["depths"], DEPTHS)
    if o["beam"] is not None:
        v.choice("beam", o["beam"], BEAM_MODES)
    o["beam_floor_db"] = v.finite("beam_floor_db", o["beam_floor_db"])
    return o


# -- the formation ---------------------------------------------------------------------------
@FORMATIONS.register("omega-k")
def form(profiles: Profiles, grid: VoxelGrid, *, backend: str | _cl.Selection | None = None, device: Any = None,
         progress=None, force: bool = False, pad_time: float = 1.5, pad: float | None = None,
         window: str | None = None, taper: float = 0.1, upsample: int | str = 1, bistatic: bool = True,
         phase_tol: float = 1e-2, band_tol: float = 1e-2, kernel_width: int = 4, tol_m: float | None = None,
         workers: int | None = None, chunk: int = 8192, max_sine: float | None = None, beam: str | None = None,
         beam_floor_db: float = -12.0, depths: str = "auto") -> Image:
    """ω-k image of ``profiles`` on ``grid`` (see the module notes for the method and its steps).

    Parameters
    ----------
    profiles : Profiles
        Complex baseband range profiles (from :func:`clsas.compress`, a sparse method, or
        :meth:`clsas.Profiles.from_range_profiles`) with speaker and microphone positions.
    grid : VoxelGrid
        On one side of the aperture's plane.
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
        Where the Stolt step runs (the FFTs run on the host, scipy.fft); ``"auto"`` (or a
        Selection that asked for it) falls back to the twin with one warning when the kernel
        will not build, ``"opencl"`` raises :class:`clsas.cl.BuildError`.
    device : optional
        OpenCL device or queue (None with a Selection).
    progress : callable(done, total), optional
        Called after each chunk of spatial-frequency columns.
    force : bool
        Accepted for the registry's interface (ω-k allocates about 16 bytes per voxel, times
        a few, and no more).
    pad_time, pad : float
        Zero padding of the delay FFT and the spatial one (each >= 1; ``pad`` None: from the geometry).
    window, taper
        ``"hann"``: a Hann window over the whole spatial band; None: the band's outer ``taper``
        (in [0, 1)) of each spatial-frequency axis under a raised cosine.
    upsample : int or "auto"
        The periodic spectrum repeated this many times along each axis (forms the aliased angles);
        ``"auto"``: enough for every voxel-stop angle.
    bistatic, phase_tol
        Compensate the speaker-microphone offset to ``phase_tol`` rad (False: the midpoint approximation).
    band_tol : float
        The band kept: frequency samples with at least ``band_tol**2`` of the strongest's energy.
    kernel_width, chunk, depths
        Cells of the spreading kernel (2-16), spatial-frequency columns per Stolt launch, and how the
        Stolt sum reaches the depths: ``"auto"``, ``"direct"`` or ``"spread"`` (step 4).
    tol_m, workers, max_sine : optional
        Lattice and plane tolerance, m (default a hundredth of the wavelength at 1.5 times the
        carrier); FFT threads (default all cores); the steepest look angle's sine kept (default
        from the geometry).
    beam, beam_floor_db
        The transducers' beams as plane-wave weights (see the module notes).

    Returns
    -------
    Image
        complex64 values on ``grid``; ``image.provenance["omega_k"]`` records what was used.
    """
    _check_types(profiles, grid)
    o = _options({"pad_time": pad_time, "pad": pad, "window": window, "taper": taper, "upsample": upsample,
                  "bistatic": bistatic, "phase_tol": phase_tol, "band_tol": band_tol, "kernel_width": kernel_width,
                  "tol_m": tol_m, "workers": workers, "chunk": chunk, "max_sine": max_sine, "beam": beam,
                  "beam_floor_db": beam_floor_db, "depths": depths})
    arrays = profiles.arrays(np.complex128)
    t_start = time.perf_counter()
    tol = _tolerance(o, arrays)  # the geometry first: a refusal costs nothing
    ap = _aperture(profiles, grid, o, tol)
    if isinstance(ap, Image):  # a 2-D line scan, imaged by the 2-D Stolt step
        return ap
    return _form_planar(arrays, grid, ap, o, tol, (backend, device), progress, t_start)


# the options form declares, with their defaults (what _options checks and fills in)
OPTIONS = {p.name: p.default for p in inspect.signature(form).parameters.values()
           if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in ("backend", "device", "progress", "force")}


def _check_types(profiles, grid) -> None:
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")


def _tolerance(o: dict, arrays) -> float:
    """The lattice and plane tolerance, m: the ``tol_m`` option, else a hundredth of the wavelength
    at 1.5 times the carrier (the band's top, about)."""
    if o["tol_m"] is not None:
        return o["tol_m"]
    data, tau0, dtau, fc, tx, rx, c = arrays
    f_hi = 1.5 * fc if fc > 0 else 0.25 / dtau
    return float(np.min(c)) / f_hi / 100


def _grid_axes(grid: VoxelGrid, ap, tol: float):
    """(pu, pv, depth): the grid's lattice axes in the aperture's order and its planes' distances from
    the aperture's plane, m (refused where one lies on it)."""
    axes = [grid.x_m, grid.y_m, grid.z_m]
    pu, pv, pw = (axes[i] for i in ap.perm)
    depth = np.abs(pw - ap.w_m)
    if depth.min() < 4 * tol:
        raise ValueError(f"grid: a voxel plane lies {depth.min():.3g} m from the aperture's plane; omega-k "
                         "needs the grid off the plane")
    return pu, pv, depth


def _form_planar(arrays, grid: VoxelGrid, ap, o: dict, tol: float, where: tuple, progress, t_start: float) -> Image:
    """Steps 1-6 for a planar aperture: the spectra, the Stolt step per lattice, onto the grid
    (``where``: the backend and device the Stolt step runs on)."""
    data, tau0, dtau, fc, tx, rx, c = arrays
    workers = o["workers"] or os.cpu_count() or 1
    pu, pv, depth = _grid_axes(grid, ap, tol)
    spec, f, c_ref, f_top = spectra(data, tau0, dtau, fc, c, o["pad_time"], o["band_tol"], workers)
    k = 4 * np.pi * f / c_ref
    flip = depth[0] > depth[-1]
    depth_inc = depth[::-1] if flip else depth
    path, runner, sel = choose_stolt_step(o, *where, ap, k, depth_inc)
    t_setup = time.perf_counter() - t_start
    info = {"groups": len(ap.groups), "n_f": len(f), "band_hz": (float(f.min()), float(f.max())), "lattices": [],
            "depths": path}
    values, t_stolt = form_lattices(ap, spec, k, (pu, pv, depth_inc), flip, o, workers, (path, runner),
                                     4 * np.pi * f_top / c_ref, progress, info["lattices"])
    values = np.transpose(values, np.argsort(ap.perm))
    if o["upsample"] == 1:
        info["cone_fraction"] = warn_outside_cone(ap, grid, f_top, c_ref, o["angular"])
    timings = {"omega_k_setup": t_setup, "stolt": t_stolt, "omega_k": time.perf_counter() - t_start}
    info["backend"] = sel.kind
    return Image(values, grid, "bp", sel.kind, sel.device, timings, provenance={"omega_k": info})


def _aperture(profiles: Profiles, grid: VoxelGrid, o: dict, tol: float):
    """The planar aperture (its beams' angular weights set in ``o["angular"]``), or, for a line
    scan, its image by :mod:`clsas.formation.omega_k_line`."""
    data, tau0, dtau, fc, tx, rx, c = profiles.arrays()
    axis = line.line_axis(tx, rx, tol)
    if axis is not None:
        return line.form_line(profiles, grid, axis, o, tol)
    ap = planar_aperture(tx, rx, grid, tol)
    o["angular"] = beam_angular(profiles, o, fc, c, ap, grid)
    return ap


def plan_sizes(profiles: Profiles, grid: VoxelGrid, *, rows: int = 256, **options) -> dict:
    """What :func:`form` would transform for ``profiles`` on ``grid``, without forming the image.

    For the cost model of ``formation="auto"`` (:mod:`clsas.formation.auto.predict`): the geometry is
    checked as :func:`form` checks it (:class:`NotPlanarUniform` or ``ValueError`` likewise), the
    band is estimated from at most ``rows`` evenly spread profiles.

    Returns
    -------
    dict
        ``n_meas``, ``n_lags``, ``n_fft`` (delay FFT length), ``n_f`` (frequencies in the band),
        ``nz``, ``f_band_hz`` (lowest, highest frequency of the band), ``f_top_hz`` (top of its
        -20 dB band), ``c_mps``, ``aperture`` (:class:`~clsas.formation.planar.PlanarAperture`),
        ``axes`` (grid axes in aperture order, depths from the plane) and ``groups``: per lattice
        ``mu``, ``mv``, ``up``, ``columns``, ``n_cells``, ``terms`` (powers of the bistatic
        expansion), ``width`` (the spreading kernel's cells); ``depths`` (the option: how the
        Stolt sum reaches the depths, see :func:`clsas.formation.stolt_numpy.depth_path`).
    """
    import scipy.fft

    o = _options(options)
    arrays = profiles.arrays()
    data, tau0, dtau, fc, tx, rx, c = arrays
    tol = _tolerance(o, arrays)
    ap = planar_aperture(tx, rx, grid, tol)
    pu, pv, depth = _grid_axes(grid, ap, tol)
    n_meas, n_lags = data.shape
    pick = np.unique(np.linspace(0, n_meas - 1, min(n_meas, int(rows))).astype(int))
    c_arr = np.broadcast_to(np.asarray(c, float), (n_meas,))
    _, f, c_ref, f_top = spectra(data[pick].astype(np.complex128), tau0[pick], dtau, fc, c_arr[pick],
                                  o["pad_time"], o["band_tol"], 1)
    k = 4 * np.pi * f / c_ref
    depth_inc = np.sort(depth)
    groups = []
    for g in ap.groups:
        lay = layout(g, k, pu, pv, depth_inc, o, 4 * np.pi * f_top / c_ref)
        u_max = 0.5 * (1.0 / depth_inc[0] - 1.0 / depth_inc[-1])
        groups.append({"mu": lay["mu"], "mv": lay["mv"], "up": lay["up"], "columns": len(lay["cols"]),
                       "n_cells": lay["n_cells"], "terms": group_terms(g, k, u_max, o),
                       "width": o["kernel_width"]})
    n_fft = scipy.fft.next_fast_len(int(math.ceil(o["pad_time"] * n_lags)))
    return {"n_meas": n_meas, "n_lags": n_lags, "n_fft": n_fft,
            "n_f": len(f), "nz": len(depth), "f_band_hz": (float(f.min()), float(f.max())), "f_top_hz": f_top,
            "c_mps": c_ref, "aperture": ap, "axes": (pu, pv, depth), "groups": groups, "depths": o["depths"]}
