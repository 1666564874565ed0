"""OpenCL plan for kernels/backproject.cl: construct once for a grid, call many times."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .. import cl as _cl
from ..compress.opencl import vec_width
from ..geometry import VoxelGrid


class BackprojectPlan:
    """Compiled kernel and device buffers for one grid and profile shape.

    Measurements go through the kernel in chunks of ``chunk`` (bounded launches, profiles of
    a chunk stay in cache); the image accumulates on the device.
    """

    def __init__(self, grid: VoxelGrid, n_meas: int, n_lags: int, queue=None, vec=None, chunk=None):
        import pyopencl as cl

        self.cl = cl
        self.queue = queue or _cl.get_queue()
        self.vec = vec or vec_width(self.queue.device)
        self.grid, self.n_meas, self.n_lags = grid, n_meas, max(2, n_lags)
        self.n_vox = grid.size
        self.n_pad = -(-self.n_vox // self.vec) * self.vec
        self.chunk = chunk or int(np.clip(4e7 // self.n_pad, 4, 256))
        ctx = self.queue.context
        self.kernel = _cl.kernel(ctx, ("common.cl", "backproject.cl"), "backproject", {"VEC": self.vec})
        mf = cl.mem_flags
        self.d_prof = cl.Buffer(ctx, mf.READ_ONLY, 16 * n_meas * self.n_lags)
        self.d_tx = cl.Buffer(ctx, mf.READ_ONLY, 16 * n_meas)
        self.d_rx = cl.Buffer(ctx, mf.READ_ONLY, 16 * n_meas)
        self.d_s0 = cl.Buffer(ctx, mf.READ_ONLY, 4 * n_meas)
        self.d_re = cl.Buffer(ctx, mf.READ_WRITE, 4 * self.n_pad)
        self.d_im = cl.Buffer(ctx, mf.READ_WRITE, 4 * self.n_pad)
        self.last_kernel_s = 0.0

    def __call__(
        self,
        data: np.ndarray,
        tau0_s: np.ndarray,
        dtau_s: float,
        fc_hz: float,
        tx_positions: np.ndarray,
        rx_positions: np.ndarray,
        c_mps: float,
        progress: Callable[[int, int], None] | None = None,
    ) -> np.ndarray:
        """Backproject; same arguments as the NumPy twin (grid fixed). Returns (n_vox,) complex64."""
        cl, q = self.cl, self.queue
        # pair layout: record k holds samples k and k + 1, so one load per voxel serves lerp
        prof = np.zeros((self.n_meas, self.n_lags + 1), np.complex64)
        prof[:, : data.shape[1]] = data
        pairs = np.empty((self.n_meas, self.n_lags, 2), np.complex64)
        pairs[:, :, 0] = prof[:, :-1]
        pairs[:, :, 1] = prof[:, 1:]
        pos4 = np.zeros((2, self.n_meas, 4), np.float32)
        pos4[0, :, :3] = tx_positions
        pos4[1, :, :3] = rx_positions
        cl.enqueue_copy(q, self.d_prof, pairs)
        cl.enqueue_copy(q, self.d_tx, pos4[0])
        cl.enqueue_copy(q, self.d_rx, pos4[1])
        cl.enqueue_copy(q, self.d_s0, (np.asarray(tau0_s) / dtau_s).astype(np.float32))
        g = self.grid
        origin = np.array([g.x_m[0], g.y_m[0], g.z_m[0], 0], np.float32)
        step = np.array([*g.spacing(), 0], np.float32)
        fixed = (
            self.d_prof, np.int32(self.n_lags), self.d_tx, self.d_rx, self.d_s0,
            np.float32(1.0 / (c_mps * dtau_s)), np.float32(fc_hz / c_mps), origin, step,
            np.int32(g.shape[1]), np.int32(g.shape[2]),
        )
        events = []
        for m0 in range(0, self.n_meas, self.chunk):
            m1 = min(self.n_meas, m0 + self.chunk)
            evt = self.kernel(
                q, (self.n_pad // self.vec,), None, *fixed, np.int32(m0), np.int32(m1),
                np.int32(m0 > 0), self.d_re, self.d_im,
            )
            events.append(evt)
            if progress is not None:
                evt.wait()
                progress(m1, self.n_meas)
        re = np.empty(self.n_pad, np.float32)
        im = np.empty(self.n_pad, np.float32)
        cl.enqueue_copy(q, re, self.d_re, wait_for=events)
        cl.enqueue_copy(q, im, self.d_im)
        self.last_kernel_s = sum((e.profile.end - e.profile.start) * 1e-9 for e in events)
        return (re[: self.n_vox] + 1j * im[: self.n_vox]).astype(np.complex64)
