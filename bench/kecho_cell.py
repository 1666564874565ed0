"""One cell of the K-echo table with more profiles than the table's 10 (one profile there is 10
points): CBP-Polar, known-count ML and BPDN + detect on the same profiles, with the bound and
the bound with the 1 % order test (bench.kecho.detection_success).

    python -m bench.kecho_cell --k 10 --ratio 0.1 --profiles 40 [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from bench.kecho import run_k_trial

METHODS = ("cbp-polar", "mlk", "bpdn-detect")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--ratio", type=float, default=0.1)
    ap.add_argument("--profiles", type=int, default=40)
    ap.add_argument("--out", default=None, help="JSON file (default: print only)")
    args = ap.parse_args()
    rows, t, load = [], time.perf_counter(), os.getloadavg()[0]
    for seed in range(args.profiles):
        rows += [run_k_trial(m, args.k, args.ratio, seed) for m in METHODS]
        print(seed, {r["method"]: r["success"] for r in rows[-len(METHODS):]}, flush=True)
    out = {"k": args.k, "ratio": args.ratio, "profiles": args.profiles, "load_start": load,
           "load_end": os.getloadavg()[0], "wall_s": time.perf_counter() - t, "rows": rows}
    for m in METHODS:
        rs = [r for r in rows if r["method"] == m]
        out[m] = float(np.mean([r["success"] for r in rs]))
        out[m + "_median_s"] = float(np.median([r["time_s"] for r in rs]))
    out["bound"] = float(np.mean([r["bound_success"] for r in rows if r["method"] == METHODS[0]]))
    out["bound_with_order_test"] = float(np.mean([r["bound_detect_success"] for r in rows
                                                  if r["method"] == METHODS[0]]))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
    print({k: v for k, v in out.items() if k != "rows"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
