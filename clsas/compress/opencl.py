"""OpenCL plans for the pulse-compression kernels: construct once, call many times."""

from __future__ import annotations

import numpy as np

from .. import cl as _cl


def vec_width(device) -> int:
    """Voxels or lags per work-item: the float vector width on CPUs, 4 elsewhere."""
    import pyopencl as cl

    if device.type & cl.device_type.CPU:
        return int(min(16, max(4, device.preferred_vector_width_float)))
    return 4


class _Plan:
    """Shared pieces: queue, program, padded output rows, timing of the last call."""

    kernel_name = ""

    def __init__(self, n_meas: int, n_samples: int, n_lags: int, queue=None, vec: int | None = None):
        import pyopencl as cl

        self.cl = cl
        self.queue = queue or _cl.get_queue()
        self.vec = vec or vec_width(self.queue.device)
        self.n_meas, self.n_samples, self.n_lags = n_meas, n_samples, n_lags
        self.stride = -(-n_lags // self.vec) * self.vec
        self.kernel = _cl.kernel(self.queue.context, ("common.cl", "compress.cl"), self.kernel_name, {"VEC": self.vec})
        mf = cl.mem_flags
        self.d_sig = cl.Buffer(self.queue.context, mf.READ_ONLY, max(4, 4 * n_meas * n_samples))
        self.d_out = cl.Buffer(self.queue.context, mf.WRITE_ONLY, 8 * n_meas * self.stride)
        self.last_kernel_s = 0.0

    def _buf(self, arr: np.ndarray):
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.queue.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=arr)

    def _run(self, signals: np.ndarray, args: list) -> np.ndarray:
        cl = self.cl
        sig = np.ascontiguousarray(signals, dtype=np.float32)
        cl.enqueue_copy(self.queue, self.d_sig, sig)
        gsize = (self.stride // self.vec, self.n_meas)
        evt = self.kernel(self.queue, gsize, None, self.d_sig, np.int32(self.n_samples), *args, self.d_out)
        out = np.empty((self.n_meas, self.stride), dtype=np.complex64)
        cl.enqueue_copy(self.queue, out, self.d_out, wait_for=[evt])
        self.last_kernel_s = (evt.profile.end - evt.profile.start) * 1e-9
        return out[:, : self.n_lags]


class MatchedFilterPlan(_Plan):
    """Matched filter over a fixed lag window for recordings of a fixed shape."""

    kernel_name = "matched_filter"

    def __init__(self, n_meas, n_samples, ref_conj, lag0, n_lags, rot, rot0, lag_step=1, queue=None, vec=None):
        super().__init__(n_meas, n_samples, n_lags, queue, vec)
        rot_p = np.zeros(self.stride, np.complex64)
        rot_p[:n_lags] = rot[:n_lags]
        self.d_ref = self._buf(np.ascontiguousarray(ref_conj, np.complex64))
        self.d_rot = self._buf(rot_p)
        self.d_rot0 = self._buf(np.ascontiguousarray(rot0, np.complex64))
        self.args = [
            self.d_ref, np.int32(len(ref_conj)), np.int32(lag0), np.int32(lag_step), np.int32(n_lags),
            self.d_rot, self.d_rot0, np.int32(self.stride),
        ]

    def __call__(self, signals: np.ndarray) -> np.ndarray:
        return self._run(signals, self.args)


class FmcwPlan(_Plan):
    """FMCW dechirp + DFT at gated delays for recordings of a fixed shape."""

    kernel_name = "fmcw_dechirp"

    def __init__(self, n_meas, n_samples, ref, slope_hz_per_s, fs_hz, taus_s, rvp, queue=None, vec=None):
        n_lags = len(taus_s)
        super().__init__(n_meas, n_samples, n_lags, queue, vec)
        rvp_p = np.zeros(self.stride, np.complex64)
        rvp_p[:n_lags] = rvp[:n_lags]
        self.d_ref = self._buf(np.ascontiguousarray(ref, np.complex64))
        self.d_rvp = self._buf(rvp_p)
        dtau = float(taus_s[1] - taus_s[0]) if n_lags > 1 else 0.0
        self.args = [
            self.d_ref, np.int32(len(ref)), np.float32(slope_hz_per_s / fs_hz),
            np.float32(taus_s[0]), np.float32(dtau), np.int32(n_lags), self.d_rvp,
            np.int32(self.stride),
        ]

    def __call__(self, signals: np.ndarray) -> np.ndarray:
        return self._run(signals, self.args)


class FftMatchedPlan:
    """Matched filter by FFT with decimation in the frequency domain (``matched_fft``).

    Parameters come from :func:`clsas.compress.fft_layout`. Scratch is two arrays of N complex
    values per recording; recordings are processed in batches that keep it under
    ``max_scratch_bytes``.
    """

    def __init__(self, n_meas, n_samples, layout, rot0, queue=None, vec=None, max_scratch_bytes=256 << 20):
        import pyopencl as cl

        self.cl = cl
        self.queue = queue or _cl.get_queue()
        self.vec = vec or vec_width(self.queue.device)
        self.n_meas, self.n_samples, self.layout = n_meas, n_samples, layout
        self.n_lags = layout.n_lags
        self.kernel = _cl.kernel(self.queue.context, ("common.cl", "compress.cl"), "matched_fft", {"VEC": self.vec})
        ctx, mf = self.queue.context, cl.mem_flags
        n = layout.n_fft
        per_item = 4 * n * self.vec * 4  # bytes of scratch per work-item
        self.items = max(1, min(-(-n_meas // self.vec), max_scratch_bytes // per_item))
        self.d_work = cl.Buffer(ctx, mf.READ_WRITE, self.items * per_item)
        self.d_sig = cl.Buffer(ctx, mf.READ_ONLY, max(4, 4 * n_meas * n_samples))
        self.d_out = cl.Buffer(ctx, mf.WRITE_ONLY, max(8, 8 * n_meas * self.n_lags))

        def buf(arr):
            return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(arr, np.complex64))

        self.d_tw, self.d_spec, self.d_post = buf(layout.twiddles), buf(layout.spec), buf(layout.post)
        self.d_rot0 = buf(rot0)
        self.last_kernel_s = 0.0

    def __call__(self, signals: np.ndarray) -> np.ndarray:
        cl, lay = self.cl, self.layout
        cl.enqueue_copy(self.queue, self.d_sig, np.ascontiguousarray(signals, dtype=np.float32))
        rows_per_batch = self.items * self.vec
        events = []
        for m0 in range(0, self.n_meas, rows_per_batch):
            rows = min(rows_per_batch, self.n_meas - m0)
            items = -(-rows // self.vec)
            events.append(self.kernel(
                self.queue, (items,), None, self.d_sig, np.int32(self.n_samples), np.int32(self.n_meas),
                np.int32(m0), np.int32(lay.s_lo), np.int32(lay.n_in), np.int32(lay.log2_n), np.int32(lay.log2_nd),
                self.d_tw, np.int32(lay.bin0), self.d_spec, np.int32(lay.idx0), np.int32(self.n_lags),
                self.d_post, self.d_rot0, self.d_work, np.int32(self.n_lags), self.d_out,
            ))
        res = np.empty((self.n_meas, self.n_lags), dtype=np.complex64)
        cl.enqueue_copy(self.queue, res, self.d_out, wait_for=events)
        self.last_kernel_s = sum((e.profile.end - e.profile.start) * 1e-9 for e in events)
        return res
