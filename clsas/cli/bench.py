"""``clsas bench``: kernel and wall rates of every formation and of the whole reconstruct, on every device."""

from __future__ import annotations

import sys
from pathlib import Path


def _check(args) -> None:
    """The command line's values, named by their flags, before any work."""
    from clsas.formation.auto.calibrate import MIN_SIDE

    if args.size < MIN_SIDE:
        raise ValueError(f"--size: stops per side must be at least {MIN_SIDE}, got {args.size}")
    if args.repeats < 1:
        raise ValueError(f"--repeats: must be at least 1, got {args.repeats}")
    if args.out is not None and Path(args.out).exists() and not Path(args.out).is_dir():
        raise ValueError(f"--out: {args.out} exists and is not a folder")
    if args.devices is not None:
        from clsas.presenting.rates import devices

        found = [d["index"] for d in devices()]
        missing = sorted(set(args.devices) - set(found))
        if missing:
            raise ValueError(f"--devices: {missing} not among the devices found here: {found} "
                             "(`clsas devices` lists the OpenCL ones)")


def cmd_bench(args) -> int:
    from clsas.presenting import rates

    _check(args)

    def status(line: str) -> None:
        if not args.quiet:
            print(f"[bench] {line}", file=sys.stderr, flush=True)

    res = rates.measure_rates(args.size, devices=args.devices, repeats=args.repeats, status=status)
    print("\n".join(rates.table(res)))
    if args.out is not None:
        stem = rates.write(res, args.out)
        print(f"wrote {stem}.json and .md")
    return 0


def add_parser(sub) -> None:
    from clsas.presenting.rates import DEFAULT_SIZE, REPEATS

    b = sub.add_parser("bench", help="kernel and wall rates of bp, omega-k, ffbp and the whole reconstruct on every "
                       "device, with the wall time's shares on the host, in transfers and in kernels (about half a "
                       "minute on a 2-core CPU)")
    b.add_argument("--size", type=int, default=DEFAULT_SIZE, metavar="N",
                   help=f"the scan's stops per side, N x N stops 5.6 mm apart (at least 8; default {DEFAULT_SIZE})")
    b.add_argument("--devices", nargs="+", metavar="P:D|numpy", default=None,
                   help="only these devices (OpenCL P:D numbers as `clsas devices` lists them, or numpy for the "
                   "NumPy twins; default every device whose kernels build, and the twins)")
    b.add_argument("--repeats", type=int, default=REPEATS, metavar="K",
                   help=f"timed calls per step after one untimed call; medians are reported (default {REPEATS})")
    b.add_argument("--out", default=None, metavar="DIR",
                   help="also write the run as <date>-rates-<cpu>.json and .md in DIR")
    b.set_defaults(func=cmd_bench)
