"""``clsas autofocus`` and ``clsas reconstruct --autofocus``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clsas.focus.final_consistency import REVERT_RATIO

from .common import add_device_options, check_grids_fit, grid_arg


def add_autofocus_options(sp) -> None:
    """The autofocus options shared by ``autofocus`` and ``reconstruct --autofocus``."""
    sp.add_argument("--methods", default="direct",
                    help="steps, comma-separated, from direct, temperature, delay, phase, points, track, los, 3d, "
                    "pga (default: direct; the benchmark's set is direct,points,track; the focus steps "
                    "phase,temperature made a third of the held-out test scenes worse, see docs/guide/autofocus.md)")
    sp.add_argument("--metric", default="sharpness", choices=("sharpness", "entropy"), help="focus metric")
    sp.add_argument("--n-basis", type=int, default=None, help="smooth functions for the line-of-sight motion")
    sp.add_argument("--temperature-range", type=float, default=5.0, metavar="C",
                    help="the thermometer's uncertainty: the temperature search covers the stated +- this, degC "
                    "(default 5); an optimum at its edge is 'not determined'")
    sp.add_argument("--temperature-tolerance", type=float, default=0.35, metavar="C",
                    help="apply the temperature only where its uncertainty is at most this, degC (default 0.35)")
    sp.add_argument("--check-margin", type=float, default=0.01,
                    help="how much better disjoint sub-apertures must agree for the motion to be applied "
                    "(default 0.01)")
    sp.add_argument("--max-delay", type=float, default=5e-4, metavar="S",
                    help="largest delay error looked for, s (default 5e-4)")
    sp.add_argument("--max-iter", type=int, default=40, help="L-BFGS iterations per stage (default 40)")
    sp.add_argument("--consistency", type=int, default=0, metavar="N",
                    help="a last check that trusts no image: fit a target in the grid to the scan before and after "
                    "the correction, N CGLS iterations each, and withdraw a correction that leaves more of the "
                    f"data unexplained than without it (excess ratio over {REVERT_RATIO:g}); one the data "
                    "neither confirm nor contradict is kept, with a note (clsas.focus.data_consistency; 30 is a "
                    "good start; up to minutes on large grids; default 0: off)")


def check_consistency(args) -> None:
    """``--consistency`` checked before any work."""
    if not 0 <= args.consistency <= 10_000:
        raise ValueError(f"--consistency must be 0 (off) to 10000 iterations, got {args.consistency}")


def run_autofocus(ds, grid, args):
    from clsas.focus import autofocus

    def say(step, n, metric):
        if not args.quiet and n % 10 == 0:
            print(f"  autofocus {step}: image {n}, metric {metric:.5g}", flush=True)

    out, rep = autofocus(ds, grid, methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
                         metric=args.metric, n_basis=args.n_basis, temperature_range_c=args.temperature_range,
                         max_delay_s=args.max_delay, max_iter=args.max_iter, backend=args.backend,
                         temperature_tolerance_c=args.temperature_tolerance, check_margin=args.check_margin,
                         device=getattr(args, "device", None), progress=say, force=getattr(args, "force", False),
                         consistency_iter=args.consistency)
    print(rep.summary())
    return out, rep


def before_after_png(before, after, path, title: str) -> None:
    """Maximum-intensity projections (x-y and x-z, dB of the common peak) before and after."""
    import matplotlib.pyplot as plt

    peak = max(np.abs(before.values).max(), np.abs(after.values).max(), 1e-300)
    g = before.grid
    fig, axes = plt.subplots(2, 2, figsize=(9, 8), squeeze=False)
    for col, (name, im) in enumerate((("before", before), ("after", after))):
        db = 20 * np.log10(np.maximum(np.abs(im.values) / peak, 1e-6))
        for row, (axis, (a, b), lab) in enumerate(((2, (g.x_m, g.y_m), "y (m)"), (1, (g.x_m, g.z_m), "z (m)"))):
            ax = axes[row][col]
            shown = ax.imshow(db.max(axis=axis).T, origin="lower", vmin=-40, vmax=0, cmap="inferno", aspect="auto",
                              extent=(a[0], a[-1], b[0], b[-1]))
            ax.set_xlabel("x (m)")
            ax.set_ylabel(lab)
            ax.set_title(f"{name}: peak {20 * np.log10(np.abs(im.values).max() / peak):.1f} dB")
    fig.suptitle(title)
    fig.tight_layout()
    fig.colorbar(shown, ax=axes.ravel().tolist(), shrink=0.8, label="dB re the common peak")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cmd_autofocus(args) -> int:
    import clsas
    from clsas.synthesis.scenes import stored_grid_and_truth

    check_consistency(args)
    ds = clsas.load(args.data)
    stored_grid, _ = stored_grid_and_truth(ds.config)
    grid = grid_arg(args.grid, args.spacing, stored_grid)
    check_grids_fit([grid], args)  # before the minutes of focusing, not at the first image
    out, rep = run_autofocus(ds, grid, args)
    out.save(args.out, overwrite=True)  # checked against --overwrite before any work
    print(f"wrote {args.out}" + ("" if rep.improved else " (the input, unchanged: nothing passed the check)"))
    if ds.truth:
        from clsas.focus import score

        s = score(rep, ds)
        print("against the stored truth: " + ", ".join(f"{k} {val:.3g}" for k, val in s.items()))
    if args.png:
        kw = dict(backend=args.backend, device=getattr(args, "device", None))
        before = clsas.reconstruct(ds, grid, **kw)
        after = clsas.reconstruct(out, grid, **kw)
        before_after_png(before, after, args.png, f"{Path(args.data).name}: autofocus ({', '.join(rep.methods)})")
        print(f"wrote {args.png}")
    return 0


def add_parser(sub) -> None:
    af = sub.add_parser("autofocus", help="estimate motion, sound speed and delay from the scan; write the "
                        "corrected dataset")
    af.add_argument("data", help="dataset file (HDF5)")
    af.add_argument("out", help="corrected dataset file to write (HDF5)")
    af.add_argument("--grid", help="x0,x1,y0,y1,z0,z1 in m where the focus is measured (default: the dataset's "
                    "[grid])")
    af.add_argument("--spacing", type=float, help="voxel spacing in m")
    af.add_argument("--png", metavar="FILE", help="write the images before and after to FILE (PNG)")
    af.add_argument("--force", action="store_true", help="go on even if the grid does not seem to fit in memory")
    add_autofocus_options(af)
    add_device_options(af)
    af.set_defaults(func=cmd_autofocus)
