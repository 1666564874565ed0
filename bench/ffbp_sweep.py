"""FFBP against exact backprojection: error-to-signal and run time for a few depth/oversampling settings.

    python -m bench.ffbp_sweep                 # the dense planar scan (128 x 128 stops, 256 x 256 x 128 voxels)
                                               # and the circular scan; bp on the dense case takes minutes
    python -m bench.ffbp_sweep --scale 0.25    # the dense scan shrunk to 32 x 32 stops (a quick look)
    python -m bench.ffbp_sweep --cases circular --settings "depth=3,oversample=2" "oversample=3"

The cases are those of the formation benchmark: ``dense`` is N x N stops
at 0.75 m / 127 pitch (N = 128 x scale) and 2N x 2N x N voxels of half that pitch from 1 m
away, six reflectors; ``circular`` is 360 stops on a 1 m circle around three reflectors, a
0.4 x 0.4 x 0.1 m grid of 5 mm. Where :mod:`bench.formation` is installed its
``make_case`` builds them and the error is taken inside its well-sampled cone
(:func:`clsas.formation.planar.well_sampled_cone`); otherwise the same cases are built here
and the mask is the voxels whose lateral position lies inside the aperture shrunk by 15 % of
its side on each edge (the circular case has no cone: the whole grid). The JSON and Markdown
say which mask was used.

Each formation runs once after a warm-up (kernels built outside the timing); the profiles
are computed once, outside the timing. Times are wall times of ``form()`` (plan included).
Record the machine's load with the numbers: the script stores ``os.getloadavg()``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import clsas
from clsas.formation import error_to_signal_db, form

FS = 96e3
PITCH = 0.75 / 127
DEFAULT_SETTINGS = [
    "oversample=1.5,range_oversample=1.5",
    "oversample=2,range_oversample=2",
    "oversample=2.5,range_oversample=2.5",
    "order=5,oversample=1.5,range_oversample=1.5",
    "order=5,oversample=2,range_oversample=2",
    "factor=8,order=5,oversample=1.5,range_oversample=1.5",
]


def _chirp():
    return clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1), {"f_start_hz": 20e3, "f_stop_hz": 30e3,
                                                              "duration_s": 2e-3}


def _own_case(name: str, scale: float):
    w, chirp = _chirp()
    if name == "dense":
        n = max(8, int(round(128 * scale)))
        side = PITCH * (n - 1)
        ap = clsas.raster_aperture(n, n, side, side)
        grid = clsas.VoxelGrid(np.linspace(-side / 2, side / 2, 2 * n), np.linspace(-side / 2, side / 2, 2 * n),
                               1.0 + side / (2 * n - 1) * np.arange(n))
        rng = np.random.default_rng(0)
        z0, z1 = grid.z_m[0], grid.z_m[-1]
        pts = np.c_[rng.uniform(-0.25 * side, 0.25 * side, (6, 2)),
                    rng.uniform(z0 + 0.2 * (z1 - z0), z1 - 0.2 * (z1 - z0), 6)]
        ds = clsas.simulate(clsas.Scene(pts, rng.uniform(0.5, 1.0, 6)), ap, w, FS, snr_db=30, chirp=chirp)
        return ds, grid, f"dense planar: {n} x {n} stops over {side:.2f} m, {2 * n} x {2 * n} x {n} voxels"
    ap = clsas.circular_aperture(360, 1.0, mode="arc")
    pts = np.array([[0.05, -0.03, 0.0], [-0.08, 0.06, 0.02], [0.0, 0.1, -0.02]])
    ds = clsas.simulate(clsas.Scene(pts), ap, w, FS, snr_db=30, chirp=chirp)
    grid = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (-0.2, 0.2), (-0.05, 0.05), 0.005)
    return ds, grid, "circular: 360 stops on a 1 m circle, 3 reflectors, 5 mm grid"


def case(name: str, scale: float):
    """(dataset, grid, description, mask, mask description)."""
    try:
        from bench.formation import make_case
        from clsas.formation.planar import NotPlanarUniform, well_sampled_cone
    except ImportError:
        ds, grid, text = _own_case(name, scale)
        if name == "dense":
            side = PITCH * (int(round(max(8, 128 * scale))) - 1)
            lim = side / 2 - 0.15 * side
            x, y = grid.x_m[:, None, None], grid.y_m[None, :, None]
            mask = np.broadcast_to((np.abs(x) <= lim) & (np.abs(y) <= lim), grid.shape)
            return ds, grid, text, mask, "lateral position inside the aperture shrunk by 15 % of its side per edge"
        return ds, grid, text, None, "whole grid (no lattice, no cone)"
    ds, grid, text = make_case(name, scale)
    try:
        mask = well_sampled_cone(ds.tx_positions, ds.rx_positions, grid, 30e3, float(np.mean(ds.c_mps)))
        return ds, grid, text, mask, "well-sampled cone of clsas.formation.planar (30 kHz, margin 0.8)"
    except NotPlanarUniform:
        return ds, grid, text, None, "whole grid (no lattice, no cone)"


def parse_setting(text: str) -> dict:
    out = {}
    for item in filter(None, text.split(",")):
        key, _, val = item.partition("=")
        val = val.strip()
        out[key.strip()] = int(val) if val.lstrip("-").isdigit() else (None if val == "None" else
                                                                     float(val) if val[0].isdigit() else val)
    return out


def run(cases, scale: float, settings: list[str], backend: str | None, say=print, reuse_bp: str | None = None) -> dict:
    result = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "host": platform.node(), "python": sys.version.split()[0],
              "clsas": clsas.__version__, "load_before": os.getloadavg(), "scale": scale, "cases": []}
    small = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (0.98, 1.0), 0.01)
    warm = clsas.compress(_own_case("dense", 0.1)[0])
    form(warm, small, "bp", backend=backend)
    for name in cases:
        ds, grid, text, mask, mask_text = case(name, scale)
        say(f"{name}: {text}; mask: {mask_text}")
        plan = clsas.types.rangegate.plan_reconstruction(ds, grid, [])
        prof = clsas.compress(ds, gate_s=plan.gate_s, backend=backend)
        row = {"case": name, "description": text, "mask": mask_text, "n_meas": prof.n_meas, "grid": list(grid.shape),
               "mask_fraction": None if mask is None else float(np.mean(mask)), "runs": []}
        cached = None if reuse_bp is None else Path(reuse_bp) / f"bp-{name}-x{scale:g}.npz"
        if cached is not None and cached.is_file():
            z = np.load(cached)
            ref = clsas.Image(z["values"], grid, "bp", str(z["backend"]), str(z["device"]))
            row["bp_s"], row["bp_reused"] = float(z["time_s"]), f"{cached} ({z['date']}, load {z['load']:.1f})"
            row["load_after_bp"] = (float(z["load"]),) * 3
            say(f"  bp: reused {cached}: {row['bp_s']:.1f} s measured {z['date']}")
        else:
            t = time.perf_counter()
            ref = form(prof, grid, "bp", backend=backend)
            row["bp_s"] = time.perf_counter() - t
            row["load_after_bp"] = os.getloadavg()
            if cached is not None:
                cached.parent.mkdir(parents=True, exist_ok=True)
                np.savez(cached, values=ref.values, time_s=row["bp_s"], backend=ref.backend, device=ref.device,
                         date=result["date"], load=row["load_after_bp"][0])
        row["backend"], row["device"] = ref.backend, ref.device
        say(f"  bp: {row['bp_s']:.1f} s on {ref.device} (load {row['load_after_bp'][0]:.1f})")
        for s in settings:
            opts = parse_setting(s)
            form(warm, small, "ffbp", backend=backend, **{k: val for k, val in opts.items() if k != "depth"})
            t = time.perf_counter()
            try:
                img = form(prof, grid, "ffbp", backend=backend, **opts)
            except ValueError as exc:
                row["runs"].append({"setting": s, "refused": str(exc)})
                say(f"  ffbp {s}: refused: {exc}")
                continue
            el = time.perf_counter() - t
            tree = img.plan
            run_row = {"setting": s, "depth": tree.depth, "time_s": el, "speedup": row["bp_s"] / el,
                       "error_db": error_to_signal_db(img.values, ref.values, mask),
                       "error_grid_db": error_to_signal_db(img.values, ref.values),
                       "samples_per_level": [lev.samples for lev in tree.levels],
                       "timings_s": {k: float(val) for k, val in img.timings_s.items()}, "load": os.getloadavg()}
            row["runs"].append(run_row)
            say(f"  ffbp {s} (depth {tree.depth}): {el:.2f} s, {run_row['speedup']:.1f}x, "
                f"{run_row['error_db']:.1f} dB in the mask, {run_row['error_grid_db']:.1f} dB on the grid "
                f"(load {run_row['load'][0]:.1f})")
        result["cases"].append(row)
    result["load_after"] = os.getloadavg()
    return result


def markdown(res: dict) -> str:
    md = [f"# FFBP against exact backprojection ({res['date']}, {res['host']})", "",
          f"Load average before {res['load_before'][0]:.2f}, after {res['load_after'][0]:.2f} "
          "(1 min; a busy machine stretches every time).", ""]
    for c in res["cases"]:
        md += [f"## {c['description']}", "",
               f"{c['n_meas']} measurements, grid {c['grid'][0]} x {c['grid'][1]} x {c['grid'][2]}; "
               f"bp {c['bp_s']:.2f} s on {c['device']} ({c['backend']}"
               + (f"; reused from {c['bp_reused']}" if c.get("bp_reused") else "") + f"). Error mask: {c['mask']}"
               + ("" if c["mask_fraction"] is None else f" ({100 * c['mask_fraction']:.0f} % of the voxels)") + ".",
               "", "| setting | depth | time (s) | speed-up | error in mask (dB) | error, grid (dB) | load |",
               "|---|---|---|---|---|---|---|"]
        for r in c["runs"]:
            if "refused" in r:
                md.append(f"| {r['setting']} | | refused: {r['refused'][:80]} | | | | |")
                continue
            md.append(f"| {r['setting']} | {r['depth']} | {r['time_s']:.2f} | {r['speedup']:.1f}x | "
                      f"{r['error_db']:.1f} | {r['error_grid_db']:.1f} | {r['load'][0]:.1f} |")
        md.append("")
    return "\n".join(md)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["dense", "circular"], choices=["dense", "circular"])
    ap.add_argument("--scale", type=float, default=1.0, help="dense scan's sides x this (default 1: 128 x 128)")
    ap.add_argument("--settings", nargs="+", default=DEFAULT_SETTINGS,
                    help='ffbp options, e.g. "depth=5,oversample=2" (default: a sweep)')
    ap.add_argument("--backend", default=None, choices=["auto", "opencl", "numpy"])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--reuse-bp", metavar="DIR", default=None,
                    help="keep each case's bp image and time in DIR and reuse them on later runs (bp on the "
                         "dense case takes minutes; the speed-ups then compare runs made at different times)")
    args = ap.parse_args(argv)
    res = run(args.cases, args.scale, args.settings, args.backend, reuse_bp=args.reuse_bp)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = "" if args.scale == 1 else f"-x{args.scale:g}"
    stem = out / f"{time.strftime('%Y-%m-%d')}-ffbp-sweep-{platform.node()}{suffix}"
    Path(f"{stem}.json").write_text(json.dumps(res, indent=1))
    Path(f"{stem}.md").write_text(markdown(res))
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
