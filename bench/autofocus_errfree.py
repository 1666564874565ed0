"""Autofocus on error-free scans of the seeded family: what it applies where nothing is wrong.

    python -m bench.autofocus_errfree [--set tuning-2] [--n-seeds N] [--out DIR]

For each seed of the set, the scene's error-free scan (``family_scene(seed, rms_m=0).clean``: no
hand motion, no group delay, no air temperature error) is autofocused with three method sets:
the default (``("direct",)``), ``FOCUS_METHODS`` and the hand-held set ``("direct", "points",
"track")``. It records what was applied and the local peak at the error-free image's brightest
voxel after against before, in dB, as the family bench scores it (``bench.autofocus_family``).
A correction applied here is one the scan did not need; the target is that nothing is applied
in 95 % of the scenes and no image gets worse. Writes ``<date>-autofocus-errfree-<set>.json``
and ``.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

METHOD_SETS = {"default": ("direct",), "focus": None, "hand": ("direct", "points", "track")}


def run(seeds, status=print) -> list[dict]:
    import clsas
    from clsas.focus import FOCUS_METHODS
    from clsas.synthesis.scene_family import family_scene

    from .autofocus_family import local_peak_db

    rows = []
    for seed in seeds:
        fs = family_scene(seed, rms_m=0.0)
        ds, grid = fs.clean, fs.grid
        image = np.abs(clsas.reconstruct(ds, grid, formation="bp").values)
        point = grid.points()[int(np.argmax(image.ravel()))]  # the reference voxel, as the family bench's
        ref_db = local_peak_db(ds, point)
        for name, methods in METHOD_SETS.items():
            t = time.perf_counter()
            out, rep = clsas.autofocus(ds, grid, methods=methods or FOCUS_METHODS)
            elapsed = time.perf_counter() - t
            change_db = local_peak_db(out, point) - ref_db if rep.improved else 0.0
            rows.append({"seed": seed, "kind": fs.kind, "methods": name, "improved": rep.improved,
                         "applied": sorted(k for k, p in rep.parameters.items() if p.applied),
                         "peak_change_db": change_db, "time_s": elapsed,
                         "estimates": {k: [p.estimate, p.uncertainty, p.determined]
                                       for k, p in rep.parameters.items()}})
            status(f"seed {seed} ({fs.kind}), {name}: applied {rows[-1]['applied'] or 'nothing'}, "
                   f"local peak {change_db:+.2f} dB")
    return rows


def summary(rows: list[dict]) -> list[str]:
    md = ["| methods | scenes | nothing applied | worse by > 0.5 dB (any) | local peak change, dB (min, max) "
          "| applied |",
          "|---|---|---|---|---|---|"]
    for name in METHOD_SETS:
        rs = [r for r in rows if r["methods"] == name]
        if not rs:
            continue
        change = [r["peak_change_db"] for r in rs]
        applied = Counter(p for r in rs for p in r["applied"])
        nothing = [not r["applied"] for r in rs]
        md.append(f"| {name} | {len(rs)} | {sum(nothing)} ({np.mean(nothing):.0%}) | "
                  f"{sum(x < -0.5 for x in change)} ({sum(x < -1e-6 for x in change)}) | "
                  f"{min(change):+.2f}, {max(change):+.2f} | "
                  f"{', '.join(f'{k} {n}' for k, n in applied.items()) or '-'} |")
    return md


def main(argv: list[str] | None = None) -> int:
    from clsas.synthesis.scene_family import SEED_SETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="tuning-2", choices=sorted(SEED_SETS), help="the seed set (default tuning-2)")
    ap.add_argument("--n-seeds", type=int, default=None, help="the first N seeds of the set only")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args(argv)
    if args.n_seeds is not None and args.n_seeds < 1:
        ap.error("--n-seeds must be at least 1")
    logging.disable(logging.WARNING)
    seeds = SEED_SETS[args.set][: args.n_seeds]
    rows = run(seeds)
    md = [f"# Autofocus on error-free scans, {args.set} seeds {seeds[0]}-{seeds[-1]}, {dt.date.today()}", "",
          "Script: `python -m bench.autofocus_errfree`; the local peak at the error-free image's brightest voxel, "
          "after against before.", "", *summary(rows)]
    print("\n".join(md))
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{dt.date.today()}-autofocus-errfree-{args.set}"
    stem.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    stem.with_suffix(".md").write_text("\n".join(md) + "\n")
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
