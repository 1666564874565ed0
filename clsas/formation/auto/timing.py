"""Seconds per unit of counted work, per formation and device: the time half of ``auto``'s model.

Each formation's work is counted (:func:`work_bp`, :func:`work_omega_k`, :func:`work_ffbp`) and
priced at :data:`BUILTIN` seconds per unit on the reference device, scaled to other devices by
their compute units and host cores (:func:`_speed`), times the factor per formation that the
device's calibration measured (:mod:`.calibrate`), kept beside the kernel-variant verdicts
(:func:`calibration_path`, :func:`store_calibration`, :func:`load_calibration`). The error half of
the model is in :mod:`.predict`.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles

__all__ = ["BUILTIN", "FORMAT", "GPU_FIXED", "OMEGA_K_CORE_EXPONENT", "calibration_path", "load_calibration",
           "store_calibration", "work_bp", "work_ffbp", "work_omega_k"]

# the model's format: factors stored under another format are not used (its terms differ)
FORMAT = 6

# seconds per unit of counted work on the reference device (2 compute units, 2 host cores: a quiet
# 2-core VM with PoCL; a fit under load over-predicts several times). omega-k's Stolt and depth terms
# are per bistatic term (the Stolt term also per cell of its 6-cell kernel); omega-k and FFBP fitted
# on the crossover scans of ``bench.crossover`` (16-128 stops a side); bp by non-negative least squares
# in relative error on the formation family's fit seeds 500-579 (``bench.formation_family``, up to
# 3e8 pairs): a fixed part, a per-measurement part (its records and profiles, host side) and a
# per-pair part. The fits and their measured-over-predicted ratios are on the benchmarks page.
BUILTIN: dict[str, dict[str, float]] = {
    "bp": {"fixed": 6.3e-4, "meas": 5.6e-6, "pairs": 1.83e-9},
    "omega-k": {"fixed": 1.5e-3, "delay": 2.3e-9, "lattice": 8e-10, "stolt": 3.8e-9, "depths": 8e-10, "out": 1.15e-9,
                "direct": 2.1e-10},
    "ffbp": {"fixed": 5e-3, "leaf": 1.1e-9, "merge": 1.4e-9, "grid": 1.4e-9},
}
# bp's fixed part on a GPU: its smallest cases took 1.45-1.9 ms in all on an H200 through NVIDIA's
# OpenCL (the GPU formation report in bench/results); a larger fixed part sizes ω-k for scans bp
# forms in a few ms
GPU_FIXED = {"bp": 1.5e-3}
HOST_TERMS = ("fixed", "meas", "plan")  # work the host does, whatever the device
REF_UNITS = 2  # compute units and host cores of the device BUILTIN was fitted on
# ω-k's host work speeds up as (cores / REF_UNITS) ** this: 1.25-1.8x on a 16-core host against the
# 2-core reference (8 ** 0.1-0.28), measured with a GPU doing bp (the GPU formation report)
OMEGA_K_CORE_EXPONENT = 0.2
NUMPY_SLOWDOWN = {"bp": 25.0, "omega-k": 2.0, "ffbp": 10.0}  # the NumPy twins against PoCL: rough guesses


# -- the device's calibration ------------------------------------------------------------------------------
def _device_key(selection) -> tuple[str, dict]:
    import hashlib
    import platform

    if selection is not None and getattr(selection, "kind", "numpy") == "opencl":
        from ...cl.variants import device_identity

        ident = device_identity(selection.queue.device)
    else:
        ident = {"numpy": platform.processor() or platform.machine(), "cores": os.cpu_count()}
    ident = {**ident, "format": FORMAT}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:32], ident


def calibration_path(selection=None) -> Path:
    """Where the calibration of ``selection``'s device is kept: ``formation_cost/<key>.json`` beside
    the kernel-variant verdicts (:func:`clsas.cl.variants.cache_dir`)."""
    from ...cl.variants import cache_dir

    return cache_dir().parent / "formation_cost" / f"{_device_key(selection)[0]}.json"


def load_calibration(selection=None) -> dict:
    """The stored factors of ``selection``'s device (formation -> measured / predicted), or {}."""
    try:
        data = json.loads(calibration_path(selection).read_text())
        return {k: float(x) for k, x in data["factors"].items() if float(x) > 0}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def store_calibration(factors: dict[str, float], selection=None, detail: Any = None) -> Path:
    """Keep ``factors`` (formation -> measured / built-in predicted time) for ``selection``'s device."""
    path = calibration_path(selection)
    ident = _device_key(selection)[1]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps({**ident, "factors": {k: float(x) for k, x in factors.items()}, "detail": detail,
                               "when": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=1, default=str))
    os.replace(tmp, path)
    return path


# -- counted work -----------------------------------------------------------------------------
def _device(selection):
    """The selection's OpenCL device, or None where it runs the NumPy twins."""
    if selection is None or getattr(selection, "kind", "numpy") != "opencl":
        return None
    return selection.queue.device


def _on_gpu(selection) -> bool:
    from ...cl import is_cpu

    dev = _device(selection)
    return dev is not None and not is_cpu(dev)


def _speed(selection, formation: str) -> float:
    """How much faster than the reference device this selection runs ``formation``'s work."""
    host = (os.cpu_count() or REF_UNITS) / REF_UNITS
    dev = _device(selection)
    if formation == "omega-k":
        # its FFTs use every host core (workers=os.cpu_count()) but at these sizes gain little from
        # them: on a 16-core host (8x the reference) ω-k ran 1.25-1.8x faster than on the reference,
        # not 8x (the GPU formation report in bench/results); hence host ** 0.2
        speed = host**OMEGA_K_CORE_EXPONENT
        return speed if dev is not None else speed / NUMPY_SLOWDOWN[formation]
    if dev is None:
        return host / NUMPY_SLOWDOWN[formation]
    units = int(getattr(dev, "max_compute_units", REF_UNITS) or REF_UNITS)
    return 4.0 * units / REF_UNITS if _on_gpu(selection) else units / REF_UNITS


def _seconds(formation: str, work: dict, selection, factors: dict) -> float:
    # the fixed part (set-up, launches, Python) and the host's per-measurement work do not scale with
    # the device's speed
    coef = BUILTIN[formation]
    fixed = GPU_FIXED.get(formation, coef["fixed"]) if _on_gpu(selection) else coef["fixed"]
    t = sum(coef[k] * float(n) for k, n in work.items() if k not in HOST_TERMS)
    host = fixed * float(work.get("fixed", 0)) + coef.get("meas", 0.0) * float(work.get("meas", 0))
    t = host + t / _speed(selection, formation) + work.get("plan", 0.0)
    return t * factors.get(formation, 1.0)


def work_bp(profiles: Profiles, grid: VoxelGrid) -> dict:
    """Counted work of exact backprojection."""
    return {"fixed": 1, "meas": float(profiles.n_meas), "pairs": float(profiles.n_meas) * grid.size}


def work_omega_k(sizes: dict, opencl: bool = True) -> dict:
    """Counted work of ω-k from :func:`clsas.formation.omega_k.plan_sizes` (the Stolt step's path as
    ω-k takes it on OpenCL, or on the NumPy twins where ``opencl`` is False)."""
    from ..stolt_numpy import depth_path, direct_work

    n_fft, n_f, nz = sizes["n_fft"], sizes["n_f"], sizes["nz"]
    pu, pv, _ = sizes["axes"]
    w = {"fixed": 1, "delay": sizes["n_meas"] * n_fft * math.log2(max(n_fft, 2)), "lattice": 0.0, "stolt": 0.0,
         "depths": 0.0, "direct": 0.0, "out": 0.0}
    for g in sizes["groups"]:
        mu, mv, up, cols, cells = g["mu"], g["mv"], g["up"], g["columns"], g["n_cells"]
        terms, width = g.get("terms", 3), g.get("width", 6)
        w["lattice"] += mu * mv * n_f * math.log2(max(mu * mv, 2))
        if depth_path(sizes.get("depths", "auto"), n_f, nz, width, terms, opencl) == "direct":
            w["direct"] += cols * direct_work(n_f, nz, terms)
        else:
            w["stolt"] += cols * n_f * terms * width
            w["depths"] += cols * cells * math.log2(max(cells, 2)) * terms
        lu, lv = up * mu + len(pu), up * mv + len(pv)
        w["out"] += up * mv * nz * lu * math.log2(lu) + len(pu) * nz * lv * math.log2(lv)
    return w


def work_ffbp(tree, grid: VoxelGrid, taps: int, plan_s: float) -> dict:
    """Counted work of FFBP for a planned tree (:func:`clsas.formation.ffbp.plan_tree`)."""
    leaves = tree.levels[-1]
    per_leaf = len(tree.order) / max(leaves.n_nodes, 1)
    merge = sum(lev.samples for lev in tree.levels[:-1]) * tree.factor * taps**3
    return {"fixed": 1, "plan": plan_s, "leaf": leaves.samples * per_leaf, "merge": merge,
            "grid": float(grid.size) * tree.factor * taps**3}

