"""Fast image formation against exact backprojection: error against run time.

For every formation in :data:`clsas.formation.FORMATIONS` (with its defaults) and every case:

- the run time of ``form(profiles, grid, name)`` (the profiles are computed once, outside the
  timing; the first call on a fresh queue builds kernels, so each formation is warmed up on a
  small grid first);
- the error-to-signal ratio against ``"bp"`` on the same grid, complex, in dB
  (:func:`clsas.formation.error_to_signal_db`), inside the aperture's well-sampled cone
  (:func:`clsas.formation.planar.well_sampled_cone`, at the chirp's top frequency) and over the
  whole grid; apertures without a lattice (a circle) have no cone, and the whole grid is used;
- a formation that refuses the case (ω-k on a circle) is listed with its message.

Cases: ``demo`` (the demo's front scene: 18 x 12 stops over 1 m, the mannequin, the demo grid),
``dense`` (a dense planar scan: 128 x 128 stops over 0.75 m, 256 x 256 x 128 voxels of 2.9 mm,
a few reflectors; ``scale`` shrinks both sides), ``circular`` (360 stops on a 1 m circle, a
5 mm grid; ``scale`` < 1 thins both), ``beams`` (directional transducers over a flat surface at
MHz in water, :func:`run_beams_case`; full set only).
Every case also times ``auto`` (:func:`clsas.formation.auto.choose`, its choosing included) and
names the formation it took. The crossover table (:func:`crossover`, in :mod:`bench.crossover`)
times bp, ω-k, FFBP and auto on dense planar scans of N x N stops (N = 16-64 quick, 16-128 full)
onto grids that grow with N, and calibrates the cost model of ``formation="auto"`` on the device.
Cost exponents: each formation timed (the faster of two calls) on planar scans of N x N stops
and 2N x 2N x N voxels, and the slope of log(time) against log(N) fitted. Benchmarks measure; nothing here asserts.
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

import clsas
from clsas.formation import FORMATIONS, error_to_signal_db, form

from .crossover import _timed, auto_row
from .crossover import cone as _cone
from .crossover import profiles as _profiles
from .stats import fit_exponent, jsonable, seconds, times

__all__ = ["CASES", "QUICK", "FULL", "make_case", "run_case", "scaling", "run", "markdown", "write"]

log = logging.getLogger(__name__)

CASES = ("demo", "dense", "circular")
# the crossover table (bench.crossover) and the directional-transducer case
# (run_beams_case) run as cases of their own
ALL_CASES = (*CASES, "beams", "crossover")
# what ``python -m bench`` runs: the quick set shrinks the dense scan to 32 x 32 stops and leaves out
# the beams case (FFBP at MHz alone takes most of a minute)
QUICK = {"cases": (*CASES, "crossover"), "scale": 0.25, "sides": (8, 12, 16)}
FULL = {"cases": ALL_CASES, "scale": 1.0, "sides": (12, 16, 24, 32, 48)}
BEAM_STOPS = 16  # the beams case: n x n stops at 1.5 mm (bench.beams.make_case)
FS = 96e3
F_TOP = 30e3
PITCH = 0.75 / 127  # the dense scan's stop spacing, m (lambda/2 at 29 kHz)


def _chirp():
    return clsas.lfm_chirp(20e3, F_TOP, 2e-3, FS, taper=0.1), {"f_start_hz": 20e3, "f_stop_hz": F_TOP,
                                                               "duration_s": 2e-3}


def _planar(n_stops: int, n_vox: int, n_z: int, seed: int = 0):
    """N x N stops at PITCH, 2N x 2N x N voxels of PITCH/2 starting 1 m away, a few reflectors."""
    w, chirp = _chirp()
    side = PITCH * (n_stops - 1)
    ap = clsas.raster_aperture(n_stops, n_stops, side, side)
    dv = side / (n_vox - 1)
    grid = clsas.VoxelGrid(np.linspace(-side / 2, side / 2, n_vox), np.linspace(-side / 2, side / 2, n_vox),
                           1.0 + dv * np.arange(n_z))
    rng = np.random.default_rng(seed)
    z0, z1 = grid.z_m[0], grid.z_m[-1]
    pts = np.c_[rng.uniform(-0.25 * side, 0.25 * side, (6, 2)), rng.uniform(z0 + 0.2 * (z1 - z0),
                                                                           z1 - 0.2 * (z1 - z0), 6)]
    amps = rng.uniform(0.5, 1.0, 6)
    ds = clsas.simulate(clsas.Scene(pts, amps), ap, w, FS, snr_db=30, chirp=chirp)
    return ds, grid


def make_case(name: str, scale: float = 1.0):
    """(dataset, grid, description) of a case; ``scale`` < 1 shrinks the dense scan's sides and the
    circular scan's stop count and grid."""
    if name == "demo":
        from clsas.synthesis.scenes import demo_configs, parse_config

        cfg = parse_config(demo_configs(0.01)["front"])
        ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=cfg.snr_db, chirp=cfg.chirp)
        return ds, cfg.grid, "demo front scene: 18 x 12 stops over 1 m, mannequin, 1 cm grid"
    if name == "dense":
        n = max(8, int(round(128 * scale)))
        ds, grid = _planar(n, 2 * n, n)
        return ds, grid, (f"dense planar scan: {n} x {n} stops over {PITCH * (n - 1):.2f} m, "
                          f"{2 * n} x {2 * n} x {n} voxels, 6 reflectors")
    if name == "circular":
        w, chirp = _chirp()
        n = max(36, int(round(360 * min(scale, 1.0))))
        sp = 0.005 / min(max(scale, 0.25), 1.0)
        ap = clsas.circular_aperture(n, 1.0, mode="arc")
        pts = np.array([[0.05, -0.03, 0.0], [-0.08, 0.06, 0.02], [0.0, 0.1, -0.02]])
        ds = clsas.simulate(clsas.Scene(pts), ap, w, FS, snr_db=30, chirp=chirp)
        grid = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (-0.2, 0.2), (-0.05, 0.05), sp)
        return ds, grid, f"circular scan: {n} stops on a 1 m circle, 3 reflectors, {sp * 1e3:.0f} mm grid"
    raise ValueError(f"case must be one of {CASES}, got {name!r}")


def _warm_up(formations) -> None:
    """Build each formation's kernels on a tiny planar case, outside any timing."""
    ds, grid = _planar(12, 8, 4)
    prof = _profiles(ds, grid)
    for name in formations:
        try:
            form(prof, grid, name)
        except ValueError as exc:
            log.info("warm-up of %s: %s", name, exc)


def _formations() -> list[str]:
    """The registered formations that form an image themselves (auto, which picks one of them, is timed
    by :func:`bench.crossover.auto_row`)."""
    return [f for f in FORMATIONS if f != "auto"]


def run_case(name: str, formations=None, scale: float = 1.0, status=None) -> dict:
    """Every formation on one case: time (the faster of two runs where one takes under 2 s; FFBP's
    remembered tree forgotten before each), error inside the cone and over the grid."""
    say = status or (lambda s: log.info("%s", s))
    formations = list(formations or _formations())
    if "bp" not in formations:
        formations = ["bp", *formations]
    ds, grid, what = make_case(name, scale)
    t = time.perf_counter()
    prof = _profiles(ds, grid)
    t_comp = time.perf_counter() - t
    cone = _cone(ds, grid)
    out = {"case": name, "what": what, "measurements": ds.n_meas, "voxels": grid.size,
           "pairs": float(ds.n_meas) * grid.size, "compress_s": t_comp, "load_before": os.getloadavg(),
           "cone_fraction": None if cone is None else float(cone.mean()), "rows": []}
    ref = None
    for f in formations:
        say(f"formation {f} on the {name} case ({what})")
        row = {"formation": f}
        try:
            row["time_s"], img = _timed(lambda f=f: form(prof, grid, f))
        except ValueError as exc:
            row.update(refused=str(exc))
            out["rows"].append(row)
            continue
        row["backend"] = img.backend
        row["load_after"] = os.getloadavg()
        if f == "bp":
            ref = img.values
            row["error_cone_db"] = row["error_all_db"] = None
        else:
            row["error_all_db"] = error_to_signal_db(img.values, ref)
            row["error_cone_db"] = (error_to_signal_db(img.values, ref, cone)
                                    if cone is not None and cone.any() else None)
            row["speedup"] = out["rows"][0]["time_s"] / row["time_s"]
            if "omega_k" in img.provenance:
                row["details"] = img.provenance["omega_k"]
        out["rows"].append(row)
    say(f"formation auto on the {name} case")
    out["rows"].append(auto_row(prof, grid, ref, cone, out["rows"]))
    return out


def run_beams_case(n: int | None = None, status=None) -> dict:
    """The directional-transducer case in the formation table's form: water, 1-4 MHz, a
    flat surface and two pins under ``n`` x ``n`` stops 2.5 wavelengths apart, 6 mm pistons
    (:func:`bench.beams.make_case`). Rows: bp with the beam model (its default with beams,
    "limited": the reference of the error columns), bp without it and weighted, ω-k limited and
    weighted, FFBP without beams, weighted (its default with beams) and limited, and auto."""
    from clsas.formation.planar import well_sampled_cone

    from .beams import C_WATER, make_case

    say = status or (lambda s: log.info("%s", s))
    n = BEAM_STOPS if n is None else int(n)
    t = time.perf_counter()
    prof, grid, what = make_case(n)
    t_prof = time.perf_counter() - t
    data, _, _, _, tx, rx, _ = prof.arrays()
    cone = well_sampled_cone(tx, rx, grid, 4e6, C_WATER)
    out = {"case": "beams", "what": what, "measurements": prof.n_meas, "voxels": grid.size,
           "pairs": float(prof.n_meas) * grid.size, "compress_s": t_prof, "load_before": os.getloadavg(),
           "cone_fraction": float(cone.mean()), "rows": []}
    ref = None
    for label, f, opts in (("bp", "bp", {}), ("bp beam=none", "bp", {"beam": "none"}),
                           ("bp beam=weighted", "bp", {"beam": "weighted"}), ("omega-k", "omega-k", {}),
                           ("omega-k beam=weighted", "omega-k", {"beam": "weighted"}),
                           ("ffbp beam=none", "ffbp", {"beam": "none"}), ("ffbp", "ffbp", {}),
                           ("ffbp beam=limited", "ffbp", {"beam": "limited"})):
        say(f"formation {label} on the beams case ({what})")
        row = {"formation": label, "options": opts}
        try:
            row["time_s"], img = _timed(lambda f=f, opts=opts: form(prof, grid, f, **opts))
        except ValueError as exc:
            row.update(refused=str(exc))
            out["rows"].append(row)
            continue
        row.update(backend=img.backend, load_after=os.getloadavg())
        if label == "bp":  # the reference: bp with its beam model (it runs first)
            ref = img.values
            row["error_cone_db"] = row["error_all_db"] = None
        elif ref is not None:
            row["error_all_db"] = error_to_signal_db(img.values, ref)
            row["error_cone_db"] = error_to_signal_db(img.values, ref, cone) if cone.any() else None
            row["speedup"] = out["rows"][0]["time_s"] / row["time_s"]
        out["rows"].append(row)
    if ref is None:  # bp refused the case: nothing to compare with
        return out
    say("formation auto on the beams case")
    out["rows"].append(auto_row(prof, grid, ref, cone if cone.any() else None, out["rows"]))
    return out


def scaling(formations=None, sides=(12, 16, 24, 32), bp_max_pairs: float = 2e9, status=None) -> dict:
    """Time of each formation on N x N stops and 2N x 2N x N voxels; fitted exponent in N."""
    say = status or (lambda s: log.info("%s", s))
    formations = list(formations or _formations())
    res = {}
    cases = {n: _planar(n, 2 * n, n) for n in sides}
    profs = {n: _profiles(*cases[n]) for n in sides}
    for f in formations:
        xs, ts = [], []
        for n in sides:
            ds, grid = cases[n]
            if f == "bp" and ds.n_meas * grid.size > bp_max_pairs:
                continue
            say(f"scaling: {f} at N = {n}")
            best = float("inf")
            try:
                for _ in range(2):  # the faster of two calls: one-time costs and load spikes aside
                    t = time.perf_counter()
                    form(profs[n], grid, f)
                    best = min(best, time.perf_counter() - t)
            except ValueError as exc:
                log.info("scaling of %s at N=%d: %s", f, n, exc)
                break
            xs.append(n)
            ts.append(best)
        if len(xs) >= 2:
            res[f] = {"sides": xs, "times_s": ts, "exponent": fit_exponent(xs, ts)}
    return res


def run(cases=CASES, formations=None, scale: float = 1.0, sides=(12, 16, 24, 32), status=None) -> dict:
    """The whole formation benchmark: every case, then the scaling."""
    formations = list(formations or _formations())
    for f in formations:
        if f not in FORMATIONS:
            raise ValueError(f"formation {f!r} is not registered; known: {', '.join(FORMATIONS)}")
    for c in cases:
        if c not in ALL_CASES:
            raise ValueError(f"case must be one of {ALL_CASES}, got {c!r}")
    _warm_up(formations)
    res = {"formations": formations, "scale": scale,
           "cases": [run_beams_case(status=status) if c == "beams"
                     else run_case(c, formations, 1.0 if c == "demo" else scale, status=status)
                     for c in cases if c != "crossover"]}
    if "crossover" in cases:
        from .crossover import CROSSOVER_FULL, CROSSOVER_QUICK, crossover

        res["crossover"] = crossover(CROSSOVER_FULL if scale >= 1 else CROSSOVER_QUICK, status=status)
    if sides:
        res["scaling"] = scaling(formations, sides, status=status)
    return res


def _db(x) -> str:
    return "n/a" if x is None else f"{x:.1f} dB"


def markdown(res: dict) -> list[str]:
    """The formation section of the benchmark report."""
    md = ["## Image formation against exact backprojection", "",
          "Error: complex error-to-signal ratio against `bp` on the same grid, inside the aperture's "
          "well-sampled cone (voxels every stop sees within 0.8 of the angle its lattice samples unaliased at "
          f"{F_TOP / 1e3:.0f} kHz) and over the whole grid. Times exclude pulse compression (given per case). "
          "Load average (1 min) as measured before the case.", "",
          "| case | formation | time | speed-up over bp | error, cone | error, grid | cone / grid | backend |",
          "|---|---|---|---|---|---|---|---|"]
    for c in res["cases"]:
        cone = "no lattice" if c["cone_fraction"] is None else f"{100 * c['cone_fraction']:.0f} %"
        for r in c["rows"]:
            if r["formation"] == "auto":
                md.append(f"| {c['case']} | auto -> {r['chose']} | {seconds(r['time_s'])} | "
                          f"{r['over_best']:.2f}x the best ({r['best']}) | {_db(r['error_cone_db'])} | "
                          f"{_db(r['error_all_db'])} | {cone} | |")
                continue
            if "refused" in r:
                md.append(f"| {c['case']} | {r['formation']} | refused: {r['refused'][:90]}... | | | | {cone} | |")
                continue
            sp = r.get("speedup")
            md.append(f"| {c['case']} | {r['formation']} | {seconds(r['time_s'])} | "
                      f"{'' if sp is None else times(sp)} | {_db(r['error_cone_db'])} | {_db(r['error_all_db'])} "
                      f"| {cone} | {r['backend']} |")
    md += [""]
    for c in res["cases"]:
        md.append(f"- {c['case']}: {c['what']}; {c['measurements']} measurements x {c['voxels']} voxels = "
                  f"{c['pairs']:.3g} pairs; compression {seconds(c['compress_s'])}; load average "
                  f"{c['load_before'][0]:.2f} before.")
    if res.get("crossover"):
        from .crossover import markdown as crossover_md

        md += crossover_md(res["crossover"])
    if res.get("scaling"):
        md += ["", "| formation | N (N x N stops, 2N x 2N x N voxels) | times | cost ~ N^ |", "|---|---|---|---|"]
        for f, s in res["scaling"].items():
            md.append(f"| {f} | {s['sides']} | {', '.join(seconds(t) for t in s['times_s'])} | "
                      f"{s['exponent']:.2f} |")
    return md + [""]


def write(res: dict, out_dir, stem: str, plots: bool = True) -> dict:
    """JSON, Markdown (and a PNG of error against time) of :func:`run`'s result."""
    import json
    from pathlib import Path


    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / f"{stem}.json", "markdown": out_dir / f"{stem}.md"}
    if plots:
        paths["png"] = out_dir / f"{stem}.png"
    res = {**res, "paths": {k: str(v) for k, v in paths.items()}}
    paths["json"].write_text(json.dumps(jsonable(res), indent=1))
    head = [f"# clsas formation benchmark, {res.get('date', '')}", "", f"Device: {res.get('device', '?')}. "
            f"Host: {res.get('host', '?')}.", ""]
    if plots:
        head += [f"![error against time]({paths['png'].name})", ""]
        _plot(res, paths["png"])
    paths["markdown"].write_text("\n".join(head + markdown(res)))
    return res["paths"]


def _plot(res: dict, path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for c in res["cases"]:
        for r in c["rows"]:
            if r.get("error_all_db") is None or r["formation"] == "auto":
                continue
            err = r["error_cone_db"] if r.get("error_cone_db") is not None else r["error_all_db"]
            ax.scatter(r["time_s"] / c["rows"][0]["time_s"], err, label=f"{r['formation']}, {c['case']}")
    ax.axhline(-30, color="grey", lw=0.5)
    ax.set_xscale("log")
    ax.set_xlabel("time / bp's time")
    ax.set_ylabel("error-to-signal, dB (cone, else grid)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
