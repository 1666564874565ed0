"""``formation="auto"`` on a seeded family of requests it was not tuned on: the distribution.

The crossover table and the three fixed cases (:mod:`bench.crossover`,
:mod:`bench.formation`) are the scans the cost model was fitted on. This module draws
requests at random from a seed (:func:`family_request`) and scores the choice on each:

- the aperture: a planar raster (half the seeds), the same raster with every stop off its
  lattice by up to a tenth of the pitch (a hand-placed or hand-held scan: ω-k refuses it), or a
  ring (a turntable);
- the raster's stops 10-64 a side (not always square), 0.4-1.2 top-band wavelengths apart; the ring
  90-360 stops of 0.4-1.2 m radius;
- the chirp: a band 4-15 kHz wide starting at 10-25 kHz, 1-4 ms, at 96 kHz;
- the target 0.3-1.5 m away: 2-10 points, or a rough tilted plane of about 100 scatterers;
  SNR 10-40 dB;
- the grid: 30-80 % of the aperture's width, 5-30 cm deep, voxels of 0.25-0.6 top-band
  wavelengths (coarser where the request would pass :data:`MAX_PAIRS` voxel-measurement pairs).

For each request, in one run on one device: every formation at its defaults and ``auto`` (its
choosing included), timed in turn round after round and each one's fastest kept
(:func:`bench.crossover._interleaved`), and their error against bp over the grid. *Best* is
the fastest formation whose measured error meets the target (bp always does). :func:`summarise`
gives the share of requests where auto took the best, the share where it is within 20 % of the
best's time (overall, and where the best takes 50 ms or more), the share where its measured error
is over its target, the median and worst time over the best, and which formations it took.

The seeds are split once: :data:`TUNING_SEEDS` (and the fit seeds 500-599 the cost and error
models were refitted on) may be looked at while changing the choice; :data:`HELD_OUT_SEEDS`,
:data:`HELD_OUT_2_SEEDS`, :data:`HELD_OUT_3_SEEDS` and :data:`HELD_OUT_4_SEEDS` are for reports
only (``python -m bench --formation-family held-out``), each run once on the code it judged.
Benchmarks measure; nothing here asserts.
"""

from __future__ import annotations

import logging
import os

import numpy as np

import clsas
from clsas import validate as v
from clsas.formation import form
from clsas.formation.auto import DEFAULT_MAX_ERROR_DB, choose, form_choice, load_calibration

from .crossover import _errors, _interleaved
from .crossover import profiles as _profiles

__all__ = ["TUNING_SEEDS", "HELD_OUT_SEEDS", "HELD_OUT_2_SEEDS", "HELD_OUT_3_SEEDS", "HELD_OUT_4_SEEDS",
           "SEED_SETS", "MAX_PAIRS", "WITHIN", "draw", "family_request", "run_request", "run_family", "summarise",
           "markdown", "run_and_write"]

log = logging.getLogger(__name__)

TUNING_SEEDS = tuple(range(0, 20))
HELD_OUT_SEEDS = tuple(range(1000, 1030))
#: Further held-out sets, each run once on the code it judged, and nothing tuned on what it showed: the
#: first before auto weighed ω-k with its aliased angles formed, the second after, the third after that
#: candidate was limited to angles under a sine of 0.75 (the crossover's 128 x 128 scan went over its
#: target with it), the fourth after FFBP's lower bound was made one (it had passed over FFBP where it
#: was faster), the fifth after auto began to measure a formation's error on a sub-lattice where its
#: prediction was near the target (clsas.formation.auto.measure), the sixth after the review's fixes to it
#: (a near candidate lowers FFBP's planning bound only where auto would try it; a flat grid's stride),
#: the seventh after plain ω-k with any aliased voxel-stop pair was taken only measured, the eighth
#: after that rule was kept to where the check costs at most as much as ω-k.
HELD_OUT_2_SEEDS = tuple(range(2000, 2030))
HELD_OUT_3_SEEDS = tuple(range(3000, 3030))
HELD_OUT_4_SEEDS = tuple(range(4000, 4030))
HELD_OUT_5_SEEDS = tuple(range(5000, 5030))
HELD_OUT_6_SEEDS = tuple(range(6000, 6030))
HELD_OUT_7_SEEDS = tuple(range(7000, 7030))
HELD_OUT_8_SEEDS = tuple(range(8000, 8030))
SEED_SETS = {"tuning": TUNING_SEEDS, "held-out": HELD_OUT_SEEDS, "held-out-2": HELD_OUT_2_SEEDS,
             "held-out-3": HELD_OUT_3_SEEDS, "held-out-4": HELD_OUT_4_SEEDS, "held-out-5": HELD_OUT_5_SEEDS,
             "held-out-6": HELD_OUT_6_SEEDS, "held-out-7": HELD_OUT_7_SEEDS,
             "held-out-8": HELD_OUT_8_SEEDS}
#: Most voxel-measurement pairs a request may have (bp's time: about 2-3 s on a 2-core CPU).
MAX_PAIRS = 1.5e9
#: auto counts as right where its time is at most this times the best's.
WITHIN = 1.2
#: The summary also counts apart the requests whose best formation takes at least this long, s: under
#: it, auto's own choosing (0.3-4 ms) and the host's jitter (a 10 ms call varies by 1.5x) weigh.
LARGE_S = 0.05
FS = 96e3
KINDS = ("planar", "jittered", "ring")
FORMS = ("bp", "omega-k", "ffbp")


def _targets(rng, centre, size, kind):
    """(points (n, 3), amplitudes (n,)): points in a box of ``size`` about ``centre``, or a rough tilted plane."""
    if kind == "points":
        n = int(rng.integers(2, 11))
        pts = centre + (rng.uniform(-0.5, 0.5, (n, 3)) * size)
        return pts, rng.uniform(0.3, 1.0, n)
    n = 100
    uv = rng.uniform(-0.5, 0.5, (n, 2)) * size[:2]
    tilt = rng.uniform(-0.4, 0.4, 2)
    z = uv @ tilt + rng.normal(0, 0.002, n)
    return centre + np.c_[uv, z], rng.uniform(0.3, 1.0, n)


def draw(seed: int, max_pairs: float = MAX_PAIRS) -> dict:
    """What the request of ``seed`` is, before anything is simulated: ``aperture``, ``scene``,
    ``waveform``, ``chirp``, ``snr_db``, ``grid`` and ``params`` (see the module notes)."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    max_pairs = v.positive("max_pairs", max_pairs)
    rng = np.random.default_rng([int(seed), 31])
    kind = KINDS[int(rng.choice(3, p=[0.5, 0.25, 0.25]))]
    f0 = rng.uniform(10e3, 25e3)
    f1 = f0 + rng.uniform(4e3, 15e3)
    dur = rng.uniform(1e-3, 4e-3)
    lam = 343.0 / f1
    rng_m = rng.uniform(0.3, 1.5)
    if kind == "ring":
        n = int(rng.integers(90, 361))
        radius = rng.uniform(0.4, 1.2)
        ap = clsas.circular_aperture(n, radius, mode="arc")
        half = radius * rng.uniform(0.1, 0.25)
        centre, box = np.zeros(3), np.array([2 * half, 2 * half, rng.uniform(0.04, 0.2)])
        what = f"ring of {n} stops, {radius:.2f} m"
    else:
        nx = int(np.exp(rng.uniform(np.log(10), np.log(64))))
        ny = max(8, int(nx * rng.uniform(0.6, 1.0)))
        pitch = lam * rng.uniform(0.4, 1.2)
        ap = clsas.raster_aperture(nx, ny, pitch * (nx - 1), pitch * (ny - 1))
        if kind == "jittered":
            j = np.c_[rng.uniform(-0.1, 0.1, (ap.n_meas, 2)) * pitch, np.zeros(ap.n_meas)]
            ap = clsas.Aperture(ap.tx_positions + j, ap.rx_positions + j, ap.stage_positions + j, ap.mics_per_stop)
        side = pitch * (nx - 1)
        frac = rng.uniform(0.3, 0.8)
        centre = np.array([0.0, 0.0, rng_m])
        box = np.array([frac * side, frac * pitch * (ny - 1), rng.uniform(0.05, 0.3)])
        what = f"{kind} {nx} x {ny} stops, {pitch * 1e3:.1f} mm pitch"
    target = "points" if rng.random() < 0.5 else "plane"
    pts, amps = _targets(rng, centre, 0.7 * box, target)
    spacing = lam * rng.uniform(0.25, 0.6)
    while np.prod(np.ceil(box / spacing) + 1) * ap.n_meas > max_pairs:
        spacing *= 1.1
    lo = centre - box / 2
    grid = clsas.VoxelGrid(*(np.arange(lo[i], lo[i] + box[i] + 0.5 * spacing, spacing) for i in range(3)))
    snr = float(rng.uniform(10, 40))
    chirp = {"f_start_hz": f0, "f_stop_hz": f1, "duration_s": dur}
    params = {"seed": int(seed), "kind": kind, "target": target, "what": what, "band_hz": [f0, f1],
              "duration_s": dur, "range_m": float(centre[2]), "snr_db": snr, "spacing_m": spacing,
              "grid_shape": list(grid.shape), "measurements": ap.n_meas, "voxels": grid.size,
              "pairs": float(ap.n_meas) * grid.size}
    return {"aperture": ap, "scene": clsas.Scene(pts, amps), "waveform": clsas.lfm_chirp(f0, f1, dur, FS, taper=0.1),
            "chirp": chirp, "snr_db": snr, "grid": grid, "params": params}


def family_request(seed: int, max_pairs: float = MAX_PAIRS):
    """``(dataset, grid, params)``: the request drawn from ``seed`` (:func:`draw`), simulated."""
    d = draw(seed, max_pairs)
    ds = clsas.simulate(d["scene"], d["aperture"], d["waveform"], FS, snr_db=d["snr_db"], seed=int(seed),
                        chirp=d["chirp"])
    return ds, d["grid"], d["params"]


def run_request(seed: int, *, target_db: float = DEFAULT_MAX_ERROR_DB, max_pairs: float = MAX_PAIRS,
                say=None) -> dict:
    """Every formation and auto on the request of ``seed``: ``params`` plus ``rows`` (each formation's
    time and error over the grid against bp, or why it refused; auto's choice, time and error), and
    ``auto`` (what it took, the best formation, its time over the best's, whether it was over its
    target). Times: :func:`_interleaved`."""
    say = say or (lambda s: log.info("%s", s))
    ds, grid, row = family_request(seed, max_pairs)
    prof = _profiles(ds, grid)
    sel = clsas.cl.select(None)
    row.update(load_before=os.getloadavg(), rows=[])
    say(f"formation family: seed {seed} ({row['what']}, {grid.size} voxels)")
    images, fns = {}, {}
    for f in FORMS:
        try:
            images[f] = form(prof, grid, f)
        except ValueError as exc:  # omega-k refuses an aperture off its lattice
            row["rows"].append({"formation": f, "refused": str(exc)})
            continue
        fns[f] = lambda f=f: form(prof, grid, f)
    images["auto"], choice = form_choice(prof, grid, choose(prof, grid, sel, max_error_db=target_db))

    def auto():
        return form_choice(prof, grid, choose(prof, grid, sel, max_error_db=target_db))[0]

    took = _interleaved({**fns, "auto": auto})
    ref = images["bp"]
    for f in fns:
        r = {"formation": f, "time_s": took[f], "backend": images[f].backend}
        r.update({"error_all_db": None} if f == "bp" else _errors(images[f], ref, None))
        row["rows"].append(r)
    ok = [r for r in row["rows"] if "time_s" in r and (r["error_all_db"] is None or r["error_all_db"] <= target_db)]
    best = min(ok, key=lambda r: r["time_s"])
    err = None if choice["formation"] == "bp" else _errors(images["auto"], ref, None)["error_all_db"]
    a = {"formation": "auto", "chose": choice["formation"], "options": choice["options"], "reason": choice["reason"],
         "checks": choice["checks"],
         "time_s": took["auto"], "error_all_db": err, "best": best["formation"],
         "over_best": took["auto"] / best["time_s"]}
    row["rows"].append(a)
    row["auto"] = {k: a[k] for k in ("chose", "best", "over_best", "error_all_db", "reason", "checks")}
    row["auto"]["over_target"] = err is not None and err > target_db
    row["load_after"] = os.getloadavg()
    return row


def run_family(seeds, *, target_db: float = DEFAULT_MAX_ERROR_DB, max_pairs: float = MAX_PAIRS,
               status=None) -> list[dict]:
    """:func:`run_request` for each seed (warmed up first); a request that raises is a row with its ``error``."""
    from .crossover import _warm_up

    _warm_up()
    rows = []
    for s in seeds:
        try:
            rows.append(run_request(int(s), target_db=target_db, max_pairs=max_pairs, say=status))
        except (ValueError, RuntimeError, MemoryError) as exc:  # a failure is a result too
            rows.append({"seed": int(s), "error": f"{type(exc).__name__}: {exc}"})
    return rows


def summarise(rows: list[dict]) -> dict:
    """The distribution over requests (rows with an ``error`` counted apart)."""
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return {"n": 0, "failed": len(rows)}
    over = np.array([r["auto"]["over_best"] for r in ok])
    chose = [r["auto"]["chose"] for r in ok]
    best_s = np.array([min(q["time_s"] for q in r["rows"] if q.get("formation") == r["auto"]["best"]) for r in ok])
    large = best_s >= LARGE_S
    return {"n": len(ok), "failed": len(rows) - len(ok),
            "within": float(np.mean(over <= WITHIN)), "within_factor": WITHIN,
            "n_large": int(large.sum()), "within_large": float(np.mean(over[large] <= WITHIN)) if large.any() else None,
            "over_target": float(np.mean([r["auto"]["over_target"] for r in ok])),
            "chose_best": float(np.mean([r["auto"]["chose"] == r["auto"]["best"] for r in ok])),
            "median_over_best": float(np.median(over)), "worst_over_best": float(over.max()),
            "worst_seed": int(ok[int(np.argmax(over))]["seed"]),
            "chose": {f: chose.count(f) for f in sorted(set(chose))},
            "measured": int(sum(bool(r["auto"].get("checks")) for r in ok)),
            "gave_way": int(sum(any(not c["kept"] for c in r["auto"].get("checks", [])) for r in ok)),
            "best": {f: [r["auto"]["best"] for r in ok].count(f) for f in FORMS}}


def _cell(r: dict) -> str:
    if "refused" in r:
        return "refused"
    err = r.get("error_all_db")
    return f"{r['time_s'] * 1e3:.0f} ms" + ("" if err is None else f", {err:.0f} dB")


def _checked(a: dict) -> str:
    """The formations auto measured and let go, as ``omega-k (-27 dB) -> ``."""
    return "".join(f"{c['formation']} ({c['error_db']:.0f} dB) -> " for c in a.get("checks", []) if not c["kept"])


def markdown(rows: list[dict], summary: dict, target_db: float) -> str:
    """The summary and one line per request."""
    s = summary
    md = [f"{s['n']} requests ({s['failed']} failed). Error target {target_db:g} dB over the grid, against bp.", "",
          f"- auto within {WITHIN:g}x the best formation's time: **{s['within']:.0%}** (median "
          f"{s['median_over_best']:.2f}x, worst {s['worst_over_best']:.2f}x on seed {s['worst_seed']}); on the "
          f"{s['n_large']} requests whose best takes {LARGE_S * 1e3:.0f} ms or more: "
          + ("none" if s["within_large"] is None else f"**{s['within_large']:.0%}**") + ";",
          f"- auto's measured error over its target: **{s['over_target']:.0%}**;",
          f"- auto took the best formation in {s['chose_best']:.0%}; took "
          + ", ".join(f"{k} {n}" for k, n in s["chose"].items()) + "; the best was "
          + ", ".join(f"{k} {n}" for k, n in s["best"].items() if n) + ";",
          f"- auto measured a formation's error on a sub-lattice in {s.get('measured', 0)} requests; in "
          f"{s.get('gave_way', 0)} of them one missed the target and gave way to the next.", "",
          "| seed | request | voxels | pairs | bp | omega-k | ffbp | auto | auto / best |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            md.append(f"| {r['seed']} | {r['error']} | | | | | | | |")
            continue
        by = {q["formation"]: q for q in r["rows"]}
        a = by["auto"]
        md.append(f"| {r['seed']} | {r['what']}, {r['target']} at {r['range_m']:.2f} m, "
                  f"{r['band_hz'][0] / 1e3:.0f}-{r['band_hz'][1] / 1e3:.0f} kHz | {r['voxels']} | {r['pairs']:.2g} | "
                  f"{_cell(by['bp'])} | {_cell(by['omega-k'])} | {_cell(by['ffbp'])} | {_checked(a)}{a['chose']}: "
                  f"{_cell(a)} | {a['over_best']:.2f} ({a['best']}) |")
    return "\n".join(md) + "\n"


def _plot(rows: list[dict], path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error" not in r]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for f, m in zip(FORMS, ("o", "s", "^"), strict=True):
        sel = [r for r in ok if r["auto"]["chose"] == f]
        ax.scatter([r["pairs"] for r in sel], [r["auto"]["over_best"] for r in sel], marker=m, label=f"auto took {f}")
    ax.axhline(WITHIN, color="k", lw=0.8, ls="--", label=f"{WITHIN:g}x the best")
    ax.set_xscale("log")
    ax.set_xlabel("voxel-measurement pairs")
    ax.set_ylabel("auto's time / the best formation's")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_and_write(seed_set: str = "tuning", *, n_seeds: int | None = None, out_dir=None, plots: bool = True,
                  target_db: float = DEFAULT_MAX_ERROR_DB, status=None) -> dict:
    """The family on ``seed_set`` (a key of :data:`SEED_SETS`; the first ``n_seeds`` only),
    summarised and written to ``out_dir`` as ``<date>-formation-family-<set>.{json,md,png}``.

    Returns ``{"summary", "rows", "paths"}``.
    """
    import datetime
    import json
    import platform
    from pathlib import Path

    from .stats import jsonable

    v.choice("seed_set", seed_set, tuple(SEED_SETS))
    if n_seeds is not None:
        n_seeds = v.positive_int("n_seeds", n_seeds)
    seeds = list(SEED_SETS[seed_set])[:n_seeds]
    rows = run_family(seeds, target_db=target_db, status=status)
    summary = summarise(rows)
    paths = {}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        stem = out / f"{datetime.date.today().isoformat()}-formation-family-{seed_set}"
        sel = clsas.cl.select(None)
        host = {"machine": platform.machine(), "cpus": os.cpu_count(), "device": sel.device,
                "calibration": load_calibration(sel) or "built-in (not calibrated on this device)",
                "load": os.getloadavg()}
        stem.with_suffix(".json").write_text(json.dumps(jsonable({"seed_set": seed_set, "seeds": seeds, "host": host,
                                                                  "target_db": target_db, "summary": summary,
                                                                  "rows": rows}), indent=1))
        md = f"# formation=\"auto\" on the request family ({seed_set} seeds {seeds[0]}-{seeds[-1]})\n\n"
        if plots and summary.get("n"):
            _plot(rows, stem.with_suffix(".png"))
            paths["png"] = stem.with_suffix(".png")
            md += f"![auto over the best]({stem.with_suffix('.png').name})\n\n"
        stem.with_suffix(".md").write_text(md + markdown(rows, summary, target_db) + f"\nhost: {host}\n")
        paths.update(json=stem.with_suffix(".json"), md=stem.with_suffix(".md"))
    return {"summary": summary, "rows": rows, "paths": paths}
