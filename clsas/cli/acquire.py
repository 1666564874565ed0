"""``clsas acquire``: a scan on a rig (or an emulated one)."""

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
        except rig.ScanAborted as exc:  # a fault or Ctrl-C: the file keeps its stops, --resume continues it
            bar.close()
            print(f"clsas acquire: {exc}", file=sys.stderr)
            return 3
        except rig.StageRefused as exc:  # GRBL's settings refuse the rig file: nothing moved, nothing to resume
            bar.close()
            print(f"clsas acquire: error: {exc}", file=sys.stderr)
            return 2
    print(f"wrote {res.path}: {res.stops_done} of {res.n_stops} stops ({res.stops_this_run} this run, "
          f"{res.retried_stops} retried) in {res.elapsed_s:.1f} s; image it with: clsas reconstruct {res.path}")
    return 0


def add_parser(sub) -> None:
    a = sub.add_parser("acquire", help="run a scan on a rig (or an emulated one) described by rig.toml")
    a.add_argument("config", nargs="?", help="rig configuration (TOML)")
    a.add_argument("out", nargs="?", help="dataset file to write (HDF5)")
    a.add_argument("--resume", action="store_true", help="continue the file at its first missing stop")
    a.add_argument("--simulate", nargs="?", const="all", default=None, choices=("all", "stage", "audio"),
                   help="all (the default when given alone): emulated GRBL stage and simulated microphone hearing "
                   "the [simulate] scene; stage: the emulated stage with the real sound card; audio: the real "
                   "stage (stage.port) with the simulated microphone")
    a.add_argument("--fault", help="with --simulate: inject faults, e.g. alarm@5, reset@2, error@3, drop-ok@2, "
                   "disconnect@4 "
                   "(at the N-th move)")
    a.add_argument("--sample-config", action="store_true", help="print a commented rig.toml and exit")
    a.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    a.add_argument("-v", "--verbose", action="store_true", help="log the stage dialogue and retries")
    a.set_defaults(func=cmd_acquire)
