"""OpenCL plan for kernels/project.cl (the forward projector): construct once for a grid and a
profile shape, call many times."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..cl import kernel
from ..formation.bp_opencl import BeamPlan, carrier_rotation, upsample_adjoint, upsample_factor
from ..physics.geometry import VoxelGrid

#: bytes of partial profiles one chunk of measurements may hold on the device
PARTIAL_BYTES = 64 << 20


class ProjectPlan(BeamPlan):
    """Compiled kernels and device buffers of the forward projection onto one profile shape.

    Each measurement's profile is accumulated in ``n_items`` private copies (one per voxel slab,
    no atomics) by ``project`` and summed by ``project_sum``; measurements go through in chunks
    that bound the copies to :data:`PARTIAL_BYTES`.

    Parameters
    ----------
    grid : VoxelGrid
    n_meas, n_lags : int
        Profiles' shape (``n_lags`` at least 2).
    n_items : int, optional
        Voxel slabs per measurement (work-items along the voxels); default from the device's
        compute units and the number of measurements.
    chunk : int, optional
        Measurements per launch.
    beam_lut : int, optional
        Samples per beam table (:class:`clsas.physics.beam.BeamWeights`): the ``-DBEAM`` variant that weights
        each pair as the backprojection does (kernels/beam.cl); 0 (default): omnidirectional.
    """

    KERNEL = "project"
    SOURCES = ("common.cl", "beam.cl", "project.cl")

    def __init__(self, grid: VoxelGrid, n_meas: int, n_lags: int, queue=None, vec=None, chunk=None,
                 n_items=None, beam_lut: int = 0):
        self.beam_lut = int(beam_lut)  # samples per beam table; 0: omnidirectional (no -DBEAM)
        super().__init__(queue, vec)
        self.sum_kernel = kernel(self.context, self.SOURCES, "project_sum", {"VEC": self.vec})
        self.grid, self.n_meas, self.n_lags = grid, n_meas, max(2, n_lags)
        self.n_vox = grid.size
        self.n_blocks = -(-self.n_vox // self.vec)
        self.n_pad = self.n_blocks * self.vec
        dev = self.queue.device
        gpu = bool(dev.type & self.cl.device_type.GPU)
        target = dev.max_compute_units * (256 if gpu else 4)
        self.n_items = int(n_items or np.clip(-(-target // n_meas), 1, self.n_blocks))
        self.n_items = min(self.n_items, self.n_blocks)
        self.user_chunk = chunk
        self._size_records(self.n_lags)
        self.d_xre = self.alloc(4 * self.n_pad, "r")
        self.d_xim = self.alloc(4 * self.n_pad, "r")
        self.d_tx = self.alloc(16 * n_meas, "r")
        self.d_rx = self.alloc(16 * n_meas, "r")
        self.d_s0 = self.alloc(4 * n_meas, "r")
        self.alloc_beam(n_meas)

    def _size_records(self, n_rec: int) -> None:
        """Chunk and buffers for ``n_rec`` records per profile (more than ``n_lags`` where the
        profile is upsampled for the carrier, :func:`~clsas.formation.bp_opencl.carrier_records`)."""
        per_meas = 16 * self.n_items * n_rec
        self.chunk = int(self.user_chunk or np.clip(PARTIAL_BYTES // per_meas, 1, self.n_meas))
        self.d_part = self.alloc(per_meas * self.chunk)
        self.d_prof = self.alloc(16 * self.n_meas * n_rec, "w")
        self.n_rec = n_rec

    def __call__(
        self,
        values: np.ndarray,
        tau0_s: np.ndarray,
        dtau_s: float,
        fc_hz: float,
        tx_positions: np.ndarray,
        rx_positions: np.ndarray,
        c_mps: float | np.ndarray,
        progress: Callable[[int, int], None] | None = None,
        beam=None,
    ) -> np.ndarray:
        """Project ``values`` ((n_vox,) complex); the twin's arguments less ``n_lags`` and the
        points (fixed by the plan), ``beam`` a :class:`clsas.physics.beam.BeamWeights` of the plan's
        ``beam_lut`` (None without one). Returns (n_meas, n_lags) complex64 profiles."""
        x = np.zeros(self.n_pad, np.complex64)
        x[: self.n_vox] = np.ravel(values)
        up = upsample_factor(fc_hz, dtau_s)
        n_rec, dtau_s = (self.n_lags - 1) * up + 1, dtau_s / up
        if n_rec != self.n_rec:
            self._size_records(n_rec)
        self.begin()
        self.write(self.d_xre, x.real, np.float32)
        self.write(self.d_xim, x.imag, np.float32)
        self.write_geometry(tau0_s, dtau_s, tx_positions, rx_positions, c_mps)
        g = self.grid
        origin = np.array([g.x_m[0], g.y_m[0], g.z_m[0], 0], np.float32)
        step = np.array([*g.spacing(), 0], np.float32)
        fixed = (self.d_xre, self.d_xim, np.int32(n_rec), self.d_tx, self.d_rx, self.d_s0, origin, step,
                 np.int32(g.shape[1]), np.int32(g.shape[2]), np.float32(2 * np.pi * fc_hz * dtau_s),
                 np.int32(self.n_blocks))
        beam_args = self.beam_args(beam)
        lag_items = -(-n_rec // 64) * 64
        for m0 in range(0, self.n_meas, self.chunk):
            m1 = min(self.n_meas, m0 + self.chunk)
            self.launch((self.n_items, m1 - m0), *fixed, np.int32(m0), self.d_part, *beam_args)
            evt = self.sum_kernel(self.queue, (lag_items, m1 - m0), None, self.d_part, np.int32(self.n_items),
                                  np.int32(n_rec), np.int32(m0), self.d_prof)
            self._events.append(evt)
            if progress is not None:
                evt.wait()
                progress(m1, self.n_meas)
        rec = self.read(self.d_prof, (self.n_meas, n_rec, 2), np.complex64)
        rot = np.conj(carrier_rotation(n_rec, tau0_s, dtau_s, fc_hz))
        prof = rec[:, :, 0] * rot  # slot A of record k to lag k, slot B to lag k + 1
        prof[:, 1:] += rec[:, :-1, 1] * rot[:, :-1]
        return (upsample_adjoint(prof, up) if up > 1 else prof).astype(np.complex64)

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """The backprojection's selftest scene (5 x 2 x 3 voxels, not a multiple of VEC; voxels in
        and out of the window; a speed of sound per measurement), two chunks, two voxel slabs."""
        from ..formation.bp_opencl import selftest_scene
        from . import project_numpy as twin

        grid, prof, tau0, fs, tx, rx, c, rng = selftest_scene()
        x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
        got = cls(grid, 3, 40, queue=queue, vec=vec, chunk=2, n_items=2)(x, tau0, 1 / fs, 25e3, tx, rx, c)
        want = twin.project(x, tau0, 1 / fs, 40, 25e3, tx, rx, c, grid.points())
        return float(np.abs(got - want).max() / np.abs(want).max())


def beam_selftest(queue, vec: int, mode: str = "weighted") -> float:
    """The selftest scene through the beam variant (-DBEAM): a piston speaker tilted per measurement
    and a cone microphone (the backprojection's :func:`clsas.formation.bp_opencl.beam_selftest`),
    ``mode`` "weighted" or "limited", two chunks, two voxel slabs; error against the twin relative
    to the peak."""
    from ..formation.bp_opencl import selftest_beam_weights, selftest_scene
    from . import project_numpy as twin

    grid, _, tau0, fs, tx, rx, c, rng = selftest_scene()
    w = selftest_beam_weights(rng, mode)
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    plan = ProjectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, n_items=2, beam_lut=w.luts.shape[1])
    got = plan(x, tau0, 1 / fs, 25e3, tx, rx, c, beam=w)
    want = twin.project(x, tau0, 1 / fs, 40, 25e3, tx, rx, c, grid.points(), beam=w)
    return float(np.abs(got - want).max() / np.abs(want).max())
