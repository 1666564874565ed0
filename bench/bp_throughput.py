"""Backprojection throughput on this machine's OpenCL device against the C/OpenMP and Numba peers.

    python -m bench.bp_throughput [--sides 64 128] [--measurements 1000] [--out bench/results]

Only the bp part of ``python -m bench``, with the sizes a GPU needs to fill. It needs no cvxpy, Dask
or Numba (Numba's peer is left out without it). The device is the one ``backend="auto"`` picks,
or ``PYOPENCL_CTX``. For each N it backprojects N³ voxels x M measurements, times the OpenCL
kernel (profiling events) and the whole call (wall, transfers included), and runs in the same
process the NumPy twin, the Numba peer and the hand-vectorised C/OpenMP peer on the host's cores.
It prints the roofline (:func:`bench.throughput.compute_bound`) and writes
``<date>-bp-<device>.json`` and ``.md``. The H200 figures in
``bench/results/2026-11-28-formation-gpu-h200.md`` came from this (its JSON files are in
``git log -- bench/results``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[64, 128], help="N of the N^3-voxel grids")
    ap.add_argument("--measurements", type=int, default=1000, help="measurements per workload")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    if any(n < 2 for n in args.sides) or args.measurements < 1 or args.repeats < 1:
        ap.error("--sides must be at least 2, --measurements and --repeats at least 1")

    import numpy as np

    from bench import package_versions
    from bench import throughput as tp

    info = tp.opencl_device_info()
    if info is None:
        print("no OpenCL device: nothing to measure (clsas devices says why)")
        return 1
    bandwidth = tp.memory_bandwidth()
    bound = tp.compute_bound(info, bandwidth)
    print(f"device: {info['name']} ({info['type']}, {info['compute_units']} compute units)")
    rng = np.random.default_rng(0)
    rows = []
    for n in args.sides:
        row = tp.bench_backprojection(f"{n}^3 voxels x {args.measurements} measurements", tp.cube_grid(n),
                                      args.measurements,
                                      repeats=args.repeats, twin_meas=1, numba_meas=4, rng=rng)
        rows.append(row)
        rates = {k: row[k]["rate_per_s"] for k in ("opencl_kernel", "opencl_wall", "c_openmp_peer", "numba_peer",
                                                    "numpy_twin") if k in row}
        print(f"{row['workload']}: " + ", ".join(f"{k} {v:.3g} pairs/s" for k, v in rates.items()))
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": info, "bandwidth_bps": bandwidth,
           "compute_bound": bound, "versions": package_versions(), "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"{dt.date.today()}-bp-{re.sub(r'[^A-Za-z0-9]+', '-', info['name']).strip('-')[:60]}"
    (args.out / f"{stem}.json").write_text(json.dumps(res, indent=1, default=str))
    (args.out / f"{stem}.md").write_text("\n".join(markdown(res)) + "\n")
    print(f"wrote {args.out / stem}.json and .md")
    return 0


def markdown(res: dict) -> list[str]:
    """The table and the roofline, in the words of ``python -m bench``'s report."""
    from bench.report import _md_backprojection

    md = [f"# bp throughput on {res['device']['name']}, {res['date']}", "",
          f"Script: `bench/bp_throughput.py`; clsas {res['versions'].get('clsas_commit') or '(not a git checkout)'}.",
          ""]
    return md + _md_backprojection({"backprojection": res["rows"], "compute_bound": res["compute_bound"],
                                    "device": res["device"]})


if __name__ == "__main__":
    raise SystemExit(main())
