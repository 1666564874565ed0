"""What separates clsas's AirSAS 20k image from the owners' delay-and-sum, one ingredient at a time.

    python -m bench.airsas_ablation /work/data/airsas [--scan 20k] [--out bench/results]

DATA as for ``bench/airsas_compare.py`` (a local copy of github.com/awreed/CSAS_Deconvolution_INR).
Starting from the guide's pipeline (import -> preprocess with ``dc, bandpass, direct_clock,
background, common, blank_direct`` -> reconstruct; clsas's geometry from ``SysParams.csv``), each
row swaps ingredients for the owners' (``sim_csas_package`` and ``airsas_utils``, as ported in
``airsas_compare.owners_das``) and measures the image against their ``scene.npy`` on their pixels
(|.|-correlation on the disc, their 5 strongest peaks within 3 mm, TCR in the target box):

- ``clock``: the clock from the direct sound (clsas) or ``Group Delay`` as stated (theirs);
- ``radius``: ``SysParams.csv`` (speaker 0.8485 m, microphone 0.8615 m) or 0.85 m for both;
- ``c``: clsas's (``clsas.speed_of_sound`` at the Dataset's humidity: since 2026-11-27 humid air,
  Cramer's humid/dry ratio on 331.3 sqrt(1 + T / 273.15), at an assumed 50 % RH; before, dry) or
  331.4 + 0.6 T (theirs), T per ping; or, for scale, Cramer's (1993) own absolute value for air at
  50 % relative humidity (``clsas.physics.sound.cramer_speed_of_sound``; the scans log no humidity);
- ``common``: clsas's mean over pings, or their weighted removal (``owners_common``);
- ``blank``: clsas's direct-path blanking, or none (theirs);
- ``filters``: clsas's DC removal and band-pass, or none (theirs: the matched filter alone).

It also states what the data say about the geometry on their own: where the direct
speaker-to-microphone sound arrives against each geometry's prediction.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import clsas  # noqa: E402
import clsas.io  # noqa: E402
from bench.airsas_compare import (
    OWNERS_RADIUS_M,
    SCANS,
    image,
    metrics,
    owners_das,
    owners_scene,
    to_clsas,
)
from clsas import preprocess as pp  # noqa: E402
from clsas.focus.direct import direct_arrivals  # noqa: E402
from clsas.physics.sound import cramer_speed_of_sound  # noqa: E402

CLSAS = {"clock": "direct", "radius": "sysparams", "c": "clsas", "common": "mean", "blank": True, "filters": True}
ROWS = [
    ("guide's pipeline (clsas throughout)", {}),
    ("their c formula", {"c": "owners"}),
    ("Group Delay as stated (no direct clock)", {"clock": "stated"}),
    ("their radius 0.85 m, direct clock", {"radius": "owners"}),
    ("their shared-response removal", {"common": "owners"}),
    ("no direct-path blanking", {"blank": False}),
    ("no DC / band-pass", {"filters": False}),
    ("their radius and clock", {"radius": "owners", "clock": "stated"}),
    ("their radius, clock and c", {"radius": "owners", "clock": "stated", "c": "owners"}),
    ("... and their shared-response removal", {"radius": "owners", "clock": "stated", "c": "owners",
                                               "common": "owners"}),
    ("... and no blanking", {"radius": "owners", "clock": "stated", "c": "owners", "common": "owners",
                             "blank": False}),
    ("... and no DC / band-pass (all theirs but the matched filter and interpolation)",
     {"radius": "owners", "clock": "stated", "c": "owners", "common": "owners", "blank": False, "filters": False}),
    ("c of air at 50 % RH (Cramer 1993 absolute; not logged)", {"c": "humid50"}),
    ("c of air at 50 % RH (Cramer absolute), Group Delay as stated", {"c": "humid50", "clock": "stated"}),
]


def owners_common(signals: np.ndarray) -> np.ndarray:
    """Their removal of what every ping shares: the mean over pings, subtracted where a sample
    agrees with it in sign and size, much less where it does not (``airsas_compare.owners_das``)."""
    cm = signals.mean(axis=0, keepdims=True)
    beta = np.where(np.sign(cm) == np.sign(signals), 1.0, 1.0 / (1.0 + np.pi**2))
    alpha = 1.0 / (1.0 + (np.abs(cm) - np.abs(signals)) ** 2)
    return signals - alpha * beta * np.abs(cm) * np.sign(signals)


def dataset(scan: Path, bg: Path, opts: dict) -> clsas.Dataset:
    """The scan with the chosen ingredients (``CLSAS`` keys), ready to image."""
    o = {**CLSAS, **opts}
    ds = clsas.io.import_airsas(scan, background=bg, radius_m=OWNERS_RADIUS_M if o["radius"] == "owners" else None)
    if o["c"] == "owners":
        ds = ds.replace(c_mps=331.4 + 0.6 * np.asarray(ds.temperature_c, float))
    elif o["c"] == "humid50":
        ds = ds.replace(c_mps=cramer_speed_of_sound(ds.temperature_c, 50.0))
    ds = pp.apply(ds, direct_clock=o["clock"] == "direct", dc=o["filters"], bandpass=o["filters"], background=True,
                  common=o["common"] == "mean", blank_direct=False)
    if o["common"] == "owners":
        ds = ds.replace(signals=owners_common(ds.signals))
    return pp.blank_direct(ds) if o["blank"] else ds


def direct_sound(scan: Path, bg: Path) -> dict:
    """The direct sound's arrival (median over pings, after DC and band-pass) against what each
    geometry predicts with ``Group Delay`` as stated: measured minus predicted, s."""
    out = {}
    for name, radius in (("sysparams", None), ("owners_0.85m", OWNERS_RADIUS_M)):
        ds = pp.apply(clsas.io.import_airsas(scan, radius_m=radius), dc=True, bandpass=True)
        arr = direct_arrivals(ds)
        spacing = np.linalg.norm(ds.tx_positions - ds.rx_positions, axis=1)
        out[name] = {"speaker_mic_spacing_m": float(np.median(spacing)),
                     "measured_minus_predicted_s": _median_offset(arr, ds, spacing)}
    return out


def _median_offset(arr, ds: clsas.Dataset, spacing: np.ndarray) -> float:
    """Median over the pings where it was detected of (arrival after sample 0) - (|tx - rx| / c - t0)."""
    off = arr.arrival_s - (spacing / ds.c_per_meas - ds.t0_s)
    return float(np.median(off[arr.detected]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--scan", default="20k", choices=list(SCANS))
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    root = args.data / "airsas_deconv_pipeline" if (args.data / "airsas_deconv_pipeline").is_dir() else args.data
    scan, bg = (root / "airsas_data" / f for f in SCANS[args.scan])
    shipped = root / f"{args.scan}_scene" / "scene.npy"
    theirs = to_clsas(owners_scene(shipped)) if shipped.is_file() else to_clsas(owners_das(scan, bg))
    out = {"date": time.strftime("%Y-%m-%d"), "host": platform.node() or "unknown", "backend": args.backend,
           "scan": args.scan, "reference": "scene.npy" if shipped.is_file() else "port of their delay-and-sum",
           "c_at_mean_temperature_mps": {}, "direct_sound": direct_sound(scan, bg), "rows": []}
    temp = float(np.mean(clsas.io.import_airsas(scan).temperature_c))
    out["c_at_mean_temperature_mps"] = {"temperature_c": temp, "clsas": float(clsas.speed_of_sound(temp, 50.0)),
                                        "clsas_dry": float(clsas.speed_of_sound(temp)), "owners": 331.4 + 0.6 * temp,
                                        "cramer_dry": float(cramer_speed_of_sound(temp, 0.0)),
                                        "cramer_50pct_rh": float(cramer_speed_of_sound(temp, 50.0))}
    for label, opts in ROWS:
        t = time.perf_counter()
        m = metrics(image(dataset(scan, bg, opts), args.backend), theirs)
        out["rows"].append({"label": label, "options": {**CLSAS, **opts}, **m, "time_s": time.perf_counter() - t})
        print(f"{label}: {m['abs_correlation']:.3f}, {m['peaks_within_3mm']}/5", flush=True)
    out["load_average_1_5_15_min"] = list(os.getloadavg())  # what else ran on the machine (uptime)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{out['date']}-airsas-ablation-{args.scan}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".md").write_text(markdown(out))
    print(markdown(out))
    return 0


def markdown(out: dict) -> str:
    load = ", ".join(f"{x:.1f}" for x in out.get("load_average_1_5_15_min", []))
    lines = [f"# AirSAS {out['scan']}: clsas against the owners' {out['reference']}, one ingredient at a time "
             f"({out['date']}, {out['host']}, backend {out['backend']}; load average at the end {load})", "",
             "| variant | \\|.\\|-corr | peaks within 3 mm (mm) | TCR clsas / theirs |", "|---|---|---|---|"]
    for r in out["rows"]:
        d = ", ".join(f"{x:.1f}" for x in r["peak_distances_mm"])
        lines.append(f"| {r['label']} | {r['abs_correlation']:.3f} | {r['peaks_within_3mm']}/5 ({d}) | "
                     f"{r['tcr_db']:.1f} / {r['reference_tcr_db']:.1f} dB |")
    lines.append("")
    c = out["c_at_mean_temperature_mps"]
    dry = f" (dry {c['clsas_dry']:.2f})" if "clsas_dry" in c else ""
    lines.append(f"Speed of sound at the scan's mean {c['temperature_c']:.2f} C: clsas {c['clsas']:.2f}{dry}, theirs "
                 f"{c['owners']:.2f}, Cramer dry {c['cramer_dry']:.2f}, Cramer 50 % RH {c['cramer_50pct_rh']:.2f} m/s.")
    lines.append("")
    for name, d in out["direct_sound"].items():
        spacing_mm, off_us = d["speaker_mic_spacing_m"] * 1e3, d["measured_minus_predicted_s"] * 1e6
        lines.append(f"Direct sound, geometry {name}: speaker-microphone spacing {spacing_mm:.2f} mm; measured "
                     f"minus predicted arrival {off_us:+.1f} us (Group Delay as stated).")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
