"""``python -m bench``: the benchmark suite (run from the repository root).

    python -m bench                  # the quick set, 3 to 6 minutes on a 2-core CPU
    python -m bench --full           # the full set
    python -m bench --formation ...  # only the image-formation benchmark (see --help)
    python -m bench --rates [N]      # kernel and wall rates of each formation and reconstruct, every device
"""

from __future__ import annotations


def cmd_bench(args) -> int:
    import time

    from bench import run, run_formation
    from bench.stats import seconds, times

    t_start = time.perf_counter()

    def status(line: str) -> None:
        if not args.quiet:
            print(f"[bench] {line}", flush=True)

    if args.autofocus_consistency and args.autofocus is None:
        raise ValueError("--autofocus-consistency needs --autofocus")
    if args.autofocus is not None:
        return _bench_autofocus(args, status)

    if args.formation_family is not None:
        return _bench_formation_family(args, status)
    if args.rates is not None:
        return _bench_rates(args, status)
    if args.superres_image:
        return _bench_superres_image(args, status)
    if args.scale == "tiles":
        if args.formation is not None:
            raise ValueError("--scale: with --formation it takes a number (the dense case's size)")
        return _bench_scale(args, status)
    if args.formation is not None:
        res = run_formation(full=args.full, out_dir=args.out, formations=args.formation or None, scale=args.scale,
                            cases=args.cases, plots=not args.no_plots, status=status)
        for c in res["cases"]:
            for r in c["rows"]:
                if r["formation"] == "auto":
                    print(f"{c['case']}: auto: took {r['chose']}, {seconds(r['time_s'])}, "
                          f"{r['over_best']:.2f}x the best "
                          f"({r['best']})")
                    continue
                what = (f"refused ({r['refused'].split(':')[0]})" if "refused" in r else
                        f"{seconds(r['time_s'])}" + (f", {times(r['speedup'])} bp, error "
                                                  f"{r['error_all_db']:.1f} dB over the grid" if "speedup" in r else "")
                        + (f", {r['error_cone_db']:.1f} dB in the cone" if r.get("error_cone_db") is not None
                           else ""))
                print(f"{c['case']}: {r['formation']}: {what}")
        for row in res.get("crossover", {}).get("rows", []):
            print(f"crossover N={row['n']}: " + ", ".join(
                f"{r['formation']} {seconds(r['time_s'])}" + (f" ({r['chose']}, {r['over_best']:.2f}x the best)"
                                                         if r["formation"] == "auto" else "") for r in row["rows"]))
        for path in res["paths"].values():
            print(f"wrote {path}")
        return 0

    res = run(full=args.full, out_dir=args.out, scheduler=args.scheduler, use_dask=True if args.dask else None,
              plots=not args.no_plots, status=status)
    which = "full set" if args.full else "quick set: smaller sizes than the full set the benchmark guide quotes"
    for r in res["backprojection"]:
        rt = r.get("ratios", {})
        if "opencl_kernel / numpy_twin" in rt:
            print(f"backprojection {r['workload']} ({which}): {r['opencl_kernel']['rate_per_s']:.3g} pairs/s, "
                  f"{rt['opencl_kernel / numpy_twin']:.0f}x the NumPy twin"
                  + (f", {rt['opencl_kernel / numba_peer']:.1f}x Numba" if "opencl_kernel / numba_peer" in rt else ""))
    rt = res["compression"].get("ratios", {})
    if "opencl_fft_kernel / fftconvolve" in rt:
        print(f"compression ({which}): kernel {rt['opencl_fft_kernel / fftconvolve']:.2f}x fftconvolve, "
              f"wall {rt['opencl_fft_wall / fftconvolve']:.2f}x")
    if "backprojection_vs_pairs" in res["scaling"]:
        print(f"backprojection cost ~ pairs^{res['scaling']['backprojection_vs_pairs']['exponent']:.2f}")
    for path in res["paths"].values():
        print(f"wrote {path}")
    print(f"the {'full' if args.full else 'quick'} set took {time.perf_counter() - t_start:.0f} s")
    return 0


def _bench_scale(args, status) -> int:
    """``python -m bench --scale``: peak RSS, tiles/s, strong scaling (see :mod:`bench.scale`)."""
    from bench.scale import run_scale
    from bench.stats import seconds

    res = run_scale(full=args.full, out_dir=args.out, parts=tuple(args.scale_parts), status=status)
    for r in res.get("rss", []):
        print(f"out of core: {r['voxels']:.3g} voxels, peak RSS {r['peak_rss_bytes'] / 1e9:.3g} GB (budget "
              f"{r['max_memory_bytes'] / 1e9:.2g} GB), {r['tiles_per_s']:.3g} tiles/s, sampled tiles vs in-memory "
              f"{r['max_rel_diff_vs_in_memory']:.2g}")
    for r in res.get("scaling", {}).get("clusters", []):
        print(f"LocalCluster {r['workers']} x 1 thread: {seconds(r['time_s'])}, "
              f"{r['speedup_vs_1_worker']:.2f}x 1 worker "
              f"(CPU share {r['cpu_share']:.2f}, load {r['load_before'][0]} -> {r['load_after'][0]})")
    for path in res["paths"].values():
        print(f"wrote {path}")
    return 0


def _bench_superres_image(args, status) -> int:
    """``python -m bench --superres-image``: model-based methods against bp (see :mod:`bench.superres_image`)."""
    from bench.superres_image import run_superres_image

    n = args.n_seeds or (50 if args.full else 10)
    res = run_superres_image(args.out, n_trials=n, noise_draws=n, airsas_root=args.airsas, status=status)
    for r in res["pairs"]:
        print(f"{r['setup']} pairs at {r['factor']} x res: {r['method']}: {r['resolved_share']:.0%} resolved")
    for r in res["airsas"]:
        print(f"AirSAS {r['scan']}: {r['method']}: TCR {r['tcr_db']:.1f} dB, edge {r['edge_width_mm']:.1f} mm")
    for path in res["paths"].values():
        print(f"wrote {path}")
    return 0


def _bench_rates(args, status) -> int:
    """``--rates [N]``: kernel and wall rates, and where the wall time goes, per device (:mod:`bench.rates`)."""
    from bench import rates

    res = rates.run_rates(args.rates, indices=args.devices, status=status)
    print("\n".join(rates.table(res)))
    rates.write(res, args.out)
    return 0


def _scale_arg(text: str) -> float | str:
    """``--scale`` alone (the scale benchmark, argparse passes its const ``"tiles"``) or a number."""
    if text == "tiles":
        return text
    import argparse

    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number (the dense case's size), got {text!r}") from None


def _bench_autofocus(args, status) -> int:
    """``--autofocus SET``: the scene family's distribution (:mod:`bench.autofocus_family`)."""
    from bench.autofocus_family import run_and_write

    if not 0 <= args.autofocus_consistency <= 10_000:
        raise ValueError("--autofocus-consistency must be 0 (off) to 10000 iterations, got "
                         f"{args.autofocus_consistency}")
    res = run_and_write(args.autofocus, args.rms_mm, n_seeds=args.n_seeds, out_dir=args.out,
                        plots=not args.no_plots, status=status, consistency_iter=args.autofocus_consistency)
    for label, r in res["results"].items():
        s = r["summary"]
        if s.get("n"):
            print(f"{label}: {s['n']} scenes, {s['within_1db']:.0%} within 1 dB, {s['worse_than_none']:.0%} "
                  f"worse than none ({s['worse_than_none_by_0_5db']:.0%} by > 0.5 dB), median "
                  f"{s['median_peak_db']:+.2f} dB, worst {s['worst_peak_db']:+.2f} dB, "
                  f"median {s['median_time_s']:.0f} s")
    for path in res["paths"].values():
        print(f"wrote {path}")
    return 0


def _bench_formation_family(args, status) -> int:
    """``--formation-family``: formation="auto" on the seeded request family, its summary printed."""
    from bench.formation_family import run_and_write

    res = run_and_write(args.formation_family, n_seeds=args.n_seeds, out_dir=args.out, plots=not args.no_plots,
                        status=status)
    s = res["summary"]
    if s.get("n"):
        large = "no request" if s["within_large"] is None else f"{s['within_large']:.0%}"
        print(f"formation family ({args.formation_family}): {s['n']} requests, auto within {s['within_factor']:g}x "
              f"the best in {s['within']:.0%} ({large} of the {s['n_large']} whose best takes 50 ms or more; median "
              f"{s['median_over_best']:.2f}x, worst {s['worst_over_best']:.2f}x), over its error target in "
              f"{s['over_target']:.0%}, took " + ", ".join(f"{k} {n}" for k, n in s["chose"].items()))
    for path in res["paths"].values():
        print(f"wrote {path}")
    return 0 if s.get("n") else 1


def build_parser():
    import argparse

    b = argparse.ArgumentParser(prog="python -m bench", description="benchmarks: kernels against their peers, "
                                "scaling, error against run time (the quick set: 3 to 6 minutes on a 2-core CPU)")
    b.add_argument("--full", action="store_true", help="the full set (3 to 8 minutes on a 2-core CPU; the quick "
                   "set, the default, 3 to 6 minutes)")
    b.add_argument("--out", default="bench/results", help="results folder (default: bench/results)")
    b.add_argument("--scheduler", help="address of a Dask scheduler for the sweeps and tiles (default: a local "
                   "cluster of 2 workers with --full)")
    b.add_argument("--dask", action="store_true", help="run the Dask part in the quick set too")
    b.add_argument("--no-plots", action="store_true", help="no PNG")
    b.add_argument("--formation", nargs="*", metavar="NAME", default=None,
                   help="run only the image-formation benchmark, for these registered formations (default all; bp, "
                   "the reference, always runs)")
    b.add_argument("--scale", type=_scale_arg, default=None, nargs="?", const="tiles",
                   help="alone: the scale benchmark (peak RSS against grid size out of core, tiles/s, tile size, "
                   "strong scaling on a LocalCluster of 1, 2 and 8 single-threaded workers); with --formation and "
                   "a number: size of the dense planar case (1 = 128 x 128 stops, 256 x 256 x 128 voxels; default 1 "
                   "with --full, else 0.25)")
    b.add_argument("--scale-parts", nargs="+", choices=("rss", "tiles", "scaling"), default=["rss", "tiles", "scaling"],
                   help="with --scale: which parts (default all)")
    b.add_argument("--cases", nargs="+", choices=("demo", "dense", "circular", "beams", "crossover"), default=None,
                   help="with --formation: which cases (default all)")
    b.add_argument("--autofocus", nargs="?", const="tuning", choices=("tuning", "tuning-2", "held-out", "held-out-2"),
                   default=None, help="run only the autofocus benchmark on the seeded scene family: its tuning seeds "
                   "(default; tuning-2: 2000-2029) or a held-out set (1000-1029; held-out-2: 3000-3029; for reports, "
                   "never for tuning)")
    b.add_argument("--formation-family", nargs="?", const="tuning", default=None,
                   choices=("tuning", "held-out", "held-out-2", "held-out-3", "held-out-4", "held-out-5",
                            "held-out-6", "held-out-7", "held-out-8"),
                   help="run only formation='auto' on a seeded family of requests (planar, jittered and ring "
                   "apertures, points and planes, audio bands): its tuning seeds (default) or either held-out set "
                   "(for reports, never for tuning); 1-3 minutes on a 2-core CPU")
    b.add_argument("--autofocus-consistency", type=int, default=0, metavar="N",
                   help="with --autofocus: run clsas.autofocus with consistency_iter=N (its last check by data "
                   "consistency; default 0: off)")
    b.add_argument("--rms-mm", type=float, nargs="+", default=[3.0],
                   help="with --autofocus: RMS of the hand motion, mm (default 3)")
    b.add_argument("--n-seeds", type=int, default=None,
                   help="with --autofocus or --formation-family: the first N seeds of the set only")
    b.add_argument("--superres-image", action="store_true",
                   help="run only the model-based reconstruction benchmark: bp, cbp-polar, psf, ls, l1, l1-psf, tv, "
                   "l1-tv and offgrid on simulated point pairs (--n-seeds trials, default 10, 50 with --full) and, "
                   "with --airsas, on the measured AirSAS scans")
    b.add_argument("--airsas", default=None, metavar="DIR",
                   help="with --superres-image: local copy of CSAS_Deconvolution_INR (or its airsas_deconv_pipeline)")
    b.add_argument("--rates", type=int, nargs="?", const=24, default=None, metavar="N",
                   help="run only the rates table: bp, omega-k, ffbp and the whole reconstruct (compression + bp) on "
                   "N x N stops (default 24: under a minute on a 2-core CPU), on every device: kernel and wall rates "
                   "and the shares of the wall time on the host, in transfers and in kernels")
    b.add_argument("--devices", nargs="+", metavar="P:D|numpy", default=None,
                   help="with --rates: only these devices (OpenCL P:D numbers as clsas devices lists them, or numpy)")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    b.add_argument("-v", "--verbose", action="store_true", help="log details")
    b.add_argument("--debug", action="store_true", help="show tracebacks")
    return b


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark the arguments name; 0 done, 1 failed, 2 bad arguments."""
    import logging
    import sys

    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.quiet:
        logging.getLogger("clsas.cl.variants").setLevel(logging.INFO)
    try:
        return cmd_bench(args)
    except (ValueError, TypeError, FileNotFoundError) as exc:
        if args.debug:
            raise
        print(f"python -m bench: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
