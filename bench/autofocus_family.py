"""Autofocus on the seeded scene family (:mod:`clsas.synthesis.scene_family`): the distribution.

Each scene is drawn from its seed, imaged as recorded, autofocused with :data:`BENCH_METHODS` (direct, points, track),
and scored against the same scan without errors:

- *peak loss*: the local peak (on a 1.5 mm grid within 1.5 cm) at the error-free image's
  brightest voxel, corrected against error-free, dB (0 is perfect, negative is a loss); the
  same for the uncorrected scan ("no autofocus");
- the line-of-sight error before and after (:func:`clsas.focus.score`: constant and tilt, which
  no focus metric sees, removed);
- the group delay and temperature errors where the report says they were determined;
- the time of :func:`clsas.autofocus` (with :data:`BENCH_METHODS`).

- *the ceiling of a per-stop correction* (``peak_oracle_db``): the scan corrected by the truth
  as a per-stop delay (each stop's two-way path error towards the grid's centre, with the
  true clock and speed of sound; positions as stated), what :func:`clsas.autofocus`'s motion
  model (one line-of-sight path per stop) could reach with a perfect estimate (within 0.2 dB of
  error-free on all 12 tuning scenes at 3 mm: the model suffices and the estimate is what is
  missing).

:func:`summarise` gives the distribution: share within 1 dB of the error-free local peak, share
worse than no autofocus (by any amount and by more than 0.5 dB), median and worst peak loss,
the share whose line-of-sight error went down, and the times. ``python -m bench --autofocus`` runs it
(``--autofocus tuning``, ``tuning-2``, ``held-out`` or ``held-out-2``) and writes JSON, Markdown
and a plot.
"""

from __future__ import annotations

import logging
import time

import numpy as np

__all__ = ["BENCH_METHODS", "oracle_per_stop", "run_family", "summarise", "family_markdown", "plot_family"]

log = logging.getLogger(__name__)

#: The methods the family is scored with: the direct sound's delay, then the phases the strong
#: points share (``"points"``, where the scene has isolated points), else the neighbouring stops'
#: phases (``"track"``). Not ``FOCUS_METHODS`` (direct, phase, temperature): on 30 held-out scenes
#: its temperature step was determined in 2 and 2-3 C wrong there.
BENCH_METHODS = ("direct", "points", "track")


def local_peak_db(ds, point, radius_m=0.015, step_m=0.0015, backend=None) -> float:
    import clsas

    ax = np.arange(-radius_m, radius_m + 1e-12, step_m)
    g = clsas.VoxelGrid(point[0] + ax, point[1] + ax, point[2] + ax)
    mag = np.abs(clsas.reconstruct(ds, g, backend=backend).values).ravel()
    near = np.linalg.norm(g.points() - point, axis=1) <= radius_m
    return float(20 * np.log10(max(mag[near].max(initial=0.0), 1e-300)))


def oracle_per_stop(fs):
    """The recorded scan of family scene ``fs`` corrected by its truth as a per-stop delay only
    (the two-way path error of each measurement towards the grid's centre, the true clock and
    speed of sound; the stated positions kept): the best a per-stop line-of-sight estimate can do."""
    ds, truth = fs.dataset, fs.dataset.truth
    centre = fs.grid.points().mean(axis=0)

    def path(tx, rx):
        return np.linalg.norm(centre - tx, axis=1) + np.linalg.norm(centre - rx, axis=1)

    c = np.broadcast_to(np.asarray(truth["c_mps"], float), (ds.n_meas,))
    error = path(truth["tx_positions"], truth["rx_positions"]) - path(ds.tx_positions, ds.rx_positions)
    return ds.replace(t0_s=np.asarray(truth["t0_s"], float) - error / c, c_mps=c)


def run_scene(seed: int, rms_m: float, *, backend=None, methods=None, **options) -> dict:
    """One scene of the family, autofocused and scored (see the module docstring)."""
    import clsas
    from clsas.focus import autofocus, score
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(seed, rms_m=rms_m)
    clean = clsas.reconstruct(fs.clean, fs.grid, backend=backend)
    point = fs.grid.points()[int(np.argmax(np.abs(clean.values).ravel()))]
    ref = local_peak_db(fs.clean, point, backend=backend)
    before = local_peak_db(fs.dataset, point, backend=backend) - ref
    oracle = local_peak_db(oracle_per_stop(fs), point, backend=backend) - ref if fs.dataset.truth else before
    t = time.perf_counter()
    out, rep = autofocus(fs.dataset, fs.grid, methods=methods or BENCH_METHODS, backend=backend, **options)
    elapsed = time.perf_counter() - t
    after = local_peak_db(out, point, backend=backend) - ref if rep.improved else before
    s = score(rep, fs.dataset)
    par = {k: p.as_dict() for k, p in rep.parameters.items()} if hasattr(rep, "parameters") else {}
    row = {"seed": seed, "kind": fs.kind, "rms_m": rms_m, **{k: fs.params[k] for k in (
               "nx", "ny", "width_m", "height_m", "range_m", "snr_db", "direct", "group_delay_s",
               "temperature_error_c")},
           "n_voxels": fs.grid.size, "peak_before_db": before, "peak_after_db": after, "peak_oracle_db": oracle,
           "improved": rep.improved,
           "time_s": elapsed, "images": len(rep.history), "device": rep.device, "notes": list(rep.notes),
           "parameters": par, "check": {k: v for k, v in rep.check.items() if not isinstance(v, dict)}, **s}
    log.info("family seed %d (%s, %.0f mm): %.2f -> %.2f dB, %.0f s", seed, fs.kind, rms_m * 1e3, before, after,
             elapsed)
    return row


def run_family(seeds, rms_m: float = 3e-3, *, backend=None, status=None, **options) -> list[dict]:
    """:func:`run_scene` for each seed; a scene that raises is a row with its ``error``."""
    rows = []
    for s in seeds:
        if status:
            status(f"autofocus family: seed {s}, {rms_m * 1e3:g} mm")
        try:
            rows.append(run_scene(int(s), rms_m, backend=backend, **options))
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as e:  # a failure is a result too
            rows.append({"seed": int(s), "rms_m": rms_m, "error": f"{type(e).__name__}: {e}"})
    return rows


def summarise(rows: list[dict]) -> dict:
    """The distribution over scenes (rows with an ``error`` counted as failures)."""
    ok = [r for r in rows if "error" not in r]
    n = len(ok)
    if not n:
        return {"n": 0, "failed": len(rows)}
    after = np.array([r["peak_after_db"] for r in ok])
    before = np.array([r["peak_before_db"] for r in ok])
    oracle = np.array([r.get("peak_oracle_db", np.nan) for r in ok])
    los_b = np.array([r.get("los_error_rms_m", np.nan) for r in ok])
    los_a = np.array([r.get("los_residual_rms_m", np.nan) for r in ok])
    gd = [abs(r["group_delay_error_s"]) for r in ok if r.get("direct") and "group_delay_error_s" in r]
    temp = [abs(r["temperature_error_c"]) for r in ok
            if r.get("parameters", {}).get("temperature", {}).get("determined")]
    temp_undet = [r for r in ok if not r.get("parameters", {}).get("temperature", {}).get("determined", True)]
    return {"n": n, "failed": len(rows) - n,
            "within_1db": float(np.mean(after >= -1.0)),
            "within_1db_before": float(np.mean(before >= -1.0)),
            "within_1db_oracle": float(np.mean(oracle >= -1.0)) if np.isfinite(oracle).all() else None,
            "worse_than_none": float(np.mean(after < before - 1e-6)),
            "worse_than_none_by_0_5db": float(np.mean(after < before - 0.5)),
            "median_peak_db": float(np.median(after)), "worst_peak_db": float(after.min()),
            "median_peak_before_db": float(np.median(before)), "worst_peak_before_db": float(before.min()),
            "los_reduced": float(np.mean(los_a < los_b)),
            "median_los_before_mm": float(np.nanmedian(los_b) * 1e3), "median_los_after_mm": float(
                np.nanmedian(los_a) * 1e3),
            "applied": float(np.mean([r["improved"] for r in ok])),
            "group_delay_error_max_us": float(max(gd) * 1e6) if gd else None,
            "temperature_error_max_c": float(max(temp)) if temp else None,
            "temperature_determined": len(temp), "temperature_not_determined": len(temp_undet),
            "median_time_s": float(np.median([r["time_s"] for r in ok])),
            "max_time_s": float(max(r["time_s"] for r in ok))}


def family_markdown(results: dict) -> str:
    """``{label: {"summary": ..., "rows": ...}}`` as Markdown: a summary table, then rows."""
    lines = ["| set | scenes | within 1 dB (before; per-stop ceiling) | worse than none (by > 0.5 dB) | "
             "median / worst peak dB (before) | LOS reduced | median LOS mm before -> after | delay err max us | "
             "temp err max C (determined / not) | median / max time s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for label, res in results.items():
        s = res["summary"]
        if not s.get("n"):
            lines.append(f"| {label} | 0 | failed {s.get('failed')} |||||||||")
            continue

        def f(x, fmt):
            return "-" if x is None else format(x, fmt)

        ceiling = "-" if s.get("within_1db_oracle") is None else format(s["within_1db_oracle"], ".0%")
        lines.append(f"| {label} | {s['n']} | {s['within_1db']:.0%} ({s['within_1db_before']:.0%}; {ceiling}) | "
                     f"{s['worse_than_none']:.0%} ({s['worse_than_none_by_0_5db']:.0%}) | "
                     f"{s['median_peak_db']:+.2f} / {s['worst_peak_db']:+.2f} ({s['median_peak_before_db']:+.1f} / "
                     f"{s['worst_peak_before_db']:+.1f}) | {s['los_reduced']:.0%} | {s['median_los_before_mm']:.2f} "
                     f"-> {s['median_los_after_mm']:.2f} | {f(s['group_delay_error_max_us'], '.2f')} | "
                     f"{f(s['temperature_error_max_c'], '.2f')} ({s['temperature_determined']} / "
                     f"{s['temperature_not_determined']}) | {s['median_time_s']:.0f} / {s['max_time_s']:.0f} |")
    lines += ["", "| set | seed | kind | stops | range m | peak before -> after dB (per-stop ceiling) | "
              "LOS mm before -> after | applied | time s |", "|---|---|---|---|---|---|---|---|---|"]
    for label, res in results.items():
        for r in res["rows"]:
            if "error" in r:
                lines.append(f"| {label} | {r['seed']} | error: {r['error']} |||||||")
                continue
            lines.append(f"| {label} | {r['seed']} | {r['kind']} | {r['nx']}x{r['ny']} | {r['range_m']:.2f} | "
                         f"{r['peak_before_db']:+.2f} -> {r['peak_after_db']:+.2f} "
                         f"({r.get('peak_oracle_db', np.nan):+.2f}) | "
                         f"{r.get('los_error_rms_m', np.nan) * 1e3:.2f} -> "
                         f"{r.get('los_residual_rms_m', np.nan) * 1e3:.2f} | {r['improved']} | {r['time_s']:.0f} |")
    return "\n".join(lines)


def plot_family(results: dict, path) -> None:
    """Peak loss before against after per scene, one colour per set; saved to ``path``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    for label, res in results.items():
        ok = [r for r in res["rows"] if "error" not in r]
        ax.scatter([r["peak_before_db"] for r in ok], [r["peak_after_db"] for r in ok], label=label, s=18)
    lo = min([-1.0] + [min(r["peak_before_db"], r["peak_after_db"]) for res in results.values()
                       for r in res["rows"] if "error" not in r])
    ax.plot([lo, 1], [lo, 1], "k:", lw=0.8, label="no change")
    finish_peak_plot(fig, ax, "local peak without autofocus, dB re error-free", path)


def finish_peak_plot(fig, ax, xlabel: str, path) -> None:
    """The 1 dB line, the labels (y: the local peak after autofocus) and the legend; saved to ``path``."""
    ax.axhline(-1.0, color="grey", lw=0.8, ls="--", label="1 dB below error-free")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("local peak after autofocus, dB re error-free")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def run_and_write(seed_set: str = "tuning", rms_mm=(3.0,), *, n_seeds: int | None = None, out_dir=None,
                  plots: bool = True, backend=None, status=None, consistency_iter: int = 0) -> dict:
    """The family at each RMS (mm) on ``seed_set`` (a name in :data:`clsas.synthesis.scene_family.SEED_SETS`:
    ``"tuning"``, ``"tuning-2"``, ``"held-out"``, ``"held-out-2"``; the first ``n_seeds`` only),
    summarised, and written to ``out_dir`` as ``<date>-autofocus-family-<set>.{json,md,png}``
    (``...-<set>-consistency<N>`` with ``consistency_iter`` N, :func:`clsas.autofocus`'s last check).

    Returns ``{"results": {label: {"summary", "rows"}}, "paths": {...}}``.
    """
    import datetime
    import json
    import os
    import platform
    from pathlib import Path

    from clsas.synthesis.scene_family import SEED_SETS

    if seed_set not in SEED_SETS:
        raise ValueError(f"seed_set must be one of {', '.join(SEED_SETS)}, got {seed_set!r}")
    seeds = list(SEED_SETS[seed_set])[:n_seeds]
    results = {}
    for mm in rms_mm:
        rows = run_family(seeds, float(mm) * 1e-3, backend=backend, status=status, consistency_iter=consistency_iter)
        results[f"{seed_set} {mm:g} mm"] = {"summary": summarise(rows), "rows": rows}
    paths = {}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        tag = f"-consistency{consistency_iter}" if consistency_iter else ""
        stem = out / f"{datetime.date.today().isoformat()}-autofocus-family-{seed_set}{tag}"
        host = {"machine": platform.machine(), "cpus": os.cpu_count(), "load": os.getloadavg()}
        stem.with_suffix(".json").write_text(json.dumps({"seed_set": seed_set, "seeds": seeds, "host": host,
                                                        "methods": list(BENCH_METHODS),
                                                        "consistency_iter": consistency_iter,
                                                        "results": results}, default=_json, indent=1))
        md = f"# Autofocus on the scene family ({seed_set} seeds {seeds[0]}-{seeds[-1]})\n\n"
        if plots:
            plot_family(results, stem.with_suffix(".png"))
            paths["png"] = stem.with_suffix(".png")
            md += f"![peak before and after]({stem.with_suffix('.png').name})\n\n"
        stem.with_suffix(".md").write_text(md + family_markdown(results) + f"\n\nhost: {host}\n")
        paths.update(json=stem.with_suffix(".json"), md=stem.with_suffix(".md"))
    return {"results": results, "paths": paths}


def _json(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
