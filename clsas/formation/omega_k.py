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
   non-uniform FFT (see :mod:`clsas.formation.stolt`: interpolation by spreading with an
   exponential-of-semicircle kernel of ``kernel_width`` cells on a 2x oversampled ``kz`` axis,
   error ~1e-3 at the default 4 cells, far under the method's own; work about
   ``n_f W + M log M``). ``"auto"`` (default) takes the one a fitted timing model
   (:func:`clsas.formation.stolt.depth_path`) predicts faster on OpenCL, and the spread on the
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
normal (:func:`clsas.beam.angular_weights`, the same tables as bp's), which needs every boresight
along the aperture's normal. A 2-D line scan goes to :mod:`clsas.formation.omega_k_line`.

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
from ..beam import BEAM_MODES, angular_weights, beam_weights, facing
from ..geometry import VoxelGrid
from ..image import Image
from ..profiles import Profiles
from . import stolt
from .planar import NotPlanarUniform, planar_aperture
from .registry import FORMATIONS
from .stolt_opencl import StoltDepthsPlan, StoltPlan

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


# -- step 1-2: frequency samples of every measurement ----------------------------------------
def _spectra(data, tau0, dtau, fc, c, pad_time, band_tol, workers):
    """(S (n_meas, n_f) complex, f (n_f,) Hz, c_ref): profile spectra on one wavenumber grid.

    ``S[m, j] df`` is measurement m's contribution at frequency ``f_j`` (for ``c_ref``), with
    backprojection's linear-interpolation response applied.
    """
    import scipy.fft

    n_meas, n_lags = data.shape
    n_fft = scipy.fft.next_fast_len(int(math.ceil(pad_time * n_lags)))
    fb = scipy.fft.fftfreq(n_fft, dtau)
    spec = scipy.fft.fft(data, n_fft, axis=1, workers=workers)
    energy = np.sum(np.abs(spec) ** 2, axis=0)
    # the band: the run of bins (in frequency order) from the first to the last whose energy
    # is at least band_tol^2 of the strongest bin's, above zero Hz
    srt = np.argsort(fb)
    strong = np.flatnonzero(energy[srt] >= band_tol**2 * energy.max())
    if energy.max() == 0:
        raise ValueError("profiles: all zero, nothing to image")
    bins = srt[strong.min(): strong.max() + 1]
    bins = bins[fb[bins] + fc != 0]  # zero Hz carries nothing to an image
    f_b = fb[bins]
    df = 1.0 / (n_fft * dtau)
    c_arr = np.broadcast_to(np.asarray(c, float), (n_meas,))
    c_ref = float(np.mean(c_arr))
    lin = np.sinc(f_b * dtau) ** 2
    if np.ptp(c_arr) <= 1e-9 * c_ref:
        s = spec[:, bins] * np.exp(-2j * np.pi * np.outer(tau0, f_b))
    else:  # one speed of sound per measurement: its own frequencies of the common kappa grid
        s = np.empty((n_meas, len(bins)), np.complex128)
        n = np.arange(n_lags)
        for m0 in range(0, n_meas, 256):
            m1 = min(n_meas, m0 + 256)
            f_m = (fc + f_b)[None, :] * (c_arr[m0:m1, None] / c_ref) - fc  # baseband, (b, n_f)
            e = np.exp(-2j * np.pi * f_m[:, None, :] * (tau0[m0:m1, None, None] + n[None, :, None] * dtau))
            s[m0:m1] = np.einsum("bn,bnf->bf", data[m0:m1], e) * (c_arr[m0:m1, None] / c_ref)
            s[m0:m1] *= (np.sinc(f_m * dtau) ** 2) / lin[None, :]
    s *= dtau * df * lin[None, :]
    e = energy[bins]
    strong20 = np.flatnonzero(e >= 1e-2 * e.max())  # the -20 dB band's highest |frequency|
    f_top = float(np.abs(fc + f_b[strong20]).max())
    return s, fc + f_b, c_ref, f_top


# -- helpers ---------------------------------------------------------------------------------
_DIRECT_MAX = 1 << 15  # entries of the largest DFT matrix _dft_axis multiplies by directly


def _dft_axis(a: np.ndarray, k: np.ndarray, x: np.ndarray, workers) -> np.ndarray:
    """``out[i, ...] = sum_q a[q, ...] exp(i k_q x_i)`` for evenly spaced ``k`` (any order) and ``x``.

    A chirp-z (Bluestein) transform: exact, O((Q + n) log(Q + n)) per line; where the
    ``n x Q`` matrix of the DFT is small (up to ``_DIRECT_MAX`` entries, e.g. a 64-voxel axis
    from 256 wavenumbers), its product with ``a`` instead (one BLAS call, several times faster
    than the three FFTs at the sizes of everyday scans; the same values to float rounding).
    """
    import scipy.fft

    Q, n = len(k), len(x)
    if n == 1 or Q == 1 or n * Q <= _DIRECT_MAX:
        e = np.exp(1j * np.outer(x, k)).astype(np.result_type(a.dtype, np.complex64))
        return np.tensordot(e, a, axes=(1, 0))
    order = np.argsort(k)
    k = k[order]
    a = a[order]
    dk, dx = k[1] - k[0], x[1] - x[0]
    w = dk * dx
    q = np.arange(Q)
    i = np.arange(n)
    dt = a.dtype
    pre = np.exp(1j * (q * dk * x[0] + 0.5 * w * q * q)).astype(dt)
    L = scipy.fft.next_fast_len(Q + n - 1)
    m = np.arange(-(Q - 1), n)
    chirp = np.zeros(L, dt)
    chirp[np.mod(m, L)] = np.exp(-0.5j * w * m * m)
    shape = (-1,) + (1,) * (a.ndim - 1)
    y = scipy.fft.fft(a * pre.reshape(shape), L, axis=0, workers=workers)
    y *= scipy.fft.fft(chirp).reshape(shape)
    conv = scipy.fft.ifft(y, axis=0, workers=workers)[:n]
    post = np.exp(1j * (k[0] * x + 0.5 * w * i * i)).astype(dt)
    return conv * post.reshape(shape)


def _edge_window(kq: np.ndarray, edge: float, taper: float, window: str | None) -> np.ndarray:
    r = np.abs(kq) / edge
    if window == "hann":
        return np.cos(0.5 * np.pi * np.clip(r, 0, 1)) ** 2
    if taper <= 0:
        return (r <= 1).astype(float)
    ramp = np.clip((r - (1 - taper)) / taper, 0, 1)
    return 0.5 * (1 + np.cos(np.pi * ramp))


def farthest_offsets(g, pu, pv) -> tuple[float, float]:
    """The largest in-plane offsets ``(du, dv)``, m, between a voxel (axes ``pu``, ``pv``) and a stop
    of the lattice group ``g``."""
    (u0, u1), (v0, v1) = g.extent_uv
    return max(abs(pu[-1] - u0), abs(u1 - pu[0])), max(abs(pv[-1] - v0), abs(v1 - pv[0]))


def steepest_sine(g, pu, pv, depth_min) -> float:
    """Sine of the steepest voxel-stop angle from the plane's normal."""
    lat = math.hypot(*farthest_offsets(g, pu, pv))
    return lat / math.hypot(lat, depth_min)


def _stolt_step(o: dict, backend, device, ap, k: np.ndarray, depth: np.ndarray):
    """(path, OpenCL plan or None, selection) of the Stolt step: the way to the depths chosen for
    the device it runs on (the twins' after a fallback)."""
    u_max = 0.5 * (1.0 / depth[0] - 1.0 / depth[-1])
    terms = max(_group_terms(g, k, u_max, o) for g in ap.groups)
    sel = _cl.select(backend, device)
    path = stolt.depth_path(o["depths"], len(k), len(depth), o["kernel_width"], terms, sel.opencl)
    cls = StoltDepthsPlan if path == "direct" else StoltPlan
    runner, sel = sel.plan(lambda q: cls(queue=q))  # None: the twin (NumPy after a fallback, logged)
    if runner is None:
        path = stolt.depth_path(o["depths"], len(k), len(depth), o["kernel_width"], terms, False)
    return path, runner, sel


def _n_cells(n_z: int, width: int) -> int:
    """Cells of the folded kz axis (2x oversampled, at least two kernel widths)."""
    import scipy.fft

    return scipy.fft.next_fast_len(max(2 * n_z, 2 * width))


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
    spec, f, c_ref, f_top = _spectra(data, tau0, dtau, fc, c, o["pad_time"], o["band_tol"], workers)
    k = 4 * np.pi * f / c_ref
    flip = depth[0] > depth[-1]
    depth_inc = depth[::-1] if flip else depth
    path, runner, sel = _stolt_step(o, *where, ap, k, depth_inc)
    t_setup = time.perf_counter() - t_start
    info = {"groups": len(ap.groups), "n_f": len(f), "band_hz": (float(f.min()), float(f.max())), "lattices": [],
            "depths": path}
    values, t_stolt = _form_lattices(ap, spec, k, (pu, pv, depth_inc), flip, o, workers, (path, runner),
                                     4 * np.pi * f_top / c_ref, progress, info["lattices"])
    values = np.transpose(values, np.argsort(ap.perm))
    if o["upsample"] == 1:
        info["cone_fraction"] = _warn_outside_cone(ap, grid, f_top, c_ref, o["angular"])
    timings = {"omega_k_setup": t_setup, "stolt": t_stolt, "omega_k": time.perf_counter() - t_start}
    info["backend"] = sel.kind
    return Image(values, grid, "bp", sel.kind, sel.device, timings, provenance={"omega_k": info})


def _form_lattices(ap, spec, k, axes, flip: bool, o: dict, workers: int, stolt_step, k_top: float, progress,
                   records: list) -> tuple[np.ndarray, float]:
    """Each lattice group's image, summed, depths in the grid's order: (values in the aperture's axis
    order, the Stolt step's seconds); each group's record appended to ``records``."""
    pu, pv, depth_inc = axes
    values = np.zeros((len(pu), len(pv), len(depth_inc)), np.complex64)
    t_stolt = 0.0
    for g in ap.groups:
        img, ginfo, dt_stolt = _form_group(g, spec[g.index], k, pu, pv, depth_inc, o, workers, stolt_step, k_top,
                                           progress)
        values += img[:, :, ::-1] if flip else img
        records.append(ginfo)
        t_stolt += dt_stolt
    return values, t_stolt


def _aperture(profiles: Profiles, grid: VoxelGrid, o: dict, tol: float):
    """The planar aperture (its beams' angular weights set in ``o["angular"]``), or, for a line
    scan, its image by :mod:`clsas.formation.omega_k_line`."""
    from . import omega_k_line as line

    data, tau0, dtau, fc, tx, rx, c = profiles.arrays()
    axis = line.line_axis(tx, rx, tol)
    if axis is not None:
        return line.form_line(profiles, grid, axis, o, tol, (_spectra, _dft_axis, _edge_window))
    ap = planar_aperture(tx, rx, grid, tol)
    o["angular"] = _beam_angular(profiles, o, fc, c, ap, grid)
    return ap


def _plane_wave_beam(weights, ku: np.ndarray, kv: np.ndarray, k: np.ndarray):
    """(columns, n_f) two-way beam weight of each plane wave (1 without beams)."""
    if weights is None:
        return 1.0
    return angular_weights(weights, np.hypot(ku, kv)[:, None] / np.abs(k))


def _beam_angular(profiles: Profiles, o: dict, fc: float, c, ap, grid: VoxelGrid):
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


def _beam_edge_sine(weights) -> float:
    """The sine of the steepest angle from the normal that the beams' angular weights keep (1
    without beams): where a weight first stays under 1e-3 of its peak."""
    if weights is None:
        return 1.0
    s = np.linspace(0.0, 1.0, 2001)
    w = angular_weights(weights, s)
    kept = np.flatnonzero(w > 1e-3 * max(float(w.max()), 1e-300))
    return float(s[kept[-1]]) if len(kept) else 0.0


def _warn_outside_cone(ap, grid: VoxelGrid, f_top: float, c_ref: float, weights=None) -> float:
    """The share of the grid in the aperture's well-sampled cone (within the beams' edge, where the
    profiles carry beams), with a warning where it is under half."""
    from .planar import cone_of

    frac = float(cone_of(ap, grid, f_top, c_ref, max_sine=_beam_edge_sine(weights)).mean())
    if frac < 0.5:
        log.warning("omega-k: the aperture's lattice samples only %.0f %% of the grid unaliased at %.0f kHz "
                    "(its well-sampled cone); elsewhere backprojection also forms aliased angles (grating "
                    "lobes), which omega-k leaves out: formation_options={'upsample': 'auto'} forms them, "
                    "or use formation='bp'", 100 * frac, f_top / 1e3)
    return frac


def _group_terms(g, k: np.ndarray, u_max: float, o: dict) -> int:
    """Powers of the bistatic expansion one lattice group needs (``phase_tol`` over its depths)."""
    alpha_max = (g.baseline_uvw[0] ** 2 + g.baseline_uvw[1] ** 2) * np.abs(k).max() / 8
    return _n_terms(alpha_max, u_max, o["phase_tol"], o["bistatic"])


def _n_terms(alpha_max: float, u_max: float, tol: float, bistatic: bool) -> int:
    if not bistatic:
        return 1
    x = alpha_max * u_max
    p = 1
    while x**p / math.factorial(p) > tol and p < 12:
        p += 1
    return p


def _layout(g, k, pu, pv, depth, o, k_top) -> dict:
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
    wu = _edge_window(ku_all, up * np.pi / du, o["taper"], o["window"])
    wv = _edge_window(kv_all, up * np.pi / dv, o["taper"], o["window"])
    # keep only columns with weight, and with any frequency inside the look-angle window
    kp_ok = np.hypot(ku_all[:, None], kv_all[None, :]) < s2 * np.abs(k).max()
    cols = np.argwhere((wu[:, None] * wv[None, :] > 0) & kp_ok)
    n_cells = _n_cells(len(depth), o["kernel_width"])
    return {"mu": mu, "mv": mv, "up": up, "s1": s1, "s2": s2, "ku": ku_all, "kv": kv_all, "wu": wu, "wv": wv,
            "cols": cols, "n_cells": n_cells}


def _form_group(g, spec, k, pu, pv, depth, o, workers, stolt_step, k_top, progress):
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
    lay = _layout(g, k, pu, pv, depth, o, k_top)
    mu, mv, up, s1, s2, cols = lay["mu"], lay["mv"], lay["up"], lay["s1"], lay["s2"], lay["cols"]
    ku_all, kv_all, wu, wv, n_cells = lay["ku"], lay["kv"], lay["wu"], lay["wv"], lay["n_cells"]
    # single precision from the lattice on (relative error ~1e-7, far below the method's); the
    # zero padding of u is transformed only along the nv columns that hold stops
    lattice = np.zeros((nu, nv, len(k)), np.complex64)
    lattice[g.iu, g.iv] = spec
    dspec = scipy.fft.fft(scipy.fft.fft(lattice, mu, axis=0, workers=workers), mv, axis=1, workers=workers)
    del lattice
    n_terms = _group_terms(g, k, u_max, o)
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
        block *= _plane_wave_beam(o["angular"], ku_all[iu_], kv_all[iv_], k)  # the beam weights: 1 without beams
        t = time.perf_counter()
        T[iu_, iv_] = _stolt_columns(stolt_step, block, k, ku_all[iu_], kv_all[iv_], params, factors, workers)
        t_stolt += time.perf_counter() - t
        if progress is not None:
            progress(min(len(cols), c0 + step), len(cols))
    del dspec
    T *= (1j * depth[None, None, :]).astype(np.complex64)
    img = _dft_axis(T, ku_all, pu - g.origin_uv[0], workers)
    img = np.moveaxis(_dft_axis(np.moveaxis(img, 1, 0), kv_all, pv - g.origin_uv[1], workers), 0, 1)
    img /= (4 * np.pi**2) / ((2 * np.pi / (mu * du)) * (2 * np.pi / (mv * dv)))
    info = {"shape": (nu, nv), "spacing_m": (du, dv), "padded": (mu, mv), "upsample": up, "columns": len(cols),
            "terms": n_terms, "z_ref_m": zref, "look_sine": (s1, s2), "cells": n_cells}
    return img, info, t_stolt


def _stolt_columns(stolt_step, block, k, ku, kv, params, factors, workers) -> np.ndarray:
    """(cols, nz) the Stolt sum of ``block``'s columns at the depths, by the step's path."""
    path, runner = stolt_step
    nz = factors.shape[1]
    if path == "direct":
        return (runner or stolt.direct)(block, k, ku, kv, params, nz, factors)
    cells = (runner or stolt.spread)(block, k, ku, kv, params)
    return stolt.terms_to_depths(cells, nz, params, factors, workers, overwrite=True)


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
        Stolt sum reaches the depths, see :func:`clsas.formation.stolt.depth_path`).
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
    _, f, c_ref, f_top = _spectra(data[pick].astype(np.complex128), tau0[pick], dtau, fc, c_arr[pick],
                                  o["pad_time"], o["band_tol"], 1)
    k = 4 * np.pi * f / c_ref
    depth_inc = np.sort(depth)
    groups = []
    for g in ap.groups:
        lay = _layout(g, k, pu, pv, depth_inc, o, 4 * np.pi * f_top / c_ref)
        u_max = 0.5 * (1.0 / depth_inc[0] - 1.0 / depth_inc[-1])
        groups.append({"mu": lay["mu"], "mv": lay["mv"], "up": lay["up"], "columns": len(lay["cols"]),
                       "n_cells": lay["n_cells"], "terms": _group_terms(g, k, u_max, o),
                       "width": o["kernel_width"]})
    n_fft = scipy.fft.next_fast_len(int(math.ceil(o["pad_time"] * n_lags)))
    return {"n_meas": n_meas, "n_lags": n_lags, "n_fft": n_fft,
            "n_f": len(f), "nz": len(depth), "f_band_hz": (float(f.min()), float(f.max())), "f_top_hz": f_top,
            "c_mps": c_ref, "aperture": ap, "axes": (pu, pv, depth), "groups": groups, "depths": o["depths"]}
