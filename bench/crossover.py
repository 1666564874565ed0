"""Where each formation wins: the crossover table (bp, ω-k, FFBP, auto) and the calibration of auto's cost model.

Dense planar scans of N x N stops 5.6 mm apart (about lambda/2 at 30 kHz), three reflectors at
0.62-0.70 m, onto grids that grow with the aperture: 4 mm voxels over the middle two thirds of
the aperture laterally, 0.58-0.74 m deep (41 planes). For each N, in one run on one device:
the time of ``form(profiles, grid, f)`` for bp, omega-k and ffbp at their defaults (FFBP's
remembered tree forgotten first, so that its planning is timed; the faster of two runs where
one takes under 2 s), their error against bp over
the grid and inside the well-sampled cone, the built-in cost model's prediction, and
``formation="auto"`` (choosing included) with what it took and its time over the best formation
that meets its error target. The load average is recorded before and after each N (the machine
may be shared: the ratios are what count).

The calibration of ``formation="auto"`` is :func:`clsas.formation.auto.calibrate_auto`'s
(``clsas calibrate``): per formation, the median over the rows of measured / predicted time,
stored for the device; the table stores it too.
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

import clsas
from clsas.formation import error_to_signal_db, form
from clsas.formation.auto import DEFAULT_MAX_ERROR_DB, choose, form_choice, store_calibration
from clsas.formation.auto.calibrate import (
    FORMS,
    PITCH,
    SIDES_FULL,
    SIDES_QUICK,
    VOXEL,
    best_time,
    calibration_case,
    case_profiles,
    factors_of,
    forget_tree,
    time_formations,
    warm_up,
)

from .stats import seconds

__all__ = [
    "FORMS", "CROSSOVER_QUICK", "CROSSOVER_FULL", "crossover_case", "profiles", "cone", "auto_row", "crossover",
    "calibrate", "markdown",
]

log = logging.getLogger(__name__)

CROSSOVER_QUICK = SIDES_QUICK
CROSSOVER_FULL = SIDES_FULL
TARGET_DB = DEFAULT_MAX_ERROR_DB
# the scans, their profiles and the timing rule are those of auto's calibration (clsas calibrate)
crossover_case = calibration_case
profiles = case_profiles
_timed = best_time
_warm_up = warm_up
_forget_tree = forget_tree


def cone(ds, grid):
    """The well-sampled cone at 30 kHz, or None for an aperture without a lattice."""
    from clsas.formation.planar import NotPlanarUniform, well_sampled_cone

    try:
        return well_sampled_cone(ds.tx_positions, ds.rx_positions, grid, 30e3, float(np.mean(ds.c_mps)))
    except NotPlanarUniform:
        return None


# fewest and most timing rounds (each times every formation and auto once, in turn); 5 at the least since
# the dense case's ω-k took 1.4-2.9 s from one call to the next, and 3 rounds gave auto 1.04-2.0x it
ROUNDS = (5, 25)
ROUNDS_FOR_S = 2.0  # ... rounds go on until this much time has been spent
# ... or one call takes this long (one round then). It was ROUNDS_FOR_S: on the dense case's 2-3 s
# formations one round each, and ω-k alone took 1.5-2.9 s from one call to the next there
LONG_CALL_S = 20.0


def _interleaved(fns: dict) -> dict:
    """The fastest time of each of ``fns`` (name: callable), timed in turn, round after round.

    On a shared 2-core host a 10 ms call varies by 1.5x and more from one moment to the next, in
    bursts that outlast several calls: taking each one's fastest of calls made in turn with the
    others gives them all the same moments (unlike timing one after the other)."""
    best = dict.fromkeys(fns, float("inf"))
    spent, rounds = 0.0, 0
    while True:
        for name, fn in fns.items():
            _forget_tree()  # FFBP's tree is planned inside each call, and auto's choosing
            t = time.perf_counter()
            fn()
            took = time.perf_counter() - t
            best[name], spent = min(best[name], took), spent + took
        rounds += 1
        if rounds >= ROUNDS[1] or max(best.values()) >= LONG_CALL_S or (rounds >= ROUNDS[0]
                                                                         and spent >= ROUNDS_FOR_S):
            return best


def _errors(img, ref, mask) -> dict:
    return {"error_all_db": error_to_signal_db(img, ref),
            "error_cone_db": error_to_signal_db(img, ref, mask) if mask is not None and mask.any() else None}


def auto_row(prof, grid, ref, mask, rows: list[dict], target_db: float = TARGET_DB) -> dict:
    """``formation="auto"`` timed (choosing included) against ``rows`` (the formations' own rows:
    ``formation``, ``time_s``, ``error_all_db``; bp's error None) at the error target ``target_db``:
    its time over the best's is taken with the two timed in turn (:func:`_interleaved`)."""
    def run():
        choice = choose(prof, grid, clsas.cl.select(None), max_error_db=target_db)
        img, record = form_choice(prof, grid, choice)
        return record, img

    choice, img = run()
    ok = [r for r in rows if "time_s" in r and (r.get("error_all_db") is None or r["error_all_db"] <= target_db)]
    best = min(ok, key=lambda r: r["time_s"])
    bp = next(r for r in rows if r["formation"] == "bp")
    # auto and the best timed in turn (the same moments of the host's load for both)
    took = _interleaved({"auto": run, "best": lambda: form(prof, grid, best["formation"])})
    return {"formation": "auto", "chose": choice["formation"], "options": choice["options"], "reason": choice["reason"],
            "checks": choice["checks"],
            "model": choice["model"], "time_s": took["auto"], "backend": img.backend, "best": best["formation"],
            "best_in_turn_s": took["best"], "over_best": took["auto"] / took["best"],
            "speedup": bp["time_s"] / took["auto"],
            **({"error_all_db": None, "error_cone_db": None} if choice["formation"] == "bp"
               else _errors(img, ref, mask))}


def _one(n: int, say) -> dict:
    ds, grid = crossover_case(n)
    prof = profiles(ds, grid)
    cone_mask = cone(ds, grid)
    sel = clsas.cl.select(None)
    row = {"n": n, "measurements": ds.n_meas, "grid_shape": list(grid.shape), "voxels": grid.size,
           "pairs": float(ds.n_meas) * grid.size,
           "cone_fraction": None if cone_mask is None else float(cone_mask.mean()),
           "load_before": os.getloadavg(), "rows": []}
    say(f"crossover: N = {n} ({ds.n_meas} stops, {grid.size} voxels)")
    timed, images = time_formations(prof, grid, sel, say)
    ref = images["bp"]
    for r in timed:
        if r["formation"] == "bp":
            r.update(error_all_db=None, error_cone_db=None)
        else:
            r.update(_errors(images[r["formation"]], ref, cone_mask), speedup=timed[0]["time_s"] / r["time_s"])
        row["rows"].append(r)
    say(f"crossover: auto at N = {n}")
    row["rows"].append(auto_row(prof, grid, ref, cone_mask, row["rows"]))
    row["load_after"] = os.getloadavg()
    return row


def calibrate(rows: list[dict]) -> dict[str, float]:
    """Per formation, the median of measured / built-in predicted time over ``rows``' entries."""
    return factors_of([r for row in rows for r in row["rows"]])


def crossover(sides=CROSSOVER_QUICK, status=None, store: bool = True) -> dict:
    """The crossover table over ``sides`` (N x N stops), then the calibration (stored unless ``store`` is False)."""
    say = status or (lambda s: log.info("%s", s))
    _warm_up()
    rows = [_one(int(n), say) for n in sides]
    factors = calibrate(rows)
    out = {"sides": list(sides), "rows": rows, "calibration": factors, "target_db": TARGET_DB}
    if store and factors:
        path = store_calibration(factors, clsas.cl.select(None), detail={"sides": list(sides)})
        out["calibration_path"] = str(path)
        say(f"crossover: cost model calibrated ({', '.join(f'{k} x{x:.2f}' for k, x in factors.items())}), "
            f"kept in {path}")
    return out


def _cell(r: dict) -> str:
    err = r.get("error_all_db")
    cone = r.get("error_cone_db")
    tail = "" if err is None else f", {r['speedup']:.1f}x, {err:.0f} dB"
    tail += "" if cone is None or err is None else f" ({cone:.0f} cone)"
    return f"{seconds(r['time_s'])}{tail}"


def markdown(res: dict) -> list[str]:
    """The crossover section of the formation report."""
    md = ["", "### Crossover: dense planar scans, grids growing with N", "",
          f"N x N stops {PITCH * 1e3:.1f} mm apart, 3 reflectors at 0.62-0.70 m, {VOXEL * 1e3:.0f} mm voxels over the "
          "middle two thirds of the aperture, 0.58-0.74 m deep. Each cell: time, speed-up over bp, error against bp "
          f"over the grid (and in the well-sampled cone). auto: what it took, its time (choosing included) over the "
          f"fastest formation within {TARGET_DB:g} dB. Load average (1 min) before each N.", "",
          "| N | stops | voxels | cone | bp | omega-k | ffbp | auto | auto / best | load |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for row in res["rows"]:
        by = {r["formation"]: r for r in row["rows"]}
        a = by["auto"]
        cone = "n/a" if row["cone_fraction"] is None else f"{100 * row['cone_fraction']:.0f} %"
        md.append(f"| {row['n']} | {row['measurements']} | {' x '.join(map(str, row['grid_shape']))} | {cone} | "
                  f"{_cell(by['bp'])} | {_cell(by['omega-k'])} | {_cell(by['ffbp'])} | {a['chose']}: "
                  f"{seconds(a['time_s'])} | {a['over_best']:.2f} ({a['best']}) | {row['load_before'][0]:.1f} |")
    if res.get("calibration"):
        md += ["", "Calibration of auto's cost model (measured / built-in prediction, median over N): "
               + ", ".join(f"{k} {x:.2f}" for k, x in res["calibration"].items())
               + (f"; kept in `{res['calibration_path']}`." if res.get("calibration_path") else ".")]
    return md
