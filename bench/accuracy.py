"""Error against run time for every reconstruction method.

Two tasks: the two-echo task (bench.trials: the paper's chirp, complex amplitudes,
separations in units of 1/B, SNR per echo sample) and the paper's Delta x lam grid (Fig. 6,
eq. 5 error). Every method sees the same data; the best setting of each method is named.
"""

from __future__ import annotations

import numpy as np

from .trials import TwoEchoTask, grid_sweep, summarise, sweep

__all__ = ["two_echo", "k_echo", "delta_lambda", "pareto_front"]


def two_echo(methods, separations_b, snrs_db, trials: int, *, amplitudes: str = "complex", client=None,
             progress=None) -> dict:
    """The two-echo sweep (serial, or on ``client``) with its per-setting summary and per-method totals.

    ``amplitudes="positive"`` is the convex CBPs' model (real atoms, positive amplitudes).
    """
    task = TwoEchoTask(amplitudes=amplitudes)
    if client is not None:
        from .distributed import sweep_dask

        rows = sweep_dask(client, task, methods, separations_b, snrs_db, trials)
    else:
        rows = sweep(task, methods, separations_b, snrs_db, trials, progress=progress)
    summary = summarise(rows)
    per_method = {}
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        sub_b = [r for r in mine if r["separation_b"] < 1.0]
        best = max((s for s in summary if s["method"] == m), key=lambda s: (s["success_rate"], -s["separation_b"]))
        per_method[m] = {
            "success_rate": float(np.mean([r["success"] for r in mine])),
            "success_rate_below_1_over_b": float(np.mean([r["success"] for r in sub_b])) if sub_b else None,
            "median_time_s": float(np.median([r["time_s"] for r in mine])),
            "best_setting": {"separation_b": best["separation_b"], "snr_db": best["snr_db"],
                             "success_rate": best["success_rate"]},
            "rmse_over_crb": _nanmean([s["rmse_over_crb"] for s in summary if s["method"] == m]),
        }
    return {"task": f"two echoes, paper chirp 20-30 kHz 2 ms Tukey 0.2 at 96 kHz, {amplitudes} amplitudes; "
                    "success = exactly two echoes each within 0.25/B",
            "methods": list(methods), "separations_b": list(separations_b), "snrs_db": list(snrs_db),
            "trials": trials, "summary": summary, "per_method": per_method,
            "rows": [{k: v for k, v in r.items() if k != "status"} for r in rows]}


def k_echo(ks, ratios, trials: int, *, methods=None, spacing_b: float = 2.0, snr_db: float = 10.0,
           progress=None) -> dict:
    """The K-echo table (:mod:`bench.kecho`): success per (K, amplitude ratio, method)
    against the Cramer-Rao bound's success and known-count ML's, with the time per profile."""
    from .kecho import KECHO_METHODS, k_sweep, k_table

    methods = tuple(methods or KECHO_METHODS)
    rows = k_sweep(ks, ratios, trials, methods, progress=progress, spacing_b=spacing_b, snr_db=snr_db)
    return {"task": f"K echoes {spacing_b:g}/B apart, every other one weaker by the ratio, paper chirp, complex "
                    f"amplitudes, {snr_db:g} dB per strong echo; success = exactly K echoes each within 0.25/B; "
                    "bound = an unbiased Gaussian estimator at the CRB; ML = known-count maximum likelihood",
            "ks": list(ks), "ratios": list(ratios), "trials": trials, "methods": list(methods),
            "table": k_table(rows), "rows": rows}


def delta_lambda(methods, deltas, lam_fracs, *, client=None, progress=None) -> dict:
    """The paper's Delta x lam grid: eq. 5 error and run time per cell; the best cell per method."""
    if client is not None:
        from .distributed import grid_sweep_dask

        rows = grid_sweep_dask(client, methods, deltas, lam_fracs)
    else:
        rows = grid_sweep(methods, deltas, lam_fracs, progress=progress)
    best = {}
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        b = min(mine, key=lambda r: r["error"])
        best[m] = {"delta_s": b["delta_s"], "lam_frac": b["lam_frac"], "error": b["error"], "time_s": b["time_s"],
                   "median_error": float(np.median([r["error"] for r in mine])),
                   "median_time_s": float(np.median([r["time_s"] for r in mine])),
                   "pareto": pareto_front([(r["time_s"], r["error"]) for r in mine])}
    return {"task": "paper Fig. 6: two shifted decaying exponentials, eq. 5 error",
            "deltas_s": list(deltas), "lam_fracs": list(lam_fracs), "rows": rows, "best": best}


def pareto_front(points) -> list[tuple[float, float]]:
    """The (time, error) points no other point beats on both, by increasing time."""
    front, best = [], np.inf
    for t, e in sorted(points):
        if e < best:
            front.append((float(t), float(e)))
            best = e
    return front


def _nanmean(xs):
    xs = [x for x in xs if np.isfinite(x)]
    return float(np.mean(xs)) if xs else None
