"""Super-resolution benchmark: error against run time on the two-echo task, and the fast BPDN
solver against cvxpy at about 3,600 atoms.

    python -m bench.bench_superres [--trials 25] [--quick] [--out bench/results]
    python -m bench.bench_superres --measured 16 [--out bench/results]
    python -m bench.bench_superres --kecho 20 [--out bench/results]

Two-echo task (bench.trials): the paper's chirp (20-30 kHz, 2 ms, Tukey 0.2) at
96 kHz, 1000-sample profiles, complex amplitudes (unknown phase), separations 0.125-2 / B,
SNR 0-30 dB (one echo's power per sample over its pulse, over the noise power per sample).
Success: exactly two echoes, each within 0.25 / B (25 us) of a true one. Every method sees the
same noisy profiles. Writes <date>-superres-<host>.json, .md and a Pareto plot (.png).

``--measured N``: instead, the imaging path (``superres_profiles``, complex amplitudes) on N
recordings that look measured (bench.trials.measured_like: 1000 samples at 100 kHz,
LFM 30 -> 10 kHz 1 ms Tukey, an extended reflector of 30 scatterers, strong static clutter,
echoes across the gate's edges, a coloured pulse, 20 dB): seconds per recording, echoes
found, recordings capped and fallen back, per method, with complex BPDN's working sets polished
(the default) and by FISTA alone (the solver before). Writes <date>-measured-<host>.json.

``--kecho N``: instead, the K-echo table (bench.kecho): K = 2, 3, 5, 10 echoes 2/B apart,
amplitude ratio 1, 0.5, 0.1, 10 dB, N profiles per cell; refined CBP-Polar, BPDN and BPDN with
its debias-and-detect step (bpdn-detect) against the Cramer-Rao bound's success and known-count
ML, with the time per profile. Writes
<date>-kecho-<host>.json and .md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path

import numpy as np

import clsas
from bench.stats import cpu_name
from bench.trials import TwoEchoTask, measured_like, summarise, sweep
from clsas.sparse import Atom, Dictionary, bpdn, bpdn_cvxpy

METHODS = ("matched", "bpdn", "cbp-polar", "ml2")
SEPARATIONS = (0.125, 0.25, 0.5, 1.0, 2.0)
SNRS = (0, 10, 20, 30)
ACCEPT = ((0.25, 10), (0.125, 20))


def bpdn_vs_cvxpy(n_atoms=3600, modes=("positive", "real")):
    """Fast BPDN and cvxpy (Clarabel) on one 1000-sample profile with ``n_atoms`` atoms."""
    fs = 96e3
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.2)
    rng = np.random.default_rng(0)
    rows = []
    for mode in modes:
        cplx = mode == "complex"
        at = Atom(w, fs, 1000, complex=cplx)
        delta = (1000 - len(w)) / fs / n_atoms
        d = Dictionary(at, delta, 0.0, n_atoms)
        b = at.matrix([3.0e-3, 3.03e-3]) @ np.array([1.0, 0.7]) + 0.05 * rng.normal(size=1000)
        if cplx:
            b = b + 0.05j * rng.normal(size=1000)
        t = time.perf_counter()
        fast = bpdn(d, b, lam_frac=0.1, amplitudes=mode)
        t_fast = time.perf_counter() - t
        ref = bpdn_cvxpy(d, b, lam=fast.lam, amplitudes=mode)
        rows.append({"mode": mode, "n_atoms": n_atoms, "n_samples": 1000, "fast_s": t_fast, "cvxpy_s": ref.time_s,
                     "speedup": ref.time_s / t_fast, "fast_objective": fast.objective,
                     "cvxpy_objective": ref.objective,
                     "rel_diff": (fast.objective - ref.objective) / abs(ref.objective), "fast_status": fast.status,
                     "cvxpy_status": ref.status})
        print(f"  {mode}: fast {t_fast:.3f} s, cvxpy {ref.time_s:.2f} s, objective rel. diff "
              f"{rows[-1]['rel_diff']:.1e}", flush=True)
    return rows


def measured(n_recordings: int, methods=("bpdn", "cbp-polar")) -> list[dict]:
    """Each method on the same measured-like recordings, one at a time (time per recording)."""
    from clsas.sparse import gram
    from clsas.sparse.profiles import superres_profiles

    ds, gates = measured_like(n_recordings)
    rows = []
    for method, polish in [(m, p) for p in (True, False) for m in methods]:
        gram.POLISH = polish  # False: complex BPDN's working sets by FISTA alone, the solver before
        times, found, capped, fell = [], [], 0, 0
        for m in range(n_recordings):
            t = time.perf_counter()
            _, (e,) = superres_profiles(ds.subset(slice(m, m + 1)), gates[m:m + 1], method)
            times.append(time.perf_counter() - t)
            found.append(len(e))
            capped += e.capped
            fell += e.fallback
        gram.POLISH = True
        rows.append({"method": method, "solver": "FISTA + Newton polish" if polish else "FISTA alone",
                     "recordings": n_recordings, "median_s": float(np.median(times)),
                     "mean_s": float(np.mean(times)), "max_s": float(np.max(times)),
                     "echoes_mean": float(np.mean(found)), "echoes_max": int(np.max(found)), "capped": int(capped),
                     "fell_back": int(fell)})
        r = rows[-1]
        print(f"  {method} ({r['solver']}): {r['median_s']:.3f} s per recording (median; mean {r['mean_s']:.3f}, max "
              f"{r['max_s']:.3f}), {r['echoes_mean']:.1f} echoes (max {r['echoes_max']}), capped {capped}, "
              f"fell back {fell} of {n_recordings}", flush=True)
    return rows


def pareto_plot(summary, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"matched": "k", "bpdn": "m", "cbp-polar": "r", "ml2": "b"}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for m in dict.fromkeys(s["method"] for s in summary):
        g = [s for s in summary if s["method"] == m]
        t = [s["median_time_s"] for s in g]
        axes[0].scatter(t, [1 - s["success_rate"] for s in g], c=colors.get(m, "g"), label=m, alpha=0.7)
        ok = [s for s in g if np.isfinite(s["rmse_over_crb"])]
        axes[1].scatter([s["median_time_s"] for s in ok], [s["rmse_over_crb"] for s in ok], c=colors.get(m, "g"),
                        label=m, alpha=0.7)
        tm, fail = float(np.median(t)), 1 - float(np.mean([s["success_rate"] for s in g]))
        axes[0].annotate(m, (tm, fail), fontsize=8)
    axes[0].set(xscale="log", xlabel="median run time per profile (s)", ylabel="failure rate (1 - success)",
                title="failure against time (one point per separation x SNR)")
    axes[1].set(xscale="log", yscale="log", xlabel="median run time per profile (s)", ylabel="RMSE / sqrt(CRB)",
                title="delay error on the successes")
    axes[1].axhline(2.0, color="gray", ls=":", lw=1)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=25)
    ap.add_argument("--accept-trials", type=int, default=100, help="trials at the two acceptance settings")
    ap.add_argument("--quick", action="store_true", help="3 trials, no cvxpy comparison")
    ap.add_argument("--out", default="bench/results")
    ap.add_argument("--kecho", type=int, default=0, metavar="N", help="the K-echo table, N profiles per cell")
    ap.add_argument("--measured", type=int, default=0, metavar="N",
                    help="time the imaging path on N measured-like recordings instead")
    args = ap.parse_args()
    if args.measured:
        return main_measured(args.measured, Path(args.out))
    if args.kecho:
        return main_kecho(args.kecho, Path(args.out))
    trials = 3 if args.quick else args.trials
    task = TwoEchoTask()
    t0 = time.perf_counter()

    def progress(done, total):
        if done % 100 == 0 or done == total:
            print(f"  {done}/{total} trials, {time.perf_counter() - t0:.0f} s", flush=True)

    print("two-echo sweep", flush=True)
    rows = sweep(task, METHODS, SEPARATIONS, SNRS, trials, progress=progress)
    summary = summarise(rows)
    accept = []
    if not args.quick:
        print("acceptance settings", flush=True)
        for sep, snr in ACCEPT:
            accept += summarise(sweep(task, ("cbp-polar", "ml2"), (sep,), (snr,), args.accept_trials, seed0=10_000))
    cvx = [] if args.quick else bpdn_vs_cvxpy()

    host = platform.node() or "host"
    cpu = platform.processor() or platform.machine()
    date = datetime.date.today().isoformat()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{date}-superres-{host}"
    meta = {"date": date, "host": host, "cpu": cpu, "python": platform.python_version(),
            "clsas": clsas.__version__, "numpy": np.__version__, "trials": trials, "task": repr(task),
            "success": "two echoes, each within 0.25/B of a true one", "wall_s": time.perf_counter() - t0}
    Path(f"{stem}.json").write_text(json.dumps({"meta": meta, "summary": summary, "acceptance": accept,
                                                "bpdn_vs_cvxpy": cvx, "trials": rows}, indent=1, default=float))
    lines = [f"# Super-resolution: error against run time ({date}, {host}, {cpu})", "",
             f"Two-echo task: {task}. {trials} trials per cell, the same profiles for every method. Success: "
             "two echoes found, each within 0.25/B (25 us) of a true one. Time: median per 1000-sample profile, "
             "one process, plain NumPy/SciPy/nlopt on the CPU.", "",
             "| method | separation (1/B) | SNR (dB) | success | RMSE (us) | RMSE / sqrt(CRB) | median time (ms) |",
             "|---|---|---|---|---|---|---|"]
    for s in summary + accept:
        lines.append(f"| {s['method']} | {s['separation_b']:g} | {s['snr_db']:g} | "
                     f"{s['success_rate']:.0%} ({s['trials']}) | {1e6 * s['rmse_s']:.2f} | {s['rmse_over_crb']:.2f} | "
                     f"{1e3 * s['median_time_s']:.0f} |")
    if cvx:
        lines += ["", "## Fast BPDN against cvxpy (Clarabel)", "",
                  "| amplitudes | atoms | fast | cvxpy | speed-up | objective rel. difference |",
                  "|---|---|---|---|---|---|"]
        for r in cvx:
            lines.append(f"| {r['mode']} | {r['n_atoms']} | {r['fast_s']:.3f} s | {r['cvxpy_s']:.2f} s | "
                         f"{r['speedup']:.0f}x | {r['rel_diff']:.1e} |")
    Path(f"{stem}.md").write_text("\n".join(lines) + "\n")
    pareto_plot(summary, f"{stem}.png")
    print("\n".join(lines))
    print(f"wrote {stem}.json, .md, .png")
    return 0


def main_measured(n_recordings: int, out: Path) -> int:
    import os

    host = platform.node() or "host"
    cpu = cpu_name()
    print(f"measured-like recordings: {n_recordings}, {cpu}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}",
          flush=True)
    rows = measured(n_recordings)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{datetime.date.today().isoformat()}-measured-{host}"
    Path(f"{stem}.json").write_text(json.dumps({"cpu": cpu, "cores": os.cpu_count(), "load_1min": os.getloadavg()[0],
                                                "clsas": clsas.__version__, "rows": rows}, indent=1))
    print(f"wrote {stem}.json")
    return 0


def main_kecho(trials: int, out: Path) -> int:
    import os

    from bench.accuracy import k_echo
    from bench.kecho import k_markdown

    host = platform.node() or "host"
    cpu = cpu_name()
    load = os.getloadavg()[0]
    print(f"K-echo table: {trials} profiles per cell, {cpu}, {os.cpu_count()} cores, load {load:.1f}", flush=True)
    t = time.perf_counter()
    res = k_echo((2, 3, 5, 10), (1.0, 0.5, 0.1), trials)
    res.update({"cpu": cpu, "cores": os.cpu_count(), "load_1min": load, "clsas": clsas.__version__,
                "wall_s": time.perf_counter() - t})
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{datetime.date.today().isoformat()}-kecho-{host}"
    Path(f"{stem}.json").write_text(json.dumps(res, indent=1))
    lines = [f"# K-echo table ({datetime.date.today().isoformat()})", "",
             f"Machine: {cpu}, {os.cpu_count()} cores (shared; load {load:.1f} at start), clsas {clsas.__version__}; "
             f"{res['wall_s']:.0f} s in all.", "", res["task"] + f"; {trials} profiles per cell, the same for "
             "every method. \"bound with order test\": the bound times the chance that every echo's likelihood "
             "ratio passes CBP-Polar's 1 % false-alarm order test (bench.kecho.detection_success).", "",
             *k_markdown(res["table"])]
    Path(f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {stem}.json, .md")
    return 0




if __name__ == "__main__":
    raise SystemExit(main())
