"""OpenCL plan for kernels/stolt.cl (the Stolt mapping and spreading of the ω-k formation)."""

from __future__ import annotations

import numpy as np

from ..cl import Plan
from . import stolt


class StoltPlan(Plan):
    """The ``stolt_spread`` kernel on one queue; buffers grow to the largest call.

    Called like :func:`clsas.formation.stolt.spread` (its NumPy twin), in float32 on the
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
