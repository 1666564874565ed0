"""JSON, Markdown and PNG of a benchmark run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .stats import jsonable

__all__ = ["write_report", "write_run", "markdown"]


def write_report(res: dict, out_dir: Path, stem: str, plots: bool = True) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / f"{stem}.json", "markdown": out_dir / f"{stem}.md"}
    if plots:
        paths["png"] = out_dir / f"{stem}.png"
    paths_s = {k: str(v) for k, v in paths.items()}
    paths["json"].write_text(json.dumps(jsonable({**res, "paths": paths_s}), indent=1))
    paths["markdown"].write_text(markdown(res, paths.get("png")))
    if plots:
        _plot(res, paths["png"])
    return paths_s


def write_run(out_dir: Path, kind: str, res: dict, md: list[str]) -> Path:
    """``<date>-<kind>-<cpu>.{json,md}`` of a run that has no picture, in ``out_dir``; their stem."""
    import datetime as dt
    import re

    out_dir.mkdir(parents=True, exist_ok=True)
    stem = out_dir / f"{dt.date.today()}-{kind}-{re.sub(r'[^A-Za-z0-9]+', '-', res['cpu']).strip('-')[:40]}"
    stem.with_suffix(".json").write_text(json.dumps(res, indent=1, default=str))
    stem.with_suffix(".md").write_text("\n".join(md) + "\n")
    print(f"wrote {stem}.json and .md")
    return stem


def _rate(row, key):
    r = row.get(key)
    if not r:
        return "n/a"
    return f"{r['rate_per_s']:.3g}" + (f" ({r['note'].split(' measurements')[0]} meas.)" if "note" in r else "")


def markdown(res: dict, png: Path | None = None) -> str:
    """The report of :func:`bench.run`'s results ``res`` as Markdown (``png``: the plots' file)."""
    md = _md_header(res, png)
    md += _md_backprojection(res)
    md += _md_compression(res)
    md += _md_scaling(res)
    md += _md_accuracy(res)
    if "formation" in res:
        from .formation import markdown as formation_markdown

        md += ["", *formation_markdown(res["formation"])]
    if "dask" in res:
        md += _md_dask(res["dask"])
    return "\n".join(md) + "\n"


def _md_dask(d: dict) -> list[str]:
    """The Dask part: the sweeps' times and equality to the serial ones, the tiled volume."""
    md = ["", "## Dask", "", f"Cluster: {d['scheduler']} ({d['workers']} workers).", "",
           f"- Two-echo sweep: {d['two_echo_s']:.1f} s on Dask; equal to the serial sweep: "
           f"**{d['two_echo_equals_serial']}**.",
           f"- Delta x lam grid: {d['delta_lambda_s']:.1f} s on Dask; equal to the serial grid: "
           f"**{d['delta_lambda_equals_serial']}**."]
    if "tiled_s" in d:
        md.append(f"- Volume of {d['voxels']} voxels in {d['n_tiles']} tiles on {', '.join(d['tile_devices'])}: "
                  f"{d['tiled_s']:.2f} s (one call: {d['untiled_s']:.2f} s); largest difference "
                  f"{d['tiled_max_diff_rel']:.1e} of the peak.")
    return md


def _md_header(res: dict, png: Path | None) -> list[str]:
    """The title, device, host and versions (and the plots)."""
    dev = res["device"]
    md = [f"# python -m benchmark ({res['mode']}), {res['date']}", "",
          f"Device: **{dev['name']}**" + (f" (driver {dev.get('driver')}, {dev.get('opencl')}, "
                                          f"{dev.get('compute_units')} compute units at {dev.get('clock_mhz')} MHz)"
                                          if "driver" in dev else "") + ".",
          f"Host: {res['host']['processor'] or res['host']['machine']}, {res['host']['cpus']} logical CPUs. "
          f"Medians of {res['repeats']} repeats after a warm-up.",
          "Versions: " + ", ".join(f"{k} {v}" for k, v in res["versions"].items() if v) + ".", ""]
    if png is not None:
        md += [f"![plots]({png.name})", ""]
    return md


def _md_backprojection(res: dict) -> list[str]:
    """The backprojection table, the C peer and the compute bound."""
    md = ["## Backprojection (voxel-measurement pairs/s)", "",
           "| workload | pairs | VEC | OpenCL kernel | OpenCL wall | NumPy twin | Numba peer | C/OpenMP peer | "
           "kernel / twin | kernel / Numba | kernel / C | wall / C |", "|---" * 12 + "|"]
    for r in res["backprojection"]:
        rt = r.get("ratios", {})
        md.append(f"| {r['workload']} | {r['pairs']:.3g} | {r.get('opencl_vec', '-')} | {_rate(r, 'opencl_kernel')} | "
                  f"{_rate(r, 'opencl_wall')} | {_rate(r, 'numpy_twin')} | {_rate(r, 'numba_peer')} | "
                  f"{_rate(r, 'c_openmp_peer')} | "
                  f"{_x(rt.get('opencl_kernel / numpy_twin'))} | {_x(rt.get('opencl_kernel / numba_peer'))} | "
                  f"{_x(rt.get('opencl_kernel / c_openmp_peer'))} | {_x(rt.get('opencl_wall / c_openmp_peer'))} |")
    peer = next((r["c_openmp_peer_build"] for r in res["backprojection"] if "c_openmp_peer_build" in r), None)
    missing = next((r["c_openmp_peer_missing"] for r in res["backprojection"] if "c_openmp_peer_missing" in r), None)
    if peer:
        md += ["", f"C/OpenMP peer: `bench/backproject_omp.c`, {peer}: float32, the same polynomial sin/cos, "
                   "hand-vectorised with vector extensions (8 lanes, 16 on AVX-512), blocks of 4 vectors of voxels per "
                   "thread, interleaved complex profiles; run on the whole workload."]
    elif missing:
        md += ["", f"C/OpenMP peer left out: {missing}."]
    cb = res.get("compute_bound")
    best = max((r["opencl_kernel"]["rate_per_s"] for r in res["backprojection"] if "opencl_kernel" in r),
               default=0.0)
    if cb and cb.get("pairs_per_s"):
        md += ["", f"Compute bound of the device: {cb['peak_flops'] / 1e9:.1f} GFLOP/s (compute units x clock x "
                   f"{cb.get('lanes_per_unit', '?')} float lanes per unit "
                   f"({cb.get('lanes_from', 'float vector width')}) x 2 for FMA) / about "
                   f"{cb['flops_per_pair']} flops per pair (the sub-sample "
                   f"sine and cosine polynomials counted in full) = {cb['pairs_per_s']:.3g} pairs/s; the kernel "
                   f"reaches {100 * best / cb['pairs_per_s']:.0f} % of it."]
    elif (dev := res.get("device")) and isinstance(dev, dict) and dev.get("lanes_per_unit", 0) is None:
        md += ["", f"No arithmetic ceiling of the device is given: {dev.get('lanes_from')}."]
    if cb and cb.get("memory_pairs_per_s"):
        arith = f"arithmetic ceiling {cb['pairs_per_s']:.3g} pairs/s; " if cb.get("pairs_per_s") else ""
        ridge = (f"ridge at {cb['ridge_flops_per_byte']:.1f} flop/B, " if cb.get("ridge_flops_per_byte") else "")
        lower = min(x for x in (cb.get("pairs_per_s"), cb["memory_pairs_per_s"]) if x)
        md += ["", f"Roofline of the bp kernel: {arith}memory "
                   f"ceiling {cb['memory_pairs_per_s']:.3g} pairs/s ({cb['bandwidth_bps'] / 1e9:.1f} GB/s measured "
                   f"by a buffer copy / {cb['bytes_per_pair']} B per pair if every profile gather came from "
                   f"memory; {ridge}the kernel's "
                   f"{cb['flops_per_pair'] / cb['bytes_per_pair']:.1f} flop/B); measured {best:.3g} pairs/s = "
                   f"{100 * best / lower:.0f} % of the lower ceiling."]
    md += ["", "The NumPy twin and the Numba peer (a float64 `prange` loop over voxels, as one would write it) "
               "run the number of measurements shown in brackets; their cost is linear in measurements and the "
               "rates are per pair.", ""]
    return md


def _md_compression(res: dict) -> list[str]:
    """The pulse-compression table."""
    md = []
    c = res["compression"]
    md += ["## Pulse compression (input samples/s)", "", f"{c['workload']}.", "",
           "| OpenCL FFT kernel | OpenCL FFT wall | OpenCL direct kernel | scipy fftconvolve | scipy oaconvolve "
           "| NumPy twin |", "|---|---|---|---|---|---|",
           f"| {_rate(c, 'opencl_fft_kernel')} | {_rate(c, 'opencl_fft_wall')} | {_rate(c, 'opencl_direct_kernel')} "
           f"| {_rate(c, 'fftconvolve')} | {_rate(c, 'oaconvolve')} | {_rate(c, 'numpy_twin')} |", ""]
    rt = c.get("ratios", {})
    if rt:
        md += ["Ratios: " + "; ".join(f"{k} = {v:.2f}x" for k, v in rt.items()) + ". scipy gets float32 recordings "
               "and a complex64 reference already in memory and returns every lag at the full rate; clsas returns "
               "baseband profiles every 2 samples (the same band-limited signal), its wall time including "
               "transfers.", ""]
    return md


def _md_scaling(res: dict) -> list[str]:
    """The scaling exponents and the plan savings."""
    md = ["## Scaling", "", "| cost of | against | fixed | decades | fitted exponent | upper half |",
           "|---|---|---|---|---|---|"]
    for key, s in res["scaling"].items():
        what = key.split("_vs_")[0]
        md.append(f"| {what} | {s['x']} | {s['fixed']} | {s['decades']:.1f} | {s['exponent']:.2f} | "
                  f"{s['exponent_upper_half']:.2f} |")
    md += ["", "| plan (demo front scene) | voxels | time | saving |", "|---|---|---|---|"]
    for k, v in res["plan_saving"].items():
        md.append(f"| {k} | {v['voxels']} | {v['median_s'] * 1e3:.1f} ms | {v['saving_x']:.1f}x |")
    return md


def _md_accuracy(res: dict) -> list[str]:
    """Error against run time: two-echo, K-echo, autofocus, Delta x lam."""
    md = ["", "## Error against run time", ""]
    for key in ("two_echo", "two_echo_convex"):
        if key not in res:
            continue
        t = res[key]
        md += [f"Two-echo task ({t['task']}); separations {t['separations_b']} x 1/B, SNR {t['snrs_db']} dB, "
               f"{t['trials']} trial(s) per setting.", "",
               "| method | success, all | success below 1/B | mean RMSE / sqrt(CRB) | median time / profile | "
               "best setting (separation x 1/B, SNR) |", "|---|---|---|---|---|---|"]
        for m, p in t["per_method"].items():
            b = p["best_setting"]
            sub = p["success_rate_below_1_over_b"]
            md.append(f"| {m} | {100 * p['success_rate']:.0f} % | {'n/a' if sub is None else f'{100 * sub:.0f} %'} | "
                      f"{_f(p['rmse_over_crb'])} | {p['median_time_s'] * 1e3:.1f} ms | {b['separation_b']:g}, "
                      f"{b['snr_db']:g} dB ({100 * b['success_rate']:.0f} %) |")
        md.append("")
    if "k_echo" in res:
        from .kecho import k_markdown

        t = res["k_echo"]
        md += [f"K-echo table ({t['task']}); {t['trials']} trial(s) per cell.", "", *k_markdown(t["table"]), ""]
    if "autofocus" in res:
        md += ["Autofocus on the demo mannequin (216 stops, 1 cm grid): focus restored against the error.", "",
               res["autofocus"]["markdown"], ""]
    g = res["delta_lambda"]
    md += [f"Paper's Delta x lam grid ({g['task']}); Delta in {g['deltas_s']} s, lam in {g['lam_fracs']} x lam_max.",
           "", "| method | best Delta | best lam / lam_max | error there | time there | median error | "
           "median time |", "|---|---|---|---|---|---|---|"]
    for m, b in g["best"].items():
        md.append(f"| {m} | {b['delta_s']:g} s | {b['lam_frac']:g} | {b['error']:.3g} | {b['time_s'] * 1e3:.1f} ms | "
                  f"{b['median_error']:.3g} | {b['median_time_s'] * 1e3:.1f} ms |")
    return md


def _x(v):
    if v is None:
        return "n/a"
    return f"{v:.2f}x" if v < 10 else f"{v:.1f}x"


def _f(v):
    return "n/a" if v is None else f"{v:.2f}"


def _plot(res: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    # a Figure of its own (saved through its canvas): the caller's pyplot backend is untouched
    fig = Figure(figsize=(12, 9))
    ax = fig.subplots(2, 2)
    a = ax[0, 0]
    labels, vals = [], []
    for r in res["backprojection"]:
        for key, name in (("opencl_kernel", "OpenCL kernel"), ("opencl_wall", "OpenCL wall"),
                          ("c_openmp_peer", "C/OpenMP"), ("numba_peer", "Numba"), ("numpy_twin", "NumPy twin")):
            if key in r:
                labels.append(f"{name}\n{r['voxels']}x{r['measurements']}")
                vals.append(r[key]["rate_per_s"])
    a.barh(range(len(vals)), vals, color="tab:blue")
    a.set_yticks(range(len(vals)), labels, fontsize=7)
    a.set_xscale("log")
    a.set_xlabel("voxel-measurement pairs / s")
    a.set_title(f"backprojection, {res['device']['name'][:50]}", fontsize=9)

    a = ax[0, 1]
    for key, s in res["scaling"].items():
        if key == "backprojection_vs_pairs":
            continue
        x, t = np.array(s["sizes"]), np.array(s["times_s"])
        a.loglog(x / x.min(), t, "o-", label=f"{key.replace('_', ' ')} (exp. {s['exponent']:.2f})")
    a.set_xlabel("size / smallest size")
    a.set_ylabel("kernel time (s)")
    a.legend(fontsize=7)
    a.set_title("cost scaling", fontsize=9)

    a = ax[1, 0]
    for key, mark in (("two_echo", "o"), ("two_echo_convex", "s")):
        for m, p in res.get(key, {}).get("per_method", {}).items():
            sub = p["success_rate_below_1_over_b"]
            if sub is None:
                continue
            a.semilogx(p["median_time_s"], 1 - sub, mark, ms=8,
                       label=m if key == "two_echo" else f"{m} (positive amplitudes)")
    a.set_xlabel("median run time per profile (s)")
    a.set_ylabel("failure rate below 1/B")
    a.set_ylim(-0.05, 1.05)
    a.legend(fontsize=7)
    a.set_title("two-echo task: error against run time (circles: complex amplitudes)", fontsize=9)

    a = ax[1, 1]
    for m in res["delta_lambda"]["best"]:
        rows = [r for r in res["delta_lambda"]["rows"] if r["method"] == m]
        line = a.loglog([r["time_s"] for r in rows], [r["error"] for r in rows], ".", alpha=0.4)[0]
        front = np.array(res["delta_lambda"]["best"][m]["pareto"])
        a.loglog(front[:, 0], front[:, 1], "-", color=line.get_color(), label=m)
    a.set_xlabel("run time (s)")
    a.set_ylabel("eq. 5 error")
    a.legend(fontsize=7)
    a.set_title("Delta x lam grid: every cell, Pareto front per method", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
