"""Every OpenCL runtime here, side by side, against the C/OpenMP peer, in one run.

    python -m bench.runtimes [--side 64] [--measurements 400] [--stops 24] [--repeats 5] [--out bench/results]

For each OpenCL device that builds kernels (the Oclgrind simulator left out), a child process
with ``PYOPENCL_CTX`` set to it times:

- bp: the backprojection kernel (profiling events) and the whole plan call (transfers included)
  on ``side``³ voxels x ``measurements`` measurements (``bench.throughput``'s workload),
  in voxel-measurement pairs/s;
- compression: the matched filter (FFT) of a planar scan's recordings, kernel and whole call, in
  input samples/s;
- ``reconstruct`` with formation bp, omega-k and FFBP on the same planar scan (``stops``² stops,
  a 0.01 m grid): the whole call's wall time and its kernel time, compression included.

The parent process runs the hand-vectorised C/OpenMP backprojection (``bench.cpeer``) on
the same bp workload, so each runtime's rates come with their ratio to the peer of this run. It
prints a table and writes ``<date>-runtimes-<cpu>.json`` and ``.md`` (each row names the runtime
and its version).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.report import write_run
from bench.stats import cpu_name

ROOT = Path(__file__).resolve().parents[1]




def _devices() -> list[dict]:
    from clsas import cl

    out = []
    for r in cl.list_devices():
        if "oclgrind" in r.platform.lower():
            continue
        out.append({"index": r.index, "platform": r.platform, "platform_version": r.platform_version,
                    "device": r.device, "driver": r.driver, "kind": r.kind, "builds": r.builds, "reason": r.reason})
    return out


def _planar_scan(stops: int):
    import numpy as np

    import clsas

    fs = 96e3
    chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    ap = clsas.raster_aperture(stops, stops, 0.64, 0.64)
    scene = clsas.Scene(np.array([[0.1, 0.05, 1.2], [-0.2, 0.1, 1.5], [0.0, -0.1, 1.35]]))
    ds = clsas.simulate(scene, ap, chirp, fs, snr_db=20, seed=0)
    grid = clsas.VoxelGrid.from_bounds((-0.32, 0.32), (-0.32, 0.32), (1.0, 1.64), 0.01)
    return ds, grid


def child(args) -> dict:
    """Measure the device that PYOPENCL_CTX names (run in a child process per runtime)."""
    import numpy as np

    import clsas
    from bench import throughput as tp
    from clsas import cl

    queue = cl.get_queue()
    row = {"runtime": cl.runtime_record(queue)}
    rng = np.random.default_rng(0)
    bp = tp.bench_backprojection("bp", tp.cube_grid(args.side), args.measurements, repeats=args.repeats,
                                 twin_meas=1, numba_meas=1, rng=rng)
    row["bp"] = {k: bp[k] for k in ("opencl_kernel", "opencl_wall", "opencl_vec", "pairs") if k in bp}
    ds, grid = _planar_scan(args.stops)
    samples = ds.signals.size
    kern, wall = [], []
    for _ in range(args.repeats + 1):
        t = time.perf_counter()
        prof = clsas.compress(ds, backend="opencl", algorithm="fft")
        wall.append(time.perf_counter() - t)
        kern.append(prof.timings_s["compress_kernel"])
    row["compression"] = {"kernel": tp._stat(kern[1:], samples), "wall": tp._stat(wall[1:], samples)}
    row["reconstruct"] = {}
    for formation in ("bp", "omega-k", "ffbp"):
        times, kernel = [], []
        for _ in range(max(2, args.repeats // 2) + 1):
            t = time.perf_counter()
            image = clsas.reconstruct(ds, grid, backend="opencl", formation=formation,
                                      )
            times.append(time.perf_counter() - t)
            kernel.append(sum(v for k, v in image.timings_s.items() if k.endswith("_kernel")))
        row["reconstruct"][formation] = {"wall_s": float(np.median(times[1:])),
                                         "kernel_s": float(np.median(kernel[1:])), "voxels": grid.size,
                                         "measurements": ds.n_meas}
    row["runtime"] = cl.runtime_record(queue)  # with the kernel widths chosen above
    return row


def _peer(args) -> dict:
    import numpy as np

    from bench import cpeer
    from bench import throughput as tp

    rng = np.random.default_rng(0)
    grid = tp.cube_grid(args.side)
    wl = tp.backprojection_workload(grid, args.measurements, rng)
    pts = grid.points()
    if cpeer.backproject(wl, pts[:8]) is None:
        return {"missing": cpeer.load()[1]}
    t = tp.timed(lambda: cpeer.backproject(wl, pts), args.repeats)
    return {"bp": tp._stat(t, grid.size * args.measurements), "build": cpeer.load()[1]}


def _ratio(x: float, peer: float | None) -> str:
    return f"{x / peer:.2f}" if peer else "-"


def markdown(res: dict) -> list[str]:
    peer = res["peer"].get("bp", {}).get("rate_per_s")
    a = res["args"]
    peer_text = (f"{res['peer']['build']}, {peer:.3g} pairs/s" if peer else
                 f"missing ({res['peer'].get('missing')})")
    md = [f"# OpenCL runtimes on {res['cpu']} ({res['cores']} cores), {res['date']}", "",
          f"Script: `bench/runtimes.py` (bp {a['side']}³ voxels x {a['measurements']} measurements; compression and "
          f"`reconstruct` on a {a['stops']}² planar scan, 0.01 m grid). C/OpenMP peer of the same run: {peer_text}.",
          "",
          "| runtime (version) | VEC bp | bp kernel, pairs/s | bp call, pairs/s | kernel / peer | call / peer | "
          "compression kernel, samples/s | compression call, samples/s | reconstruct bp, s | omega-k, s | FFBP, s |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        rt = r.get("runtime", {})
        name = f"{rt.get('platform', r['platform'])} ({rt.get('platform_version', r['platform_version'])})"
        if "error" in r:
            md.append(f"| {name} | failed: {r['error']} |" + " |" * 9)
            continue
        k, w = r["bp"]["opencl_kernel"]["rate_per_s"], r["bp"]["opencl_wall"]["rate_per_s"]
        comp, rec = r["compression"], r["reconstruct"]
        md.append(f"| {name} | {r['bp'].get('opencl_vec')} | {k:.3g} | {w:.3g} | {_ratio(k, peer)} | "
                  f"{_ratio(w, peer)} | {comp['kernel']['rate_per_s']:.3g} | {comp['wall']['rate_per_s']:.3g} | "
                  f"{rec['bp']['wall_s']:.3f} | {rec['omega-k']['wall_s']:.3f} | {rec['ffbp']['wall_s']:.3f} |")
    refused = "; ".join(f"{d['platform']} ({d['platform_version']}): {d['reason']}" for d in res["refused"])
    md += ["", f"Runtimes that build no kernel here: {refused or 'none'}."]
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=64, help="N of the bp workload's N^3 voxels")
    ap.add_argument("--measurements", type=int, default=400, help="measurements of the bp workload")
    ap.add_argument("--stops", type=int, default=24, help="stops a side of the planar scan")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.side < 2 or args.measurements < 1 or args.stops < 2 or args.repeats < 1:
        ap.error("--side and --stops must be at least 2, --measurements and --repeats at least 1")
    if args.child:
        sys.stdout.write(json.dumps(child(args), default=str) + "\n")
        return 0
    devices = _devices()
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "cpu": cpu_name(), "cores": os.cpu_count(),
           "args": {k: v for k, v in vars(args).items() if k not in ("out", "child")}, "rows": [],
           "refused": [d for d in devices if not d["builds"]]}
    res["peer"] = _peer(args)
    forwarded = [f"--side={args.side}", f"--measurements={args.measurements}", f"--stops={args.stops}",
                 f"--repeats={args.repeats}"]
    for d in (d for d in devices if d["builds"]):
        print(f"timing {d['device']} on {d['platform']} ({d['platform_version']})", flush=True)
        env = {**os.environ, "PYOPENCL_CTX": d["index"]}
        proc = subprocess.run([sys.executable, __file__, "--child", *forwarded], capture_output=True, text=True,
                              env=env, timeout=3600)
        lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
        if proc.returncode != 0 or not lines:
            res["rows"].append({**d, "error": f"exit {proc.returncode}: {proc.stderr.strip()[-300:]}"})
            continue
        res["rows"].append({**d, **json.loads(lines[-1])})
    md = markdown(res)
    print("\n".join(md))
    write_run(args.out, "runtimes", res, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
