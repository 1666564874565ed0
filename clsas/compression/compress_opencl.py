"""OpenCL plans for the pulse-compression kernels: construct once, call many times.

Each plan's ``selftest(queue, vec)`` runs it on a small input against its NumPy twin and
returns the error relative to the peak; the device layer runs it in a child process to
verify a kernel variant before it is used (:mod:`clsas.cl.variants`). ``enqueue(signals)`` runs
the kernel and leaves the profiles on the device as :class:`clsas.cl.DeviceRows` for the next
plan on the same queue (backprojection), reading nothing back: their host copy is read when
something asks for it (:attr:`clsas.cl.DeviceRows.host`), or before the plan's next call
overwrites them. A call, ``plan(signals)``, is ``enqueue`` and that host copy (read-only).
"""

from __future__ import annotations

import hashlib

import numpy as np

from ..cl import DeviceRows, Plan
from . import compress_numpy as twin
from .layout import fft_layout

_FS = 96e3


def _selftest_inputs(rows: int = 3, n: int = 120):
    from ..physics.signals import analytic, lfm_chirp

    rng = np.random.default_rng(7)
    wave = lfm_chirp(20e3, 30e3, 0.4e-3, _FS, taper=0.1)
    return rng, analytic(wave), rng.normal(size=(rows, n))


def table_key(*parts) -> tuple:
    """A key for :func:`clsas.cl.reused` from a plan's constructor arguments: arrays by shape,
    dtype and a digest of their bytes, everything else as it is."""
    out = []
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            out.append((a.shape, a.dtype.str, hashlib.sha1(a.tobytes()).hexdigest()))
        else:
            out.append(p)
    return tuple(out)


def layout_key(layout) -> tuple:
    """:func:`table_key` of an :class:`~clsas.compression.layout.FftLayout`'s sizes and tables."""
    return table_key(layout.s_lo, layout.n_in, layout.log2_n, layout.log2_nd, layout.bin0, layout.idx0,
                     layout.n_lags, layout.twiddles, layout.spec, layout.post)


def _rel_err(got, want) -> float:
    return float(np.abs(got - want).max() / np.abs(want).max())


class _RowPlan(Plan):
    """Shared pieces of the direct kernels: one work-item per VEC lags of one recording."""

    def __init__(self, n_meas: int, n_samples: int, n_lags: int, queue=None, vec: int | None = None):
        super().__init__(queue, vec)
        self.n_meas, self.n_samples, self.n_lags = n_meas, n_samples, n_lags
        self.stride = -(-n_lags // self.vec) * self.vec
        self.d_sig = self.alloc(4 * n_meas * n_samples, "r")
        self.d_out = self.alloc(8 * n_meas * self.stride, "rw")
        self.args: list = []  # the kernel's arguments between the recordings' and the output (each plan's own)

    def enqueue(self, signals: np.ndarray) -> DeviceRows:
        """Compress ``signals`` ((n_meas, n_samples) real) into rows left on the device, once the
        kernel has ended (``last_kernel_s``, s); nothing is read back. The plan keeps no reference
        to the rows: those nobody holds any more are not read before its next call."""
        self.begin()
        self.write(self.d_sig, signals, np.float32)
        self.launch((self.stride // self.vec, self.n_meas), self.d_sig, np.int32(self.n_samples), *self.args,
                    self.d_out)
        self.finish()
        return self.lend(self.d_out, self.n_meas, self.n_lags, self.stride)

    def __call__(self, signals: np.ndarray) -> np.ndarray:
        """The profiles of ``signals``, (n_meas, n_lags) complex64, read-only (:meth:`enqueue`, read back)."""
        return self.enqueue(signals).host


class MatchedFilterPlan(_RowPlan):
    """Matched filter over a fixed lag window for recordings of a fixed shape."""

    KERNEL = "matched_filter"
    SOURCES = ("common.cl", "compress.cl")

    def __init__(self, n_meas, n_samples, ref_conj, lag0, n_lags, rot, rot0, lag_step=1, queue=None, vec=None):
        super().__init__(n_meas, n_samples, n_lags, queue, vec)
        rot_p = np.zeros(self.stride, np.complex64)
        rot_p[:n_lags] = rot[:n_lags]
        self.d_rot0 = self.upload(rot0, np.complex64)
        self.args = [
            self.upload(ref_conj, np.complex64), np.int32(len(ref_conj)), np.int32(lag0), np.int32(lag_step),
            np.int32(n_lags), self.upload(rot_p, np.complex64), self.d_rot0, np.int32(self.stride),
        ]

    def set_rot0(self, rot0: np.ndarray) -> None:
        """The per-recording rotation of the next calls ((n_meas,) complex), written in place."""
        self.write(self.d_rot0, rot0, np.complex64)

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """A lag window past both edges of the recording, lag steps 1 and 2; error vs the twin."""
        rng, ref_a, sig = _selftest_inputs()
        ref = np.conj(ref_a)
        err = 0.0
        for step, n_lags in [(1, 130), (2, 65)]:
            rot = np.exp(-2j * np.pi * 0.26 * step * np.arange(n_lags))
            rot0 = np.exp(-2j * np.pi * rng.uniform(size=len(sig)))
            got = cls(len(sig), sig.shape[1], ref, -10, n_lags, rot, rot0, step, queue=queue, vec=vec)(sig)
            err = max(err, _rel_err(got, twin.matched_filter(sig, ref, -10, n_lags, rot, rot0, step)))
        return err


class FmcwPlan(_RowPlan):
    """FMCW dechirp + DFT at gated delays for recordings of a fixed shape."""

    KERNEL = "fmcw_dechirp"
    SOURCES = ("common.cl", "compress.cl")

    def __init__(self, n_meas, n_samples, ref, slope_hz_per_s, fs_hz, taus_s, rvp, queue=None, vec=None):
        n_lags = len(taus_s)
        super().__init__(n_meas, n_samples, n_lags, queue, vec)
        rvp_p = np.zeros(self.stride, np.complex64)
        rvp_p[:n_lags] = rvp[:n_lags]
        dtau = float(taus_s[1] - taus_s[0]) if n_lags > 1 else 0.0
        self.args = [
            self.upload(ref, np.complex64), np.int32(len(ref)), np.float32(slope_hz_per_s / fs_hz),
            np.float32(taus_s[0]), np.float32(dtau), np.int32(n_lags), self.upload(rvp_p, np.complex64),
            np.int32(self.stride),
        ]

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        rng, ref_a, sig = _selftest_inputs()
        ref = np.conj(ref_a) * np.hanning(len(ref_a))
        taus = 1e-4 + np.arange(21) / _FS
        rvp = np.exp(1j * rng.uniform(size=21))
        slope = 10e3 / 0.4e-3
        got = cls(len(sig), sig.shape[1], ref, slope, _FS, taus, rvp, queue=queue, vec=vec)(sig)
        return _rel_err(got, twin.fmcw_dechirp(sig, ref, slope, _FS, taus, rvp))


class FftMatchedPlan(Plan):
    """Matched filter by FFT with decimation in the frequency domain (``matched_fft``).

    Parameters come from :func:`clsas.compression.layout.fft_layout`. Scratch is two arrays of N complex
    values per recording; recordings are processed in batches that keep it under
    ``max_scratch_bytes``.
    """

    KERNEL = "matched_fft"
    SOURCES = ("common.cl", "compress.cl")

    def __init__(self, n_meas, n_samples, layout, rot0, queue=None, vec=None, max_scratch_bytes=256 << 20):
        super().__init__(queue, vec)
        self.n_meas, self.n_samples, self.layout = n_meas, n_samples, layout
        self.n_lags = layout.n_lags
        per_item = 4 * layout.n_fft * self.vec * 4  # bytes of scratch per work-item
        self.items = max(1, min(-(-n_meas // self.vec), max_scratch_bytes // per_item))
        self.d_work = self.alloc(self.items * per_item)
        self.d_sig = self.alloc(4 * n_meas * n_samples, "r")
        self.d_out = self.alloc(8 * n_meas * self.n_lags, "rw")
        self.d_tw, self.d_spec, self.d_post = (self.upload(a, np.complex64)
                                               for a in (layout.twiddles, layout.spec, layout.post))
        self.d_rot0 = self.upload(rot0, np.complex64)

    def set_rot0(self, rot0: np.ndarray) -> None:
        """The per-recording rotation of the next calls ((n_meas,) complex), written in place."""
        self.write(self.d_rot0, rot0, np.complex64)

    def enqueue(self, signals: np.ndarray) -> DeviceRows:
        """Compress ``signals`` ((n_meas, n_samples) real) into rows left on the device, once the
        kernels have ended (``last_kernel_s``, s); nothing is read back (:meth:`_RowPlan.enqueue`)."""
        lay = self.layout
        self.begin()
        self.write(self.d_sig, signals, np.float32)
        rows_per_batch = self.items * self.vec
        for m0 in range(0, self.n_meas, rows_per_batch):
            rows = min(rows_per_batch, self.n_meas - m0)
            self.launch(
                (-(-rows // self.vec),), self.d_sig, np.int32(self.n_samples), np.int32(self.n_meas),
                np.int32(m0), np.int32(lay.s_lo), np.int32(lay.n_in), np.int32(lay.log2_n), np.int32(lay.log2_nd),
                self.d_tw, np.int32(lay.bin0), self.d_spec, np.int32(lay.idx0), np.int32(self.n_lags),
                self.d_post, self.d_rot0, self.d_work, np.int32(self.n_lags), self.d_out,
            )
        self.finish()
        return self.lend(self.d_out, self.n_meas, self.n_lags, self.n_lags)

    def __call__(self, signals: np.ndarray) -> np.ndarray:
        """The profiles of ``signals``, (n_meas, n_lags) complex64, read-only (:meth:`enqueue`, read back)."""
        return self.enqueue(signals).host

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """Lag step 1 against the direct twin, rows in two batches (more rows than one work-item)."""
        rng, ref_a, _ = _selftest_inputs()
        rows = rng.normal(size=(2 * vec + 3, 120))
        n_lags, lag0 = 130, -10
        rot = np.exp(-2j * np.pi * 0.26 * np.arange(n_lags))
        rot0 = np.exp(-2j * np.pi * rng.uniform(size=len(rows)))
        lay = fft_layout(ref_a, _FS, 25e3, 0, 120, lag0, 1, n_lags, rot)
        plan = cls(len(rows), 120, lay, rot0, queue=queue, vec=vec, max_scratch_bytes=16 * lay.n_fft * vec * 2)
        want = twin.matched_filter(rows, np.conj(ref_a), lag0, n_lags, rot, rot0, 1)
        return _rel_err(plan(rows), want)
