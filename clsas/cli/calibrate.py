"""``clsas calibrate``: measure ``formation="auto"``'s cost model on this machine's device."""

from __future__ import annotations


def cmd_calibrate(args) -> int:
    from clsas.formation.auto.calibrate import MIN_SIDE, SIDES_FULL, SIDES_QUICK, calibrate_auto

    sides = args.sides or (SIDES_FULL if args.full else SIDES_QUICK)
    bad = [n for n in sides if n < MIN_SIDE]
    if bad:
        raise ValueError(f"--sides: each must be at least {MIN_SIDE} stops a side, got {bad}")

    def status(line: str) -> None:
        if not args.quiet:
            print(f"[calibrate] {line}", flush=True)

    res = calibrate_auto(tuple(sides), backend=args.backend, device=args.device, store=not args.dry_run,
                         status=status)
    print(f"device: {res['device']}")
    for name, factor in res["factors"].items():
        print(f"  {name}: measured / built-in predicted time = {factor:.2f}")
    print(f"kept in {res['path']} (formation='auto' reads it)" if "path" in res else "not kept (--dry-run)")
    return 0


def add_parser(sub) -> None:
    from .common import add_device_options

    c = sub.add_parser("calibrate", help="measure formation='auto''s cost model on this device and keep it "
                       "(about a minute on a 2-core CPU; --full about five)")
    c.add_argument("--full", action="store_true", help="also the 96 and 128 stop-a-side scans")
    c.add_argument("--sides", type=int, nargs="+", metavar="N", default=None,
                   help="the N x N-stop scans to time (each at least 8; default 16 24 32 48 64)")
    c.add_argument("--dry-run", action="store_true", help="measure and print, keep nothing")
    add_device_options(c)
    c.set_defaults(func=cmd_calibrate)
