"""Kernel throughput against the twins and the peers a user would pick instead, and cost scaling.

Backprojection is reported in complex voxel-measurement pairs/s, compression in input samples/s.
OpenCL kernel times come from profiling events after a warm-up; wall times wrap the whole call
(transfers included, ending in ``finish()``). Peers run in the same process, on the same data.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.signal

import clsas
from clsas.compression import compress
from clsas.formation import bp_numpy as twin
from clsas.types.rangegate import path_bounds

from .stats import fit_exponent, timed

log = logging.getLogger(__name__)

# floating-point operations per voxel-measurement pair in backproject.cl, counted by hand:
# two distances (3 sub, 3 mul, 2 add, 1 sqrt each), delay and index (3), interpolation (6),
# the sub-sample carrier angle (2) with its sine and cosine polynomials (x^2, then 4 and 5
# multiply-adds: 19), complex multiply-accumulate (8).
FLOPS_PER_PAIR = 2 * 9 + 3 + 6 + 2 + 19 + 8


def backprojection_workload(grid, n_meas, rng, fs=96e3, lag_step=2, c=343.2):
    """Profiles as the pipeline makes them: baseband, every ``lag_step`` samples, covering the
    range gate of this grid and aperture (every voxel-measurement pair reads inside)."""
    side = int(np.ceil(np.sqrt(n_meas)))
    ap = clsas.raster_aperture(side, side, 1.0, 1.0)
    tx, rx = ap.tx_positions[:n_meas], ap.rx_positions[:n_meas]
    b = grid.bounds()
    pmin, pmax = path_bounds(b[:, 0], b[:, 1], tx, rx)
    dtau = lag_step / fs
    n_lags = int(np.ceil((pmax.max() - pmin.min()) / c / dtau)) + 4
    tau0 = np.full(n_meas, pmin.min() / c - 2 * dtau)
    data = (rng.normal(size=(n_meas, n_lags)) + 1j * rng.normal(size=(n_meas, n_lags))).astype(np.complex64)
    return {"data": data, "tau0": tau0, "dtau": dtau, "fc": 25e3, "tx": tx, "rx": rx, "c": c}


def _numba_kernel():
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(parallel=True, cache=False)
    def bp(data, tau0, dtau, fc, tx, rx, c, pts, out):  # the straightforward "write it yourself" loop
        n_meas, n_lags = data.shape
        for v in numba.prange(pts.shape[0]):
            acc = 0j
            for m in range(n_meas):
                dt = np.sqrt((pts[v, 0] - tx[m, 0]) ** 2 + (pts[v, 1] - tx[m, 1]) ** 2 + (pts[v, 2] - tx[m, 2]) ** 2)
                dr = np.sqrt((pts[v, 0] - rx[m, 0]) ** 2 + (pts[v, 1] - rx[m, 1]) ** 2 + (pts[v, 2] - rx[m, 2]) ** 2)
                tau = (dt + dr) / c
                idx = (tau - tau0[m]) / dtau
                if idx >= 0 and idx <= n_lags - 1:
                    i0 = min(int(idx), n_lags - 2)
                    w = idx - i0
                    val = (1 - w) * data[m, i0] + w * data[m, i0 + 1]
                    acc += val * np.exp(2j * np.pi * fc * tau)
            out[v] = acc

    return bp


_NUMBA = {}


def numba_backproject(wl, pts):
    """The Numba-parallel peer (float64, one voxel per iteration); None if Numba is missing."""
    if "bp" not in _NUMBA:
        _NUMBA["bp"] = _numba_kernel()
    bp = _NUMBA["bp"]
    if bp is None:
        return None
    out = np.zeros(len(pts), np.complex128)
    bp(wl["data"].astype(np.complex128), wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"], wl["c"], pts, out)
    return out


# bytes a pair reads when its profile gather misses every cache: two complex float32 samples
BYTES_PER_PAIR_GATHER = 16


def memory_bandwidth(nbytes: int = 256 * 2**20, repeats: int = 3) -> float | None:
    """Memory bandwidth the bp kernel's device sees, bytes/s (read + write counted), the fastest of
    ``repeats`` copies: on a CPU device, a NumPy copy in host memory (one thread: a lower bound);
    on other devices a buffer-to-buffer copy timed by profiling events. None without a device."""
    import time

    from clsas import cl as ccl

    try:
        q = ccl.get_queue()
    except ccl.OpenCLUnavailable:
        return None
    best = float("inf")
    if ccl.is_cpu(q.device):
        a = np.ones(nbytes // 8)
        b = np.empty_like(a)
        for _ in range(repeats + 1):  # the first copy touches the pages
            t = time.perf_counter()
            np.copyto(b, a)
            best = min(best, time.perf_counter() - t)
        return 2 * a.nbytes / best
    best = ccl.copy_seconds(q, nbytes, repeats)
    if best is None:
        return None
    return 2 * nbytes / best if best > 0 else None


# FP32 lanes per streaming multiprocessor of NVIDIA GPUs by compute capability (CUDA's programming
# guide, "arithmetic instructions"): the one GPU figure OpenCL does not report itself
NV_LANES = {(3, None): 192, (5, None): 128, (6, 0): 64, (6, None): 128, (7, None): 64, (8, 0): 64,
            (8, None): 128, (9, None): 128, (10, None): 128, (11, None): 128, (12, None): 128}


def lanes_per_unit(device) -> tuple[int | None, str]:
    """(float lanes per compute unit, where the figure comes from) of an OpenCL device.

    A CPU: the preferred float vector width (one core's SIMD). An NVIDIA GPU: the lanes of its
    compute capability; an AMD GPU: SIMDs per unit x SIMD width x instruction width (the vendors'
    attribute extensions). Any other GPU: (None, why), since OpenCL does not say.
    """
    from clsas import cl as ccl

    if ccl.is_cpu(device):
        return max(1, int(device.preferred_vector_width_float)), "preferred float vector width"
    try:
        major, minor = int(device.compute_capability_major_nv), int(device.compute_capability_minor_nv)
        lanes = NV_LANES.get((major, minor)) or NV_LANES.get((major, None))
        if lanes:
            return lanes, f"FP32 lanes per SM of compute capability {major}.{minor}"
        return None, f"the FP32 lanes per SM of compute capability {major}.{minor} are not in clsas's table"
    except Exception:  # noqa: BLE001 - the attribute is an NVIDIA extension; absent elsewhere
        pass
    try:
        lanes = (int(device.simd_per_compute_unit_amd) * int(device.simd_width_amd)
                 * int(device.simd_instruction_width_amd))
        if lanes > 0:
            return lanes, "SIMDs per unit x SIMD width x instruction width (cl_amd_device_attribute_query)"
    except Exception:  # noqa: BLE001 - an AMD extension; absent elsewhere
        pass
    return None, "this GPU's lanes per compute unit are not reported through OpenCL"


def compute_bound(device_info: dict, bandwidth_bps: float | None = None) -> dict | None:
    """The bp kernel's roofline: peak pairs/s from the device's arithmetic (compute units x clock x
    float lanes per unit x 2 for FMA, over :data:`FLOPS_PER_PAIR`) and from its memory bandwidth
    (over :data:`BYTES_PER_PAIR_GATHER`, every gather from memory), where the bandwidth is given.

    ``lanes_per_unit`` (see :func:`lanes_per_unit`; dual issue and packed FP32 not counted) falls
    back to ``vector_width_float``. Where the lanes are not known (None: a GPU whose lanes OpenCL
    does not report) no arithmetic ceiling is claimed (``pairs_per_s`` None), and the memory
    ceiling alone is given; None where neither can be."""
    lanes = device_info.get("lanes_per_unit") if "lanes_per_unit" in device_info else \
        device_info.get("vector_width_float")
    out: dict = {"flops_per_pair": FLOPS_PER_PAIR, "peak_flops": None, "pairs_per_s": None,
                 "lanes_from": device_info.get("lanes_from", "float vector width")}
    try:
        if lanes is not None:
            peak = device_info["compute_units"] * device_info["clock_mhz"] * 1e6 * max(1, int(lanes)) * 2
            out.update(peak_flops=peak, pairs_per_s=peak / FLOPS_PER_PAIR, lanes_per_unit=max(1, int(lanes)))
    except (KeyError, TypeError):
        pass
    if bandwidth_bps:
        out.update(bandwidth_bps=bandwidth_bps, bytes_per_pair=BYTES_PER_PAIR_GATHER,
                   memory_pairs_per_s=bandwidth_bps / BYTES_PER_PAIR_GATHER)
        if out["peak_flops"]:
            out["ridge_flops_per_byte"] = out["peak_flops"] / bandwidth_bps
    return out if out["pairs_per_s"] or out.get("memory_pairs_per_s") else None


def opencl_device_info() -> dict | None:
    from clsas import cl as ccl

    try:
        q = ccl.get_queue()
    except ccl.OpenCLUnavailable:
        return None
    d = q.device
    lanes, lanes_from = lanes_per_unit(d)
    return {"name": ccl.device_info(q), "platform": d.platform.name, "driver": d.driver_version,
            "opencl": d.version, "type": ccl.device_kind(d),
            "compute_units": d.max_compute_units, "clock_mhz": d.max_clock_frequency,
            "vector_width_float": d.preferred_vector_width_float, "global_mem_mib": d.global_mem_size // 2**20,
            "lanes_per_unit": lanes, "lanes_from": lanes_from}


def cube_grid(side: int):
    """The bench's bp grid: ``side`` voxels a side over a 0.64 m cube from 1 m in range."""
    return clsas.VoxelGrid.from_bounds((-0.32, 0.32), (-0.32, 0.32), (1.0, 1.64), 0.64 / (side - 1))


def bench_backprojection(name, grid, n_meas, *, repeats, twin_meas, numba_meas, rng, opencl=True):
    """OpenCL kernel and wall time, NumPy twin and Numba peer on one workload (rates per pair)."""
    wl = backprojection_workload(grid, n_meas, rng)
    pts = grid.points()
    pairs = grid.size * n_meas
    row = {"workload": name, "voxels": grid.size, "measurements": n_meas, "lags": wl["data"].shape[1],
           "pairs": pairs}
    if opencl:
        from clsas.formation.bp_opencl import BackprojectPlan

        plan = BackprojectPlan(grid, n_meas, wl["data"].shape[1])
        row["opencl_vec"] = plan.vec
        args = (wl["data"], wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"], wl["c"])
        kern = []

        def run():
            plan(*args)  # ends in queue.finish() (results copied back)
            kern.append(plan.last_kernel_s)

        wall = timed(run, repeats)
        kern = kern[1:]  # drop the warm-up
        row.update(opencl_kernel=_stat(kern, pairs), opencl_wall=_stat(wall, pairs))
    sub = slice(0, twin_meas)
    t = timed(lambda: twin.backproject(wl["data"][sub].astype(np.complex128), wl["tau0"][sub], wl["dtau"],
                                       wl["fc"], wl["tx"][sub], wl["rx"][sub], wl["c"], pts), 1, warmup=False)
    row["numpy_twin"] = _stat(t, grid.size * twin_meas, note=f"{twin_meas} measurements timed")
    from . import cpeer

    if cpeer.backproject(wl, pts[:8]) is not None:  # compiles once (cached), then timed on the whole workload
        t = timed(lambda: cpeer.backproject(wl, pts), repeats)
        row["c_openmp_peer"] = _stat(t, pairs)
        row["c_openmp_peer_build"] = cpeer.load()[1]
    else:
        row["c_openmp_peer_missing"] = cpeer.load()[1]
    nsub = {k: (v[:numba_meas] if isinstance(v, np.ndarray) else v) for k, v in wl.items()}
    if numba_backproject(nsub, pts[:8]) is not None:  # compiles
        t = timed(lambda: numba_backproject(nsub, pts), max(1, repeats // 2))
        row["numba_peer"] = _stat(t, grid.size * numba_meas, note=f"{numba_meas} measurements timed")
    _ratios(row, "opencl_kernel", ("numpy_twin", "numba_peer", "c_openmp_peer"))
    _ratios(row, "opencl_wall", ("numpy_twin", "numba_peer", "c_openmp_peer"))
    return row


def bench_compression(ds, *, repeats, opencl=True):
    """Full-window matched filter of every recording: OpenCL (FFT, direct), scipy, the NumPy twin."""
    ref = np.conj(clsas.analytic(ds.waveform))[::-1].astype(np.complex64)
    sig = ds.signals.astype(np.float32)
    samples = sig.size
    row = {"workload": f"{ds.n_meas} recordings x {ds.n_samples} samples, full window", "samples": samples}
    if opencl:
        for alg in ("fft", "direct"):
            kern = []

            def run(alg=alg, kern=kern):
                kern.append(compress(ds, backend="opencl", algorithm=alg).timings_s["compress_kernel"])

            wall = timed(run, repeats)
            row[f"opencl_{alg}_kernel"] = _stat(kern[1:], samples)
            row[f"opencl_{alg}_wall"] = _stat(wall, samples)
    for name, fn in (("fftconvolve", scipy.signal.fftconvolve), ("oaconvolve", scipy.signal.oaconvolve)):
        row[name] = _stat(timed(lambda fn=fn: fn(sig, ref[None, :], axes=1), repeats), samples)
    row["numpy_twin"] = _stat(timed(lambda: compress(ds, backend="numpy"), 1, warmup=False), samples)
    for ours in ("opencl_fft_kernel", "opencl_fft_wall"):
        _ratios(row, ours, ("fftconvolve", "oaconvolve", "numpy_twin"))
    return row


def _stat(times, work, note=None) -> dict:
    t = np.asarray(times, float)
    med = float(np.median(t))
    out = {"median_s": med, "min_s": float(t.min()), "max_s": float(t.max()), "repeats": len(t),
           "rate_per_s": work / med if med > 0 else float("inf")}
    if note:
        out["note"] = note
    return out


def _ratios(row, ours, peers) -> None:
    if ours not in row:
        return
    row.setdefault("ratios", {})
    for p in peers:
        if p in row:
            row["ratios"][f"{ours} / {p}"] = row[ours]["rate_per_s"] / row[p]["rate_per_s"]


def bench_scaling(*, voxel_sides, meas_counts, sample_counts, repeats, rng, opencl=True) -> dict:
    """Cost against voxels, measurements and samples, with the fitted exponents."""
    out = {}
    if opencl:
        from clsas.formation.bp_opencl import BackprojectPlan

        def bp_time(side, n_meas):
            g = clsas.VoxelGrid.from_bounds((-0.3, 0.3), (-0.3, 0.3), (1.0, 1.6), 0.6 / (side - 1))
            wl = backprojection_workload(g, n_meas, rng)
            plan = BackprojectPlan(g, n_meas, wl["data"].shape[1])
            ks = []

            def call():
                plan(wl["data"], wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"], wl["c"])
                ks.append(plan.last_kernel_s)

            timed(call, repeats)
            return g.size, float(np.median(ks[1:]))

        vox = [bp_time(s, meas_counts[len(meas_counts) // 2]) for s in voxel_sides]
        out["backprojection_vs_voxels"] = _series(vox, "voxels", f"{meas_counts[len(meas_counts) // 2]} measurements")
        side = voxel_sides[len(voxel_sides) // 2]
        meas = [(m, bp_time(side, m)[1]) for m in meas_counts]
        out["backprojection_vs_measurements"] = _series(meas, "measurements", f"{side}^3 voxels")
        pairs = [(n * meas_counts[len(meas_counts) // 2], t) for n, t in vox] + \
                [(m * side**3, t) for m, t in meas]
        out["backprojection_vs_pairs"] = _series(pairs, "pairs", "both sweeps together")

    fs = 96e3
    w = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    pts = []
    for n in sample_counts:
        sig = rng.normal(size=(32, n))
        if opencl:
            ks = []
            timed(lambda sig=sig, ks=ks: ks.append(compress(sig, w, fs, backend="opencl", algorithm="fft")
                                                    .timings_s["compress_kernel"]), repeats)
            pts.append((32 * n, float(np.median(ks[1:]))))
        else:
            pts.append((32 * n, float(np.median(timed(lambda sig=sig: compress(sig, w, fs, backend="numpy"), 1)))))
    out["compression_vs_samples"] = _series(pts, "samples", "32 recordings, OpenCL FFT kernel"
                                            if opencl else "32 recordings, NumPy twin")
    return out


def _series(points, x_name, fixed) -> dict:
    x = np.array([p[0] for p in points], float)
    t = np.array([p[1] for p in points], float)
    return {"x": x_name, "fixed": fixed, "sizes": x.tolist(), "times_s": t.tolist(),
            "exponent": fit_exponent(x, t), "exponent_upper_half": fit_exponent(x[len(x) // 2:], t[len(t) // 2:]),
            "decades": float(np.log10(x.max() / x.min()))}


def bench_plan_saving(*, repeats, backend, spacing_m=0.01) -> dict:
    """The demo's front scene: the scene-aware plan against a full-window, full-volume one, and a plane."""
    from clsas.synthesis.scenes import demo_configs, parse_config

    cfg = parse_config(demo_configs(spacing_m)["front"])
    ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=20)
    full_grid = clsas.VoxelGrid.from_bounds((-0.6, 0.6), (-0.6, 0.7), (0.5, 2.5), spacing_m)
    plane = clsas.VoxelGrid.from_bounds((-0.45, 0.45), (-0.55, 0.7), (1.5, 1.5), spacing_m)

    def full():
        prof = compress(ds, backend=backend)  # no gate: every lag of the recording
        return clsas.backproject(prof, full_grid, backend=backend)

    rows = {
        "scene-aware (gate + scene grid)": (cfg.grid.size, timed(lambda: clsas.reconstruct(ds, cfg.grid,
                                                                                        backend=backend), repeats)),
        "full window + full volume": (full_grid.size, timed(full, max(1, repeats // 2))),
        "plane only (z = 1.5 m)": (plane.size, timed(lambda: clsas.reconstruct(ds, plane, backend=backend), repeats)),
    }
    out = {k: {"voxels": n, "median_s": float(np.median(t))} for k, (n, t) in rows.items()}
    base = out["full window + full volume"]["median_s"]
    for v in out.values():
        v["saving_x"] = base / v["median_s"]
    log.info("plan saving: %s", {k: round(v["saving_x"], 1) for k, v in out.items()})
    return out

