"""``clsas acquire`` (a scan on a rig or an emulated one) and ``clsas bench`` (the benchmark suite)."""

from __future__ import annotations

import sys


def cmd_acquire(args) -> int:
    from clsas import rig

    if args.sample_config:
        print(rig.SAMPLE_RIG_TOML, end="")
        return 0
    if not args.config or not args.out:
        raise ValueError("clsas acquire needs a rig configuration and an output file: clsas acquire rig.toml out.h5 "
                         "(clsas acquire --sample-config > rig.toml writes a commented example)")
    if args.fault and args.simulate not in ("all", "stage"):
        raise ValueError("--fault injects faults into the emulated stage: use it with --simulate or --simulate stage")
    cfg = rig.load_rig_config(args.config)
    faults = rig.Faults.parse(args.fault) if args.fault else None
    flags = "" if not args.simulate else " --simulate" if args.simulate == "all" else f" --simulate {args.simulate}"
    hint = f"resume with: clsas acquire {args.config} {args.out} --resume{flags}"
    kind = {"all": "emulated ", "stage": "emulated-stage ", "audio": "simulated-audio "}.get(args.simulate, "")
    print(f"{kind}scan: {cfg.n_stops} stops x {cfg.n_mics} microphone(s), "
          f"{cfg.repeats} chirp(s) per stop at {cfg.fs_hz:g} Hz -> {args.out}")
    from tqdm import tqdm

    with tqdm(total=cfg.n_stops, desc="acquire", unit="stop", disable=args.quiet) as bar:
        def progress(done: int, total: int) -> None:
            bar.n = done
            bar.refresh()

        try:
            res = rig.acquire(cfg, args.out, resume=args.resume, simulate=args.simulate or False, faults=faults,
                              progress=progress, resume_hint=hint)
        except rig.ScanInterrupted as exc:
            bar.close()
            print(f"clsas acquire: {exc}", file=sys.stderr)
            return 130
        except rig.ScanAborted as exc:
            bar.close()
            print(f"clsas acquire: {exc}", file=sys.stderr)
            return 3
    print(f"wrote {res.path}: {res.stops_done} of {res.n_stops} stops ({res.stops_this_run} this run, "
          f"{res.retried_stops} retried) in {res.elapsed_s:.1f} s; image it with: clsas reconstruct {res.path}")
    return 0


def cmd_bench(args) -> int:
    from clsas.bench import run, run_formation

    def status(line: str) -> None:
        if not args.quiet:
            print(f"[bench] {line}", flush=True)

    if args.formation is not None:
        res = run_formation(full=args.full, out_dir=args.out, formations=args.formation or None, scale=args.scale,
                            cases=args.cases, plots=not args.no_plots, status=status)
        for c in res["cases"]:
            for r in c["rows"]:
                what = (f"refused ({r['refused'].split(':')[0]})" if "refused" in r else
                        f"{r['time_s']:.2f} s" + (f", {r['speedup']:.0f}x bp, error {r['error_all_db']:.1f} dB over "
                                                  "the grid" if "speedup" in r else "")
                        + (f", {r['error_cone_db']:.1f} dB in the cone" if r.get("error_cone_db") is not None
                           else ""))
                print(f"{c['case']}: {r['formation']}: {what}")
        for path in res["paths"].values():
            print(f"wrote {path}")
        return 0

    res = run(full=args.full, out_dir=args.out, scheduler=args.scheduler, use_dask=True if args.dask else None,
              plots=not args.no_plots, status=status)
    for r in res["backprojection"]:
        rt = r.get("ratios", {})
        if "opencl_kernel / numpy_twin" in rt:
            print(f"backprojection {r['workload']}: {r['opencl_kernel']['rate_per_s']:.3g} pairs/s, "
                  f"{rt['opencl_kernel / numpy_twin']:.0f}x the NumPy twin"
                  + (f", {rt['opencl_kernel / numba_peer']:.1f}x Numba" if "opencl_kernel / numba_peer" in rt else ""))
    rt = res["compression"].get("ratios", {})
    if "opencl_fft_kernel / fftconvolve" in rt:
        print(f"compression: kernel {rt['opencl_fft_kernel / fftconvolve']:.2f}x fftconvolve, "
              f"wall {rt['opencl_fft_wall / fftconvolve']:.2f}x")
    if "backprojection_vs_pairs" in res["scaling"]:
        print(f"backprojection cost ~ pairs^{res['scaling']['backprojection_vs_pairs']['exponent']:.2f}")
    for path in res["paths"].values():
        print(f"wrote {path}")
    return 0
