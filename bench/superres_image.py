"""``python -m bench --superres-image``: model-based reconstruction against backprojection.

Error against run time for ``bp``, per-profile ``cbp-polar``, ``psf`` (Wiener deconvolution), ``ls``,
``l1``, ``l1-psf`` (L1 on the PSF model of the Gram), ``tv``, ``l1-tv`` and ``offgrid``, in one run:

- simulated point pairs (:func:`pair_trial`): two reflectors ``s`` x the cross-range resolution
  ``lambda R / (2 D)`` apart (``s`` in 0.25, 0.5, 1), random centre, amplitudes in [0.7, 1], 20 dB,
  on a 2-D set-up (a line of stops, the paper's 10-pair room made a well-sampled line) and the
  paper's 3-D rig (18 x 12 stops over 1 m x 1 m); the share of pairs resolved (:func:`resolved`)
  and the RMS position error of the resolved ones, in resolutions;
- measured AirSAS scans (:func:`airsas`): imported and preprocessed exactly as the guide's "Your own
  data" page does it, the target-to-clutter ratio in the target's box, the -6 dB width across the
  target's long edges (:func:`edge_width_mm`), run time, and the pictures side by side.

Benchmarks measure; nothing here asserts.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import clsas

__all__ = ["METHODS", "airsas", "edge_width_mm", "pair_trial", "resolved", "run_noise", "run_superres_image"]

log = logging.getLogger(__name__)

METHODS = ("bp", "cbp-polar", "psf", "ls", "l1", "l1-psf", "tv", "l1-tv", "offgrid")
FC_HZ, C_MPS = 25e3, 343.0
SETUPS = {
    # stops along x (y = 0), range R, aperture D, grid half-widths (x, z) and spacing, m
    "2d-line": {"nx": 31, "ny": 1, "D": 0.3, "H": 0.0, "R": 0.6, "half": (0.03, 0.0, 0.02), "step": 0.002},
    "3d-rig": {"nx": 18, "ny": 12, "D": 1.0, "H": 1.0, "R": 1.5, "half": (0.025, 0.015, 0.02), "step": 0.0025},
}


def resolution_m(setup: dict) -> float:
    """Cross-range resolution ``lambda R / (2 D)`` at the set-up's range, m."""
    return C_MPS / FC_HZ * setup["R"] / (2 * setup["D"])


def pair_trial(name: str, factor: float, seed: int, snr_db: float = 20.0):
    """One simulated pair: ``(dataset, grid, truth (2, 3), resolution_m)``."""
    s = SETUPS[name]
    rng = np.random.default_rng(seed)
    res = resolution_m(s)
    centre = np.array([rng.uniform(-0.2, 0.2) * res, 0.0, s["R"] + rng.uniform(-0.2, 0.2) * res])
    angle = rng.uniform(0, np.pi) if s["ny"] > 1 else 0.0
    d = 0.5 * factor * res * np.array([np.cos(angle), np.sin(angle), 0.0])
    truth = np.array([centre - d, centre + d])
    chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    ap = clsas.raster_aperture(s["nx"], s["ny"], s["D"], s["H"])
    data = clsas.simulate(clsas.Scene(truth, rng.uniform(0.7, 1.0, 2)), ap, chirp, 96e3, snr_db=snr_db, seed=seed)
    hx, hy, hz = s["half"]
    grid = clsas.VoxelGrid.from_bounds((-hx, hx), (-hy, hy), (s["R"] - hz, s["R"] + hz), s["step"])
    return data, grid, truth, res


def _candidates(image, method: str, sep: float) -> list[tuple[np.ndarray, float]]:
    if method == "offgrid":
        from clsas.inverse.offgrid import reflector_peaks

        return [(p.position_m, p.magnitude) for p in reflector_peaks(image)]
    return [(p.position_m, p.magnitude) for p in image.peaks(4, min_separation_m=0.3 * sep)]


def resolved(image, method: str, truth: np.ndarray, res: float) -> tuple[bool, float]:
    """Whether the image shows the two reflectors as two, and the RMS position error (resolutions).

    Two of the strongest peaks (local maxima; off-grid: the reflectors) at or above -6 dB of the
    strongest must lie each within half the separation of a different reflector, and (on the grid)
    the image halfway between them must dip below 0.8 of the weaker one.
    """
    sep = float(np.linalg.norm(truth[1] - truth[0]))
    cands = _candidates(image, method, sep)
    if not cands:
        return False, float("nan")
    top = max(m for _, m in cands)
    strong = [(p, m) for p, m in cands if m >= 0.5 * top]
    best = None
    for i in range(len(strong)):
        for j in range(len(strong)):
            if i == j:
                continue
            e0 = np.linalg.norm(strong[i][0] - truth[0])
            e1 = np.linalg.norm(strong[j][0] - truth[1])
            if e0 <= sep / 2 and e1 <= sep / 2 and (best is None or e0**2 + e1**2 < best[0]):
                best = (e0**2 + e1**2, i, j)
    if best is None:
        return False, float("nan")
    _, i, j = best
    if method != "offgrid":
        mid = 0.5 * (strong[i][0] + strong[j][0])
        g = image.grid
        idx = tuple(int(np.argmin(np.abs(ax - c))) for ax, c in zip((g.x_m, g.y_m, g.z_m), mid, strict=True))
        if np.abs(image.values[idx]) >= 0.8 * min(strong[i][1], strong[j][1]):
            return False, float("nan")
    return True, float(np.sqrt(best[0] / 2) / res)


def run_pairs(name: str, factors, n_trials: int, methods, status: Callable[[str], None], seed0: int = 1000) -> list:
    """Every method on ``n_trials`` pairs per separation factor: share resolved, RMS error, time."""
    rows = []
    for factor in factors:
        acc = {m: {"resolved": 0, "errors": [], "time_s": []} for m in methods}
        for t in range(n_trials):
            data, grid, truth, res = pair_trial(name, factor, seed0 + t)
            for m in methods:
                t0 = time.perf_counter()
                kw = {"inverse": {"max_iter": 30}} if m in ("ls", "l1", "tv", "l1-tv", "offgrid") else {}
                image = clsas.reconstruct(data, grid, method=m, **kw)
                acc[m]["time_s"].append(time.perf_counter() - t0)
                ok, err = resolved(image, m, truth, res)
                acc[m]["resolved"] += int(ok)
                if ok:
                    acc[m]["errors"].append(err)
            status(f"{name} x{factor}: trial {t + 1}/{n_trials}: "
                   + ", ".join(f"{m} {a['resolved']}" for m, a in acc.items()))
        for m, a in acc.items():
            e = np.array(a["errors"])
            rows.append({"setup": name, "factor": factor, "method": m, "trials": n_trials,
                         "resolved_share": a["resolved"] / n_trials,
                         "rms_error_res": float(np.sqrt(np.mean(e**2))) if len(e) else None,
                         "median_time_s": float(np.median(a["time_s"]))})
    return rows


def run_noise(name: str, n_draws: int, status: Callable[[str], None], seed0: int = 5000) -> dict:
    """Pure-noise recordings in the set-up's geometry: the share of draws whose ``"l1"`` image (weight
    from the noise-level rule) holds no reflector at all."""
    from dataclasses import replace

    base, grid, _, _ = pair_trial(name, 0.5, seed0)
    empty = 0
    for i in range(n_draws):
        noise = np.random.default_rng(seed0 + i).normal(size=base.signals.shape)
        image = clsas.reconstruct(replace(base, signals=noise), grid, method="l1", inverse={"seed": seed0 + i})
        empty += int(not np.any(np.asarray(image.values)))
        status(f"{name} pure noise: {empty} of {i + 1} draws empty")
    return {"setup": name, "draws": n_draws, "empty_share": empty / n_draws}


# -- measured ------------------------------------------------------------------------------------------
AIRSAS_SCANS = {"20k": ("small_features_cutout_20k", "bg_20k"), "5k": ("small_features_cutout_5k", "bg_5k")}
AIRSAS_BOX = ((-0.07, 0.07), (-0.11, 0.11))  # the target (cork cut-out) in clsas's frame, as bench/airsas_compare
AIRSAS_EDGES_X = (-0.045, 0.045)  # its long edges (along y)


def airsas_dataset(root: Path, scan: str):
    """The guide's "Your own data" steps for this data: import, then the preprocessing it lists."""
    import clsas.io
    from clsas import preprocess as pp

    folder, bg = (root / "airsas_data" / f for f in AIRSAS_SCANS[scan])
    ds = clsas.io.import_airsas(folder, background=bg)
    return pp.apply(ds, direct_clock=True, dc=True, bandpass=True, background=True, common=True, blank_direct=True)


def tcr_db(mag: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """Target-to-clutter ratio: the peak in the target's box over the RMS outside it, dB."""
    xx, yy = np.meshgrid(x, y, indexing="ij")
    box = (xx >= AIRSAS_BOX[0][0]) & (xx <= AIRSAS_BOX[0][1]) & (yy >= AIRSAS_BOX[1][0]) & (yy <= AIRSAS_BOX[1][1])
    return float(20 * np.log10(mag[box].max() / np.sqrt(np.mean(mag[~box] ** 2))))


def edge_width_mm(mag: np.ndarray, x: np.ndarray, y: np.ndarray, window_m: float = 0.02) -> tuple[float, int]:
    """Median -6 dB width across the target's long edges, mm, and the number of cuts measured.

    Each row (fixed y, within the middle 70 % of the target's length) is cut across each long edge
    (within ``window_m`` of it); the strongest value there, if within 20 dB of the image's peak, is
    the edge, and its full width where the magnitude stays above half of it is measured (linear
    interpolation of both crossings).
    """
    step = float(x[1] - x[0])
    peak = mag.max()
    widths = []
    for j in np.flatnonzero(np.abs(y) < 0.7 * AIRSAS_BOX[1][1]):
        for xe in AIRSAS_EDGES_X:
            sel = np.flatnonzero(np.abs(x - xe) <= window_m)
            row = mag[sel, j]
            k = int(np.argmax(row))
            if row[k] < 0.1 * peak:
                continue
            half = row[k] / 2
            lo, hi = k, k
            while lo > 0 and row[lo] > half:
                lo -= 1
            while hi < len(row) - 1 and row[hi] > half:
                hi += 1
            if row[lo] > half or row[hi] > half:
                continue
            left = lo + (half - row[lo]) / (row[lo + 1] - row[lo])
            right = hi - (half - row[hi]) / (row[hi - 1] - row[hi])
            widths.append((right - left) * step)
    return (float(np.median(widths) * 1e3) if widths else float("nan")), len(widths)


def airsas(root: Path, scan: str, methods, status: Callable[[str], None], step_m: float = 0.0015,
           max_iter: int = 10) -> tuple[list, dict]:
    """Every method on one measured scan (all pings): TCR, edge width, time (also in units of a warm
    ``reconstruct(method="bp")``, compression included, the median of 3); and the images."""
    ds = airsas_dataset(root, scan)
    x = np.arange(-0.12, 0.12 + 1e-9, step_m)
    y = np.arange(-0.16, 0.16 + 1e-9, step_m)
    grid = clsas.VoxelGrid(x, y, np.array([0.0]))
    clsas.reconstruct(ds, grid)  # warm-up: kernel builds and variant checks are not the method's time
    rows, pics, t_bp = [], {}, None
    for m in methods:
        if m == "offgrid":  # point reflectors: not a model of an extended target
            continue
        kw = {"inverse": {"max_iter": max_iter}} if m in ("ls", "l1", "tv", "l1-tv") else {}
        times = []
        for _ in range(3 if m == "bp" else 1):  # bp: the median of 3 (the unit of time)
            t0 = time.perf_counter()
            image = clsas.reconstruct(ds, grid, method=m, **kw)
            times.append(time.perf_counter() - t0)
        dt = float(np.median(times))
        if m == "bp":
            t_bp = dt
        mag = np.abs(np.asarray(image.values)[:, :, 0])
        width, cuts = edge_width_mm(mag, x, y)
        info = image.provenance.get("inverse", {})
        rows.append({"scan": scan, "pings": ds.n_meas, "method": m, "time_s": dt, "tcr_db": tcr_db(mag, x, y),
                     "edge_width_mm": width, "edge_cuts": cuts, "iterations": info.get("iterations"),
                     "n_forward": info.get("n_forward"), "n_adjoint": info.get("n_adjoint")})
        pics[m] = mag
        status(f"airsas {scan}: {m}: TCR {rows[-1]['tcr_db']:.1f} dB, edge {width:.1f} mm, {dt:.1f} s")
    for r in rows:
        r["time_in_bp"] = r["time_s"] / t_bp if t_bp else None
    return rows, {"x": x, "y": y, "images": pics}


def picture(path: Path, scan: str, pics: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    imgs = pics["images"]
    x, y = pics["x"], pics["y"]
    fig, axes = plt.subplots(1, len(imgs), figsize=(2.6 * len(imgs), 3.8))
    for ax, (name, mag) in zip(np.atleast_1d(axes), imgs.items(), strict=True):
        db = 20 * np.log10(np.maximum(mag / mag.max(), 1e-6))
        ax.imshow(db.T, origin="lower", extent=(x[0], x[-1], y[0], y[-1]), vmin=-30, vmax=0)
        ax.set_title(name, fontsize=9)
        ax.set_xticks([-0.1, 0, 0.1])
    np.atleast_1d(axes)[0].set_ylabel(f"AirSAS {scan}: y (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def markdown(out: dict) -> str:
    lines = [f"# Model-based reconstruction, {out['date']}", "",
             f"Device: {out['device']}; load before {out['load_before']}, after {out['load_after']}.", ""]
    if out["pairs"]:
        lines += ["## Simulated pairs (20 dB)", "", "| set-up | separation (x res) | method | resolved | RMS error "
                  "(x res) | median time (s) |", "|---|---|---|---|---|---|"]
        for r in out["pairs"]:
            err = "-" if r["rms_error_res"] is None else f"{r['rms_error_res']:.3f}"
            lines.append(f"| {r['setup']} | {r['factor']} | {r['method']} | {r['resolved_share']:.0%} of "
                         f"{r['trials']} | {err} | {r['median_time_s']:.2f} |")
    for r in out.get("noise", []):
        lines += ["", f"Pure noise ({r['setup']}): the l1 image with the noise-level weight is empty in "
                  f"{r['empty_share']:.0%} of {r['draws']} draws."]
    if out["airsas"]:
        lines += ["", "## Measured AirSAS scans (all pings)", "", "Time (bp's): in units of a warm "
                  "`reconstruct(method=\"bp\")` on the same grid (compression included).", "",
                  "| scan | method | TCR (dB) | -6 dB edge width (mm) "
                  "| time (s) | time (bp's) |", "|---|---|---|---|---|---|"]
        for r in out["airsas"]:
            tb = "-" if r["time_in_bp"] is None else f"{r['time_in_bp']:.1f}"
            lines.append(f"| {r['scan']} | {r['method']} | {r['tcr_db']:.1f} | {r['edge_width_mm']:.1f} "
                         f"({r['edge_cuts']} cuts) | {r['time_s']:.1f} | {tb} |")
    return "\n".join(lines) + "\n"


def run_superres_image(out_dir: str | Path = "bench/results", *, methods=METHODS, setups=("2d-line", "3d-rig"),
                       factors=(0.25, 0.5, 1.0), n_trials: int = 10, airsas_root: str | Path | None = None,
                       scans=("20k", "5k"), max_iter: int = 10, noise_draws: int = 0, tag: str = "",
                       status: Callable[[str], None] = log.info) -> dict:
    """The whole benchmark; writes ``<out>/<date>-superres-image[-tag].{json,md}`` and a PNG per scan."""
    from clsas import cl

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sel = cl.select(None)
    out = {"date": time.strftime("%Y-%m-%d"), "device": sel.device, "load_before": os.getloadavg(),
           "methods": list(methods), "pairs": [], "airsas": []}
    for name in setups:
        out["pairs"] += run_pairs(name, factors, n_trials, methods, status)
    out["noise"] = [run_noise(name, noise_draws, status) for name in setups if noise_draws]
    stem = out_dir / f"{out['date']}-superres-image{('-' + tag) if tag else ''}"
    if airsas_root is not None:
        root = Path(airsas_root)
        root = root / "airsas_deconv_pipeline" if (root / "airsas_deconv_pipeline").is_dir() else root
        for scan in scans:
            rows, pics = airsas(root, scan, methods, status, max_iter=max_iter)
            out["airsas"] += rows
            picture(stem.with_name(f"{stem.name}-airsas-{scan}.png"), scan, pics)
    out["load_after"] = os.getloadavg()
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1, default=float))
    stem.with_suffix(".md").write_text(markdown(out))
    out["paths"] = {"json": str(stem.with_suffix(".json")), "md": str(stem.with_suffix(".md"))}
    return out
