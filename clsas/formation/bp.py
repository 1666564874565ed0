"""Backprojection: the NumPy twin (``bp_numpy.py``) and the OpenCL plan (``bp_opencl.py``) behind one
dispatcher, and the ``"bp"`` formation (exact, the reference every other formation is measured against).

By default the OpenCL plan runs only kernel variants as exact as the plain float kernel. A caller
that allows an error against the float64 twin (``max_error_db``) lets the plan's variant machinery
(:mod:`clsas.cl.shapes`) also try the variants whose stated bound (``BackprojectPlan.ERROR_BOUND``,
relative to the image's peak) is within it; ``image.provenance["bp"]`` names the variant that ran
and its bound (:func:`variant_record`)."""

from __future__ import annotations

import logging
import math
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.beam import BEAM_MODES, Beams, BeamWeights, beam_weights
from ..physics.geometry import VoxelGrid
from ..types.image import Image
from ..types.profiles import Profiles
from . import bp_numpy as twin
from .bp_opencl import BackprojectPlan, RecordsPlan, upsample_factor
from .guard import check_grid
from .registry import FORMATIONS

__all__ = ["Backprojector", "PendingBackprojection", "backproject", "form", "form_tiles", "BP_OPTIONS",
           "allowed_error", "variant_record"]

BP_OPTIONS = ("beam", "beam_floor_db", "max_error_db")  # the options the formation declares

log = logging.getLogger(__name__)


def allowed_error(max_error_db) -> float | None:
    """``max_error_db`` checked (None, or a finite number of dB below 0) as the plan's ``max_error``:
    the error against the float64 twin a kernel variant may have, as a fraction of the image's peak,
    ``10 ** (max_error_db / 20)``; None (only variants as exact as the plain float kernel) for None."""
    if max_error_db is None:
        return None
    if isinstance(max_error_db, bool) or not isinstance(max_error_db, int | float | np.integer | np.floating):
        raise TypeError(f"max_error_db must be None or a number of dB below 0 (e.g. -60), "
                        f"got {type(max_error_db).__name__}")
    db = float(max_error_db)
    if not math.isfinite(db) or db >= 0:
        raise ValueError(f"max_error_db must be None or a finite number of dB below 0 (e.g. -60), got {max_error_db!r}")
    # the plan takes a fraction in (0, 1): the far ends of the dB scale round into it
    return min(max(10.0 ** (db / 20.0), sys.float_info.min), math.nextafter(1.0, 0.0))


def variant_record(plan: BackprojectPlan | None, max_error_db: float | None) -> dict:
    """What ``image.provenance["bp"]`` says of the kernel that formed an image, read from the plan
    after its last call (what ran, not what was planned).

    ``variant``: the kernel that ran (``"plain"``: the plain float kernel, also where a variant
    fell back to it; ``"local_profiles"``: the same image, records staged in local memory;
    ``"half_profiles"``: the records in half precision; ``"range_expansion"``: the distances by
    their expansion along z in runs of ``expansion_run`` voxels), or ``"twin"`` (the float64
    NumPy twin, ``plan`` None); ``shape``: the plan's tuned shape (None for the twin);
    ``error_bound``: the stated error against the float64 twin relative to the image's peak where
    the kernel is less exact than the plain one (half: ``BackprojectPlan.ERROR_BOUND``; the range
    expansion: its bound predicted for this grid and geometry), else None (the float kernels match
    the twin to their float32 rounding, about 1e-4 of the peak); ``max_error_db``: the allowance
    it was chosen under (None: exact variants only).
    """
    if plan is None:
        return {"variant": "twin", "shape": None, "error_bound": None, "max_error_db": max_error_db}
    variant = plan.last_variant or plan.shape.variant or "plain"
    record = {"variant": variant, "shape": plan.shape.label, "error_bound": plan.ERROR_BOUND.get(variant),
              "max_error_db": max_error_db}
    if variant == "range_expansion":
        record.update(error_bound=float(plan.last_error_bound), expansion_run=int(plan.last_expansion_run))
    return record


def _half(plan: BackprojectPlan | None) -> bool:
    """Whether ``plan`` runs on half-precision records (made on the host: the device's are float)."""
    return plan is not None and plan.shape.variant == "half_profiles"


class Backprojector:
    """Backprojection onto one grid: built once, called many times.

    The OpenCL plan (kernel variant chosen and verified, buffers allocated) is made on the
    first call and kept while the profiles keep their number of measurements and do not grow
    longer; :func:`backproject` is one call of a fresh Backprojector.

    Parameters
    ----------
    grid : VoxelGrid
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"``. With ``"auto"``, a device that cannot
        build the kernel (:class:`clsas.cl.BuildError`) falls back to the NumPy twin with one
        warning naming the device and the reason; ``"opencl"`` raises instead. A Selection
        resolved by the caller (:func:`clsas.cl.select`) keeps its request.
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
        The OpenCL device (default: ``PYOPENCL_CTX``, else the preferred one); None with a
        Selection.
    chunk : int, optional
        Measurements per kernel launch.
    force : bool
        Go on even if the grid does not seem to fit in memory (otherwise a ``ValueError``
        gives the numbers and a spacing that fits; see :func:`clsas.formation.guard.check_grid`).
    beam : {"none", "limited", "weighted"}, optional
        Apodization by the transducers' beams (the profiles' ``beams``, from the dataset):
        ``"none"`` lets every measurement see every voxel (omnidirectional, the behaviour
        before beams); ``"limited"`` keeps a voxel-measurement pair only where the two-way
        beam amplitude is at least ``beam_floor_db``; ``"weighted"`` scales each pair by the
        two-way amplitude. Default: ``"limited"`` where the profiles carry a directional beam,
        else ``"none"``. Patterns are evaluated at the carrier ``fc_hz`` (see :mod:`clsas.physics.beam`).
    beam_floor_db : float
        The two-way level of ``beam="limited"``, dB (default -12: each transducer's -6 dB
        beam when speaker and microphone are together).
    resident : bool
        On OpenCL, keep the data on the device (default): the carrier records are made there
        (kernels/records.cl) from the profiles the OpenCL compression left there
        (``profiles.on_device``, still holding ``profiles.data``), else from ``profiles.data``
        uploaded once; bp reads them there, and the image is read back once as complex64
        (``-DCOMPLEX_IMAGE``). The records are kept on the device for the next call on the same
        read-only profiles array (tiles of a grid, a Dask worker's tiles), whatever its grid;
        ``image.provenance["bp"]["records"]`` says where they came from (``"rows"``,
        ``"uploaded"``, ``"kept"``). False: the step-by-step path (records made on the host and
        written, the image read as two planes and joined), kept for comparison. A plan whose variant
        stores the records in half precision (``max_error_db``) takes the records made on the host
        (``records`` ``"host"``).
    max_error_db : float, optional
        The error against the float64 twin the OpenCL kernel may have, dB relative to the image's
        peak (a finite number below 0): the plan's variant machinery also tries the variants whose
        stated bound (``BackprojectPlan.ERROR_BOUND``; ``half_profiles``: 1e-3, -60 dB, on devices
        with ``cl_khr_fp16``) is at most ``10 ** (max_error_db / 20)``, and takes one where it is
        faster. Default None: only variants as exact as the plain float kernel (bp is the reference
        the other formations are measured against). ``image.provenance["bp"]`` names the variant that
        ran and its bound (:func:`variant_record`).

    Examples
    --------
    One plan for a grid, called for several profile sets:

    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> bp = clsas.Backprojector(grid, backend="numpy")
    >>> image = bp(clsas.compress(data, backend="numpy"))
    >>> image.backend
    'numpy'
    """

    def __init__(self, grid: VoxelGrid, *, backend: str | _cl.Selection | None = None, device: Any = None,
                 chunk: int | None = None, force: bool = False, beam: str | None = None,
                 beam_floor_db: float = -12.0, resident: bool = True, max_error_db: float | None = None):
        if not isinstance(grid, VoxelGrid):
            raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
        if chunk is not None:
            chunk = v.positive_int("chunk", chunk)
        self.grid = grid
        self.chunk = chunk
        self.beam = None if beam is None else v.choice("beam", beam, BEAM_MODES)
        self.beam_floor_db = v.finite("beam_floor_db", beam_floor_db)
        if not isinstance(resident, bool):
            raise TypeError(f"resident must be True or False, got {resident!r}")
        self.resident = resident
        self.max_error = allowed_error(max_error_db)
        self.max_error_db = None if max_error_db is None else float(max_error_db)
        self.selection = _cl.select(backend, device)
        check_grid(grid, self.selection.kind, self.selection.cl_device, force=force)
        self._force = force
        self._plan = None

    @property
    def backend(self) -> str:
        """``"opencl"`` or ``"numpy"``: where the next call runs."""
        return self.selection.kind

    def _opencl_plan(self, n_meas: int, n_lags: int, beam_lut: int = 0):
        p = self._plan
        if p is None or p.n_meas != n_meas or p.n_lags < n_lags or p.beam_lut != beam_lut:
            was = self.selection.kind
            # any grid: the plan is retargeted; the allowance picks the variants it may be built with
            key = (n_meas, n_lags, self.chunk, beam_lut, self.resident, self.max_error)
            self._plan, self.selection = self.selection.plan(lambda q: _cl.reused(q, "backproject", key, lambda q:
                BackprojectPlan(self.grid, n_meas, n_lags, queue=q, chunk=self.chunk, beam_lut=beam_lut,
                                complex_image=self.resident, max_error=self.max_error)))
            if self.selection.kind != was:  # fell back to the twin: its memory is the host's, per voxel more
                check_grid(self.grid, self.selection.kind, None, force=self._force)
        if self._plan is not None:
            self._plan.retarget(self.grid)
        return self._plan

    def _records_plan(self, n_meas: int, n_lags: int, up: int):
        """The carrier-records plan of the resident path (None where it fell back to the twin)."""
        records, self.selection = self.selection.plan(lambda q: _cl.reused(
            q, "carrier_records", (n_meas, n_lags, up), lambda q: RecordsPlan(n_meas, n_lags, up, queue=q)))
        return records

    def _weights(self, beams, fc_hz: float, c) -> BeamWeights | None:
        """The pair weights of this Backprojector's ``beam`` mode for ``beams`` (None: none)."""
        if beams is not None and not isinstance(beams, Beams):
            raise TypeError(f"beams must be clsas.physics.beam.Beams or None, got {type(beams).__name__}")
        mode = self.beam or ("limited" if beams is not None and not beams.is_omni else "none")
        if self.beam is None and mode == "limited":
            log.info("bp: the profiles carry directional beams: beam='limited' (pairs above %g dB)",
                     self.beam_floor_db)
        return beam_weights(beams, mode, fc_hz, c, self.beam_floor_db)

    def __call__(
        self,
        profiles: Profiles,
        *,
        tx_positions: np.ndarray | None = None,
        rx_positions: np.ndarray | None = None,
        c_mps: float | np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        beams: Beams | None = None,
    ) -> Image:
        """Backproject ``profiles`` (see :func:`backproject` for the arguments; ``beams``
        default the profiles')."""
        return self.enqueue(profiles, tx_positions=tx_positions, rx_positions=rx_positions, c_mps=c_mps,
                            progress=progress, beams=beams).result()

    def enqueue(
        self,
        profiles: Profiles,
        *,
        tx_positions: np.ndarray | None = None,
        rx_positions: np.ndarray | None = None,
        c_mps: float | np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        beams: Beams | None = None,
    ) -> PendingBackprojection:
        """Begin backprojecting ``profiles`` (the arguments of :meth:`__call__`); the image is
        :meth:`PendingBackprojection.result`. On the resident OpenCL path the kernels are enqueued
        and the image read back on a second queue without waiting, so that a Backprojector of the
        next tile, enqueued before this result is asked for, runs its kernels during the read
        (:func:`form_tiles`); elsewhere the image is formed here."""
        if not isinstance(profiles, Profiles):
            raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
        n = profiles.n_meas
        tx = v.array("tx_positions", profiles.tx_positions if tx_positions is None else tx_positions, shape=(n, 3))
        rx = v.array("rx_positions", profiles.rx_positions if rx_positions is None else rx_positions, shape=(n, 3))
        c = v.speeds("c_mps", profiles.c_mps if c_mps is None else c_mps, n)
        rows = profiles.device_rows() if self.resident else None  # read there by the kernels, never here
        data = None if rows is not None else v.array("profiles.data", profiles.data, ndim=2, dtype=None,
                                                     allow_complex=True)
        tau0 = v.array("profiles.tau0_s", profiles.tau0_s, shape=(n,))
        dtau = v.positive("profiles.dtau_s", profiles.dtau_s)
        fc = v.non_negative("profiles.fc_hz", profiles.fc_hz)
        beams = profiles.beams if beams is None else beams
        weights = self._weights(beams, fc, c)
        if weights is not None and len(weights.tx_dir) != n:
            raise ValueError(f"beams must have {n} boresights (one per measurement), got {len(weights.tx_dir)}")
        t_start = time.perf_counter()
        lut = 0 if weights is None else weights.luts.shape[1]
        plan = self._opencl_plan(n, profiles.n_lags, lut) if self.selection.opencl else None
        records = None
        if plan is not None and self.resident and not _half(plan):
            records = self._records_plan(n, plan.n_lags, upsample_factor(fc, dtau))
            plan = None if records is None else plan  # None: the records kernel fell back to the twin
        if records is None and data is None:  # the host's way after all: the rows read back
            data = v.array("profiles.data", profiles.data, ndim=2, dtype=None, allow_complex=True)
        source = None
        if records is not None:
            # profiles.data itself (not the checked copy), or None for the rows: the records are kept for it
            pending, source = plan.enqueue_resident(None if rows is not None else profiles.data, rows, records, tau0,
                                                    dtau, fc, tx, rx, c, progress, beam=weights)
        elif plan is not None:
            values = plan(data, tau0, dtau, fc, tx, rx, c, progress, beam=weights)
            pending = _Done(values, {"backproject_kernel": plan.last_kernel_s})
            source = "host" if self.resident else None  # half records: made on the host, the device's are float
        else:
            values = twin.backproject(data.astype(np.complex128), tau0, dtau, fc, tx, rx, c, self.grid.points(),
                                      progress, beam=weights)
            pending = _Done(values, {})
        bp_record = variant_record(plan, self.max_error_db)  # after the launch: what ran
        if source is not None:
            bp_record["records"] = source
        # with beams, the mode applied (the default resolves to "limited") is kept with the image
        if beams is not None:
            mode = "none" if weights is None else ("weighted" if weights.gate is None else "limited")
            bp_record.update(beam=mode, beam_floor_db=self.beam_floor_db)
        sel = self.selection
        return PendingBackprojection(pending, self.grid, sel.kind, sel.device, t_start, {"bp": bp_record})


class _Done:
    """An image formed already (the twin, the step-by-step path), as a pending one."""

    def __init__(self, values: np.ndarray, timings: dict):
        self.values, self.timings = values, timings

    def result(self) -> np.ndarray:
        return self.values


class PendingBackprojection:
    """What :meth:`Backprojector.enqueue` started; :meth:`result` waits for the :class:`~clsas.Image`."""

    def __init__(self, pending, grid: VoxelGrid, kind: str, device: str, t_start: float, provenance: dict):
        self._pending, self.grid, self._kind, self._device = pending, grid, kind, device
        self._t_start, self._provenance = t_start, provenance
        self._image = None
        self.spans_ns: dict = {}  # OpenCL: device clock (start, end) of the kernels and of the read back, ns

    def result(self) -> Image:
        """The image (formed once; later calls return the same Image)."""
        if self._image is None:
            p = self._pending
            values = p.result().reshape(self.grid.shape)
            on_device = None
            if isinstance(p, _Done):
                timings = dict(p.timings)
            else:
                timings = {"records_kernel": p.records_s, "backproject_kernel": p.kernel_s - p.records_s,
                           "image_read": p.read_s}
                on_device = p.on_device(values)
            timings["backproject"] = time.perf_counter() - self._t_start
            self.spans_ns = getattr(p, "spans_ns", {})
            self._image = Image(values, self.grid, "bp", self._kind, self._device, timings,
                                provenance=self._provenance, on_device=on_device)
            self._pending = None
        return self._image


def form_tiles(profiles: Profiles, grids: Iterable[VoxelGrid], *, backend: str | _cl.Selection | None = None,
               device: Any = None, force: bool = False, beam: str | None = None, beam_floor_db: float = -12.0,
               overlap: bool = True, max_error_db: float | None = None) -> Iterator[Image]:
    """The bp image of ``profiles`` on each grid of ``grids`` (tiles of one grid), in order.

    Each grid is one :class:`Backprojector` call; on OpenCL they share one plan (same profile
    shapes) and the records made on the device for the first (:meth:`RecordsPlan.records_of`).
    With ``overlap`` the next grid's kernels are enqueued before the last image is read back and
    handed on, so that its read back and what the caller does with it (a file write) run beside
    them; without, one grid after the other. The images are the same either way.

    Parameters
    ----------
    profiles : Profiles
    grids : iterable of VoxelGrid
        Taken one at a time, as the previous image is handed on.
    backend, device, force, beam, beam_floor_db, max_error_db : see :class:`Backprojector`.
    overlap : bool
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    if not isinstance(overlap, bool):
        raise TypeError(f"overlap must be True or False, got {overlap!r}")
    allowed_error(max_error_db)  # checked before the first tile
    selection = _cl.select(backend, device)
    depth = 2 if overlap else 1
    pending: deque = deque()
    for grid in grids:
        bp = Backprojector(grid, backend=selection, force=force, beam=beam, beam_floor_db=beam_floor_db,
                           max_error_db=max_error_db)
        pending.append(bp.enqueue(profiles))
        selection = bp.selection  # a fallback to the twin holds for the next tiles
        if len(pending) == depth:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def backproject(
    profiles: Profiles,
    grid: VoxelGrid,
    *,
    tx_positions: np.ndarray | None = None,
    rx_positions: np.ndarray | None = None,
    c_mps: float | np.ndarray | None = None,
    backend: str | _cl.Selection | None = None,
    device: Any = None,
    chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    beam: str | None = None,
    beam_floor_db: float = -12.0,
    max_error_db: float | None = None,
) -> Image:
    """Bistatic delay-and-sum of complex baseband profiles onto ``grid``.

    For each voxel and measurement the profile is linearly interpolated at the bistatic
    delay ``(|v - tx| + |v - rx|) / c`` and the carrier phase restored; samples outside the
    profile window contribute nothing. Positions and ``c`` default to those the profiles
    carry (from a Dataset); ``c_mps`` may be an (n_meas,) array, one speed of sound per
    measurement (air that changes during a scan). To image many profile sets onto one grid, build a
    :class:`Backprojector` once and call it.

    Parameters
    ----------
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"`` (see :class:`Backprojector`).
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
    beam, beam_floor_db : apodization by the profiles' transducer beams (see :class:`Backprojector`).
    max_error_db : float, optional
        The error against the float64 twin the kernel may trade for speed, dB relative to the peak
        (see :class:`Backprojector`); default None: exact float kernels only.

    Returns
    -------
    Image
        complex64 values (OpenCL) or complex128 (NumPy), shape ``grid.shape``.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> image = clsas.backproject(clsas.compress(data), grid)
    >>> image.values.shape == grid.shape
    True
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    bp = Backprojector(grid, backend=backend, device=device, chunk=chunk, beam=beam, beam_floor_db=beam_floor_db,
                       max_error_db=max_error_db)
    return bp(profiles, tx_positions=tx_positions, rx_positions=rx_positions, c_mps=c_mps, progress=progress)


@FORMATIONS.register("bp")
def form(profiles: Profiles, grid: VoxelGrid, *, backend: str | _cl.Selection | None = None, device: Any = None,
         progress: Callable[[int, int], None] | None = None, force: bool = False, beam: str | None = None,
         beam_floor_db: float = -12.0, max_error_db: float | None = None) -> Image:
    """The ``"bp"`` formation: :class:`Backprojector` with its options ``beam``, ``beam_floor_db`` and
    ``max_error_db`` (default None: exact float kernels only; ``formation="auto"`` gives its target
    less its margin where it forms by bp, :func:`clsas.reconstruct` its ``max_error_db`` where the
    caller gives one)."""
    bp = Backprojector(grid, backend=backend, device=device, force=force, beam=beam, beam_floor_db=beam_floor_db,
                       max_error_db=max_error_db)
    return bp(profiles, progress=progress)


form.form_tiles = form_tiles  # the tiles of one grid, overlapped (clsas.pipeline.tiling)
