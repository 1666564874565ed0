"""Imaging-core benchmark: backprojection and pulse compression, OpenCL against the NumPy twin
and scipy, on the demo workload and on 64^3 voxels x 1000 measurements.

    python bench/bench_core.py            # writes bench/results/<date>-<device>.{json,md}

Kernel times come from OpenCL profiling events after a warm-up; wall times include the
transfers. The NumPy twin runs a subset of the measurements on the large workload (its cost
is linear in measurements) and the rate is stated per pair.
"""

from __future__ import annotations

import datetime as dt
import json
import platform
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import scipy.signal

import clsas
from clsas import cl as ccl
from clsas.compress import compress
from clsas.imaging import numpy as twin
from clsas.imaging.opencl import BackprojectPlan
from clsas.imaging.plan import plan_reconstruction
from clsas.scenes import demo_configs, parse_config

REPEATS = 5


def _median(ts):
    return statistics.median(ts), (min(ts), max(ts))


def bench_backprojection(name, grid, n_meas, n_lags, twin_meas, rng):
    ap = clsas.raster_aperture(int(np.ceil(np.sqrt(n_meas))), int(np.ceil(np.sqrt(n_meas))), 1.0, 1.0)
    tx, rx = ap.tx_positions[:n_meas], ap.rx_positions[:n_meas]
    data = (rng.normal(size=(n_meas, n_lags)) + 1j * rng.normal(size=(n_meas, n_lags))).astype(np.complex64)
    tau0, dtau, fc, c = np.full(n_meas, 5.0e-3), 1 / 96e3, 25e3, 343.2
    plan = BackprojectPlan(grid, n_meas, n_lags)
    plan(data, tau0, dtau, fc, tx, rx, c)  # warm-up (build, first touch)
    kern, wall = [], []
    for _ in range(REPEATS):
        t = time.perf_counter()
        plan(data, tau0, dtau, fc, tx, rx, c)
        wall.append(time.perf_counter() - t)
        kern.append(plan.last_kernel_s)
    pts = grid.points()
    t = time.perf_counter()
    twin.backproject(data[:twin_meas].astype(np.complex128), tau0, dtau, fc, tx, rx, c, pts)
    t_twin = time.perf_counter() - t
    pairs = grid.size * n_meas
    k_med, k_spread = _median(kern)
    w_med, _ = _median(wall)
    twin_rate = grid.size * twin_meas / t_twin
    return {
        "workload": name, "voxels": grid.size, "measurements": n_meas, "lags": n_lags, "pairs": pairs,
        "opencl_kernel_s": k_med, "opencl_kernel_spread_s": k_spread, "opencl_wall_s": w_med,
        "opencl_pairs_per_s": pairs / k_med, "opencl_wall_pairs_per_s": pairs / w_med,
        "numpy_measurements_timed": twin_meas, "numpy_s": t_twin, "numpy_pairs_per_s": twin_rate,
        "speedup_vs_numpy": pairs / k_med / twin_rate, "vec": plan.vec, "chunk": plan.chunk,
    }


def bench_compression(ds):
    wave = ds.waveform
    ref = np.conj(clsas.analytic(wave))[::-1]
    sig = ds.signals.astype(np.float32)
    compress(ds, backend="opencl")  # warm-up
    walls, kern = [], []
    for _ in range(REPEATS):
        t = time.perf_counter()
        p = compress(ds, backend="opencl")
        walls.append(time.perf_counter() - t)
        kern.append(p.timings_s["compress_kernel"])
    fft = []
    for _ in range(REPEATS):
        t = time.perf_counter()
        scipy.signal.fftconvolve(sig, ref[None, :].astype(np.complex64), axes=1)
        fft.append(time.perf_counter() - t)
    t = time.perf_counter()
    compress(ds, backend="numpy")
    t_twin = time.perf_counter() - t
    samples = sig.size
    k, w, f = _median(kern)[0], _median(walls)[0], _median(fft)[0]
    return {
        "workload": f"demo scan, {ds.n_meas} stops x {ds.n_samples} samples, full window",
        "opencl_kernel_s": k, "opencl_wall_s": w, "fftconvolve_s": f, "numpy_twin_s": t_twin,
        "opencl_samples_per_s": samples / k, "fftconvolve_samples_per_s": samples / f,
        "kernel_vs_fftconvolve": f / k, "wall_vs_fftconvolve": f / w,
    }


def main() -> int:
    rng = np.random.default_rng(0)
    queue = ccl.get_queue()
    device = ccl.device_info(queue)
    cfg = parse_config(demo_configs()["front"])
    ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=20)
    gate_s = plan_reconstruction(ds, cfg.grid, []).gate_s
    gate = compress(ds, gate_s=gate_s, backend="opencl").n_lags  # lags the demo reconstruction uses
    results = {
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "device": device,
        "host": f"{platform.processor() or platform.machine()}, {__import__('os').cpu_count()} logical CPUs",
        "versions": {"clsas": clsas.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
                     "pyopencl": __import__("pyopencl").VERSION_TEXT, "python": sys.version.split()[0]},
        "repeats": REPEATS,
        "backprojection": [
            bench_backprojection("demo (mannequin, 1 cm grid)", cfg.grid, ds.n_meas, gate, 24, rng),
            bench_backprojection("64^3 voxels x 1000 measurements",
                                 clsas.VoxelGrid.from_bounds((-0.32, 0.31), (-0.32, 0.31), (1.0, 1.63), 0.01),
                                 1000, 1200, 8, rng),
        ],
        "compression": bench_compression(ds),
    }
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    stem = f"{dt.date.today()}-{re.sub(r'[^A-Za-z0-9]+', '-', device).strip('-')[:60]}"
    (out / f"{stem}.json").write_text(json.dumps(results, indent=2))
    md = [f"# clsas imaging-core benchmark, {results['date']}", "",
          f"Device: **{device}**; host {results['host']}; {REPEATS} repeats, medians.", "",
          "## Backprojection (complex voxel-measurement pairs/s)", "",
          "| workload | pairs | OpenCL kernel | OpenCL wall | NumPy twin | kernel / twin |",
          "|---|---|---|---|---|---|"]
    for r in results["backprojection"]:
        md.append(f"| {r['workload']} | {r['pairs']:.3g} | {r['opencl_pairs_per_s']:.3g} | "
                  f"{r['opencl_wall_pairs_per_s']:.3g} | {r['numpy_pairs_per_s']:.3g} "
                  f"({r['numpy_measurements_timed']} meas. timed) | {r['speedup_vs_numpy']:.0f}x |")
    c = results["compression"]
    md += ["", "## Pulse compression", "", f"{c['workload']}.", "",
           "| OpenCL kernel | OpenCL wall (incl. transfers) | scipy.signal.fftconvolve | NumPy twin |",
           "|---|---|---|---|",
           f"| {c['opencl_kernel_s'] * 1e3:.2f} ms | {c['opencl_wall_s'] * 1e3:.2f} ms | "
           f"{c['fftconvolve_s'] * 1e3:.2f} ms | {c['numpy_twin_s'] * 1e3:.1f} ms |", "",
           f"fftconvolve / OpenCL kernel = {c['kernel_vs_fftconvolve']:.2f}x; "
           f"fftconvolve / OpenCL wall = {c['wall_vs_fftconvolve']:.2f}x."]
    (out / f"{stem}.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
