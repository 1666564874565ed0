"""OpenCL plan for kernels/stolt.cl (the Stolt mapping and spreading of the ω-k formation)."""

from __future__ import annotations

import numpy as np

from ..cl import Plan
from . import stolt_numpy as stolt


class StoltPlan(Plan):
    """The ``stolt_spread`` kernel on one queue; buffers grow to the largest call.

    Called like :func:`clsas.formation.stolt_numpy.spread` (its NumPy twin), in float32 on the
    device; returns complex64 cells (n_terms, n_cols, n_cells).
    """

    KERNEL = "stolt_spread"
    SOURCES = ("common.cl", "stolt.cl")

    def __init__(self, queue=None, vec=None):
        super().__init__(queue, vec)
        self._bufs: dict[str, tuple[int, object]] = {}

    def _buf(self, name: str, nbytes: int, access: str):
        size, buf = self._bufs.get(name, (0, None))
        if size < nbytes:
            buf = self.alloc(nbytes, access)
            self._bufs[name] = (nbytes, buf)
        return buf

    def __call__(self, spec: np.ndarray, k: np.ndarray, ku: np.ndarray, kv: np.ndarray,
                 p: stolt.StoltParams) -> np.ndarray:
        n_cols, n_f = spec.shape
        M = p.n_cells
        d_spec = self._buf("spec", 8 * n_cols * n_f, "r")
        d_k = self._buf("k", 4 * n_f, "r")
        d_kuv = self._buf("kuv", 8 * n_cols, "r")
        d_out = self._buf("cells", 8 * p.n_terms * n_cols * M, "rw")  # read-modify-write
        self.begin()
        self.write(d_spec, spec, np.complex64)
        self.write(d_k, k, np.float32)
        self.write(d_kuv, np.stack([ku, kv], axis=1), np.float32)
        geo = np.array([p.dz_m * M / (2 * np.pi), p.zc_m / (2 * np.pi), 1 / p.zref_m, 1 / (2 * np.pi * p.zref_m)],
                       np.float32)
        win = np.array([*p.baseline_uv, p.s1, 1 / max(p.s2 - p.s1, 1e-12)], np.float32)
        self.launch((-(-n_cols // self.vec),), d_spec, d_k, d_kuv, np.int32(n_cols), np.int32(n_f), geo, win,
                    np.float32(p.s2), np.int32(M), np.int32(p.width), np.float32(p.beta), np.int32(p.n_terms), d_out)
        return self.read(d_out, (p.n_terms, n_cols, M), np.complex64)

    @staticmethod
    def selftest_inputs(n_cols: int = 37, n_f: int = 23):
        """A small column set: evanescent, windowed and kept samples, several terms, folding."""
        rng = np.random.default_rng(3)
        k = np.linspace(-300.0, 1100.0, n_f)  # negative frequencies too
        ku = rng.uniform(-900, 900, n_cols)
        kv = rng.uniform(-500, 500, n_cols)
        spec = (rng.normal(size=(n_cols, n_f)) + 1j * rng.normal(size=(n_cols, n_f))) * 1e-3
        p = stolt.StoltParams(dz_m=0.006, zc_m=0.9, zref_m=0.85, baseline_uv=(-0.04, 0.01), n_cells=24, width=6,
                              n_terms=3, s1=0.6, s2=0.8)
        return spec, k, ku, kv, p

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """Kernel against the twin on :meth:`selftest_inputs`; error relative to the peak."""
        spec, k, ku, kv, p = cls.selftest_inputs()
        got = cls(queue=queue, vec=vec)(spec, k, ku, kv, p)
        want = stolt.spread(spec, k, ku, kv, p)
        return float(np.abs(got - want).max() / np.abs(want).max())


class StoltDepthsPlan(StoltPlan):
    """The ``stolt_depths`` kernel on one queue: the Stolt sum evaluated directly at the depths.

    Called like :func:`clsas.formation.stolt_numpy.direct` (its NumPy twin), in float32 on the
    device; returns complex64 (n_cols, n_z).
    """

    KERNEL = "stolt_depths"

    def __call__(self, spec: np.ndarray, k: np.ndarray, ku: np.ndarray, kv: np.ndarray,  # type: ignore[override]
                 p: stolt.StoltParams, n_z: int, factors: np.ndarray) -> np.ndarray:
        n_cols, n_f = spec.shape
        n_z = int(n_z)
        n_items = -(-n_cols // self.vec)
        pad = n_items * self.vec
        d_re = self._buf("spec_r", 4 * n_f * pad, "r")
        d_im = self._buf("spec_i", 4 * n_f * pad, "r")
        d_k = self._buf("k", 4 * n_f, "r")
        d_ku = self._buf("ku", 4 * pad, "r")
        d_kv = self._buf("kv", 4 * pad, "r")
        d_fac = self._buf("fac", 8 * p.n_terms * n_z, "r")
        d_acc = self._buf("acc", 8 * pad * n_z, "rw")  # the work-items' sums
        d_out = self._buf("out", 8 * n_cols * n_z, "w")
        # lanes contiguous: (n_f, pad) planes, the padding columns zero
        planes = np.zeros((2, n_f, pad), np.float32)
        planes[0, :, :n_cols] = spec.real.T
        planes[1, :, :n_cols] = spec.imag.T
        kuv = np.zeros((2, pad), np.float32)
        kuv[0, :n_cols], kuv[1, :n_cols] = ku, kv
        self.begin()
        self.write(d_re, planes[0], np.float32)
        self.write(d_im, planes[1], np.float32)
        self.write(d_k, k, np.float32)
        self.write(d_ku, kuv[0], np.float32)
        self.write(d_kv, kuv[1], np.float32)
        self.write(d_fac, factors, np.complex64)
        geo = np.array([p.dz_m / (2 * np.pi), p.zc_m / (2 * np.pi), 1 / p.zref_m, 1 / (2 * np.pi * p.zref_m)],
                       np.float32)
        win = np.array([*p.baseline_uv, p.s1, 1 / max(p.s2 - p.s1, 1e-12)], np.float32)
        self.launch((n_items,), d_re, d_im, d_k, d_ku, d_kv, np.int32(n_cols), np.int32(n_f), geo, win,
                    np.float32(p.s2), np.int32(n_z), np.int32(p.n_terms), d_fac, d_acc, d_out)
        return self.read(d_out, (n_cols, n_z), np.complex64)

    @staticmethod
    def selftest_factors(p: stolt.StoltParams, n_z: int = 40) -> np.ndarray:
        """(n_terms, n_z) bistatic weights ``(i u_z)^p / p!`` about ``zref`` for the self-test."""
        import math

        depth = p.zc_m + (np.arange(n_z) - n_z // 2) * p.dz_m
        u = 1 / depth - 1 / p.zref_m
        return np.array([(1j * u) ** q / math.factorial(q) for q in range(p.n_terms)])

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """Kernel against the twin on :meth:`StoltPlan.selftest_inputs` at 40 depths (two runs of
        rotations, the second partial); error relative to the peak."""
        spec, k, ku, kv, p = cls.selftest_inputs()
        fac = cls.selftest_factors(p)
        got = cls(queue=queue, vec=vec)(spec, k, ku, kv, p, fac.shape[1], fac)
        want = stolt.direct(spec, k, ku, kv, p, fac.shape[1], fac)
        return float(np.abs(got - want).max() / np.abs(want).max())
