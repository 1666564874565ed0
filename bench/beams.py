"""Directional transducers: a simulated MHz scan in water of a flat surface and pins
under a coarse planar raster, imaged by every formation with and without the beam model, a
dense line scan (omega-k's 2-D Stolt step against bp), and FFBP on a 1e6-voxel grid.

Run ``python -m bench.beams [--quick] [--out bench/results]``; the formation table of
``python -m bench --formation`` has the directional case too (:func:`make_case`).

Measured per image, inside the beam's footprint (the columns over the stops' extent):

- ``surface_share``: columns whose brightest voxel lies within one voxel of the true surface;
- ``error_vs_*_db``: complex error-to-signal against bp with the beam model (``beam="limited"``)
  and against omega-k with it, :func:`clsas.formation.error_to_signal_db`, no rescaling;
- ``abs_corr_vs_omega_k``: the ``|.|``-correlation with omega-k's image (the measure this case is judged by).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

import clsas
from clsas.formation import error_to_signal_db, form
from clsas.physics.beam import Beams, Piston
from clsas.physics.specular import Surface

from .stats import jsonable

__all__ = ["make_case", "run", "markdown", "write", "C_WATER"]

log = logging.getLogger(__name__)

C_WATER = 1480.0
FS = 12.5e6
DEPTH = 0.030  # the surface, m
VOXEL = 0.25e-3


def _chirp():
    return clsas.lfm_chirp(1e6, 4e6, 4e-6, FS, taper=0.2)


@functools.lru_cache(maxsize=2)
def make_case(n: int = 16, pitch: float = 1.5e-3, facet: float = 1e-3):
    """(profiles, grid, description): ``n`` x ``n`` stops at ``pitch`` (2.5 wavelengths at 2.5 MHz
    for 1.5 mm), 6 mm pistons facing +z, a rigid flat surface at 30 mm cut into ``facet`` facets,
    two faint pins above it; the grid covers the central 14 mm at 0.25 mm."""
    side = (n - 1) * pitch
    ap = clsas.raster_aperture(n, n, side, side, tx_offset_m=(0, 0, 0), rx_offset_m=(0, 0, 0))
    beams = Beams(Piston(6e-3), Piston(6e-3), (0, 0, 1), (0, 0, 1), ap.n_meas)
    surf = Surface.plane((0, 0, DEPTH), (side + 0.014, side + 0.014), facet)
    pins = clsas.Scene(np.array([[0.002, -0.003, 0.022], [-0.004, 0.002, 0.025]]), np.array([0.002, 0.002]))
    ds = clsas.simulate(pins, ap, _chirp(), FS, beams=beams, surfaces=[surf], c_mps=C_WATER)
    h = min(7e-3, side / 2)
    grid = clsas.VoxelGrid.from_bounds((-h, h), (-h, h), (0.018, 0.034), VOXEL)
    what = (f"water, 1-4 MHz, {n} x {n} stops at {pitch * 1e3:.1f} mm "
            f"({pitch * 2.5e6 / C_WATER:.1f} wavelengths at 2.5 MHz), 6 mm pistons, flat surface at 30 mm "
            f"({surf.n_facets} facets of {facet * 1e3:.1f} mm) + 2 pins, {grid.size} voxels of {VOXEL * 1e3} mm")
    return clsas.compress(ds), grid, what


ROWS = (("bp", {"beam": "none"}), ("bp", {"beam": "limited"}), ("bp", {"beam": "weighted"}),
        ("omega-k", {"beam": "none"}), ("omega-k", {"beam": "limited"}), ("omega-k", {"beam": "weighted"}),
        ("ffbp", {"beam": "none"}), ("ffbp", {"beam": "limited"}), ("ffbp", {"beam": "weighted"}),
        ("ffbp", {"beam": "limited", "oversample": 8.0}), ("ffbp", {"beam": "weighted", "oversample": 8.0}))


def _beam_label(opts: dict) -> str:
    """The table's beam column: the mode, and any other option (``limited, oversample=8``)."""
    return ", ".join([opts.get("beam", "default")] + [f"{k}={v:g}" for k, v in opts.items() if k != "beam"])


def _surface_share(values: np.ndarray, grid) -> float:
    z = grid.z_m[np.abs(values).argmax(axis=2)]
    return float(np.mean(np.abs(z - DEPTH) <= VOXEL + 1e-9))


def _abs_corr(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.abs(a).ravel(), np.abs(b).ravel()
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def run_planar(n: int = 16) -> dict:
    """Every row of :data:`ROWS` on :func:`make_case`."""
    prof, grid, what = make_case(n)
    out = {"case": "directional", "what": what, "measurements": prof.n_meas, "voxels": grid.size, "rows": []}
    images = {}
    for name, opts in ROWS:
        label = f"{name} {_beam_label(opts)}"
        row = {"formation": name, "options": opts, "label": label}
        t = time.perf_counter()
        try:
            img = form(prof, grid, name, **opts)
        except ValueError as exc:
            row["refused"] = str(exc)
            out["rows"].append(row)
            continue
        row["time_s"] = time.perf_counter() - t
        row["backend"] = img.backend
        row["surface_share"] = _surface_share(img.values, grid)
        images[label] = img.values
        out["rows"].append(row)
    ref_bp, ref_ok = images["bp limited"], images["omega-k limited"]
    for row in out["rows"]:
        if row["label"] in images:
            val = images[row["label"]]
            row["error_vs_bp_limited_db"] = error_to_signal_db(val, ref_bp)
            row["error_vs_omega_k_limited_db"] = error_to_signal_db(val, ref_ok)
            row["abs_corr_vs_omega_k"] = _abs_corr(val, ref_ok)
            same = images.get(f"bp {row['options'].get('beam', 'limited')}")
            row["error_vs_bp_same_beam_db"] = None if same is None else error_to_signal_db(val, same)
    return out


def run_floors(n: int = 16, floors=(-6.0, -12.0, -20.0, -30.0)) -> list[dict]:
    """bp and omega-k, both ``beam="limited"``, at several floors: their agreement and bp's surface."""
    prof, grid, _ = make_case(n)
    rows = []
    for fl in floors:
        bp = form(prof, grid, "bp", beam="limited", beam_floor_db=fl).values
        ok = form(prof, grid, "omega-k", beam="limited", beam_floor_db=fl).values
        rows.append({"floor_db": fl, "error_db": error_to_signal_db(bp, ok), "abs_corr": _abs_corr(bp, ok),
                     "surface_share": _surface_share(bp, grid)})
    return rows


def run_line(n: int = 64, pitch: float = 0.15e-3) -> dict:
    """Omega-k on a 2-D line scan (lambda/4 at 2.5 MHz) of four pins against bp."""
    ap = clsas.raster_aperture(n, 1, (n - 1) * pitch, 0.0, tx_offset_m=(0, 0, 0), rx_offset_m=(0, 0, 0))
    pins = np.array([[-1.5e-3, 0, 0.012], [0.5e-3, 0, 0.014], [2e-3, 0, 0.016], [0, 0, 0.018]])
    prof = clsas.compress(clsas.simulate(clsas.Scene(pins), ap, _chirp(), FS, c_mps=C_WATER))
    grid = clsas.VoxelGrid.from_bounds((-4e-3, 4e-3), (0, 0), (0.010, 0.020), 0.1e-3)
    t = time.perf_counter()
    ref = form(prof, grid, "bp")
    t_bp = time.perf_counter() - t
    t = time.perf_counter()
    img = form(prof, grid, "omega-k")
    t_ok = time.perf_counter() - t
    return {"case": "line", "what": f"line of {n} stops at {pitch * 1e3:.2f} mm, 4 pins, {grid.size} voxels",
            "bp_s": t_bp, "omega_k_s": t_ok, "error_db": error_to_signal_db(img, ref),
            "abs_corr": _abs_corr(img.values, ref.values)}


def run_ffbp_large(n: int = 16, voxel: float = 0.15e-3) -> dict:
    """FFBP at its defaults (beams off) against bp without beams on a ~1e6-voxel grid."""
    prof, _, what = make_case(n)
    grid = clsas.VoxelGrid.from_bounds((-7e-3, 7e-3), (-7e-3, 7e-3), (0.018, 0.034), voxel)
    out = {"case": "ffbp-1e6", "what": what.split(", flat")[0], "voxels": grid.size}
    t = time.perf_counter()
    ref = form(prof, grid, "bp", beam="none")
    out["bp_s"] = time.perf_counter() - t
    t = time.perf_counter()
    try:
        img = form(prof, grid, "ffbp", beam="none")
    except ValueError as exc:
        out["refused"] = str(exc)
        return out
    out["ffbp_s"] = time.perf_counter() - t
    out["error_db"] = error_to_signal_db(img, ref)
    out["samples_per_level"] = img.provenance["ffbp"]["samples_per_level"]
    return out


def run(quick: bool = False) -> dict:
    load = os.getloadavg()
    res = {"device": clsas.cl.select("auto").device, "load_before": load,
           "planar": run_planar(12 if quick else 16), "line": run_line(32 if quick else 64),
           "floors": run_floors(12 if quick else 16)}
    if not quick:
        res["ffbp"] = run_ffbp_large()
    res["load_after"] = os.getloadavg()
    return res


def _db(x) -> str:
    return "n/a" if x is None else f"{x:.1f} dB"


def markdown(res: dict) -> list[str]:
    p = res["planar"]
    lines = ["# Directional transducers", "", f"Device: {res['device']}; load (1, 5, 15 min) "
             f"before {res['load_before']}, after {res['load_after']}.", "", f"## {p['what']}", "",
             "| formation | beam | time | surface within one voxel | vs bp limited | vs omega-k limited | "
             "abs-corr vs omega-k | vs bp, same beam |", "|---|---|---|---|---|---|---|---|"]
    for r in p["rows"]:
        if "refused" in r:
            lines.append(f"| {r['formation']} | {_beam_label(r['options'])} | refused: "
                         f"{r['refused'][:80]}... | | | | | |")
            continue
        vs_bp = "reference" if r["label"] == "bp limited" else _db(r["error_vs_bp_limited_db"])
        vs_ok = "reference" if r["label"] == "omega-k limited" else _db(r["error_vs_omega_k_limited_db"])
        lines.append(f"| {r['formation']} | {_beam_label(r['options'])} | {r['time_s']:.2f} s | "
                     f"{100 * r['surface_share']:.0f} % | {vs_bp} | {vs_ok} | {r['abs_corr_vs_omega_k']:.3f} | "
                     f"{'-' if r['formation'] == 'bp' else _db(r.get('error_vs_bp_same_beam_db'))} |")
    lines += ["", "bp and omega-k, both beam-limited, by floor (the whole grid lies in the beams' footprint):", "",
              "| beam_floor_db | bp vs omega-k | abs-corr | bp surface within one voxel |", "|---|---|---|---|"]
    lines += [f"| {r['floor_db']:g} | {_db(r['error_db'])} | {r['abs_corr']:.3f} | {100 * r['surface_share']:.0f} % |"
              for r in res["floors"]]
    ln = res["line"]
    lines += ["", f"## Line scan: {ln['what']}", "", f"omega-k {ln['omega_k_s']:.2f} s, bp {ln['bp_s']:.2f} s; "
              f"omega-k vs bp {_db(ln['error_db'])}, abs-corr {ln['abs_corr']:.4f}."]
    if "ffbp" in res:
        f = res["ffbp"]
        body = (f"refused: {f['refused']}" if "refused" in f else
                f"bp {f['bp_s']:.1f} s, ffbp {f['ffbp_s']:.1f} s ({f['bp_s'] / f['ffbp_s']:.2f}x), ffbp vs bp "
                f"{_db(f['error_db'])}, sub-image samples per level {f['samples_per_level']}")
        lines += ["", f"## FFBP at its defaults on {f['voxels']} voxels ({f['what']}, beams off)", "", body]
    return lines


def write(res: dict, out_dir, stem: str = "beams") -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / f"{stem}.json", "md": out / f"{stem}.md"}
    paths["json"].write_text(json.dumps(jsonable(res), indent=1))
    paths["md"].write_text("\n".join(markdown(res)) + "\n")
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default="bench/results")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    res = run(args.quick)
    stem = time.strftime("%Y-%m-%d-beams") + ("-quick" if args.quick else "")
    for path in write(res, args.out, stem).values():
        log.warning("wrote %s", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
