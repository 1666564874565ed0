"""The benchmark suite behind ``python -m bench``.

One call of :func:`run` measures, on the OpenCL device that ``backend="auto"`` picks (or the
one ``PYOPENCL_CTX`` names):

- kernel throughput: backprojection (pairs/s) and pulse compression (samples/s), each against
  its NumPy twin and the peer a user would pick instead (a Numba-parallel loop; scipy's
  ``fftconvolve`` and ``oaconvolve``), with the device's compute bound where it can be stated;
- cost scaling against voxels, measurements and samples, with fitted exponents, and the saving
  of the scene-aware plan against a full-window, full-volume one;
- error against run time for every reconstruction method on the two-echo task and on the
  paper's Delta x lam grid;
- fast image formation (:mod:`bench.formation`): every registered formation against exact
  backprojection, error against run time on the demo, a dense planar and a circular scan,
  with fitted cost exponents (``python -m bench --formation`` runs this part alone);
- with Dask (``--full``, or ``--scheduler``): the sweeps run on the cluster and are checked
  against a serial run, and a volume is backprojected in tiles and checked against one call.

It writes ``<out>/<date>-<device>[-quick].json``, a Markdown report and a PNG of plots.
Benchmarks measure; nothing here asserts a timing.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import platform
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["run", "run_formation", "QUICK", "FULL"]

log = logging.getLogger(__name__)

QUICK = {
    "repeats": 3,
    "backprojection": [("32^3 voxels x 200 measurements", 32, 200, 2, 20)],
    "compression_stops": 216,
    "scaling": {"voxel_sides": (8, 12, 16, 24, 32), "meas_counts": (10, 30, 100), "sample_counts": (1000, 3000, 10000)},
    "plan_spacing_m": 0.02,
    "two_echo": {"methods": ("matched", "fmcw", "bpdn", "cbp-polar", "ml2"), "separations_b": (0.25, 1.0),
                 "snrs_db": (10, 30), "trials": 2},
    "k_echo": {"ks": (2, 3, 5, 10), "ratios": (1.0, 0.5, 0.1), "trials": 1},
    "grid": {"methods": ("bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar"), "deltas": (0.025, 0.05),
             "lam_fracs": (0.01, 0.03)},
    "tiles": None,
    "autofocus": "quick",
}
FULL = {
    "repeats": 5,
    "backprojection": [("demo grid (mannequin, 1 cm) x 216 measurements", "demo", 216, 4, 24),
                       ("64^3 voxels x 1000 measurements", 64, 1000, 4, 40)],
    "compression_stops": 216,
    "scaling": {"voxel_sides": (12, 16, 24, 32, 48, 64), "meas_counts": (10, 30, 100, 300, 1000),
                "sample_counts": (1000, 3000, 10000, 30000, 100000)},
    "plan_spacing_m": 0.01,
    "two_echo": {"methods": ("matched", "fmcw", "bpdn", "cbp-polar", "ml2"),
                 "separations_b": (0.125, 0.25, 0.5, 1.0, 2.0), "snrs_db": (0, 10, 20, 30), "trials": 10},
    "two_echo_convex": {"methods": ("matched", "bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar", "ml2"),
                        "separations_b": (0.25, 0.5, 1.0, 2.0), "snrs_db": (20,), "trials": 3,
                        "amplitudes": "positive"},
    "k_echo": {"ks": (2, 3, 5, 10), "ratios": (1.0, 0.5, 0.1), "trials": 20},
    "grid": {"methods": ("bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar"),
             "deltas": (0.0125, 0.025, 0.05, 0.1, 0.2), "lam_fracs": (0.001, 0.003, 0.01, 0.03, 0.1, 0.3)},
    "tiles": {"grid": ((-0.45, 0.45), (-0.55, 0.7), (1.0, 2.0), 0.01), "n_tiles": 4},
    "autofocus": "full",
}


def package_versions() -> dict:
    import scipy

    import clsas

    from .stats import source_commit

    out = {"clsas": clsas.__version__, "clsas_commit": source_commit(), "python": sys.version.split()[0],
           "numpy": np.__version__, "scipy": scipy.__version__}
    for mod in ("pyopencl", "numba", "dask", "distributed", "cvxpy", "nlopt"):
        try:
            m = __import__(mod)
            out[mod] = getattr(m, "VERSION_TEXT", None) or getattr(m, "__version__", "?")
        except ImportError:
            out[mod] = None
    return out


def run(full: bool = False, out_dir: str | Path = "bench/results", *, scheduler: str | None = None,
        use_dask: bool | None = None, plots: bool = True,
        status: Callable[[str], None] | None = None) -> dict:
    """Run the quick (default) or full set and write JSON, Markdown and PNG to ``out_dir``.

    Parameters
    ----------
    full : bool
        The full set (several minutes to an hour on a 2-core CPU) instead of the quick one (~1 min).
    out_dir : path
        Where the results go.
    scheduler : str, optional
        Address of an existing Dask scheduler for the sweeps and tiles.
    use_dask : bool, optional
        Run the Dask part; default: with ``full`` or a ``scheduler``.
    status : callable(str), optional
        Called with a line before each part (the CLI prints them).

    Returns
    -------
    dict
        The results, as written to the JSON file, plus ``paths``.
    """
    from . import throughput
    from .report import write_report

    say = status or (lambda s: log.info("%s", s))
    cfg = FULL if full else QUICK
    use_dask = bool(full or scheduler) if use_dask is None else use_dask
    _check_dependencies(use_dask, say)
    rng = np.random.default_rng(0)
    info = throughput.opencl_device_info()
    opencl = info is not None
    device = info["name"] if opencl else "NumPy only (no OpenCL device)"
    res = {
        "date": dt.datetime.now().isoformat(timespec="seconds"), "mode": "full" if full else "quick",
        "device": info or {"name": device},
        "compute_bound": throughput.compute_bound(info, throughput.memory_bandwidth()) if opencl else None,
        "host": {"machine": platform.machine(), "processor": platform.processor(), "cpus": os.cpu_count(),
                 "system": platform.platform()},
        "versions": package_versions(), "repeats": cfg["repeats"],
        "sizes": {k: v for k, v in cfg.items() if k != "repeats"},
    }

    _throughput_part(res, cfg, rng, opencl, device, say)
    _accuracy_part(res, cfg, say)
    if cfg.get("autofocus"):
        from . import autofocus as af

        say("autofocus: focus restored against the size of the error (demo mannequin)")
        rows = af.run_cases(af.CASES_FULL if cfg["autofocus"] == "full" else af.CASES_QUICK, status=say)
        res["autofocus"] = {"rows": rows, "markdown": af.markdown(rows)}

    from . import formation

    say("image formation against exact backprojection")
    fcfg = formation.FULL if full else formation.QUICK
    res["formation"] = formation.run(fcfg["cases"], scale=fcfg["scale"], sides=fcfg["sides"], status=say)

    if use_dask:
        res["dask"] = _dask_part(cfg, res, scheduler, say)

    stem = f"{dt.date.today()}-{re.sub(r'[^A-Za-z0-9]+', '-', device).strip('-')[:60]}" + ("" if full else "-quick")
    res["paths"] = write_report(res, Path(out_dir), stem, plots=plots)
    return res


def _throughput_part(res: dict, cfg: dict, rng, opencl: bool, device: str, say) -> None:
    """The throughput benchmarks of :func:`run` (backprojection, compression, scaling, plans), into ``res``."""
    from . import throughput

    say(f"backprojection throughput on {device}")
    res["backprojection"] = []
    for name, side, n_meas, twin_meas, numba_meas in cfg["backprojection"]:
        if side == "demo":
            from clsas.synthesis.scenes import demo_configs, parse_config

            grid = parse_config(demo_configs(0.01)["front"]).grid
        else:
            grid = throughput.cube_grid(side)
        res["backprojection"].append(throughput.bench_backprojection(
            name, grid, n_meas, repeats=cfg["repeats"], twin_meas=twin_meas, numba_meas=numba_meas, rng=rng,
            opencl=opencl))

    say("pulse compression throughput")
    ds = _demo_dataset(cfg["compression_stops"])
    res["compression"] = throughput.bench_compression(ds, repeats=cfg["repeats"], opencl=opencl)

    say("cost scaling")
    res["scaling"] = throughput.bench_scaling(**cfg["scaling"], repeats=cfg["repeats"], rng=rng, opencl=opencl)
    say("scene-aware plan against a full-volume plan")
    res["plan_saving"] = throughput.bench_plan_saving(repeats=cfg["repeats"], backend="auto",
                                                      spacing_m=cfg["plan_spacing_m"])


def _accuracy_part(res: dict, cfg: dict, say) -> None:
    """The accuracy benchmarks of :func:`run` (two-echo, K-echo, Delta x lam), into ``res``."""
    from . import accuracy

    say("error against run time: two-echo task")
    res["two_echo"] = accuracy.two_echo(**cfg["two_echo"])
    if "two_echo_convex" in cfg:
        say("error against run time: the two-echo task with positive amplitudes (the convex CBPs' model)")
        res["two_echo_convex"] = accuracy.two_echo(**cfg["two_echo_convex"])
    say("success against the bound: K echoes x amplitude ratio")
    res["k_echo"] = accuracy.k_echo(**cfg["k_echo"])
    say("error against run time: the paper's Delta x lam grid")
    res["delta_lambda"] = accuracy.delta_lambda(**cfg["grid"])


def run_formation(full: bool = False, out_dir: str | Path = "bench/results", *, formations=None,
                  scale: float | None = None, cases=None, sides=None, plots: bool = True,
                  status: Callable[[str], None] | None = None) -> dict:
    """Only the image-formation part (:mod:`bench.formation`), written to
    ``<out>/<date>-formation-<device>[-quick].json`` and ``.md`` (and ``.png``).

    ``scale`` shrinks the dense planar case (1: 128 x 128 stops, 256 x 256 x 128 voxels; the
    quick set uses 0.25); ``formations`` picks registered formations (bp always runs: it is
    the reference); ``cases`` picks among ``demo``, ``dense``, ``circular``; ``sides`` are the
    scans (N x N stops) of the cost fit (empty: no fit).
    """
    from . import formation, throughput

    say = status or (lambda s: log.info("%s", s))
    cfg = formation.FULL if full else formation.QUICK
    info = throughput.opencl_device_info()
    device = info["name"] if info else "NumPy only (no OpenCL device)"
    res = formation.run(tuple(cases or cfg["cases"]), formations, cfg["scale"] if scale is None else scale,
                        cfg["sides"] if sides is None else sides, status=say)
    res.update(date=dt.datetime.now().isoformat(timespec="seconds"), device=device, mode="full" if full else "quick",
               host=f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
               versions=package_versions())
    stem = (f"{dt.date.today()}-formation-{re.sub(r'[^A-Za-z0-9]+', '-', device).strip('-')[:60]}"
            + ("" if full else "-quick"))
    res["paths"] = formation.write(res, Path(out_dir), stem, plots=plots)
    return res


def _check_dependencies(use_dask: bool, say) -> None:
    """Refuse before any work if a part cannot run; say what a missing optional peer leaves out."""
    from importlib.util import find_spec

    need = ["cvxpy", "nlopt"] + (["distributed"] if use_dask else [])
    missing = [m for m in need if find_spec(m) is None]
    if missing:
        raise ImportError(f"python -m bench needs {', '.join(missing)} (the sparse methods"
                          f"{' and the Dask runs' if 'distributed' in missing else ''}): pip install 'clsas[bench]'")
    if find_spec("numba") is None:
        say("numba is not installed: the Numba peer is left out of the report (pip install 'clsas[bench]')")


def _demo_dataset(n_stops: int):
    import clsas
    from clsas.synthesis.scenes import demo_configs, parse_config

    cfg = parse_config(demo_configs(0.01)["front"])
    return clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=20).subset(slice(0, n_stops))


def _dask_part(cfg, res, scheduler, say) -> dict:
    import time

    import clsas

    from . import accuracy
    from .distributed import backproject_tiled, dask_client

    out = {"scheduler": scheduler or "local cluster, 2 worker processes"}
    say(f"Dask: sweeps on {out['scheduler']}")
    with dask_client(scheduler) as client:
        out["workers"] = len(client.scheduler_info()["workers"])
        t = time.perf_counter()
        two = accuracy.two_echo(**cfg["two_echo"], client=client)
        out["two_echo_s"] = time.perf_counter() - t
        out["two_echo_equals_serial"] = _same_rows(two["rows"], res["two_echo"]["rows"])
        t = time.perf_counter()
        grid = accuracy.delta_lambda(**cfg["grid"], client=client)
        out["delta_lambda_s"] = time.perf_counter() - t
        out["delta_lambda_equals_serial"] = _same_rows(grid["rows"], res["delta_lambda"]["rows"])
        if cfg.get("tiles"):
            say("Dask: a volume in tiles against one call")
            (x, y, z, sp), n_tiles = cfg["tiles"]["grid"], cfg["tiles"]["n_tiles"]
            grid_v = clsas.VoxelGrid.from_bounds(x, y, z, sp)
            ds = _demo_dataset(216)
            prof = clsas.compress(ds, gate_s=(0.0, 2 * 2.2 / ds.c_mps))
            t = time.perf_counter()
            one = clsas.backproject(prof, grid_v).values
            out["untiled_s"] = time.perf_counter() - t
            t = time.perf_counter()
            tiled, devices = backproject_tiled(client, prof, grid_v, n_tiles)
            out["tiled_s"] = time.perf_counter() - t
            out.update(voxels=grid_v.size, n_tiles=n_tiles, tile_devices=sorted(set(devices)),
                       tiled_max_diff_rel=float(np.abs(tiled - one).max() / np.abs(one).max()))
    return out


def _same_rows(a, b) -> bool:
    """Equal field for field, run times aside (NaN equals NaN)."""
    if len(a) != len(b):
        return False
    for ra, rb in zip(a, b, strict=True):
        for k in ra:
            if k in ("time_s", "status"):
                continue
            va, vb = ra[k], rb.get(k)
            if isinstance(va, float) and isinstance(vb, float) and np.isnan(va) and np.isnan(vb):
                continue
            if va != vb:
                return False
    return True
