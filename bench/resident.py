"""The whole ``reconstruct`` (compression + bp) against the bp kernel alone, per OpenCL runtime.

    python -m bench.resident [--sides 64 128] [--measurements 1000] [--repeats 3] [--code DIR ...]
                             [--devices P:D ...] [--out DIR]
    python -m bench.resident --merge RUN.json RUN.json RUN.json   # medians over whole runs

A planar scan of ``measurements`` stops (simulated once per process, three points) is imaged
by ``clsas.reconstruct(..., formation="bp", backend="opencl")`` onto ``side``³ voxels
(``bench.throughput.cube_grid``). For each run it reads the call's wall time and the kernel
times the image carries (``compress_kernel``, ``records_kernel``, ``backproject_kernel``:
profiling events), and
reports in voxel-measurement pairs/s: the bp kernel's rate, the whole call's rate, their ratio,
and the host's share of the wall time (wall minus kernel time, over wall: host steps,
transfers, launches, checks); the medians over ``repeats`` runs after one warm-up run.

Each OpenCL device that builds kernels (Oclgrind left out) is measured in a child process with
``PYOPENCL_CTX`` set; with ``--code DIR`` (repeatable) the child imports clsas from ``DIR``
(another checkout: the code before a change), so one run compares code versions on the same
machine load. The parent times the hand-vectorised C/OpenMP backprojection (``bench.cpeer``)
on a workload of the same size (``bench.throughput.backprojection_workload``). It prints a table
and writes ``<date>-resident-<cpu>.json`` and ``.md``. ``--merge`` reads the JSON of several
whole runs (a loaded machine: run it again, later) and prints the medians over them of each
figure, per code, runtime and size, with the spread (min-max).
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

ROOT = Path(__file__).resolve().parents[1]


def _scan(n_meas: int):
    import numpy as np

    import clsas

    fs = 96e3
    chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    nx = int(np.ceil(np.sqrt(n_meas)))
    while n_meas % nx:
        nx += 1
    ap = clsas.raster_aperture(nx, n_meas // nx, 1.0, 1.0)
    scene = clsas.Scene(np.array([[0.1, 0.05, 1.2], [-0.2, 0.1, 1.5], [0.0, -0.1, 1.35]]))
    return clsas.simulate(scene, ap, chirp, fs, snr_db=20, seed=0)


def child(args) -> dict:
    """Measure the device PYOPENCL_CTX names with the clsas this process imports."""
    import numpy as np

    import clsas
    from bench import throughput as tp
    from clsas import cl

    ds = _scan(args.measurements)
    out = {"clsas": str(Path(clsas.__file__).parent), "rows": []}
    for side in args.sides:
        grid = tp.cube_grid(side)
        pairs = grid.size * ds.n_meas
        runs = []
        for _ in range(args.repeats + 1):
            t = time.perf_counter()
            image = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
            wall = time.perf_counter() - t
            ts = image.timings_s
            runs.append({"wall_s": wall, "compress_s": ts.get("compress", 0.0),
                         "compress_kernel_s": ts.get("compress_kernel", 0.0),
                         "backproject_s": ts.get("backproject", 0.0),
                         "backproject_kernel_s": ts.get("backproject_kernel", 0.0),
                         "records_kernel_s": ts.get("records_kernel", 0.0)})
        runs = runs[1:]  # the first run builds, probes and allocates
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        kernel = med["compress_kernel_s"] + med["backproject_kernel_s"] + med["records_kernel_s"]
        out["rows"].append({
            "side": side, "voxels": grid.size, "measurements": ds.n_meas, "pairs": pairs, "runs": runs,
            "median": med, "bp_kernel_rate": pairs / med["backproject_kernel_s"],
            "reconstruct_rate": pairs / med["wall_s"],
            "whole_over_kernel": med["backproject_kernel_s"] / med["wall_s"],
            "host_share": 1.0 - kernel / med["wall_s"],
        })
    out["runtime"] = cl.runtime_record(cl.get_queue())
    return out


def peer(sides, n_meas: int, repeats: int) -> dict:
    """The C/OpenMP backprojection's rate per side (median of ``repeats``), or why it is missing."""
    import numpy as np

    from bench import cpeer
    from bench import throughput as tp

    rng = np.random.default_rng(0)
    res = {}
    for side in sides:
        grid = tp.cube_grid(side)
        wl = tp.backprojection_workload(grid, n_meas, rng)
        pts = grid.points()
        if cpeer.backproject(wl, pts[:8]) is None:
            return {"missing": cpeer.load()[1]}
        t = tp.timed(lambda wl=wl, pts=pts: cpeer.backproject(wl, pts), repeats)
        res[side] = {"rate": grid.size * n_meas / float(np.median(t)), "times_s": list(map(float, t))}
    res["build"] = cpeer.load()[1]
    return res


def _devices() -> list[dict]:
    from clsas import cl

    return [{"index": r.index, "platform": r.platform, "platform_version": r.platform_version, "device": r.device}
            for r in cl.list_devices() if r.builds and "oclgrind" not in r.platform.lower()]


def _ratio(x: float, peer: float | None) -> str:
    return f"{x / peer:.2f}" if peer else "-"


def markdown(res: dict) -> list[str]:
    a = res["args"]
    md = [f"# Whole reconstruct vs the bp kernel on {res['cpu']} ({res['cores']} cores), {res['date']}", "",
          f"Script: `bench/resident.py` ({a['measurements']} measurements, medians of {a['repeats']} runs after a "
          "warm-up; compression + bp through `clsas.reconstruct(formation='bp')`). The machine was shared with "
          "other jobs: the figures are noisy.", "",
          "| code | runtime (version) | N³ | bp kernel, pairs/s | reconstruct, pairs/s | reconstruct / kernel | "
          "host share of wall | kernel / C peer | reconstruct / C peer |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        if "error" in r:
            md.append(f"| {r['code']} | {r['platform']} ({r['platform_version']}) | failed: {r['error'][:200]} |"
                      + " |" * 6)
            continue
        for row in r["rows"]:
            p = res["peer"].get(row["side"], res["peer"].get(str(row["side"]), {})).get("rate")
            md.append(f"| {r['code']} | {r['platform']} ({r['platform_version']}) | {row['side']} | "
                      f"{row['bp_kernel_rate']:.3g} | {row['reconstruct_rate']:.3g} | {row['whole_over_kernel']:.2f} | "
                      f"{100 * row['host_share']:.0f} % | {_ratio(row['bp_kernel_rate'], p)} | "
                      f"{_ratio(row['reconstruct_rate'], p)} |")
    peer_rates = ", ".join(f"{k}³ {v['rate']:.3g} pairs/s" for k, v in res["peer"].items() if isinstance(v, dict))
    md += ["", f"C/OpenMP peer ({res['peer'].get('build', res['peer'].get('missing'))}): {peer_rates}."]
    return md


def merge(paths: list[Path]) -> list[str]:
    """The medians over whole runs (their JSON files) of each figure, per code, runtime and side."""
    import numpy as np

    runs = [json.loads(Path(p).read_text()) for p in paths]
    figures = ("bp_kernel_rate", "reconstruct_rate", "whole_over_kernel", "host_share")
    cells: dict[tuple, dict[str, list]] = {}
    peers: dict[str, list] = {}
    for res in runs:
        for side, v in res["peer"].items():
            if isinstance(v, dict):
                peers.setdefault(str(side), []).append(v["rate"])
        for r in res["rows"]:
            for row in r.get("rows", []):
                cell = cells.setdefault((r["code"], r["platform"], r["platform_version"][:24], row["side"]), {})
                for f in figures:
                    cell.setdefault(f, []).append(row[f])
                cell.setdefault("peer", []).append(res["peer"].get(str(row["side"]), {}).get("rate"))

    def fmt(xs, spec, scale=1.0):
        m = float(np.median(xs)) * scale
        return f"{m:{spec}} ({min(xs) * scale:{spec}}-{max(xs) * scale:{spec}})"

    md = [f"Medians over {len(runs)} runs (min-max in brackets): {', '.join(str(p) for p in paths)}", "",
          "| code | runtime | N³ | bp kernel, pairs/s | reconstruct, pairs/s | reconstruct / kernel | host share, % | "
          "kernel / C peer | reconstruct / C peer |", "|---|---|---|---|---|---|---|---|---|"]
    for (code, platform, version, side), c in cells.items():
        ok = [p for p in c["peer"] if p]
        kp = [k / p for k, p in zip(c["bp_kernel_rate"], c["peer"], strict=True) if p] if ok else None
        rp = [k / p for k, p in zip(c["reconstruct_rate"], c["peer"], strict=True) if p] if ok else None
        md.append(f"| {code} | {platform} ({version}) | {side} | {fmt(c['bp_kernel_rate'], '.3g')} | "
                  f"{fmt(c['reconstruct_rate'], '.3g')} | {fmt(c['whole_over_kernel'], '.2f')} | "
                  f"{fmt(c['host_share'], '.1f', 100)} | {fmt(kp, '.2f') if kp else '-'} | "
                  f"{fmt(rp, '.2f') if rp else '-'} |")
    md += ["", "C/OpenMP peer: " + ", ".join(f"{side}³ {fmt(v, '.3g')} pairs/s" for side, v in peers.items())]
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[64])
    ap.add_argument("--measurements", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--code", type=Path, action="append", default=[],
                    help="a checkout whose clsas the children import (repeatable; default this one)")
    ap.add_argument("--devices", nargs="*", default=None, help="PYOPENCL_CTX indices (default every one)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--merge", type=Path, nargs="+", help="JSON files of whole runs: print the medians over them")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.merge:
        print("\n".join(merge(args.merge)))
        return 0
    if any(n < 2 for n in args.sides) or args.measurements < 1 or args.repeats < 1:
        ap.error("--sides must be at least 2, --measurements and --repeats at least 1")
    if args.child:
        sys.stdout.write(json.dumps(child(args), default=str) + "\n")
        return 0
    from bench.report import write_run
    from bench.stats import cpu_name

    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "cpu": cpu_name(), "cores": os.cpu_count(),
           "args": {"sides": args.sides, "measurements": args.measurements, "repeats": args.repeats}, "rows": []}
    res["peer"] = peer(args.sides, args.measurements, args.repeats)
    devices = [d for d in _devices() if args.devices is None or d["index"] in args.devices]
    forwarded = ["--sides", *map(str, args.sides), f"--measurements={args.measurements}", f"--repeats={args.repeats}"]
    for code in args.code or [ROOT]:
        for d in devices:
            print(f"timing {d['platform']} ({d['platform_version']}) with {code}", flush=True)
            env = {**os.environ, "PYOPENCL_CTX": d["index"],
                   "PYTHONPATH": os.pathsep.join([str(code), str(ROOT)])}
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", *forwarded],
                                  capture_output=True, text=True, env=env, timeout=3600, cwd=str(code))
            lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
            if proc.returncode != 0 or not lines:
                res["rows"].append({**d, "code": str(code), "error": f"exit {proc.returncode}: "
                                    f"{proc.stderr.strip()[-300:]}"})
                continue
            res["rows"].append({**d, "code": str(code), **json.loads(lines[-1])})
    md = markdown(res)
    print("\n".join(md))
    write_run(args.out, "resident", res, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
