"""OpenCL plan for kernels/backproject.cl: construct once for a grid, call many times."""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np

from ..cl import DeviceRows, Plan, Shape, transfer_queue
from ..physics.geometry import VoxelGrid
from .bp_numpy import (  # noqa: F401 - the twins of records.cl, imported from here by the projector
    MAX_CYCLES_PER_SAMPLE,
    carrier_factors,
    carrier_records,
    carrier_rotation,
    range_expansion_error,
    upsample,
    upsample_adjoint,
    upsample_factor,
)


class BeamPlan(Plan):
    """What a backprojection-type plan built with or without a beam (kernels/beam.cl) shares: the
    beam buffers, the ``-DBEAM`` define, the beam arguments and the per-measurement geometry.
    Subclasses set ``self.beam_lut`` before ``super().__init__`` (the build reads :meth:`defines`)."""

    beam_lut = 0  # samples per beam table; 0: omnidirectional (no -DBEAM)

    def defines(self) -> dict:
        return {"BEAM": 1} if self.beam_lut else {}

    def alloc_beam(self, n_meas: int) -> None:
        """The beam buffers (boresights, tables) where the plan is built with a beam."""
        if self.beam_lut:
            self.d_beam_dir = self.alloc(32 * n_meas, "r")
            self.d_beam_lut = self.alloc(8 * self.beam_lut, "r")

    def beam_args(self, beam) -> tuple:
        """The kernel's beam arguments (beam.cl's BEAM_ARGS), buffers written; () without -DBEAM."""
        if not self.beam_lut:
            if beam is not None:
                raise ValueError("this plan was built without a beam (beam_lut=0)")
            return ()
        if beam is None or beam.luts.shape != (2, self.beam_lut):
            raise ValueError(f"beam: a plan built with beam_lut={self.beam_lut} needs BeamWeights of that size")
        dirs = np.zeros((2, self.n_meas, 4), np.float32)
        dirs[0, :, :3], dirs[1, :, :3] = beam.tx_dir, beam.rx_dir
        self.write_changed(self.d_beam_dir, dirs, np.float32)
        self.write_changed(self.d_beam_lut, beam.luts, np.float32)
        gate = 0.0 if beam.gate is None else beam.gate
        return self.d_beam_dir, self.d_beam_lut, np.int32(self.beam_lut), np.int32(self.n_meas), np.float32(gate)

    def write_geometry(self, tau0_s, dtau_s: float, tx_positions, rx_positions, c_mps) -> None:
        """Positions (tx's w lane: profile samples per metre of path; rx's unused: the carrier
        rides in the records, :func:`carrier_records`) and the zero-delay index, to the device."""
        c = np.broadcast_to(np.asarray(c_mps, float), (self.n_meas,))
        pos4 = np.zeros((2, self.n_meas, 4), np.float32)
        pos4[0, :, :3] = tx_positions
        pos4[0, :, 3] = 1.0 / (c * dtau_s)
        pos4[1, :, :3] = rx_positions
        self.write_changed(self.d_tx, pos4[0], np.float32)
        self.write_changed(self.d_rx, pos4[1], np.float32)
        self.write_changed(self.d_s0, np.asarray(tau0_s) / dtau_s, np.float32)


def selftest_beam_weights(rng, mode: str, n_meas: int = 3):
    """The beams the beam selftests use: a piston speaker tilted per measurement (drawn from
    ``rng``) and a cone microphone, for ``n_meas`` measurements (the bp selftest scene's 3) at
    25 kHz."""
    from ..physics.beam import Beams, Piston, beam_weights

    tilt = np.c_[rng.uniform(-0.3, 0.3, (n_meas, 2)), np.ones(n_meas)]
    beams = Beams(Piston(0.03), {"model": "cone", "half_angle_deg": 25.0}, tilt, (0.0, 0.0, 1.0), n_meas)
    return beam_weights(beams, mode, 25e3, 343.0, -12.0)


def _profiles_shape(data: np.ndarray | None, rows) -> tuple[int, ...]:
    """The shape of the profiles ``data``, or of those ``rows`` hold where ``data`` is None."""
    if data is None and rows is None:
        raise ValueError("data: None stands for the profiles rows hold, and rows is None too")
    return (rows.n_rows, rows.n_cols) if data is None else data.shape


class RecordsPlan(Plan):
    """kernels/records.cl: the carrier records of ``n_meas`` profiles of ``n_lags`` samples,
    upsampled ``up`` times, made on the device (the twin: :func:`carrier_records`). With
    ``row_map``, record row m is made from profile row ``row_of[m]`` (:meth:`enqueue`): the rows in
    another order (FFBP's tree order) without moving them."""

    KERNEL = "carrier_records"
    SOURCES = ("records.cl",)

    def __init__(self, n_meas: int, n_lags: int, up: int, queue=None, vec=None, row_map: bool = False):
        self.row_map = bool(row_map)
        super().__init__(queue, vec)
        self.n_meas, self.n_lags, self.up = int(n_meas), max(2, int(n_lags)), int(up)
        self.n_rec = (self.n_lags - 1) * self.up + 1
        self.d_pairs = self.alloc(16 * self.n_meas * self.n_rec)
        self.d_rot0 = self.alloc(8 * self.n_meas, "r")
        self.d_row_of = self.alloc(4 * self.n_meas, "r") if self.row_map else None
        self.d_rot, self._cycles = None, None
        self.d_host, self._host_bytes = None, 0  # host profiles uploaded by :meth:`records_of`
        self._held = None  # (weakref to the profiles, their delays) whose records d_pairs holds

    def defines(self) -> dict:
        return {"ROW_MAP": 1} if self.row_map else {}

    def enqueue(self, d_prof, stride: int, n_data: int, tau0_s, dtau_s: float, fc_hz: float, row_of=None):
        """Launch on profiles already on the device (``d_prof``: (n_meas, stride) complex64,
        ``n_data`` <= n_lags samples of each row used) at lag step ``dtau_s``; returns
        ``(event, dtau / up, phi)``, the records in :attr:`d_pairs`. A ``row_map`` plan takes
        ``row_of`` (n_meas,), a permutation of the rows, and ``tau0_s`` in the records' order."""
        if not 1 <= n_data <= self.n_lags or stride < n_data:
            raise ValueError(f"n_data must be in [1, {self.n_lags}] and at most stride={stride}, got {n_data}")
        self._held = None  # d_pairs is overwritten
        fine = dtau_s / self.up
        rot, rot0 = carrier_factors(self.n_rec, tau0_s, fine, fc_hz)
        if self._cycles != fc_hz * fine:  # the per-record factor depends on the shape and fc dtau only
            self.d_rot, self._cycles = self.upload(rot, np.complex64), fc_hz * fine
        self.write(self.d_rot0, rot0, np.complex64)
        evt = self.launch((-(-self.n_rec // self.vec), self.n_meas), d_prof, np.int32(stride), np.int32(n_data),
                          np.int32(self.up), np.int32(self.n_rec), self.d_rot, self.d_rot0, self.d_pairs,
                          *self._row_of(row_of))
        return evt, fine, 2 * np.pi * fc_hz * fine

    def records_of(self, data: np.ndarray | None, rows, tau0_s, dtau_s: float, fc_hz: float):
        """The records of the profiles ``data`` ((n_meas, n_data) baseband; None: those ``rows``
        hold, not read to the host) in :attr:`d_pairs`, made once: kept from the last call where
        they were made from this very array (read-only, hence unchanged) or these very rows at the
        same delays; else made from ``rows`` (a :class:`clsas.cl.DeviceRows` of ``data`` on this
        queue) where they are valid; else from ``data`` (the rows' host copy for None) uploaded.
        Returns ``(event or None, dtau / up, phi, source)``, ``source`` one of ``"kept"``,
        ``"rows"``, ``"uploaded"``."""
        key = (np.asarray(tau0_s, float).tobytes(), float(dtau_s), float(fc_hz), _profiles_shape(data, rows))
        fine, phi = dtau_s / self.up, 2 * np.pi * fc_hz * dtau_s / self.up
        held, ident = self._held, rows if data is None else data
        if held is not None and held[0]() is ident and held[1] == key and (data is None or not data.flags.writeable):
            return None, fine, phi, "kept"
        if rows is not None and rows.valid(self.queue, data):
            evt, fine, phi = self.enqueue(rows.buffer, rows.stride, rows.n_cols, tau0_s, dtau_s, fc_hz)
            source = "rows"
        else:
            host = np.ascontiguousarray(rows.host if data is None else data, np.complex64)
            if self.d_host is None or self._host_bytes < host.nbytes:
                self.d_host, self._host_bytes = self.alloc(host.nbytes, "r"), host.nbytes
            self.write(self.d_host, host, np.complex64)
            evt, fine, phi = self.enqueue(self.d_host, host.shape[1], host.shape[1], tau0_s, dtau_s, fc_hz)
            source = "uploaded"
        if data is None or not data.flags.writeable:
            self._held = (weakref.ref(ident), key)
        return evt, fine, phi, source

    def _row_of(self, row_of) -> tuple:
        """The row-map argument of a ``row_map`` plan (``row_of`` written to the device), else none."""
        if not self.row_map:
            if row_of is not None:
                raise ValueError("row_of: this plan was made without row_map")
            return ()
        rows = np.asarray(row_of)
        if rows.shape != (self.n_meas,) or not np.array_equal(np.sort(rows), np.arange(self.n_meas)):
            raise ValueError(f"row_of must be a permutation of the {self.n_meas} rows, got shape {rows.shape}")
        self.write(self.d_row_of, rows, np.int32)
        return (self.d_row_of,)

    def __call__(self, data: np.ndarray, tau0_s, dtau_s: float, fc_hz: float):
        """:func:`carrier_records` of host profiles (uploaded, made, read back): ``(records
        (n_meas, n_rec, 2) complex64, dtau / up, phi)``."""
        self.begin()
        d_prof = self.upload(data, np.complex64)
        _, fine, phi = self.enqueue(d_prof, data.shape[1], data.shape[1], tau0_s, dtau_s, fc_hz)
        return self.read(self.d_pairs, (self.n_meas, self.n_rec, 2), np.complex64), fine, phi

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """Profiles shorter than the records' window (zero-padded), upsampled 4 times and not at
        all, against :func:`carrier_records`; error relative to the peak."""
        _, prof, tau0, fs, *_ = selftest_scene()
        err = 0.0
        for dtau in (1 / fs, 8 / fs):  # fc dtau 0.26 and 2.08 at 25 kHz: not upsampled, 4 x upsampled
            want, *_ = carrier_records(prof[:, :37], 40, tau0, dtau, 25e3)
            plan = cls(3, 40, upsample_factor(25e3, dtau), queue=queue, vec=vec)
            got, *_ = plan(prof[:, :37], tau0, dtau, 25e3)
            err = max(err, float(np.abs(got - want).max() / np.abs(want).max()))
        return err


class PendingImage:
    """A backprojection whose kernels are enqueued and whose image is being read back on the copy
    queue (:func:`clsas.cl.transfer_queue`); :meth:`result` waits for it. ``kernel_s`` and
    ``records_s`` are the kernel time of its launches and of its records, ``read_s`` the read
    back's (profiling events, s), and ``spans_ns`` the device clock's (start, end) of its bp
    kernels and of its read back (ns: where two images overlapped), known once it is done."""

    def __init__(self, plan: BackprojectPlan, slot: int, hosts: tuple, reads: list, events: list, records_evt,
                 n_vox: int, rows: DeviceRows | None = None):
        self._plan, self._slot, self._hosts, self._reads = plan, slot, hosts, reads
        self._events, self._records_evt, self.n_vox = events, records_evt, n_vox
        self._rows = rows
        self.kernel_s = self.records_s = self.read_s = 0.0
        self.spans_ns: dict = {}  # device clock (start, end) of the bp kernels and of the read back, ns
        self._values = None

    def result(self) -> np.ndarray:
        """The image, (n_vox,) complex64 (waits for the read back once)."""
        if self._values is None:
            for evt in self._reads:
                evt.wait()
            seconds = self._plan.seconds
            self.records_s = 0.0 if self._records_evt is None else seconds(self._records_evt)
            self.kernel_s = sum(seconds(e) for e in self._events) + self.records_s
            self.read_s = sum(seconds(e) for e in self._reads)
            self.spans_ns = {"kernels": (self._events[0].profile.start, self._events[-1].profile.end),
                             "read": (min(e.profile.start for e in self._reads),
                                      max(e.profile.end for e in self._reads))}
            self._plan.collected(self._slot, self)
            self._plan.last_kernel_s, self._plan.last_records_s = self.kernel_s, self.records_s
            if len(self._hosts) == 1:
                self._values = self._hosts[0][: self.n_vox]
            else:
                out = np.empty(self.n_vox, np.complex64)  # filled in place: 5x faster than re + 1j * im, cast
                out.real, out.imag = self._hosts[0][: self.n_vox], self._hosts[1][: self.n_vox]
                self._values = out
            self._hosts = self._reads = self._events = None
        return self._values

    def on_device(self, values: np.ndarray) -> DeviceRows | None:
        """The complex image left in its device buffer, as one row of ``n_vox`` values whose host
        copy is ``values`` (the result, as the caller keeps it: made read-only here); valid until
        the plan's next call. None for an image written as two planes."""
        if self._rows is None:
            return None
        values.flags.writeable = False
        self._rows.host = values
        return self._rows


# the half-profiles variant's error against the float64 twin, relative to the peak (each record
# rounded to half, 2^-11 of it; tests/kernels/test_shapes.py checks it, bench/bp_shapes.py states it)
HALF_TOLERANCE = 1e-3
# the range-expansion variant's largest admitted error against the float64 twin, relative to the peak
# (-50 dB): the variant is tried only for plans that admit it, and each call checks its geometry's bound
EXPANSION_LIMIT = 10 ** (-50 / 20)
# voxels per expansion of the range-expansion variant: the shortest (the one built, self-tested and timed)
SHORTEST_RUN = 4


class BackprojectPlan(BeamPlan):
    """Compiled kernel and device buffers for ``n_meas`` profiles of at most ``n_lags`` samples.

    Measurements go through the kernel in chunks of ``chunk`` (bounded launches, profiles of
    a chunk stay in cache); the image accumulates on the device. With ``complex_image`` the
    kernel writes the image as one complex array (``-DCOMPLEX_IMAGE``), read back once as
    complex64; without, as two float planes the host joins.

    The grid is the last one given (``grid``, then :meth:`retarget`): one plan forms every tile
    of a grid, its image buffers reallocated only where a grid needs more voxels than they hold
    (or fewer than a quarter). The image is read back without waiting (:meth:`enqueue_resident`
    returns a :class:`PendingImage`), on a second queue of the same device on a GPU, in order on
    the plan's queue on a CPU (:func:`clsas.cl.transfer_queue`): two image buffers take turns,
    so that the next grid's kernels run while the last image is read and collected; a grid
    whose last image was collected writes into the first buffer again (one buffer where nothing
    overlaps).

    ``shape`` (:class:`clsas.cl.Shape`): the work-items per group and the build variant,
    ``"local_profiles"`` (``-DLOCAL_PROFILES``: each group's run of records staged in local memory,
    the same image), ``"half_profiles"`` (``-DHALF_PROFILES``: the records stored as half, scaled
    into its range; on devices with ``cl_khr_fp16`` only; the image within :data:`HALF_TOLERANCE`
    of its peak), ``"range_expansion"`` (``-DRANGE_EXPANSION=R``: the two distances exact once per
    run of R voxels along z, expanded to second order within it; each call takes the longest run
    R in VEC, VEC / 2, ... :data:`SHORTEST_RUN` whose predicted error for the call's geometry,
    :func:`~clsas.formation.bp_numpy.range_expansion_error`, is within ``max_error``, or
    :data:`EXPANSION_LIMIT` where it is None) or the plain kernel; ``"auto"``: the one tuned for
    the device (:mod:`clsas.cl.shapes`), among the variants as exact as the plain kernel unless
    ``max_error`` (relative to the peak) admits half profiles or the range expansion. Where a
    geometry's staged run would not fit the device's local memory, for records made on the device
    (:meth:`from_device`) under half profiles, and where no run's error bound is within the
    limit, the plain kernel runs with the same local size. ``last_variant`` names the kernel the
    last call ran (``"plain"`` or the variant), ``last_expansion_run`` its run (0: not expanded)
    and ``last_error_bound`` the expansion's predicted error (0: exact).
    """

    KERNEL = "backproject"
    SOURCES = ("common.cl", "beam.cl", "backproject.cl")
    SHAPES = True
    VARIANTS = {"": {}, "local_profiles": {"LOCAL_PROFILES": 1}, "half_profiles": {"HALF_PROFILES": 1},
                "range_expansion": {"RANGE_EXPANSION": SHORTEST_RUN}}
    NEEDS_LOCAL = frozenset({"local_profiles"})
    NEEDS_EXTENSION = {"half_profiles": "cl_khr_fp16"}
    ERROR_BOUND = {"half_profiles": HALF_TOLERANCE, "range_expansion": EXPANSION_LIMIT}

    def __init__(self, grid: VoxelGrid, n_meas: int, n_lags: int, queue=None, vec=None, chunk=None,
                 beam_lut: int = 0, complex_image: bool = False, shape: Shape | str = "auto",
                 max_error: float | None = None):
        self.beam_lut = int(beam_lut)  # samples per beam table; 0: omnidirectional (no -DBEAM)
        self.complex_image = bool(complex_image)
        super().__init__(queue, vec, shape, max_error)
        self.n_meas, self.n_lags = n_meas, max(2, n_lags)
        self.per_group = self.vec * (self.shape.local or 1)  # voxels per work-group (or per work-item)
        self._chunk = chunk
        self.d_prof, self.n_lags_dev = None, 0  # the host-made records (__call__), allocated on first use
        self.d_tx = self.alloc(16 * n_meas, "r")
        self.d_rx = self.alloc(16 * n_meas, "r")
        self.d_s0 = self.alloc(4 * n_meas, "r")
        self.capacity = 0  # voxels each image buffer holds
        self.last_records_s = 0.0  # kernel time of the last call's records (:meth:`from_device`), s
        self.last_variant, self.last_expansion_run, self.last_error_bound = "", 0, 0.0  # what the last call ran
        # the runs the range-expansion variant may take, longest first (the timing takes the shortest only)
        self.expansion_runs = tuple(r for r in (16, 8, 4) if SHORTEST_RUN <= r <= self.vec)
        self.expansion_limit = EXPANSION_LIMIT  # the most the expansion may err, whatever max_error admits
        self.retarget(grid)  # the image buffers before the beam tables: in the other order, Oclgrind's
        self.alloc_beam(n_meas)  # uninitialised-value plugin reports bp's image writes (test_beam_formation.py)

    def defines(self) -> dict:
        return {**super().defines(), **({"COMPLEX_IMAGE": 1} if self.complex_image else {})}

    def retarget(self, grid: VoxelGrid) -> None:
        """Form the next calls on ``grid`` (any shape)."""
        if not isinstance(grid, VoxelGrid):
            raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
        self.grid, self.n_vox = grid, grid.size
        self.n_pad = -(-self.n_vox // self.per_group) * self.per_group
        self.chunk = self._chunk or int(np.clip(4e7 // self.n_pad, 4, 256))
        if self.n_pad > self.capacity or 4 * self.n_pad < self.capacity:
            self.capacity = self.n_pad
            self._images = [None, None]  # the two image buffers (each a tuple: one complex, or re and im)
            self._reads = [None, None]  # the read-back events of the image each buffer last held
            self._pending: list = [None, None]  # the PendingImage not yet collected from each buffer
            self._last = 0
            self._slot()  # the first buffer now, the second where images overlap

    def _slot(self) -> int:
        """The image buffer the next call writes: the last one, or the other while the last one's
        image is not collected (allocated on first use)."""
        slot = self._last if self._pending[self._last] is None else 1 - self._last
        if self._images[slot] is None:
            n = self.capacity
            self._images[slot] = (self.alloc(8 * n),) if self.complex_image else (self.alloc(4 * n),
                                                                                    self.alloc(4 * n))
        self._last = slot
        return slot

    @property
    def image_buffers(self) -> int:
        """Image buffers allocated (1, or 2 where images overlapped)."""
        return sum(b is not None for b in self._images)

    def collected(self, slot: int, pending: PendingImage) -> None:
        """``pending``'s image, read from buffer ``slot``, is on the host (the buffer is free)."""
        if self._pending[slot] is pending:
            self._pending[slot] = None

    def __call__(
        self,
        data: np.ndarray,
        tau0_s: np.ndarray,
        dtau_s: float,
        fc_hz: float,
        tx_positions: np.ndarray,
        rx_positions: np.ndarray,
        c_mps: float | np.ndarray,
        progress: Callable[[int, int], None] | None = None,
        beam=None,
    ) -> np.ndarray:
        """Backproject; same arguments as the NumPy twin (grid fixed). Returns (n_vox,) complex64.
        The carrier records are made on the host (:func:`carrier_records`) and written."""
        pairs, dtau_s, phi = carrier_records(data, self.n_lags, tau0_s, dtau_s, fc_hz)
        n_lags = pairs.shape[1]
        if self.d_prof is None or n_lags != self.n_lags_dev:  # upsampled (fc dtau > MAX_CYCLES_PER_SAMPLE): larger
            self.d_prof, self.n_lags_dev = self.alloc(pairs.nbytes, "r"), n_lags
        self.begin()
        if self.shape.variant != "half_profiles":
            self.write(self.d_prof, pairs, np.complex64)
            return self._form(self.d_prof, n_lags, tau0_s, dtau_s, phi, tx_positions, rx_positions, c_mps,
                              progress, beam).result()
        parts = np.ascontiguousarray(pairs, np.complex64).view(np.float32)
        scale = float(np.abs(parts).max()) or 1.0  # into half's range (|x| <= 65504); the image scaled back
        self.write(self.d_prof, parts / scale, np.float16)
        image = self._form(self.d_prof, n_lags, tau0_s, dtau_s, phi, tx_positions, rx_positions, c_mps, progress,
                           beam, half=True).result()
        image *= np.float32(scale)
        return image

    def _check_records(self, records: RecordsPlan, fc_hz: float, dtau_s: float) -> None:
        up = upsample_factor(fc_hz, dtau_s)
        if (records.n_meas, records.n_lags, records.up) != (self.n_meas, self.n_lags, up):
            raise ValueError(f"records: a plan for {records.n_meas} x {records.n_lags} upsampled {records.up} x, "
                             f"these profiles need {self.n_meas} x {self.n_lags} upsampled {up} x")

    def from_device(self, rows, records: RecordsPlan, tau0_s, dtau_s: float, fc_hz: float, tx_positions,
                    rx_positions, c_mps, progress: Callable[[int, int], None] | None = None,
                    beam=None) -> np.ndarray:
        """Backproject profiles another plan left on this queue's device (:class:`clsas.cl.DeviceRows`,
        ``n_meas`` rows of at most ``n_lags`` samples): ``records`` (a :class:`RecordsPlan` for
        this plan's profiles, upsampled by :func:`upsample_factor`) makes the carrier records there
        and the bp kernel reads them; nothing but the geometry and one value per measurement goes
        to the device. Returns (n_vox,) complex64; ``last_kernel_s`` covers both kernels,
        ``last_records_s`` the records'."""
        if rows.n_rows != self.n_meas or rows.n_cols > self.n_lags:
            raise ValueError(f"rows: {rows.n_rows} rows of {rows.n_cols} samples do not fit a plan for "
                             f"{self.n_meas} profiles of at most {self.n_lags}")
        self._check_records(records, fc_hz, dtau_s)
        self.begin()
        evt, fine, phi = records.enqueue(rows.buffer, rows.stride, rows.n_cols, tau0_s, dtau_s, fc_hz)
        return self._form(records.d_pairs, records.n_rec, tau0_s, fine, phi, tx_positions, rx_positions, c_mps,
                          progress, beam, evt).result()

    def enqueue_resident(self, data: np.ndarray | None, rows, records: RecordsPlan, tau0_s, dtau_s: float,
                         fc_hz: float, tx_positions, rx_positions, c_mps,
                         progress: Callable[[int, int], None] | None = None, beam=None) -> tuple[PendingImage, str]:
        """Backproject the host profiles ``data`` ((n_meas, <= n_lags); None: those ``rows`` hold,
        never read to the host) from records on the device (:meth:`RecordsPlan.records_of`: kept
        from an earlier call on the same read-only array or rows, else made from ``rows``, the
        compression's rows on the device, else from ``data`` uploaded) without waiting for the
        image. Returns ``(PendingImage, source)``, ``source`` what the records came from
        (``"kept"``, ``"rows"``, ``"uploaded"``)."""
        n_rows, n_data = _profiles_shape(data, rows)
        if n_rows != self.n_meas or n_data > self.n_lags:
            raise ValueError(f"data: {n_rows} rows of {n_data} samples do not fit a plan for "
                             f"{self.n_meas} profiles of at most {self.n_lags}")
        self._check_records(records, fc_hz, dtau_s)
        self.begin()
        evt, fine, phi, source = records.records_of(data, rows, tau0_s, dtau_s, fc_hz)
        pending = self._form(records.d_pairs, records.n_rec, tau0_s, fine, phi, tx_positions, rx_positions, c_mps,
                             progress, beam, evt)
        return pending, source

    def _form(self, d_pairs, n_lags: int, tau0_s, dtau_s: float, phi: float, tx_positions, rx_positions, c_mps,
              progress, beam, records_evt=None, half: bool = False) -> PendingImage:
        """The bp kernel over every chunk of measurements on records ``d_pairs`` (n_meas, n_lags;
        float, or half with ``half``) at lag step ``dtau_s`` into the next image buffer, and its
        read back begun."""
        self.write_geometry(tau0_s, dtau_s, tx_positions, rx_positions, c_mps)
        g = self.grid
        origin = np.array([g.x_m[0], g.y_m[0], g.z_m[0], 0], np.float32)
        step = np.array([*g.spacing(), 0], np.float32)
        fixed = (
            d_pairs, np.int32(n_lags), self.d_tx, self.d_rx, self.d_s0, origin, step,
            np.int32(g.shape[1]), np.int32(g.shape[2]), np.float32(phi),
        )
        beam_args = self.beam_args(beam)
        slot = self._slot()
        image, after = self._images[slot], self._reads[slot]  # the buffer's last image read before it is written
        kern, local_args = self._staging(dtau_s, c_mps, half, (tx_positions, rx_positions, phi))
        local = None if self.shape.local is None else (self.shape.local,)
        events = []
        for m0 in range(0, self.n_meas, self.chunk):
            m1 = min(self.n_meas, m0 + self.chunk)
            evt = kern(self.queue, (self.n_pad // self.vec,), local, *fixed, np.int32(m0), np.int32(m1),
                       np.int32(m0 > 0), *local_args, *image, *beam_args, wait_for=after if m0 == 0 else None)
            self._events.append(evt)
            events.append(evt)
            if progress is not None:
                evt.wait()
                progress(m1, self.n_meas)
        return self._read_back(slot, image, events, records_evt)

    def _read_back(self, slot: int, image: tuple, events: list, records_evt) -> PendingImage:
        """Begin reading buffer ``slot`` (``image``) back on the transfer queue once ``events`` end."""
        self.queue.flush()  # the kernels start before anything waits on them from the other queue
        copy = transfer_queue(self.queue)
        dtype = np.complex64 if self.complex_image else np.float32
        hosts = tuple(np.empty(self.n_pad, dtype) for _ in image)
        reads = [self.cl.enqueue_copy(copy, h, b, wait_for=events, is_blocking=False)
                 for h, b in zip(hosts, image, strict=True)]
        copy.flush()
        # the image stays in the buffer until this plan's next call: DeviceRows is valid until then
        rows = DeviceRows(self, image[0], 1, self.n_vox, self.n_pad, None) if self.complex_image else None
        pending = PendingImage(self, slot, hosts, reads, events, records_evt, self.n_vox, rows)
        self._reads[slot], self._pending[slot] = reads, pending
        return pending

    def _staging(self, dtau_s: float, c_mps, half: bool = False, geometry: tuple | None = None) -> tuple:
        """The kernel to launch on float records (or half ones, ``half``) and its -DLOCAL_PROFILES
        arguments (none for the others): the staged run's records, sized by :func:`staged_records`.
        The plain kernel where the run would not fit the device's local memory, for float
        records under -DHALF_PROFILES (the resident path's, made on the device), and under
        -DRANGE_EXPANSION where no run's error bound for ``geometry`` ((tx, rx, phi)) is within
        the limit (:meth:`_expansion`). Sets ``last_variant``, ``last_expansion_run`` and
        ``last_error_bound``."""
        self.last_variant, self.last_expansion_run, self.last_error_bound = "plain", 0, 0.0
        variant = self.shape.variant
        if variant == "half_profiles":
            if not half:
                return self._plain_kernel(), ()
        elif half:
            raise ValueError(f"half records, but this plan runs the {self.shape.label} kernel")
        if variant == "range_expansion":
            return self._expansion(dtau_s, c_mps, *geometry), ()
        if variant != "local_profiles":
            self.last_variant = variant or "plain"
            return self.kernel, ()
        per_m = float(np.max(1.0 / (np.asarray(c_mps, float) * dtau_s)))
        seg_len = staged_records(self.grid, self.per_group, per_m)
        if 16 * seg_len + 64 > int(self.queue.device.local_mem_size):
            return self._plain_kernel(), ()
        self.last_variant = variant
        return self.kernel, (self.cl.LocalMemory(16 * seg_len), np.int32(seg_len), np.int32(self.n_vox))

    def _expansion(self, dtau_s: float, c_mps, tx_positions, rx_positions, phi: float):
        """The -DRANGE_EXPANSION kernel at the longest run of ``expansion_runs`` whose predicted
        error on this grid and geometry (:func:`range_expansion_error`, the envelope of profiles
        at lag step ``dtau_s`` included) is within ``max_error`` and never above
        ``expansion_limit`` (:data:`EXPANSION_LIMIT`, -50 dB, whatever the allowance), built
        without the exact branch (-DROWS_ALIGNED) where every work-item lies in one z row; else
        the plain kernel."""
        limit = min(self.expansion_limit, EXPANSION_LIMIT if self.max_error is None else self.max_error)
        fc_hz = phi / (2 * np.pi * dtau_s)
        if self.grid.shape[2] < self.vec:  # no work-item's voxels lie in one z row: none would be expanded
            return self._plain_kernel()
        for run in self.expansion_runs:
            if run > self.grid.shape[2]:
                continue
            bound = range_expansion_error(self.grid, tx_positions, rx_positions, c_mps, fc_hz, run, dtau_s)
            if bound <= limit:
                self.last_variant, self.last_expansion_run, self.last_error_bound = "range_expansion", run, bound
                aligned = {"ROWS_ALIGNED": 1} if self.grid.shape[2] % self.vec == 0 else {}
                if run == SHORTEST_RUN and not aligned:
                    return self.kernel
                return self._kernel_with({"RANGE_EXPANSION": run, **aligned})
        return self._plain_kernel()

    def _plain_kernel(self):
        """The plain kernel at this plan's width and defines (built once per context)."""
        return self._kernel_with({})

    def _kernel_with(self, variant: dict):
        """The kernel at this plan's width and defines with ``variant``'s defines (built once per context)."""
        from ..cl import kernel

        return kernel(self.context, self.SOURCES, self.KERNEL, {**self.defines(), **variant, "VEC": self.vec})

    @classmethod
    def selftest(cls, queue, vec: int, shape: Shape | None = None) -> float:
        """5 x 2 x 3 voxels (not a multiple of VEC), two chunks, voxels in and out of the window,
        a different speed of sound for each measurement; at ``shape`` (default: the plain kernel,
        the runtime's local size). The range-expansion variant on 3 x 2 x 37 voxels (work-items in
        one z row, expanded, and across a row's end, exact) against its own twin
        (:func:`~clsas.formation.bp_numpy.backproject_range_expansion`) at its shortest run."""
        from . import bp_numpy as twin

        grid, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
        shape = shape or Shape()
        if shape.variant != "range_expansion":
            plan = cls(grid, 3, 40, queue=queue, vec=vec, chunk=2, shape=shape)
            got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c)
            want = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points())
        else:
            return cls._expansion_selftest(queue, vec, shape, (prof, tau0, 1 / fs, 25e3, tx, rx, c))
        if not (np.any(want == 0) and np.any(want != 0)):
            raise RuntimeError("selftest scene must have voxels inside and outside the profile window")
        return float(np.abs(got - want).max() / np.abs(want).max())

    @classmethod
    def _expansion_selftest(cls, queue, vec: int, shape: Shape, args: tuple) -> float:
        """The range-expansion variant against its twin at every build a call may take at this
        width: each run (4 up to VEC), on rows of 37 voxels (work-items across a row's end: the
        exact branch) and of 32 (aligned: -DROWS_ALIGNED); the largest error relative to the peak."""
        from . import bp_numpy as twin

        err = 0.0
        for nz in (37, 32):
            grid = VoxelGrid(np.linspace(-0.1, 0.1, 3), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, nz))
            for run in (r for r in (4, 8, 16) if r <= vec):
                plan = cls(grid, 3, 40, queue=queue, vec=vec, chunk=2, shape=shape, max_error=0.5)
                # the arithmetic against its own twin, on a near grid: whatever the expansion's error
                plan.expansion_runs, plan.expansion_limit, plan.max_error = (run,), np.inf, np.inf
                got = plan(*args)
                if plan.last_expansion_run != run:
                    raise RuntimeError(f"the range-expansion selftest ran {plan.last_variant!r}, not run {run}")
                want = twin.backproject_range_expansion(*args, grid, run, vec)
                if not (np.any(want == 0) and np.any(want != 0)):
                    raise RuntimeError("selftest scene must have voxels inside and outside the profile window")
                err = max(err, float(np.abs(got - want).max() / np.abs(want).max()))
        return err


    @classmethod
    def time_shapes(cls, queue, vec: int, shapes: list[Shape], rounds: int = 5) -> list[list[float]]:
        """Kernel seconds of each shape in each of ``rounds`` interleaved rounds (after a warm-up)
        on a 40^3 grid x 32 measurements (a raster in front of it, every pair inside the profiles);
        the range-expansion variant at its shortest run (the slowest it runs)."""
        grid, args = timing_scene(np.random.default_rng(1))
        plans = [cls(grid, 32, args[0].shape[1], queue=queue, vec=vec, shape=s) for s in shapes]
        for plan in plans:
            plan.expansion_runs = (SHORTEST_RUN,)
            plan(*args)
            if plan.shape.variant == "range_expansion" and plan.last_variant != "range_expansion":
                raise RuntimeError(f"shape {plan.shape.label} ran the {plan.last_variant} kernel on the timing scene")
        out = [[] for _ in plans]
        for _ in range(rounds):
            for times, plan in zip(out, plans, strict=True):
                plan(*args)
                times.append(plan.last_kernel_s)
        return out


def staged_records(grid: VoxelGrid, per_group: int, samples_per_m: float) -> int:
    """Records a work-group of ``per_group`` consecutive voxels (C order) stages per measurement
    under -DLOCAL_PROFILES: its largest bounding-box diagonal ``d`` over the grid's groups, then
    ``ceil(2 d samples_per_m) + 2`` (the two distances of a path each change by at most ``d``
    within the box; the left samples of two lanes differ by at most the ceiling of their lags')."""
    if per_group < 1 or not samples_per_m > 0:
        raise ValueError(f"per_group must be >= 1 and samples_per_m > 0, got {per_group}, {samples_per_m}")
    nx, ny, nz = grid.shape
    first = np.arange(0, grid.size, per_group)
    last = np.minimum(first + per_group, grid.size) - 1
    ix0, rest0 = np.divmod(first, ny * nz)
    ix1, rest1 = np.divmod(last, ny * nz)
    (iy0, iz0), (iy1, iz1) = np.divmod(rest0, nz), np.divmod(rest1, nz)
    one_x = ix0 == ix1
    one_y = one_x & (iy0 == iy1)
    ext_x = ix1 - ix0
    ext_y = np.where(one_x, iy1 - iy0, ny - 1)
    ext_z = np.where(one_y, iz1 - iz0, nz - 1)
    sx, sy, sz = (abs(s) if n > 1 else 0.0 for s, n in zip(grid.spacing(), grid.shape, strict=True))
    diag = float(np.sqrt((ext_x * sx) ** 2 + (ext_y * sy) ** 2 + (ext_z * sz) ** 2).max())
    return int(np.ceil(2 * diag * samples_per_m)) + 2


def timing_scene(rng) -> tuple[VoxelGrid, tuple]:
    """What :meth:`BackprojectPlan.time_shapes` times: a 40^3 grid of 1 cm voxels 0.5 m in front of
    a 6 x 6 raster (32 positions used) of 1 m, profiles every 2 samples at 96 kHz covering every
    pair, 25 kHz; returns ``(grid, (profiles, tau0, dtau, fc, tx, rx, c))``."""
    ax = np.arange(40) * 0.01 - 0.195
    grid = VoxelGrid(ax, ax, 0.7 + ax)
    u = np.linspace(-0.5, 0.5, 6)
    tx = np.c_[np.repeat(u, 6), np.tile(u, 6), np.zeros(36)][:32]
    rx = tx + [0.03, 0.0, 0.0]
    c, dtau = 343.0, 2 / 96e3
    corners = np.array(np.meshgrid(*grid.bounds(), indexing="ij")).reshape(3, -1).T
    near = grid.z_m[0]  # the grid's face nearest to the raster (at z = 0): no path is shorter than 2 near
    far = np.linalg.norm(corners[:, None] - tx[None], axis=2).max() + 0.03  # nor longer than 2 far
    tau0 = np.full(32, 2 * near / c - 4 * dtau)
    n_lags = int(np.ceil((2 * far / c - tau0[0]) / dtau)) + 4
    prof = (rng.normal(size=(32, n_lags)) + 1j * rng.normal(size=(32, n_lags))).astype(np.complex64)
    return grid, (prof, tau0, dtau, 25e3, tx, rx, c)


def beam_selftest(queue, vec: int, mode: str = "weighted") -> float:
    """The selftest scene through the beam variant (-DBEAM): a piston speaker tilted per
    measurement and a cone microphone, ``mode`` "weighted" or "limited"; error against the twin
    relative to the peak."""
    from . import bp_numpy as twin

    grid, prof, tau0, fs, tx, rx, c, rng = selftest_scene()
    w = selftest_beam_weights(rng, mode)
    plan = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, beam_lut=w.luts.shape[1])
    got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c, beam=w)
    want = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points(), beam=w)
    return float(np.abs(got - want).max() / np.abs(want).max())


def selftest_scene():
    """The small scene the backprojection-type plans check themselves on: a 5 x 2 x 3 grid (not
    a multiple of VEC), 3 measurements of 40 lags whose window is centred on the grid's centre
    (voxels inside and outside it), a speed of sound per measurement. Returns ``(grid, profiles,
    tau0_s, fs_hz, tx, rx, c_mps, rng)``, the rng (seed 7) left where the scene's draws end."""
    rng = np.random.default_rng(7)
    fs = 96e3
    grid = VoxelGrid(np.linspace(-0.1, 0.1, 5), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, 3))
    tx = np.c_[rng.uniform(-0.2, 0.2, (3, 2)), np.zeros(3)]
    rx = tx + [0.03, 0, 0]
    prof = (rng.normal(size=(3, 40)) + 1j * rng.normal(size=(3, 40))) * np.hanning(40)
    centre = np.array([0.0, 0.025, 0.4])
    path = np.linalg.norm(centre - tx, axis=1) + np.linalg.norm(centre - rx, axis=1)
    tau0 = path / 343.0 - 20 / fs
    c = np.array([343.0, 340.0, 346.0])
    return grid, prof, tau0, fs, tx, rx, c, rng
