"""Autofocus benchmark: focus restored against the size of the error, with run time.

On the demo mannequin (``clsas demo``'s front scene, 216 stops, its 1 cm grid, the direct sound
added): hand-like 3-D jitter of a given RMS, a wrong air temperature, an unknown group delay.
Each row gives the error, what autofocus estimated, the residual, every reflector's peak
against the error-free image, and the time. ``python -m bench.autofocus`` runs the
quick cases and prints the table (``--jitter``: the 0.5, 1, 3, 5 and 10 mm jitter rows only;
``--full``: every row; ``--out DIR``: also write JSON and Markdown there).

Each reflector's peak is measured two ways against the error-free image's: on the scene's 1 cm
grid (the largest magnitude of the voxels within 1.5 cm of it), and as the local peak (the same
on a 1.5 mm local grid). The grid value moves by up to a dB with a sub-millimetre shift of the
image, and the constant and tilt of the motion across the aperture shift the image while no
focus metric sees them; so jitter rows also give the grid value of the image at the true
positions less that constant and tilt (the best any autofocus can give on that measure).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["CASES_QUICK", "CASES_FULL", "CASES_JITTER", "run_cases", "markdown"]

CASES_QUICK = [("delay", 20e-6), ("temperature", 5.0), ("jitter", 0.5e-3)]
CASES_JITTER = [("jitter", r) for r in (0.5e-3, 1e-3, 3e-3, 5e-3, 10e-3)]
CASES_FULL = [("delay", d) for d in (-20e-6, 5e-6, 20e-6)] + [("temperature", t) for t in (-5.0, 2.0, 5.0)] + \
    CASES_JITTER


def peaks_db(image, truth_m, grid, radius_m=0.015) -> np.ndarray:
    """Peak magnitude within ``radius_m`` of each true reflector, dB."""
    pts = grid.points()
    mag = np.abs(image.values).ravel()
    out = []
    for p in truth_m:
        near = np.linalg.norm(pts - p, axis=1) <= radius_m
        out.append(20 * np.log10(max(mag[near].max(initial=0.0), 1e-300)))
    return np.asarray(out)


def fine_peaks_db(ds, truth_m, radius_m=0.015, step_m=0.0015, backend=None) -> np.ndarray:
    """Peak magnitude within ``radius_m`` of each true reflector on a local grid ``step_m``
    apart, dB: the peak itself rather than its value at the nearest voxels of a coarse grid
    (which moves by up to a dB with a sub-millimetre shift of the image)."""
    import clsas

    ax = np.arange(-radius_m, radius_m + 1e-12, step_m)
    out = []
    for p in truth_m:
        g = clsas.VoxelGrid(p[0] + ax, p[1] + ax, p[2] + ax)
        mag = np.abs(clsas.reconstruct(ds, g, backend=backend).values).ravel()
        near = np.linalg.norm(g.points() - p, axis=1) <= radius_m
        out.append(20 * np.log10(max(mag[near].max(initial=0.0), 1e-300)))
    return np.asarray(out)


def untilted_truth(ds):
    """``ds`` at its true positions less their constant and tilt across the aperture (what no
    focus metric sees): the best any autofocus can give, up to a sub-mm shift of the image."""
    from clsas.focus.motion import stops_of

    stop, _, xy = stops_of(ds)
    d = ds.truth["tx_positions"] - ds.tx_positions
    q, _ = np.linalg.qr(np.c_[np.ones(len(xy)), xy - xy.mean(axis=0)])
    per_stop = np.stack([np.bincount(stop, d[:, k]) / np.bincount(stop) for k in range(3)], axis=1)
    d = (per_stop - q @ (q.T @ per_stop))[stop]
    return ds.replace(tx_positions=ds.tx_positions + d, rx_positions=ds.rx_positions + d)


def run_cases(cases=CASES_QUICK, *, spacing_m: float = 0.01, max_iter: int = 40, backend: str | None = None,
              status=None) -> list[dict]:
    """Run each ``(kind, size)`` case; kinds: ``"jitter"`` (RMS of the 3-D displacement, m),
    ``"temperature"`` (°C), ``"delay"`` (s)."""
    import clsas
    from clsas.focus import autofocus, score
    from clsas.physics.scan_errors import HandMotion
    from clsas.synthesis.scenes import demo_configs, parse_config

    cfg = parse_config(demo_configs(spacing_m)["front"])
    grid, truth = cfg.grid, cfg.scene.image_sources()[0]
    common = dict(snr_db=20, direct_gain=1.0, chirp=cfg.chirp)
    clean = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, **common)
    ref = peaks_db(clsas.reconstruct(clean, grid, backend=backend), truth, grid)
    ref_fine = fine_peaks_db(clean, truth, backend=backend)
    rows = []
    for kind, size in cases:
        if status:
            status(f"autofocus: {kind} {size:g}")
        err = {"position_error": HandMotion(size)} if kind == "jitter" else \
            {"temperature_error_c": size} if kind == "temperature" else {"group_delay_s": size}
        methods = {"jitter": ("direct", "phase", "3d", "pga"), "temperature": ("direct", "temperature"),
                   "delay": ("direct",)}[kind]
        ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, **common, **err)
        t = time.perf_counter()
        out, rep = autofocus(ds, grid, methods=methods, max_iter=max_iter, backend=backend)
        elapsed = time.perf_counter() - t
        s = score(rep, ds)
        before = peaks_db(clsas.reconstruct(ds, grid, backend=backend), truth, grid) - ref
        after = peaks_db(clsas.reconstruct(out, grid, backend=backend), truth, grid) - ref
        fine = fine_peaks_db(out, truth, backend=backend) - ref_fine
        extra = {}
        if kind == "jitter":
            floor = peaks_db(clsas.reconstruct(untilted_truth(ds), grid, backend=backend), truth, grid) - ref
            extra = {"worst_peak_untilted_truth_db": float(floor.min()),
                     "within_1db_untilted_truth": int(np.sum(floor >= -1.0)),
                     "pga": next(({k: st.get(k) for k in ("kept", "points", "candidates")}
                                  for st in rep.stages if st["step"] == "pga"), None)}
        rows.append({"kind": kind, "size": size, "methods": list(methods), "improved": rep.improved,
                     "time_s": elapsed, "images": len(rep.history), "device": rep.device,
                     "worst_peak_before_db": float(before.min()), "worst_peak_after_db": float(after.min()),
                     "peaks_before_db": before.round(2).tolist(), "peaks_after_db": after.round(2).tolist(),
                     "within_1db_after": int(np.sum(after >= -1.0)), "n_reflectors": len(after),
                     "worst_peak_after_fine_db": float(fine.min()), "within_1db_after_fine": int(np.sum(fine >= -1.0)),
                     "peaks_after_fine_db": fine.round(2).tolist(), **extra,
                     "metric_before": rep.metric_before, "metric_after": rep.metric_after, **s,
                     "estimate": {"group_delay_s": rep.group_delay_s,
                                  "temperature_offset_c": rep.temperature_offset_c}})
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = ["| error | size | estimate / residual | worst reflector peak vs error-free, before -> after "
             "(1 cm grid; local peak) | reflectors within 1 dB after (grid; local peak) | images | time |",
             "|---|---|---|---|---|---|---|"]
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
                     f"{r['worst_peak_after_db']:+.2f} dB; {r['worst_peak_after_fine_db']:+.2f} dB | "
                     f"{r['within_1db_after']}; {r['within_1db_after_fine']} of {r['n_reflectors']} | "
                     f"{r['images']} | {r['time_s']:.0f} s |")
    return "\n".join(lines)


if __name__ == "__main__":
    import datetime
    import json
    import pathlib
    import subprocess
    import sys

    def _uptime() -> str:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()

    cases = CASES_FULL if "--full" in sys.argv else CASES_JITTER if "--jitter" in sys.argv else CASES_QUICK
    load_start = _uptime()
    rows = run_cases(cases, status=print)
    load_end = _uptime()
    table = markdown(rows)
    print(load_start, load_end, table, sep="\n")
    if "--out" in sys.argv:
        out = pathlib.Path(sys.argv[sys.argv.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        stem = out / f"{datetime.date.today().isoformat()}-autofocus{'-full' if '--full' in sys.argv else ''}"
        stem.with_suffix(".json").write_text(json.dumps({"uptime_start": load_start, "uptime_end": load_end,
                                                        "rows": rows}, default=float, indent=1))
        stem.with_suffix(".md").write_text(f"# Autofocus benchmark (demo mannequin)\n\n{table}\n\n"
                                           f"uptime at start: `{load_start}`\n\nuptime at end: `{load_end}`\n")
        print(f"wrote {stem}.json and .md")
    else:
        print(json.dumps(rows, default=float, indent=1))
