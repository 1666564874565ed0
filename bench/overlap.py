"""Tiles with and without overlap: what running the next tile's kernels during the last tile's
read back and file write changes, per OpenCL runtime.

    python -m bench.overlap [--side 64] [--measurements 1000] [--tile-x 8] [--repeats 5]
                            [--dask-workers N] [--devices P:D ...] [--out DIR]

A planar scan of ``measurements`` stops (``bench.resident``'s scene) is compressed once on the
device; its profiles are then formed onto ``side``³ voxels (``bench.throughput.cube_grid``) in
tiles of ``tile_x`` x-planes by :func:`clsas.pipeline.tiling.form_tiled` with ``overlap`` on and off, in
memory and into an HDF5 file (each tile written and synced before the next is handed on), the
variants interleaved in each repeat so that a change of machine load touches all of them; and
onto the whole grid at once (one Backprojector call). With ``--dask-workers N`` the tiles are
also formed on a local Dask cluster of N one-thread worker processes (each on a sub-device of one
compute unit of a CPU device), with and without overlap inside each task's run of tiles
(:func:`clsas.pipeline.tiling.dask.tile_runs`), the cluster started before the repeats. It
reports the medians of the wall times, the bp kernel time and the image read back time of the
tiles (profiling events), the share of each tile's read back that ran while the next tile's
kernels ran and the device's idle time between one tile's kernels and the next's (device
clock), and the overlap's gain (sequential wall over overlapped wall).

Each OpenCL device that builds kernels (Oclgrind left out) is measured in a child process with
``PYOPENCL_CTX`` set. It prints a table and writes ``<date>-overlap-<cpu>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = ("memory, sequential", "memory, overlapped", "file, sequential", "file, overlapped")
DASK_VARIANTS = ("dask, sequential", "dask, overlapped")


def _tiles_timed(prof, grid, shape, overlap: bool, out, client=None) -> tuple:
    """(wall, bp kernel, read back, share of the read back under the next tile's kernels, device idle
    between tiles) seconds of one tiled formation; the last four from the same tiles formed again
    for their events (in memory, in this process only)."""
    from clsas import cl
    from clsas.pipeline.tiling import TiledRequest, form_tiled

    sel = cl.select("opencl")
    t = time.perf_counter()
    image = form_tiled(prof, grid, "bp", {}, sel, TiledRequest(out=out, tile_shape=shape, overlap=overlap,
                                                               client=client))
    wall = time.perf_counter() - t
    if image.provenance["tiles"]["overlap"] is not overlap:
        raise RuntimeError(f"asked overlap={overlap}, the tiles say {image.provenance['tiles']['overlap']}")
    if out is not None or client is not None:
        return wall, 0.0, 0.0, 0.0, 0.0
    return wall, *_events(prof, grid, shape, overlap, sel)


@contextmanager
def _cluster(n_workers: int):
    """A client of a local cluster of ``n_workers`` one-thread processes (None for 0)."""
    if not n_workers:
        yield None
        return
    from bench.distributed import dask_client

    with dask_client(None, n_workers=n_workers) as client:
        yield client


def _events(prof, grid, shape, overlap: bool, sel) -> tuple[float, float, float, float]:
    """The tiles formed as :func:`clsas.formation.bp.form_tiles` forms them, timed by their events:
    (kernel s, read back s, share of the read back under the next tile's kernels, device idle s
    between one tile's last kernel and the next one's first)."""
    from collections import deque

    from clsas.formation.bp import Backprojector
    from clsas.pipeline.tiling import tile_grid

    pending, done = deque(), []
    for tile in tile_grid(grid, shape):
        pending.append(Backprojector(tile.grid, backend=sel).enqueue(prof))
        if len(pending) == (2 if overlap else 1):
            done.append(pending.popleft())
    done += list(pending)
    images = [p.result() for p in done]
    kernel = sum(i.timings_s["backproject_kernel"] + i.timings_s["records_kernel"] for i in images)
    read = sum(i.timings_s["image_read"] for i in images)
    under = idle = 0.0
    for a, b in zip(done, done[1:], strict=False):
        (r0, r1), (k0, k1) = a.spans_ns["read"], b.spans_ns["kernels"]
        under += max(0, min(r1, k1) - max(r0, k0)) * 1e-9
        idle += max(0, k0 - a.spans_ns["kernels"][1]) * 1e-9
    return kernel, read, under / read if read else 0.0, idle


def child(args) -> dict:
    """Measure the device PYOPENCL_CTX names."""
    import numpy as np

    import clsas
    from bench import throughput as tp
    from bench.resident import _scan
    from clsas import cl
    from clsas.formation.bp import Backprojector

    ds = _scan(args.measurements)
    grid = tp.cube_grid(args.side)
    shape = (args.tile_x, args.side, args.side)
    prof = clsas.compress(ds, backend="opencl", gate_s=clsas.reconstruct(ds, grid, backend="opencl",
                                                                         formation="bp").plan.gate_s)
    variants = VARIANTS + (DASK_VARIANTS if args.dask_workers else ())
    runs: dict[str, list] = {v: [] for v in (*variants, "whole grid")}
    with tempfile.TemporaryDirectory() as tmp, _cluster(args.dask_workers) as client:
        for rep in range(args.repeats + 1):
            for name in variants:
                out = Path(tmp) / f"{rep}-{name.replace(', ', '-')}.h5" if name.startswith("file") else None
                runs[name].append(_tiles_timed(prof, grid, shape, name.endswith("overlapped"), out,
                                               client if name.startswith("dask") else None))
                if out is not None:
                    out.unlink()
            t = time.perf_counter()
            image = Backprojector(grid, backend="opencl")(prof)
            runs["whole grid"].append((time.perf_counter() - t, image.timings_s["backproject_kernel"]
                                       + image.timings_s["records_kernel"], image.timings_s["image_read"], 0.0, 0.0))
    med = {k: [float(np.median([r[i] for r in v[1:]])) for i in range(5)] for k, v in runs.items()}  # after warm-up
    return {"runtime": cl.runtime_record(cl.get_queue()), "pairs": grid.size * ds.n_meas,
            "tiles": -(-args.side // args.tile_x), "median_s": med, "runs_s": runs}


def markdown(res: dict) -> list[str]:
    a = res["args"]
    dask = f"; Dask: a local cluster of {a['dask_workers']} one-thread workers" if a.get("dask_workers") else ""
    md = [f"# Tiles with and without overlap on {res['cpu']} ({res['cores']} cores), {res['date']}", "",
          f"Script: `bench/overlap.py` ({a['side']}³ voxels in tiles of {a['tile_x']} x-planes, "
          f"{a['measurements']} measurements; medians of {a['repeats']} interleaved runs after a warm-up"
          f"{dask}). "
          f"Load average before the run: {res['load_before']}, after: {res['load_after']}.", "",
          "| runtime (version) | variant | wall, s | pairs/s | bp kernels, s | image read back, s | "
          "read back under the next kernels | device idle between tiles, s | sequential / overlapped wall |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        name = f"{r['platform']} ({r['platform_version'][:28]})"
        if "error" in r:
            md.append(f"| {name} | failed: {r['error'][:200]} |" + " |" * 5)
            continue
        med = r["median_s"]
        for v, (wall, kernel, read, under, idle) in med.items():
            gain = ""
            if v.endswith("overlapped"):
                gain = f"{med[v.replace('overlapped', 'sequential')][0] / wall:.3f}"
            ev = [f"{kernel:.4f}", f"{read:.4f}", f"{100 * under:.0f} %", f"{idle:.4f}"] if kernel else ["-"] * 4
            if v == "whole grid" and kernel:
                ev[2:] = ["-", "-"]
            md.append(f"| {name} | {v} | {wall:.4f} | {r['pairs'] / wall:.3g} | {' | '.join(ev)} | {gain} |")
    return md


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=64)
    ap.add_argument("--measurements", type=int, default=1000)
    ap.add_argument("--tile-x", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dask-workers", type=int, default=0, help="also form the tiles on a local Dask cluster")
    ap.add_argument("--devices", nargs="*", default=None, help="PYOPENCL_CTX indices (default every one)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.side < 2 or not 1 <= args.tile_x <= args.side or args.measurements < 1 or args.repeats < 1:
        ap.error("--side must be at least 2, --tile-x between 1 and --side, --measurements and --repeats at least 1")
    if args.dask_workers < 0:
        ap.error("--dask-workers must be 0 (no cluster) or more")
    if args.child:
        sys.stdout.write(json.dumps(child(args), default=str) + "\n")
        return 0
    from bench.report import write_run
    from bench.resident import _devices
    from bench.stats import cpu_name

    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "cpu": cpu_name(), "cores": os.cpu_count(),
           "args": {"side": args.side, "measurements": args.measurements, "tile_x": args.tile_x,
                    "repeats": args.repeats, "dask_workers": args.dask_workers}, "rows": [], "load_before": _load()}
    forwarded = [f"--side={args.side}", f"--measurements={args.measurements}", f"--tile-x={args.tile_x}",
                 f"--repeats={args.repeats}", f"--dask-workers={args.dask_workers}"]
    for d in [d for d in _devices() if args.devices is None or d["index"] in args.devices]:
        print(f"timing {d['platform']} ({d['platform_version']})", flush=True)
        env = {**os.environ, "PYOPENCL_CTX": d["index"], "PYTHONPATH": str(ROOT)}
        # as a module: run as a script, its folder would come first on sys.path and bench/distributed.py
        # would shadow the distributed package
        proc = subprocess.run([sys.executable, "-m", "bench.overlap", "--child", *forwarded],
                              capture_output=True, text=True, env=env, timeout=3600, cwd=str(ROOT))
        lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
        if proc.returncode != 0 or not lines:
            res["rows"].append({**d, "error": f"exit {proc.returncode}: {proc.stderr.strip()[-300:]}"})
            continue
        res["rows"].append({**d, **json.loads(lines[-1])})
    res["load_after"] = _load()
    md = markdown(res)
    print("\n".join(md))
    write_run(args.out, "overlap", res, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
