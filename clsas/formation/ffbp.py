"""3-D fast factorized backprojection (FFBP, after Ulander, Hellsten and Stenström 2003) for any
trajectory and bistatic pairs.

``reconstruct(dataset, grid, formation="ffbp", formation_options={...})`` or
:func:`form` here. The measurements are split into a tree of sub-apertures by position (each
node's phase centres split along their widest direction into ``factor`` groups of equal count:
quadrants of a raster, arcs of a circle, stretches of a hand-held track). Each leaf's
sub-image is formed by exact backprojection onto a coarse spherical grid about the leaf's
centre (range and two direction cosines, sampled as finely as the leaf's size needs); parents
interpolate their children's sub-images onto their own finer grids and sum them, level by
level; the top sub-images are finally interpolated onto the user's Cartesian grid. Every
sub-image is kept at baseband: the carrier of the node's reference path (through its mean
speaker and microphone positions) is removed when it is formed and restored at each
interpolation, so what is interpolated varies only at the band's width in range and at the
node's size in angle. The result has exact backprojection's values and phase convention
(:func:`clsas.backproject`); ``depth=0`` *is* exact backprojection.

Cost and error. Exact backprojection costs voxels x measurements. FFBP costs about
(samples per level) x (levels) x ``factor`` x ``(order + 1)³`` for the merges, plus
(leaf samples) x (measurements per leaf) for the leaves and voxels x ``factor`` x
``(order + 1)³`` for the last step; the samples per level are about the voxels at which the
aperture's image is Nyquist-sampled, times ``oversample² x range_oversample``, and hardly
depend on the number of measurements. The error against exact backprojection comes from the
interpolations, one per level plus the last step. It is mostly a systematic loss near the
band's edge, the same in every sub-image, so the levels' errors add almost coherently:
``depth`` levels of -50 dB each give about -50 + 20 log10(depth + 1) dB. It falls fast as
``oversample``, ``range_oversample`` and ``order`` rise and grows with ``depth``; fewer,
bigger leaves err less but cost their measurements per leaf sample. Measured on a dense
raster (128 x 128 stops over 0.75 m, 256 x 256 x 128 voxels, depth 5, cubic least-squares
weights; ``bench/ffbp_sweep.py``): -26 dB at 1.5 times the Nyquist rate and 60x faster than
exact backprojection, -36 dB at twice (the default) and 36x faster.
``order=1`` (linear) needs far more oversampling than ``order=3`` for the same error;
``order=5`` costs (6/4)³ ≈ 3.4x the cubic's per sample.

When it pays. FFBP wins where many measurements fall on each resolution cell of a grid that
samples the image finely enough: a dense raster (thousands of stops) onto a grid at about
the image's resolution. On a grid much coarser than the image's detail (a 360-degree circle of
a few hundred stops onto 5 mm voxels) the sub-images, which must be sampled at the aperture's
own bandwidth, hold more samples than the grid has voxels, and exact backprojection is faster.

The speed of sound may differ per measurement: the leaves use each measurement's own, the
reference paths their mean.

Transducer beams (``beam``, ``beam_floor_db``, as bp's) are applied at the leaves: each pair is
weighted (or gated) by its two-way beam at the leaf sub-image's own samples, and the merges
interpolate the weighted sub-images. The angular sampling must then also resolve the beam
(a warning names the ``oversample`` that does); a gate (``"limited"``) is not band-limited, so
its image keeps an error against bp's at any sampling (see the beams guide).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.geometry import VoxelGrid
from ..types.image import Image
from ..types.profiles import Profiles
from . import ffbp_numpy as twin
from .bp_numpy import upsample_factor
from .bp_opencl import RecordsPlan
from .ffbp_opencl import FfbpPipeline
from .ffbp_tree import Tree, build_tree, default_depth, estimate_band, max_depth
from .guard import available_memory_bytes, check_grid
from .registry import FORMATIONS

__all__ = ["form", "plan_tree", "ORDERS"]

log = logging.getLogger(__name__)

ORDERS = (1, 3, 5)  # interpolation orders: linear, cubic, quintic Lagrange (order + 1 taps per axis)
OPTIONS = ("depth", "factor", "oversample", "range_oversample", "order", "interpolator", "band_hz", "band_tail")


def _options(n_meas: int, depth=None, factor=4, oversample=2.0, range_oversample=2.0, order=3,
             interpolator="lsq", band_hz=None, band_tail=1e-4) -> dict:
    factor = v.positive_int("factor", factor)
    if factor < 2:
        raise ValueError(f"factor must be >= 2 (children per merge), got {factor}")
    if depth is None:
        depth = default_depth(n_meas, factor)
    else:
        if isinstance(depth, bool) or not isinstance(depth, int | np.integer):
            raise TypeError(f"depth must be an integer or None, got {depth!r}")
        depth = int(depth)
        deepest = max_depth(n_meas, factor)
        if depth < 0 or depth > deepest:
            raise ValueError(f"depth must be in 0..{deepest} for {n_meas} measurements and factor {factor} "
                             f"(factor ** depth <= n_meas), got {depth}")
    oversample = v.positive("oversample", oversample)
    range_oversample = v.positive("range_oversample", range_oversample)
    for name, val in (("oversample", oversample), ("range_oversample", range_oversample)):
        if not 1.0 <= val <= 16.0:
            raise ValueError(f"{name} must be in [1, 16] (times the Nyquist rate), got {val:g}")
    if order not in ORDERS or isinstance(order, bool):
        raise ValueError(f"order must be one of {ORDERS} (Lagrange interpolation), got {order!r}")
    v.choice("interpolator", interpolator, twin.INTERPOLATORS)
    if band_hz is not None:
        lo, hi = v.array("band_hz", band_hz, shape=(2,))
        if not 0 <= lo < hi:
            raise ValueError(f"band_hz must be (f_lo, f_hi) with 0 <= f_lo < f_hi, got ({lo:g}, {hi:g})")
        band_hz = (float(lo), float(hi))
    band_tail = v.positive("band_tail", band_tail)
    if band_tail >= 0.5:
        raise ValueError(f"band_tail must be < 0.5 (fraction of the energy left outside the band), got {band_tail:g}")
    return {"depth": depth, "factor": factor, "oversample": oversample, "range_oversample": range_oversample,
            "order": int(order), "interpolator": interpolator, "band_hz": band_hz, "band_tail": band_tail}


def plan_tree(profiles: Profiles, grid: VoxelGrid, **options) -> Tree:
    """The sub-aperture tree and sub-image grids FFBP would use (``options`` as :func:`form`'s;
    the beam's do not change the tree)."""
    data, tau0, dtau, fc, tx, rx, c = profiles.arrays()
    opts = _options(len(data), **{k: val for k, val in options.items() if k not in ("beam", "beam_floor_db")})
    return _tree(data, dtau, fc, tx, rx, c, grid, opts)


# the last tree planned, and what it was planned for: formation="auto" plans a tree to cost
# FFBP (clsas.formation.auto.predict) and the formation then runs with the same request
_LAST_TREE: list = []


def _tree_key(data, dtau, fc, tx, rx, c, grid: VoxelGrid, opts: dict) -> str:
    import hashlib

    h = hashlib.sha1()
    step = max(1, data.shape[0] // 64)
    for a in (np.ascontiguousarray(data[::step]), tx, rx, c, grid.bounds()):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr((data.shape, data.dtype.str, float(dtau), float(fc), sorted(opts.items()))).encode())
    return h.hexdigest()


def _tree(data, dtau, fc, tx, rx, c, grid: VoxelGrid, opts: dict) -> Tree:
    """The tree for this request (the last one planned, if it was planned for the same request)."""
    key = _tree_key(data, dtau, fc, tx, rx, c, grid, opts)
    if _LAST_TREE and _LAST_TREE[0] == key:
        return _LAST_TREE[1]
    tree = _plan(data, dtau, fc, tx, rx, c, grid, opts)
    _LAST_TREE[:] = [key, tree]
    return tree


def _plan(data, dtau, fc, tx, rx, c, grid: VoxelGrid, opts: dict) -> Tree:
    band = opts["band_hz"] or estimate_band(data, dtau, fc, opts["band_tail"])
    band = (max(band[0], 1e-3 * band[1]), band[1])
    tree = build_tree(tx, rx, c, grid.bounds(), band, depth=opts["depth"], factor=opts["factor"],
                      oversample=opts["oversample"], range_oversample=opts["range_oversample"],
                      taps=opts["order"] + 1)
    return tree


def _beam_weights(profiles: Profiles, beam: str | None, floor_db: float, fc: float, c):
    """The leaves' pair weights for ``beam``, or None; and the mode applied ("none" where nothing
    is weighted). The default where the profiles carry a directional beam is ``"weighted"``, not
    bp's ``"limited"``: a weighted sub-image interpolates, a gated one does not (its edges are
    not band-limited: -10 dB or worse against bp's gate on the tests' tilted scan)."""
    from ..physics.beam import BEAM_MODES, beam_weights

    floor_db = v.finite("beam_floor_db", floor_db)
    mode = None if beam is None else v.choice("beam", beam, BEAM_MODES)
    beams = profiles.beams
    directional = beams is not None and not beams.is_omni
    if directional and beams.n_meas != profiles.n_meas:
        raise ValueError(f"beams must have {profiles.n_meas} boresights (one per measurement), got {beams.n_meas}")
    if mode is None:
        mode = "weighted" if directional else "none"
        if directional:
            log.info("ffbp: the profiles carry directional beams: beam='weighted' (bp's default 'limited' gates "
                     "pairs, and a gate's edges do not interpolate)")
    elif mode == "none" and directional:
        log.warning("ffbp: beam='none': imaging directional transducers as omnidirectional (grating lobes "
                    "of stops whose beams never saw a voxel are kept)")
    weights = beam_weights(beams, mode, fc, c, floor_db)
    return weights, (mode if weights is not None else "none")


def _check_beam_sampling(tree: Tree, weights, oversample: float) -> None:
    """Warn where the leaves' angular step is coarse for the beam: a weighted sub-image must
    resolve the two-way pattern for the merges to interpolate it. On the tests' 4 x 4-stop water
    case, with the -6 dB half-angle over 0.6 / 1.2 / 2.5 steps of direction cosine, "weighted"
    erred by -11 / -26 / -41 dB against bp's; "limited" by -7 / -12 / -14 dB (a gate's edges are
    not band-limited: no sampling makes them exact)."""
    if weights is None:
        return
    two_way = weights.luts[0] * weights.luts[1]
    u = np.linspace(0.0, 1.0, len(two_way))
    below = np.flatnonzero(two_way < 0.5 * two_way[0])
    if not below.size:
        return
    # the -6 dB half-angle as a direction cosine (past 90 degrees the whole hemisphere)
    half = float(np.sin(min(2 * np.arcsin(u[below[0]]), 0.5 * np.pi)))
    step = float(np.max(tree.levels[-1].geom[:, 22:24]))
    if step > half / 1.5:
        need = math.ceil(oversample * 1.5 * step / half * 1.05 * 100) / 100  # a little over, rounded up
        fix = (f"oversample={need:g} would give 1.5" if need <= 16 else
               "even oversample=16 would not give 1.5; use formation='bp'")
        log.warning("ffbp: the beams' -6 dB half-angle spans %.1f angular steps of the leaf sub-images (1.5 or "
                    "more keep a weighted image within about -25 dB of bp's; a gate errs more); %s",
                    half / step, fix)


def _check_memory(tree: Tree, grid: VoxelGrid, kind: str, device, force: bool) -> None:
    sizes = [lev.size for lev in tree.levels]
    pairs = max((a + b for a, b in zip(sizes, sizes[1:], strict=False)), default=sizes[0] if sizes else 0)
    bytes_per = 16 if kind == "numpy" else 8
    need = bytes_per * pairs
    if max(sizes) >= 2**31:
        raise ValueError(f"ffbp: a level of {max(sizes):.3g} samples exceeds the kernels' 32-bit indexing "
                         "(lower oversample/range_oversample, or a coarser grid)")
    problems = []
    avail = available_memory_bytes()
    if avail is not None and need > 0.5 * avail:
        problems.append(f"two levels of sub-images need {need / 1e9:.3g} GB of host memory, {avail / 1e9:.3g} GB "
                        "available")
    if kind == "opencl" and device is not None and 8 * max(sizes) > int(device.max_mem_alloc_size):
        problems.append(f"a level of {8 * max(sizes) / 1e9:.3g} GB exceeds the device's largest allocation "
                        f"({int(device.max_mem_alloc_size) / 1e9:.3g} GB)")
    if problems:
        text = "; ".join(problems) + " (lower oversample/range_oversample, or a coarser grid)"
        if not force:
            raise ValueError(f"ffbp: {text}; force=True tries anyway")
        log.warning("ffbp: %s; going on (force=True)", text)


@FORMATIONS.register("ffbp")
def form(
    profiles: Profiles, grid: VoxelGrid, *, backend: str | _cl.Selection | None = None, device: Any = None,
    progress: Callable[[int, int], None] | None = None, force: bool = False, depth: int | None = None,
    factor: int = 4, oversample: float = 2.0, range_oversample: float = 2.0, order: int = 3,
    interpolator: str = "lsq", band_hz: tuple[float, float] | None = None, band_tail: float = 1e-4,
    beam: str | None = None, beam_floor_db: float = -12.0,
) -> Image:
    """Image ``profiles`` on ``grid`` by fast factorized backprojection.

    Parameters
    ----------
    profiles : Profiles
        Complex baseband range profiles with their positions and speed of sound (from
        :func:`clsas.compress`); one bistatic pair per row, any trajectory.
    grid : VoxelGrid
        Must lie in front of the aperture: within 72 degrees of each sub-aperture's line of
        sight to the grid's centre (else a ``ValueError`` names ``formation='bp'``).
    backend, device
        As :func:`clsas.backproject` (``device`` None with a Selection); the NumPy path works alone.
        ``"auto"`` (or a Selection that asked for it) falls back to it with one warning when a kernel
        will not build, ``"opencl"`` raises :class:`clsas.cl.BuildError`.
    progress : callable(done, total), optional
        Called after each level (leaves, each merge, the final interpolation).
    force : bool
        Go on even if the sub-images seem not to fit in memory.
    depth : int, optional
        Factorisation levels: 0 is exact backprojection; ``d`` splits the aperture ``d`` times
        (leaves of ``n_meas / factor**d`` measurements). Default: leaves of 16 or more
        measurements (fewer levels err less; a leaf costs its measurements per sample).
    factor : int
        Children per merge (>= 2; 4 splits a raster into quadrants).
    oversample, range_oversample : float
        Sampling of the sub-images over their Nyquist rate in angle and in range (1 to 16);
        the error falls and the cost rises (as ``oversample² x range_oversample``).
    order : {1, 3, 5}
        Interpolation order on every axis (``order + 1`` taps each).
    interpolator : {"lsq", "lagrange"}
        ``"lsq"``: weights with the least squared error over the band the sub-images are
        sampled for (at twice the Nyquist rate, 4 taps err by -30 dB at worst against
        Lagrange's -19 dB, for the same cost); ``"lagrange"``: the polynomial through the taps.
    band_hz, band_tail
        The frequencies the profiles hold, ``(f_lo, f_hi)`` with the carrier included; default:
        estimated from their spectrum, all but ``band_tail`` (1e-4) of the energy.
    beam, beam_floor_db
        As :func:`clsas.backproject`, applied at the leaves, but ``"weighted"`` by default with beams.

    Returns
    -------
    Image
        Values as :func:`clsas.backproject` gives them; ``image.plan`` is the
        :class:`~clsas.formation.ffbp_tree.Tree` (``reconstruct`` puts its own plan there instead),
        ``image.provenance["ffbp"]`` the options used (depth resolved, band estimated) and the
        samples per level, ``image.timings_s`` the time of each step.
    """
    _check_types(profiles, grid)
    data, tau0, dtau, fc, tx, rx, c = profiles.arrays()
    opts = _options(len(data), depth, factor, oversample, range_oversample, order, interpolator, band_hz, band_tail)
    weights, mode = _beam_weights(profiles, beam, beam_floor_db, fc, c)
    if opts["depth"] == 0:
        return _exact(profiles, grid, backend, device, force, progress, mode, beam_floor_db)
    sel = _cl.select(backend, device)
    check_grid(grid, sel.kind, sel.cl_device, force=force)
    t_start = time.perf_counter()
    tree = _planned_tree(data, dtau, fc, tx, rx, c, grid, opts, sel, force, weights)
    timings = {"ffbp_plan": time.perf_counter() - t_start}
    values, sel = _run(tree, grid, (data, tau0, dtau, fc, tx, rx, c), opts, sel, progress, timings, weights,
                       rows=_rows_of(profiles))
    timings["ffbp"] = time.perf_counter() - t_start
    return Image(values.reshape(grid.shape), grid, "bp", sel.kind, sel.device, timings, plan=tree,
                 provenance={"ffbp": _record(opts, tree, mode, beam_floor_db)})


def _planned_tree(data, dtau, fc, tx, rx, c, grid: VoxelGrid, opts: dict, sel: _cl.Selection, force: bool,
                  weights) -> Tree:
    """The tree for this request, checked before any sub-image is formed (its memory on the device,
    the beams' sampling) and described in the log."""
    tree = _tree(data, dtau, fc, tx, rx, c, grid, opts)
    _check_memory(tree, grid, sel.kind, sel.cl_device, force)
    _check_beam_sampling(tree, weights, opts["oversample"])
    for line in tree.describe().splitlines():
        log.info("ffbp: %s", line)
    return tree


def _record(opts: dict, tree: Tree, beam: str, beam_floor_db: float) -> dict:
    """What the image's provenance keeps: the options used (depth resolved), the beam, the band the
    tree was sampled for and the samples per level."""
    used = {k: opts[k] for k in OPTIONS if k != "band_hz"}
    return used | {"beam": beam, "beam_floor_db": float(beam_floor_db), "band_hz": list(tree.band_hz),
                   "samples_per_level": [lev.samples for lev in tree.levels]}


def _check_types(profiles, grid) -> None:
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")


def _exact(profiles, grid, backend, device, force, progress, beam: str, beam_floor_db: float) -> Image:
    """Depth 0: exact backprojection, with the same beam."""
    from .bp import Backprojector

    bp = Backprojector(grid, backend=backend, device=device, force=force, beam=beam, beam_floor_db=beam_floor_db)
    image = bp(profiles, progress=progress)
    return replace(image, provenance={**image.provenance, "ffbp_depth": 0, "ffbp": {"depth": 0, "beam": beam,
                                                                                 "beam_floor_db": beam_floor_db}})


def _rows_of(profiles: Profiles):
    """The rows the OpenCL compression left on the device with ``profiles.data`` (valid on their own
    queue: :meth:`clsas.cl.DeviceRows.valid`), or None."""
    return profiles.device_rows()


def _device_records(pipe: FfbpPipeline, rows, n_lags: int, dtau: float, fc: float):
    """The row-map records plan that makes the leaves' records from ``rows`` on the pipeline's queue,
    or None (the rows are on another queue, or the kernel does not build there: the records are
    then made on the host)."""
    if rows is None or rows.queue is not pipe.leaf.queue or rows.n_cols > max(2, n_lags):
        return None
    up = upsample_factor(fc, dtau)
    key = (rows.n_rows, max(2, n_lags), up, "row_map")
    try:
        return _cl.reused(pipe.leaf.queue, "carrier_records", key,
                          lambda q: RecordsPlan(rows.n_rows, n_lags, up, queue=q, row_map=True))
    except _cl.BuildError as exc:
        log.info("ffbp: the records kernel does not build here (%s); records made on the host", exc)
        return None


def _run(tree: Tree, grid: VoxelGrid, arrays: tuple, opts: dict, sel: _cl.Selection, progress, timings: dict,
         weights=None, rows=None):
    """The tree's levels on the device (or the twin where the kernels will not build): (values, selection).
    ``rows``: the profiles as the compression left them on the device (their records are then made
    there, in tree order), or None."""
    data, tau0, dtau, fc, tx, rx, c = arrays
    o = tree.order
    geometry = (tau0[o], dtau, fc, tx[o], rx[o], c[o])  # the profiles' rows are put in tree order where used
    if weights is not None:  # the boresights in tree order, as the profiles
        weights = replace(weights, tx_dir=np.asarray(weights.tx_dir)[o], rx_dir=np.asarray(weights.rx_dir)[o])
    taps = opts["order"] + 1
    tables = (twin.weight_table(taps, opts["range_oversample"], opts["interpolator"]),
              twin.weight_table(taps, opts["oversample"], opts["interpolator"]))
    lut = 0 if weights is None else weights.luts.shape[1]
    pipe, sel = sel.plan(lambda q: FfbpPipeline(tree, grid, data.shape[1], tables, queue=q, beam_lut=lut,
                                                n_meas=len(data)))
    if pipe is None:
        return _run_numpy(tree, grid, (data[o], *geometry), tables, progress, timings, weights), sel
    records = _device_records(pipe, rows, data.shape[1], dtau, fc)
    if records is not None:
        values = pipe.from_device(rows, records, o, *geometry, progress=progress, beam=weights)
    else:
        values = pipe(data[o], *geometry, progress=progress, beam=weights)
    timings.update(pipe.timings_s)
    return values, sel


def _run_numpy(tree: Tree, grid: VoxelGrid, args, tables, progress, timings: dict, weights=None) -> np.ndarray:
    total = tree.depth + 1
    t = time.perf_counter()
    values = twin.form_leaves(*args, tree.levels[-1], tree.kref, weights)
    timings["ffbp_leaves"] = time.perf_counter() - t
    done = 1
    if progress is not None:
        progress(done, total)
    t = time.perf_counter()
    for d in range(tree.depth - 1, 0, -1):
        values = twin.merge(values, tree.levels[d], tree.levels[d - 1], tree.kref, tables)
        done += 1
        if progress is not None:
            progress(done, total)
    timings["ffbp_merges"] = time.perf_counter() - t
    t = time.perf_counter()
    out = twin.to_grid(values, tree.levels[0], grid.points(), tree.kref, tables)
    timings["ffbp_grid"] = time.perf_counter() - t
    if progress is not None:
        progress(total, total)
    return out
