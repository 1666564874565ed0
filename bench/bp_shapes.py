"""The bp kernel at each work-group shape (local size, build variant) against the C/OpenMP peer.

    python -m bench.bp_shapes [--sides 64 128] [--measurements 1000] [--shapes tuned plain/auto ...] [--vec N]

On the device ``backend="auto"`` picks (or ``PYOPENCL_CTX``), for each N: the bench's bp workload
(``bench.throughput.backprojection_workload``, N³ voxels x M measurements), the C/OpenMP peer
timed before and after the shapes (the host's load moves; both are kept), then each shape: kernel
time from profiling events (best and median of ``--repeats`` after a warm-up), and its error
against the float64 NumPy twin on ``--check-voxels`` voxels drawn from the grid (every
measurement), in dB: 20 log10 of the largest error over the largest value, and of the RMS error
over the RMS value. ``tuned`` is the shape :mod:`clsas.cl.shapes` chose for this device among
the variants as exact as the plain kernel; ``tuned-approximate`` among those within
``HALF_TOLERANCE`` (half profiles where the device has them);
``plain/auto`` is the kernel as it was before shapes were tuned (the runtime's local size);
``range_expansion/...`` the range-expansion variant, which each call runs at the longest run
whose predicted error for the geometry is within -50 dB, or falls back to the plain kernel (the
kernel that ran, its run and its predicted error are recorded). The shapes are timed in
interleaved rounds (each shape once per round, after one warm-up each); ``x first`` is the
median over rounds of the first shape's time over each shape's in the same round.
The load average (``os.getloadavg``) is recorded next to every figure. Writes
``<date>-bp-shapes-<device>.json`` and ``.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import time
from pathlib import Path


def _shape(label: str):
    from clsas import cl

    variant, local = label.split("/")
    return cl.Shape(None if local == "auto" else int(local), "" if variant == "plain" else variant)


def _error_db(got, want) -> dict:
    import numpy as np

    err = got - want
    return {"peak_db": float(20 * np.log10(np.abs(err).max() / np.abs(want).max())),
            "rms_db": float(20 * np.log10(np.sqrt(np.mean(np.abs(err) ** 2) / np.mean(np.abs(want) ** 2))))}


def _time_rounds(plans: dict, args, repeats: int) -> tuple[dict, dict]:
    """Each plan once per round, ``repeats`` rounds after a warm-up of each: label -> stats, label -> image."""
    import numpy as np

    images = {label: plan(*args) for label, plan in plans.items()}  # warm-up (PoCL builds per local size)
    kern = {label: [] for label in plans}
    wall = {label: [] for label in plans}
    loads = []
    for _ in range(repeats):
        for label, plan in plans.items():
            t0 = time.perf_counter()
            images[label] = plan(*args)
            wall[label].append(time.perf_counter() - t0)
            kern[label].append(plan.last_kernel_s)
        loads.append(os.getloadavg()[0])
    first = next(iter(plans))
    stats = {label: {"kernel_best_s": min(k), "kernel_median_s": float(np.median(k)),
                     "wall_median_s": float(np.median(wall[label])), "load": float(np.median(loads)),
                     "x_first": float(np.median(np.asarray(kern[first]) / np.asarray(k)))}
             for label, k in kern.items()}
    return stats, images


def bench_side(n: int, n_meas: int, labels: list[str], repeats: int, check_voxels: int, rng, vec=None) -> dict:
    """One workload: the peer, every shape, the peer again; rates per pair and errors in dB."""
    import numpy as np

    from bench import cpeer
    from bench import throughput as tp
    from clsas.formation import bp_numpy as twin
    from clsas.formation.bp_opencl import HALF_TOLERANCE, BackprojectPlan

    grid = tp.cube_grid(n)
    wl = tp.backprojection_workload(grid, n_meas, rng)
    pts = grid.points()
    pairs = grid.size * n_meas
    args = (wl["data"], wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"], wl["c"])
    pick = np.sort(rng.choice(grid.size, min(check_voxels, grid.size), replace=False))
    want = twin.backproject(wl["data"].astype(np.complex128), wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"],
                            wl["c"], pts[pick])
    row = {"workload": f"{n}^3 voxels x {n_meas} measurements", "pairs": pairs, "check_voxels": len(pick),
           "peer": [], "shapes": {}}

    def peer():
        if cpeer.backproject(wl, pts[:8]) is None:
            return
        t = [0.0] * repeats
        for i in range(repeats):
            t0 = time.perf_counter()
            cpeer.backproject(wl, pts)
            t[i] = time.perf_counter() - t0
        row["peer"].append({"best_s": min(t), "rate_per_s": pairs / min(t), "load": os.getloadavg()[0]})

    peer()
    plans = {}
    for label in labels:
        shape = "auto" if label.startswith("tuned") else _shape(label)
        max_error = HALF_TOLERANCE if label == "tuned-approximate" else None
        try:
            plans[label] = BackprojectPlan(grid, n_meas, wl["data"].shape[1], vec=vec, shape=shape,
                                           max_error=max_error)
        except ValueError as exc:  # a variant this device does not offer (half without cl_khr_fp16)
            row.setdefault("refused", {})[label] = str(exc)
            print(f"  {label:22s} not run: {exc}", flush=True)
    stats, images = _time_rounds(plans, args, repeats)
    for label, plan in plans.items():
        stat = stats[label]
        stat.update(shape=plan.shape.label, vec=plan.vec, rate_per_s=pairs / stat["kernel_best_s"],
                    ran=plan.last_variant, run=plan.last_expansion_run, **_error_db(images[label][pick], want))
        if plan.shape.variant == "range_expansion":
            stat["predicted_db"] = {r: float(20 * np.log10(twin.range_expansion_error(
                grid, wl["tx"], wl["rx"], wl["c"], wl["fc"], r, wl["dtau"]))) for r in plan.expansion_runs}
        if plan.tuning is not None:
            stat["tuning"] = {"reason": plan.tuning.reason, "seconds": plan.tuning.seconds}
            print(f"  (tuning: {plan.tuning.reason})")
        row["shapes"][label] = stat
        ran = stat["ran"] + (f" R={stat['run']}" if stat["run"] else "")
        print(f"  {label:22s} {plan.shape.label:20s} VEC={plan.vec:<2d} ran {ran:20s} kernel "
              f"{stat['rate_per_s']:.3g} pairs/s (best of {repeats}), x first {stat['x_first']:.3f}, error "
              f"{stat['peak_db']:.1f} dB peak / {stat['rms_db']:.1f} dB rms, load {stat['load']:.2f}"
              + (f", predicted {stat['predicted_db']}" if "predicted_db" in stat else ""), flush=True)
    del plans
    peer()
    if row["peer"]:
        best_peer = max(p["rate_per_s"] for p in row["peer"])
        for stat in row["shapes"].values():
            stat["x_peer"] = stat["rate_per_s"] / best_peer
        runs = ", ".join(f"{p['rate_per_s']:.3g} (load {p['load']:.2f})" for p in row["peer"])
        print(f"  C/OpenMP peer {runs} pairs/s; ratios against the faster of the two", flush=True)
    return row


def markdown(res: dict) -> list[str]:
    md = [f"# bp kernel per work-group shape on {res['device']}, {res['date']}", "",
          "Script: `bench/bp_shapes.py`. Kernel rate: best of the repeats (profiling events); x peer: against "
          "the faster of the two C/OpenMP peer runs that bracket the shapes; error: against the float64 twin "
          "on the drawn voxels. Load: 1-minute load average when the figure was taken (2 cores).", ""]
    for row in res["rows"]:
        peers = ", ".join(f"{p['rate_per_s']:.3g} (load {p['load']:.2f})" for p in row["peer"]) or "n/a"
        md += [f"## {row['workload']}", "", f"C/OpenMP peer: {peers} pairs/s", "",
               "| shape asked | shape run | kernel that ran | VEC | kernel pairs/s | x first | x peer | error peak dB "
               "| error rms dB | load |",
               "|---|---|---|---|---|---|---|---|---|---|"]
        for label, s in row["shapes"].items():
            ran = s["ran"] + (f", run {s['run']}" if s["run"] else "")
            md.append(f"| {label} | {s['shape']} | {ran} | {s['vec']} | {s['rate_per_s']:.3g} | {s['x_first']:.3f} | "
                      f"{s.get('x_peer', 0):.2f} | {s['peak_db']:.1f} | {s['rms_db']:.1f} | {s['load']:.2f} |")
        md += [f"| {label} | not run: {why} | | | | | | | | |" for label, why in row.get("refused", {}).items()]
        md.append("")
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--measurements", type=int, default=1000)
    ap.add_argument("--shapes", nargs="+",
                    default=["tuned", "plain/auto", "plain/64", "local_profiles/64", "half_profiles/auto"],
                    help="'tuned', 'tuned-approximate', or variant/local with variant plain, local_profiles, "
                         "half_profiles or range_expansion, local auto or a number")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--vec", type=int, choices=[4, 8, 16], default=None,
                    help="the kernel's vector width (default: the widest the device layer verified)")
    ap.add_argument("--check-voxels", type=int, default=1500)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    if any(n < 2 for n in args.sides) or args.measurements < 1 or args.repeats < 1 or args.check_voxels < 1:
        ap.error("--sides must be at least 2; --measurements, --repeats, --check-voxels at least 1")
    for label in args.shapes:
        if label.startswith("tuned") and label not in ("tuned", "tuned-approximate"):
            ap.error(f"--shapes {label!r}: 'tuned' or 'tuned-approximate'")
        if not label.startswith("tuned"):
            try:
                _shape(label)
            except ValueError as exc:
                ap.error(f"--shapes {label!r}: {exc}")

    import numpy as np

    from clsas import cl

    queue = cl.get_queue()
    device = cl.describe(queue.device)
    print(f"device: {device}")
    rng = np.random.default_rng(0)
    rows = []
    for n in args.sides:
        print(f"{n}^3 x {args.measurements}:", flush=True)
        rows.append(bench_side(n, args.measurements, args.shapes, args.repeats, args.check_voxels, rng, args.vec))
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": device,
           "runtime": cl.runtime_record(queue), "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{dt.date.today()}-bp-shapes-{re.sub(r'[^A-Za-z0-9]+', '-', device).strip('-')[:60]}"
    stem.with_suffix(".json").write_text(json.dumps(res, indent=1, default=str))
    stem.with_suffix(".md").write_text("\n".join(markdown(res)) + "\n")
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
