"""Paper, Fig. 6: the error over grid spacing and regularisation
=============================================================

Paper, Fig. 6: the error (eq. 5) of each method over the grid spacing Delta and the
regularisation lam, on the 1-D problem of Fig. 4 (two shifted decaying exponentials).

    python examples/fig6_heatmaps.py [--out DIR] [--quick]

Writes fig6.png (one heat map per method, log10 of the error) and fig6.md (the best setting
of each method and its error). Methods: BPDN, CBP-Taylor and CBP-Polar (the convex SOCP), as
in the paper, and the refined CBP-Polar.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from clsas.sparse.paper import grid_cell, grid_problem

TRUTH = grid_problem()[2]
DELTAS = (0.0125, 0.025, 0.05, 0.1, 0.2)
LAM_FRACS = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3)
METHODS = {"BPDN": "bpdn", "CBP-Taylor": "cbp-taylor", "CBP-Polar (convex)": "cbp-polar-socp",
           "CBP-Polar (refined)": "cbp-polar"}


def grid_errors(deltas=DELTAS, lam_fracs=LAM_FRACS):
    """{method: (len(deltas), len(lam_fracs)) eq. 5 errors}, and the run time per method
    (the cells are computed by clsas.sparse.paper.grid_cell, which the benchmark suite uses too)."""
    errs = {m: np.full((len(deltas), len(lam_fracs)), np.nan) for m in METHODS}
    times = dict.fromkeys(METHODS, 0.0)
    for i, delta in enumerate(deltas):
        for j, lf in enumerate(lam_fracs):
            for m, key in METHODS.items():
                cell = grid_cell(key, delta, lf)
                times[m] += cell["time_s"]
                errs[m][i, j] = cell["error"]
    return errs, times


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    ap.add_argument("--out", default="examples/out")
    ap.add_argument("--quick", action="store_true", help="a 3 x 3 corner of the grid")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    deltas, lams = (DELTAS[1:4], LAM_FRACS[1:4]) if args.quick else (DELTAS, LAM_FRACS)
    errs, times = grid_errors(deltas, lams)
    rows = ["| method | best Delta (s) | best lam / lam_max | error there | median over the grid "
            "| run time, whole grid |",
            "|---|---|---|---|---|---|"]
    for m, e in errs.items():
        i, j = np.unravel_index(np.nanargmin(e), e.shape)
        rows.append(f"| {m} | {deltas[i]:g} | {lams[j]:g} | {e[i, j]:.3g} | {np.nanmedian(e):.3g} | {times[m]:.2f} s |")
    text = "\n".join(rows)
    (out / "fig6.md").write_text(
        f"Eq. 5 error over Delta in {list(deltas)} s and lam in {list(lams)} x lam_max; truth: delays "
        f"{TRUTH.delays_s.tolist()} s, amplitudes {TRUTH.amplitudes.tolist()}.\n\n{text}\n")
    print(text)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(errs), figsize=(3.6 * len(errs), 3.4), sharey=True)
    lo = np.log10(min(np.nanmin(e) for e in errs.values()))
    hi = np.log10(max(np.nanmax(e) for e in errs.values()))
    for ax, (m, e) in zip(axes, errs.items(), strict=True):
        im = ax.imshow(np.log10(e), origin="lower", cmap="jet", vmin=lo, vmax=hi, aspect="auto")
        ax.set_xticks(range(len(lams)), [f"{x:g}" for x in lams], rotation=45)
        ax.set_yticks(range(len(deltas)), [f"{x:g}" for x in deltas])
        ax.set_xlabel("lam / lam_max")
        ax.set_title(m, fontsize=10)
    axes[0].set_ylabel("Delta (s)")
    fig.colorbar(im, ax=axes, label="log10 eq. 5 error (red = large)")
    fig.savefig(out / "fig6.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {out / 'fig6.png'} and {out / 'fig6.md'}")
    return 0


if __name__ == "__main__":
    status = main()  # not raised when 0: sphinx-gallery runs this file and would stop at SystemExit
    if status:
        raise SystemExit(status)
