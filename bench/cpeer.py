"""The compiled C/OpenMP backprojection peer (``backproject_omp.c``), built on first use.

Built with the machine's C compiler (``$CC``, default ``gcc``) as ``-O3 -march=native -fopenmp``
into the clsas cache directory (next to the kernel-variant verdicts), keyed by the source and
the flags; loaded with ctypes. Where no compiler or OpenMP exists, :func:`load` returns None
and says why, and the bench leaves the peer out.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

FLAGS = ["-O3", "-march=native", "-ffp-contract=fast", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC"]
_LIB: dict[str, object] = {}


def _source() -> str:
    return (Path(__file__).with_name("backproject_omp.c")).read_text()


def load() -> tuple[object | None, str]:
    """(the ctypes function, a description) or (None, why it is unavailable)."""
    if "fn" in _LIB:
        return _LIB["fn"], _LIB["why"]
    from clsas.cl.variants import cache_dir

    cc = os.environ.get("CC", "gcc")
    if shutil.which(cc) is None:
        _LIB.update(fn=None, why=f"no C compiler ({cc!r} not on PATH)")
        return None, _LIB["why"]
    src = _source()
    digest = hashlib.sha256((src + " ".join([cc, *FLAGS])).encode()).hexdigest()[:16]
    out_dir = cache_dir().parent / "peers"
    lib_path = out_dir / f"backproject_omp-{digest}.so"
    if not lib_path.exists():
        out_dir.mkdir(parents=True, exist_ok=True)
        c_file = out_dir / f"backproject_omp-{digest}.c"
        c_file.write_text(src)
        tmp = lib_path.with_suffix(f".{os.getpid()}.tmp")
        res = subprocess.run([cc, *FLAGS, str(c_file), "-o", str(tmp), "-lm"], capture_output=True, text=True)
        if res.returncode != 0:
            _LIB.update(fn=None, why=f"{cc} failed: {res.stderr.strip()[-500:]}")
            return None, _LIB["why"]
        os.replace(tmp, lib_path)
    lib = ctypes.CDLL(str(lib_path))
    fn = lib.backproject_omp
    f32p = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
    fn.argtypes = [f32p, ctypes.c_int, ctypes.c_int, f32p, f32p, f32p, ctypes.c_float, ctypes.c_float,
                   f32p, f32p, f32p, ctypes.c_int, f32p, f32p]
    fn.restype = None
    _LIB.update(fn=fn, why=f"C/OpenMP ({cc} {' '.join(FLAGS[:4])}, {os.cpu_count()} threads)")
    return fn, _LIB["why"]


def backproject(wl: dict, pts: np.ndarray) -> np.ndarray | None:
    """Run the peer on a bench workload (see ``throughput.backprojection_workload``)."""
    fn, _ = load()
    if fn is None:
        return None
    data = np.asarray(wl["data"])
    n_meas, n_lags = data.shape
    f32 = np.float32
    prof = np.empty((n_meas, n_lags + 1, 2), f32)  # interleaved complex, one zero sample past the end
    prof[:, :n_lags, 0] = data.real
    prof[:, :n_lags, 1] = data.imag
    prof[:, n_lags] = 0
    tx = np.ascontiguousarray(wl["tx"], f32)
    rx = np.ascontiguousarray(wl["rx"], f32)
    s0 = np.ascontiguousarray(np.asarray(wl["tau0"]) / wl["dtau"], f32)
    px, py, pz = (np.ascontiguousarray(pts[:, i], f32) for i in range(3))
    re = np.empty(len(pts), f32)
    im = np.empty(len(pts), f32)
    fn(prof.reshape(-1), n_meas, n_lags, tx, rx, s0, f32(1 / (wl["c"] * wl["dtau"])), f32(wl["fc"] / wl["c"]),
       px, py, pz, len(pts), re, im)
    return re + 1j * im
