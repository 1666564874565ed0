"""How fast can any backprojection go on this OpenCL device? The bp kernel with its work removed.

    python -m bench.bp_floor [--side 64] [--measurements 1024] [--vec 8] [--out bench/results]

The formation work asked for bp at >= 2.5x the C/OpenMP peer (``bench/backproject_omp.c``). This
script times, on ``throughput.backprojection_workload`` (the bench's cube grid), the shipped
kernel and three copies of it with parts taken out:

- ``full``: the kernel as shipped;
- ``no carrier``: the sub-sample carrier rotation (``sincos_small``) replaced by 1;
- ``no sqrt``: the two square roots replaced by ``|dz|`` (the paths stay within the profile);
- ``read only``: both: what is left is the profile read (``lerp_pairs``) and the sum.

The stripped copies are not backprojection (their images are wrong); they are built through
:func:`clsas.cl.program.override_source` with the twin check bypassed, and exist only to
bound from above what any variant that still reads one interpolated sample per
voxel-measurement pair can reach on the device. The peer runs in the same process.

Writes ``<date>-bp-floor-<tag>.{json,md}`` under --out.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from pathlib import Path

import numpy as np

import clsas.cl.plan as plan_module
from bench import cpeer, throughput
from clsas.cl.program import kernel_source, override_source
from clsas.formation.bp_opencl import BackprojectPlan

SQRT = """vsqrt(dtx * dtx + dty * dty + dtz * dtz)
                          + vsqrt(drx * drx + dry * dry + drz * drz);"""
CARRIER = "floatV s = sincos_small(phi * (f - 0.5f), &c);"


def variant_source(name: str) -> str:
    src = kernel_source("backproject.cl")
    if name in ("no sqrt", "read only"):
        assert SQRT in src, "backproject.cl changed: update bench/bp_floor.py"
        src = src.replace(SQRT, "fabs(dtz) + fabs(drz);")
    if name in ("no carrier", "read only"):
        assert CARRIER in src, "backproject.cl changed: update bench/bp_floor.py"
        src = src.replace(CARRIER, "floatV s = (floatV)(0.0f); c = (floatV)(1.0f);")
    return src


def time_variant(name, grid, wl, vec, repeats):
    args = (wl["data"], wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"], wl["c"])
    choose = plan_module.choose
    plan_module.choose = lambda queue, kernel, v: v  # the stripped copies fail the twin check by design
    try:
        with override_source("backproject.cl", variant_source(name)):
            plan = BackprojectPlan(grid, len(wl["tx"]), wl["data"].shape[1], vec=vec)
            plan(*args)
            times = []
            for _ in range(repeats):
                plan(*args)
                times.append(plan.last_kernel_s)
    finally:
        plan_module.choose = choose
    return plan, float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=64)
    ap.add_argument("--measurements", type=int, default=1024)
    ap.add_argument("--vec", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tag", default="vm")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    a = ap.parse_args()
    grid = throughput.cube_grid(a.side)
    wl = throughput.backprojection_workload(grid, a.measurements, np.random.default_rng(0))
    pairs = grid.size * a.measurements
    pts = grid.points()
    if cpeer.backproject(wl, pts[:8]) is None:
        raise SystemExit(f"the C/OpenMP peer is not available: {cpeer.load()[1]}")
    rows, device = [], None
    for name in ("full", "no carrier", "no sqrt", "read only"):
        plan, kern = time_variant(name, grid, wl, a.vec, a.repeats)
        peer = []
        for _ in range(max(3, a.repeats // 2)):
            t = time.perf_counter()
            cpeer.backproject(wl, pts)
            peer.append(time.perf_counter() - t)
        device = plan.device
        peer_s = float(np.median(peer))
        rows.append({"variant": name, "kernel_pairs_per_s": pairs / kern, "peer_pairs_per_s": pairs / peer_s,
                     "ratio": peer_s / kern})
        print(f"{name:>10}: {pairs / kern:.3e} pairs/s, peer {pairs / peer_s:.3e}, x{peer_s / kern:.2f}")
    out = {"device": device, "vec": a.vec, "voxels": grid.size, "measurements": a.measurements, "pairs": pairs,
           "peer_build": cpeer.load()[1], "rows": rows}
    stem = a.out / f"{dt.date.today().isoformat()}-bp-floor-{a.tag}"
    a.out.mkdir(parents=True, exist_ok=True)
    Path(f"{stem}.json").write_text(json.dumps(out, indent=1) + "\n")
    lines = [f"# bp with its work removed: {device}, VEC={a.vec}", "",
             f"{grid.size} voxels x {a.measurements} measurements; medians of {a.repeats} kernel times; "
             f"peer: C/OpenMP ({out['peer_build']}), medians in the same process.", "",
             "| variant | kernel pairs/s | peer pairs/s | kernel / peer |", "|---|---|---|---|"]
    lines += [f"| {r['variant']} | {r['kernel_pairs_per_s']:.3e} | {r['peer_pairs_per_s']:.3e} | {r['ratio']:.2f}x |"
              for r in rows]
    Path(f"{stem}.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {stem}.json and .md")


if __name__ == "__main__":
    main()
