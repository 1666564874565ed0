"""Does each family scene's data determine its motion, and how much of it does autofocus remove?

For each scene of :mod:`clsas.synthesis.scene_family`, :func:`clsas.focus.data_consistency`
fits a target in the scene's grid to

- the scan as recorded (stated positions, clock and air),
- the same recordings at their true geometry (``dataset.truth``: positions, clock, air), and
- the scan as :func:`clsas.autofocus` returns it (:data:`bench.autofocus_family.BENCH_METHODS`),

all with ``max_iter`` CGLS iterations and the recorded scan's noise floor. The recorded scan's
errors are *determined by the data* where the residual they leave beyond the true geometry's
carries more energy than the whole noise draw does (``residual_recorded**2 - residual_true**2 >
floor**2``): a target in the grid cannot explain them away. ``removed`` is the share of that
energy the autofocus correction took away (1: all of it; 0 or less: none).

Run ``python -m bench.consistency_family SET [--max-iter N] [--n-seeds K] [--out DIR]``;
it writes ``<date>-consistency-<set>.{json,md}``. A scene costs 3 fits plus a noise fit plus
an autofocus: one to several minutes on 2 cores.
"""

from __future__ import annotations

import logging
import time

import numpy as np

__all__ = ["run_scene", "excess_ratio", "summarise", "markdown", "plot", "write"]

log = logging.getLogger(__name__)


def _true_geometry(ds):
    tr = ds.truth
    c = np.broadcast_to(np.asarray(tr["c_mps"], float), (ds.n_meas,))
    return ds.replace(t0_s=np.asarray(tr["t0_s"], float), c_mps=c, tx_positions=tr["tx_positions"],
                      rx_positions=tr["rx_positions"])


def run_scene(seed: int, rms_m: float = 3e-3, *, max_iter: int = 30, backend=None) -> dict:
    """One scene: the three fits, the autofocus, the peaks (see the module docstring)."""
    import clsas
    from bench.autofocus_family import BENCH_METHODS, local_peak_db
    from clsas.focus import autofocus
    from clsas.focus.consistency import data_consistency
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(seed, rms_m=rms_m)
    t = time.perf_counter()
    rec = data_consistency(fs.dataset, fs.grid, max_iter=max_iter, backend=backend)
    true = data_consistency(_true_geometry(fs.dataset), fs.grid, max_iter=max_iter, floor_of=rec, backend=backend)
    t_fit = time.perf_counter() - t  # three fits: the scan, its noise draw, the true geometry
    out, rep = autofocus(fs.dataset, fs.grid, methods=BENCH_METHODS, backend=backend)
    after = data_consistency(out, fs.grid, max_iter=max_iter, floor_of=rec, backend=backend) if rep.improved else rec
    clean = clsas.reconstruct(fs.clean, fs.grid, backend=backend)
    point = fs.grid.points()[int(np.argmax(np.abs(clean.values).ravel()))]
    ref = local_peak_db(fs.clean, point, backend=backend)
    peak_before = local_peak_db(fs.dataset, point, backend=backend) - ref
    peak_after = local_peak_db(out, point, backend=backend) - ref if rep.improved else peak_before
    gap = rec.residual ** 2 - true.residual ** 2
    p = fs.params
    pitch = max(p["width_m"] / (p["nx"] - 1), p["height_m"] / (p["ny"] - 1))
    speckle = 343.0 / 25e3 * p["range_m"] / (2 * p["extent_m"])
    row = {"seed": seed, "kind": fs.kind, "rms_m": rms_m, "nx": p["nx"], "ny": p["ny"], "range_m": p["range_m"],
           "snr_db": p["snr_db"], "pitch_over_speckle": pitch / speckle, "n_voxels": fs.grid.size,
           "residual_recorded": rec.residual, "residual_true": true.residual, "residual_after": after.residual,
           "floor": rec.floor, "determined": bool(gap > rec.floor ** 2),
           "removed": float((rec.residual ** 2 - after.residual ** 2) / gap) if gap > 0 else float("nan"),
           "improved": rep.improved, "peak_before_db": peak_before, "peak_after_db": peak_after,
           "fit_time_s": t_fit / 3, "max_iter": max_iter, "device": rec.device}
    log.info("consistency seed %d (%s): recorded %.3f, true %.3f, after %.3f, floor %.3f; peak %.2f -> %.2f dB",
             seed, fs.kind, rec.residual, true.residual, after.residual, rec.floor, peak_before, peak_after)
    return row


def excess_ratio(r: dict) -> float:
    """The corrected scan's excess over the recorded one's (what a user sees without the truth)."""
    def excess(x):
        return np.sqrt(max(x ** 2 - r["floor"] ** 2, 0.0))

    before = excess(r["residual_recorded"])
    return float(excess(r["residual_after"]) / before) if before > 0 else float("nan")


def summarise(rows: list[dict]) -> dict:
    """Shares over the scenes: determined, within 1 dB after autofocus among them, removed."""
    ok = [r for r in rows if "error" not in r]
    det = [r for r in ok if r["determined"]]
    return {"n": len(ok), "failed": len(rows) - len(ok), "determined": len(det),
            "determined_within_1db": sum(r["peak_after_db"] >= -1.0 for r in det),
            "undetermined_within_1db": sum(r["peak_after_db"] >= -1.0 for r in ok if not r["determined"]),
            "median_removed_determined": float(np.nanmedian([r["removed"] for r in det])) if det else None,
            "median_fit_time_s": float(np.median([r["fit_time_s"] for r in ok])) if ok else None}


def markdown(label: str, rows: list[dict]) -> str:
    s = summarise(rows)
    med = s["median_removed_determined"]
    lines = [f"{label}: {s['n']} scenes; the data determine the errors in {s['determined']} "
             f"({s['determined_within_1db']} of them within 1 dB after autofocus; "
             f"{s['undetermined_within_1db']} of the others); median share of the errors' residual energy removed "
             f"where determined: {'-' if med is None else format(med, '.2f')}", "",
             "| seed | kind | stops | pitch / speckle | residual recorded / true / after autofocus | noise floor | "
             "determined | removed | excess after / before | peak before -> after dB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['seed']} | error: {r['error']} |||||||||")
            continue
        lines.append(f"| {r['seed']} | {r['kind']} | {r['nx']}x{r['ny']} | {r['pitch_over_speckle']:.2f} | "
                     f"{r['residual_recorded']:.3f} / {r['residual_true']:.3f} / {r['residual_after']:.3f} | "
                     f"{r['floor']:.3f} | {r['determined']} | {r['removed']:.2f} | {excess_ratio(r):.2f} | "
                     f"{r['peak_before_db']:+.2f} -> {r['peak_after_db']:+.2f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path) -> None:
    """Peak after autofocus against the share of the errors' residual energy it removed."""
    from matplotlib.figure import Figure

    from bench.autofocus_family import finish_peak_plot

    fig = Figure(figsize=(6, 4.5))
    ax = fig.subplots()
    for kind, marker in (("points", "o"), ("plane", "s"), ("sphere", "^")):
        ok = [r for r in rows if "error" not in r and r["kind"] == kind]
        ax.scatter([np.clip(r["removed"], -0.1, 1.05) if np.isfinite(r["removed"]) else -0.1 for r in ok],
                   [r["peak_after_db"] for r in ok], marker=marker, s=22, label=kind)
    finish_peak_plot(fig, ax, "share of the errors' residual energy removed by autofocus", path)


def write(rows: list[dict], label: str, stem) -> None:
    """``stem``.json, .md and .png of the rows."""
    import json
    import os

    host = {"cpus": os.cpu_count(), "load": os.getloadavg()}
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps({"label": label, "rows": rows, "summary": summarise(rows),
                                                    "host": host}, indent=1, default=str))
    plot(rows, stem.with_suffix(".png"))
    stem.with_suffix(".md").write_text(f"# Data consistency on the scene family\n\n![peak against the share removed]"
                                       f"({stem.with_suffix('.png').name})\n\n{markdown(label, rows)}\n\n"
                                       f"host: {host}\n")


def _main(argv=None) -> str:
    """The command line (module docstring); returns the Markdown table (empty with ``--rewrite``)."""
    import argparse
    import datetime
    import json
    from pathlib import Path

    from clsas.synthesis.scene_family import SEED_SETS

    ap = argparse.ArgumentParser(prog="python -m bench.consistency_family", description=__doc__.split("\n")[0])
    ap.add_argument("seed_set", choices=sorted(SEED_SETS))
    ap.add_argument("--max-iter", type=int, default=30)
    ap.add_argument("--n-seeds", type=int, default=None)
    ap.add_argument("--rms-mm", type=float, default=3.0)
    ap.add_argument("--out", default="bench/results")
    ap.add_argument("--rewrite", metavar="JSON", help="write the Markdown and plot again from an earlier JSON")
    a = ap.parse_args(argv)
    if not 1 <= a.max_iter <= 10_000:
        ap.error(f"--max-iter must be 1 to 10000, got {a.max_iter}")
    stem = Path(a.out) / f"{datetime.date.today().isoformat()}-consistency-{a.seed_set}"
    if a.rewrite:
        old = json.loads(Path(a.rewrite).read_text())
        write(old["rows"], old["label"], Path(a.rewrite).with_suffix(""))
        return ""
    rows = []
    for s in list(SEED_SETS[a.seed_set])[:a.n_seeds]:
        log.info("consistency: seed %s", s)
        try:
            rows.append(run_scene(int(s), a.rms_mm * 1e-3, max_iter=a.max_iter))
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as e:
            rows.append({"seed": int(s), "error": f"{type(e).__name__}: {e}"})
        log.info("%s", json.dumps(rows[-1]))
    label = f"{a.seed_set} {a.rms_mm:g} mm, max_iter {a.max_iter}"
    write(rows, label, stem)
    return markdown(label, rows)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if text := _main():
        print(text)
