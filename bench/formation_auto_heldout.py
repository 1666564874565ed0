"""formation='auto' on held-out crossover scans: sizes and seeds the cost model was not fitted on.

    python -m bench.formation_auto_heldout [--out bench/results]

The built-in cost model (:data:`clsas.formation.auto.BUILTIN`) was fitted on the crossover scans
of :mod:`bench.crossover` (N = 16-128 stops a side, seed 0). Here: N = 20, 40, 56, 80 with
seeds 1001-1004 (one seed per size), every formation timed as the crossover times it, auto with
its choosing; no device calibration is used (the cache is pointed at an empty folder).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import tempfile
from pathlib import Path

HELD_OUT = ((20, 1001), (40, 1002), (56, 1003), (80, 1004))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    os.environ["CLSAS_CACHE_DIR"] = tempfile.mkdtemp()  # the built-in model, no stored calibration
    import clsas
    from bench import crossover as X
    from bench.stats import jsonable
    from clsas.formation import form

    X._warm_up()
    rows = []
    for n, seed in HELD_OUT:
        ds, grid = X.crossover_case(n, seed)
        prof = X.profiles(ds, grid)
        mask = X.cone(ds, grid)
        out = []
        ref = None
        for f in X.FORMS:
            took, img = X._timed(lambda f=f, p=prof, g=grid: form(p, g, f))
            r = {"formation": f, "time_s": took}
            if f == "bp":
                ref = img
                r.update(error_all_db=None, error_cone_db=None)
            else:
                r.update(X._errors(img, ref, mask))
            out.append(r)
        auto = X.auto_row(prof, grid, ref, mask, out)
        rows.append({"n": n, "seed": seed, "voxels": grid.size, "rows": out, "auto": auto})
        print(f"N={n} seed {seed}: " + ", ".join(f"{r['formation']} {r['time_s']:.3f} s" for r in out)
              + f"; auto -> {auto['chose']} {auto['time_s']:.3f} s, best {auto['best']}, "
              f"{auto['over_best']:.2f}x the best", flush=True)
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": clsas.cl.select(None).device,
           "load": os.getloadavg(), "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{dt.date.today()}-formation-auto-held-out"
    stem.with_suffix(".json").write_text(json.dumps(jsonable(res), indent=1))
    md = [f"# formation='auto' on held-out crossover scans, {res['date']}", "",
          f"Device: {res['device']}; load at the end {res['load']}. Script: `bench/formation_auto_heldout.py` "
          "(built-in cost model, fitted on the crossover scans N = 16-128, seed 0).", "",
          "| N | seed | voxels | bp | omega-k (error) | ffbp (error) | auto chose | best | auto / best |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = {x["formation"]: x for x in r["rows"]}
        a = r["auto"]

        def cell(f, t=t):
            x = t[f]
            return f"{x['time_s']:.3f} s ({x['error_all_db']:.0f} dB)"

        md.append(f"| {r['n']} | {r['seed']} | {r['voxels']} | {t['bp']['time_s']:.3f} s | {cell('omega-k')} | "
                  f"{cell('ffbp')} | {a['chose']} | {a['best']} | {a['over_best']:.2f} |")
    stem.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
