"""Autofocus benchmark: focus restored against the size of the error, with run time.

On the demo mannequin (``clsas demo``'s front scene, 216 stops, its 1 cm grid, the direct sound
added): hand-like 3-D jitter of a given RMS, a wrong air temperature, an unknown group delay.
Each row gives the error, what autofocus estimated, the residual, every reflector's peak
against the error-free image, and the time. ``python -m clsas.bench.autofocus`` runs the
acceptance cases and prints the table (``--jitter``: the 1, 3 and 10 mm jitter rows only;
``--full``: every row).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["CASES_QUICK", "CASES_FULL", "CASES_JITTER", "run_cases", "markdown"]

CASES_QUICK = [("delay", 20e-6), ("temperature", 5.0), ("jitter", 0.5e-3)]
CASES_FULL = [("delay", d) for d in (-20e-6, 5e-6, 20e-6)] + [("temperature", t) for t in (-5.0, 2.0, 5.0)] + \
    [("jitter", r) for r in (0.5e-3, 1e-3, 3e-3, 10e-3)]
CASES_JITTER = [("jitter", r) for r in (1e-3, 3e-3, 10e-3)]


def _peaks_db(image, truth_m, grid, radius_m=0.015) -> np.ndarray:
    """Peak magnitude within ``radius_m`` of each true reflector, dB."""
    pts = grid.points()
    mag = np.abs(image.values).ravel()
    out = []
    for p in truth_m:
        near = np.linalg.norm(pts - p, axis=1) <= radius_m
        out.append(20 * np.log10(max(mag[near].max(initial=0.0), 1e-300)))
    return np.asarray(out)


def run_cases(cases=CASES_QUICK, *, spacing_m: float = 0.01, max_iter: int = 40, backend: str | None = None,
              status=None) -> list[dict]:
    """Run each ``(kind, size)`` case; kinds: ``"jitter"`` (RMS of the 3-D displacement, m),
    ``"temperature"`` (°C), ``"delay"`` (s)."""
    import clsas
    from clsas.autofocus import autofocus, score
    from clsas.scan_errors import HandMotion
    from clsas.scenes import demo_configs, parse_config

    cfg = parse_config(demo_configs(spacing_m)["front"])
    grid, truth = cfg.grid, cfg.scene.image_sources()[0]
    common = dict(snr_db=20, direct_gain=1.0, chirp=cfg.chirp)
    clean = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, **common)
    ref = _peaks_db(clsas.reconstruct(clean, grid, backend=backend), truth, grid)
    rows = []
    for kind, size in cases:
        if status:
            status(f"autofocus: {kind} {size:g}")
        err = {"jitter": {"position_error": HandMotion(size)}, "temperature": {"temperature_error_c": size},
               "delay": {"group_delay_s": size}}[kind]
        methods = {"jitter": ("direct", "phase", "3d"), "temperature": ("direct", "temperature"),
                   "delay": ("direct",)}[kind]
        ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, **common, **err)
        t = time.perf_counter()
        out, rep = autofocus(ds, grid, methods=methods, max_iter=max_iter, backend=backend)
        elapsed = time.perf_counter() - t
        s = score(rep, ds)
        before = _peaks_db(clsas.reconstruct(ds, grid, backend=backend), truth, grid) - ref
        after = _peaks_db(clsas.reconstruct(out, grid, backend=backend), truth, grid) - ref
        rows.append({"kind": kind, "size": size, "methods": list(methods), "improved": rep.improved,
                     "time_s": elapsed, "images": len(rep.history), "device": rep.device,
                     "worst_peak_before_db": float(before.min()), "worst_peak_after_db": float(after.min()),
                     "peaks_before_db": before.round(2).tolist(), "peaks_after_db": after.round(2).tolist(),
                     "within_1db_after": int(np.sum(after >= -1.0)), "n_reflectors": len(after),
                     "metric_before": rep.metric_before, "metric_after": rep.metric_after, **s,
                     "estimate": {"group_delay_s": rep.group_delay_s,
                                  "temperature_offset_c": rep.temperature_offset_c}})
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = ["| error | size | estimate / residual | worst reflector peak vs error-free, before -> after | "
             "reflectors within 1 dB after | images | time |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["kind"] == "jitter":
            size = f"{r['size'] * 1e3:g} mm RMS 3-D"
            est = (f"LOS {r['los_error_rms_m'] * 1e3:.2f} -> {r['los_residual_rms_m'] * 1e3:.2f} mm RMS "
                   f"(raw residual {r['los_residual_raw_rms_m'] * 1e3:.2f} mm)")
        elif r["kind"] == "temperature":
            size = f"{r['size']:+g} °C"
            est = (f"estimated {r['estimate']['temperature_offset_c']:+.2f} °C "
                   f"(error {r['temperature_error_c']:+.2f} °C)")
        else:
            size = f"{r['size'] * 1e6:+g} µs"
            est = (f"estimated {r['estimate']['group_delay_s'] * 1e6:+.2f} µs "
                   f"(error {r['group_delay_error_s'] * 1e6:+.3f} µs)")
        lines.append(f"| {r['kind']} | {size} | {est} | {r['worst_peak_before_db']:+.1f} -> "
                     f"{r['worst_peak_after_db']:+.2f} dB | {r['within_1db_after']} of {r['n_reflectors']} | "
                     f"{r['images']} | {r['time_s']:.0f} s |")
    return "\n".join(lines)


if __name__ == "__main__":
    import json
    import subprocess
    import sys

    cases = CASES_FULL if "--full" in sys.argv else CASES_JITTER if "--jitter" in sys.argv else CASES_QUICK
    rows = run_cases(cases, status=print)
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    print(markdown(rows))
    print(json.dumps(rows, default=float, indent=1))
