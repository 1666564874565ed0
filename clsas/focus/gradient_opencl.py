"""OpenCL plan for kernels/autofocus.cl (the focus metric's gradient sums): built once for a
grid and profile shape, called once per optimiser step."""

from __future__ import annotations

import numpy as np

from ..cl import Plan
from ..physics.geometry import VoxelGrid


class FocusGradientPlan(Plan):
    """Compiled ``focus_gradient`` kernel and device buffers for one grid and profile shape.

    Same arguments and result as :func:`clsas.focus.gradient_numpy.focus_gradient` (the grid fixed):
    (n_meas, 5) sums, accumulated in float32 per work-item and added in float64 on the host.
    """

    KERNEL = "focus_gradient"
    SOURCES = ("common.cl", "autofocus.cl")

    def __init__(self, grid: VoxelGrid, n_meas: int, n_lags: int, queue=None, vec=None, chunk=None,
                 n_items: int | None = None):
        super().__init__(queue, vec)
        self.grid, self.n_meas, self.n_lags = grid, n_meas, max(2, n_lags)
        self.n_vox = grid.size
        self.n_blocks = -(-self.n_vox // self.vec)
        self.n_pad = self.n_blocks * self.vec
        # work-items per measurement: enough to fill a GPU with a few hundred measurements
        self.n_items = int(n_items or min(self.n_blocks, 128))
        self.chunk = chunk or int(np.clip(4e7 // self.n_pad, 4, 256))
        self.d_prof = self.alloc(16 * n_meas * self.n_lags, "r")
        self.d_tx = self.alloc(16 * n_meas, "r")
        self.d_rx = self.alloc(16 * n_meas, "r")
        self.d_s0 = self.alloc(4 * n_meas, "r")
        self.d_wre = self.alloc(4 * self.n_pad, "rw")  # written here or by FocusWeightPlan
        self.d_wim = self.alloc(4 * self.n_pad, "rw")
        self.d_out = self.alloc(4 * 5 * n_meas * self.n_items, "w")

    def __call__(self, data, tau0_s, dtau_s, fc_hz, tx_positions, rx_positions, c_mps, weight) -> np.ndarray:
        """(n_meas, 5) float64 sums (see the NumPy twin). ``weight`` None: the planes
        ``d_wre``/``d_wim`` hold it already, written on this plan's queue
        (:class:`clsas.focus.metric_opencl.FocusWeightPlan`)."""
        prof = np.zeros((self.n_meas, self.n_lags + 1), np.complex64)
        prof[:, : data.shape[1]] = data
        pairs = np.empty((self.n_meas, self.n_lags, 2), np.complex64)
        pairs[:, :, 0] = prof[:, :-1]
        pairs[:, :, 1] = prof[:, 1:]
        c = np.broadcast_to(np.asarray(c_mps, float), (self.n_meas,))
        pos4 = np.zeros((2, self.n_meas, 4), np.float32)
        pos4[0, :, :3] = tx_positions
        pos4[0, :, 3] = 1.0 / (c * dtau_s)
        pos4[1, :, :3] = rx_positions
        pos4[1, :, 3] = fc_hz / c
        self.begin()
        self.write(self.d_prof, pairs, np.complex64)
        self.write(self.d_tx, pos4[0], np.float32)
        self.write(self.d_rx, pos4[1], np.float32)
        self.write(self.d_s0, np.asarray(tau0_s) / dtau_s, np.float32)
        if weight is not None:
            w = np.zeros(self.n_pad, np.complex64)
            w[: self.n_vox] = np.asarray(weight).ravel()
            self.write(self.d_wre, w.real, np.float32)
            self.write(self.d_wim, w.imag, np.float32)
        g = self.grid
        origin = np.array([g.x_m[0], g.y_m[0], g.z_m[0], 0], np.float32)
        step = np.array([*g.spacing(), 0], np.float32)
        deriv = np.array([1.0 / dtau_s, 2 * np.pi * fc_hz], np.float32)
        for m0 in range(0, self.n_meas, self.chunk):
            m1 = min(self.n_meas, m0 + self.chunk)
            self.launch((self.n_items, m1 - m0), self.d_prof, np.int32(self.n_lags), self.d_tx, self.d_rx, self.d_s0,
                        origin, step, np.int32(g.shape[1]), np.int32(g.shape[2]), np.int32(self.n_blocks), deriv,
                        self.d_wre, self.d_wim, np.int32(m0), self.d_out)
        part = self.read(self.d_out, (self.n_meas, self.n_items, 5), np.float32)
        return part.astype(np.float64).sum(axis=1)

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """5 x 2 x 3 voxels (not a multiple of VEC), two chunks, fewer work-items than blocks,
        voxels in and out of the window, a speed of sound per measurement."""
        from ..formation.bp_opencl import selftest_scene
        from . import gradient_numpy as twin

        grid, prof, tau0, fs, tx, rx, c, rng = selftest_scene()
        weight = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
        plan = cls(grid, 3, 40, queue=queue, vec=vec, chunk=2, n_items=2)
        got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c, weight)
        want = twin.focus_gradient(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points(), weight)
        return float(np.abs(got - want).max() / np.abs(want).max())
