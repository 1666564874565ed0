"""Why beam-limited bp and omega-k disagree on the directional-transducer case.

    python -m bench.beams_agreement [--out bench/results]

On :func:`bench.beams.make_case` (water, 1-4 MHz, 6 mm pistons, a flat surface at 30 mm
and two pins), for each beam mode (``limited``, ``weighted``, ``none``):

1. bp against omega-k (complex error-to-signal, |.|-correlation) at the case's 1.5 mm pitch
   (2.5 wavelengths at 2.5 MHz) and at half of it (32 x 32 stops at 0.75 mm, the same side):
   if bp's sparse sum over the few stops in a beam were the cause, the finer pitch would close
   the gap;
2. the same on a grid over the beam's footprint with the depth sampled at 0.25, 0.1 and 0.05
   mm (omega-k's folded kz axis against bp's samples), with the ratio of the two images'
   brightest voxels.

The scale that decides it: a stop's beam (gate at -12 dB two-way, about sin theta = 0.07 at
2.5 MHz) covers a disc of radius ``z sin theta`` on the surface at depth ``z``; the first Fresnel
zone of a flat reflector has radius ``sqrt(lambda z / 2)``. Printed per depth: their ratio.
Omega-k weights each plane wave by the beam at its angle (a smooth filter of the whole
aperture); bp keeps the stops whose beams see the voxel. The two are the same operation where
the footprint spans many Fresnel zones (far beyond the transducer's far-field distance
``D^2 / lambda``), and differ where it does not.

Writes ``<date>-beams-agreement.{json,md}`` under --out.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import time
from pathlib import Path

import numpy as np

import clsas
from bench import beams as B
from bench.stats import jsonable
from clsas.formation import error_to_signal_db, form

MODES = ("limited", "weighted", "none")


def pitch_rows() -> list[dict]:
    rows = []
    for n, pitch in ((16, 1.5e-3), (32, 0.75e-3)):
        prof, grid, what = B.make_case(n, pitch)
        for mode in MODES:
            bp = form(prof, grid, "bp", beam=mode).values
            ok = form(prof, grid, "omega-k", beam=mode).values
            rows.append({"stops": n, "pitch_m": pitch, "what": what, "beam": mode,
                         "bp_vs_omega_k_db": error_to_signal_db(bp, ok), "abs_corr": B._abs_corr(bp, ok),
                         "surface_share_bp": B._surface_share(bp, grid),
                         "surface_share_omega_k": B._surface_share(ok, grid)})
            print(rows[-1], flush=True)
    return rows


def depth_rows() -> list[dict]:
    prof, _, _ = B.make_case(16, 1.5e-3)
    rows = []
    for dz in (0.25e-3, 0.1e-3, 0.05e-3):
        lat = np.arange(-3e-3, 3e-3 + 1e-9, 0.25e-3)
        grid = clsas.VoxelGrid(lat, lat, np.arange(0.026, 0.034 + 1e-9, dz))
        for mode in MODES:
            bp = form(prof, grid, "bp", beam=mode).values
            ok = form(prof, grid, "omega-k", beam=mode).values
            rows.append({"dz_m": dz, "beam": mode, "bp_vs_omega_k_db": error_to_signal_db(bp, ok),
                         "peak_ratio_omega_k_over_bp": float(np.abs(ok).max() / np.abs(bp).max())})
            print(rows[-1], flush=True)
    return rows


def fresnel_rows(sin_beam: float = 0.069, f_hz: float = 2.5e6, d_m: float = 6e-3) -> list[dict]:
    lam = B.C_WATER / f_hz
    return [{"depth_m": z, "footprint_radius_m": z * sin_beam, "fresnel_radius_m": math.sqrt(lam * z / 2),
             "ratio": z * sin_beam / math.sqrt(lam * z / 2), "far_field_m": d_m**2 / lam}
            for z in (0.03, 0.1, 0.3, 1.0, 3.0)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    t = time.perf_counter()
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": clsas.cl.select("auto").device,
           "load_before": os.getloadavg(), "pitch": pitch_rows(), "depth": depth_rows(), "fresnel": fresnel_rows()}
    res["time_s"] = time.perf_counter() - t
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{dt.date.today()}-beams-agreement"
    stem.with_suffix(".json").write_text(json.dumps(jsonable(res), indent=1))
    md = [f"# Beam-limited bp against omega-k on the directional case, {res['date']}", "",
          f"Device: {res['device']}; load before {res['load_before']}; {res['time_s']:.0f} s. Script: "
          "`bench/beams_agreement.py` (see its docstring).", "",
          "## 1. Pitch: the error does not close at half the pitch", "",
          "| stops | pitch | beam | bp vs omega-k | abs-corr | surface within a voxel, bp / omega-k |",
          "|---|---|---|---|---|---|"]
    md += [f"| {r['stops']} x {r['stops']} | {r['pitch_m'] * 1e3:.2f} mm | {r['beam']} | "
           f"{r['bp_vs_omega_k_db']:.1f} dB | {r['abs_corr']:.3f} | {100 * r['surface_share_bp']:.0f} % / "
           f"{100 * r['surface_share_omega_k']:.0f} % |"
           for r in res["pitch"]]
    md += ["", "## 2. Depth sampling: nor at a finer z (a 6 x 6 mm grid over the surface)", "",
           "| dz | beam | bp vs omega-k | brightest voxel, omega-k / bp |", "|---|---|---|---|"]
    md += [f"| {r['dz_m'] * 1e3:.2f} mm | {r['beam']} | {r['bp_vs_omega_k_db']:.1f} dB | "
           f"{r['peak_ratio_omega_k_over_bp']:.2f} |" for r in res["depth"]]
    md += ["", "## 3. The scale: a beam's footprint against the first Fresnel zone (2.5 MHz, 6 mm piston)", "",
           "| depth | footprint radius | Fresnel radius | ratio |", "|---|---|---|---|"]
    md += [f"| {r['depth_m']:g} m | {r['footprint_radius_m'] * 1e3:.1f} mm | {r['fresnel_radius_m'] * 1e3:.1f} mm | "
           f"{r['ratio']:.2f} |" for r in res["fresnel"]]
    md += ["", f"The transducer's far-field distance D^2 / lambda is {res['fresnel'][0]['far_field_m'] * 1e3:.0f} mm."]
    stem.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
