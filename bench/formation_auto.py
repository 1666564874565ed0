"""The formation figures in one run: the crossover table (bp, omega-k, FFBP, auto over N = 16-128
stops a side, grids growing with N; it calibrates auto's cost model on this device), then auto on the
demo, circular and dense cases (calibrated model), written to bench/results/<date>-formation-auto-<tag>.*

Usage: python -m bench.formation_auto [--tag vm] [--sides 16 24 32 48 64 96 128] [--dense-scale 0.5]
"""

import argparse
import datetime as dt
import json
import os
import platform
from pathlib import Path

from bench import crossover as cx
from bench import formation as bf
from bench.stats import jsonable
from bench.throughput import opencl_device_info


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tag", default="vm")
    ap.add_argument("--sides", type=int, nargs="+", default=list(cx.CROSSOVER_FULL))
    ap.add_argument("--dense-scale", type=float, default=0.5)
    ap.add_argument("--out", default="bench/results")
    args = ap.parse_args()
    info = opencl_device_info() or {"name": "NumPy only"}
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "device": info["name"],
           "host": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
           "uptime_before": os.getloadavg()}
    res["crossover"] = cx.crossover(tuple(args.sides), status=lambda s: print(s, flush=True))
    res["cases"] = [bf.run_case(c, None, args.dense_scale if c == "dense" else 1.0, status=print)
                    for c in ("demo", "circular", "dense")]
    res["uptime_after"] = os.getloadavg()
    out = Path(args.out)
    stem = f"{dt.date.today()}-formation-auto-{args.tag}"
    (out / f"{stem}.json").write_text(json.dumps(jsonable(res), indent=1))
    md = [f"# formation='auto' and the crossover table, {res['date']}", "",
          f"Device: {res['device']}. Host: {res['host']}. Load average (1, 5, 15 min) before "
          f"{res['uptime_before']}, after {res['uptime_after']}.", ""]
    md += bf.markdown({"cases": res["cases"], "crossover": res["crossover"]})
    (out / f"{stem}.md").write_text("\n".join(md))
    print(f"wrote {out / stem}.json and .md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
