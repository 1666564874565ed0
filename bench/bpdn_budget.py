"""The BPDN budget (default <= 1 s per 1000-sample profile): ``superres(..., method="bpdn")``
on the stress suite's 1000-sample profile (five echoes of the paper's chirp, two of them 2.8
samples apart, in white noise), one seed per profile, with the working-set solver's Newton
polish (the default) and without it (FISTA alone, the solver before), in the same run.

    python -m bench.bpdn_budget [--profiles 20] [--out bench/results/DATE-bpdn-budget-vm]
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
from clsas.sparse import gram, superres

FS = 96e3
TAUS = np.array([100.3, 103.1, 400.0, 640.7, 900.2]) / FS
AMPS = [1.0, 0.6, 0.8, 0.3, 1.0]


def profile(pulse, seed: int, n: int = 1000) -> np.ndarray:
    """The stress suite's long profile (tests/unit/sparse/test_sparse_stress.py's ``_long_profile``)."""
    x = np.zeros(n)
    spec = np.fft.rfft(pulse, 4 * n)
    f = np.fft.rfftfreq(4 * n, 1 / FS)
    for tau, a in zip(TAUS, AMPS, strict=True):
        x += a * np.fft.irfft(spec * np.exp(-2j * np.pi * f * (tau + n / FS)), 4 * n)[n:2 * n]
    return x + 0.02 * np.random.default_rng(seed).normal(size=n)


def run(pulse, seeds, polish: bool, tol: float) -> list[dict]:
    rows = []
    gram.POLISH = polish
    try:
        for s in seeds:
            x = profile(pulse, s)
            t = time.perf_counter()
            e = superres(x, pulse, FS, method="bpdn", tol=tol)
            dt = time.perf_counter() - t
            rows.append({"seed": s, "polish": polish, "tol": tol, "time_s": dt, "status": e.status,
                         "iterations": int(e.iterations), "echoes": len(e), "delays_s": e.delays_s.tolist()})
    finally:
        gram.POLISH = True
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", type=int, default=20)
    ap.add_argument("--out", default=None, help="path stem for .json and .md (default: print only)")
    args = ap.parse_args()
    pulse = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.2)
    seeds = range(args.profiles)
    load = os.getloadavg()[0]
    superres(profile(pulse, 0), pulse, FS, method="bpdn")  # imports and first-call set-up out of the timing
    rows = []
    for tol in (1e-4, 1e-7):
        for polish in (True, False):
            rows += run(pulse, seeds, polish, tol)
            print(tol, polish, "done", flush=True)
    summary = []
    for tol in (1e-4, 1e-7):
        for polish in (True, False):
            g = [r for r in rows if r["tol"] == tol and r["polish"] == polish]
            t = np.array([r["time_s"] for r in g])
            summary.append({"tol": tol, "solver": "FISTA + Newton polish" if polish else "FISTA alone",
                            "median_s": float(np.median(t)), "max_s": float(t.max()), "min_s": float(t.min()),
                            "over_1s": int((t > 1).sum()),
                            "median_iterations": float(np.median([r["iterations"] for r in g])),
                            "max_iterations": int(max(r["iterations"] for r in g)),
                            "statuses": sorted({r["status"] for r in g}),
                            "echo_counts": sorted({r["echoes"] for r in g})})
    same = sum(a["echoes"] == b["echoes"] and np.allclose(a["delays_s"], b["delays_s"], atol=0.5 / FS)
               for a, b in zip([r for r in rows if r["tol"] == 1e-4 and r["polish"]],
                               [r for r in rows if r["tol"] == 1e-4 and not r["polish"]], strict=True))
    meta = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "python": sys.version.split()[0],
            "load_start": load, "load_end": os.getloadavg()[0], "profiles": args.profiles,
            "same_echoes_polish_vs_alone_tol_1e-4": f"{same}/{args.profiles}"}
    lines = [f"BPDN budget, {args.profiles} profiles of 1000 samples (superres, method='bpdn'); load {load:.2f} -> "
             f"{meta['load_end']:.2f}; same echoes with and without the polish at tol 1e-4: "
             f"{meta['same_echoes_polish_vs_alone_tol_1e-4']}",
             "", "| tol | solver | median s | min s | max s | > 1 s | median / max FISTA steps | status |",
             "|---|---|---|---|---|---|---|---|"]
    for c in summary:
        lines.append(f"| {c['tol']:g} | {c['solver']} | {c['median_s']:.3f} | {c['min_s']:.3f} "
                     f"| {c['max_s']:.3f} | {c['over_1s']} | {c['median_iterations']:.0f} / {c['max_iterations']} "
                     f"| {', '.join(c['statuses'])} |")
    print("\n".join(lines))
    if args.out:
        Path(args.out + ".json").write_text(json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=1))
        Path(args.out + ".md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
