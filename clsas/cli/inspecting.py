"""``clsas inspect``: a look at a dataset before imaging it (:mod:`clsas.presenting.inspection`)."""

from __future__ import annotations

from pathlib import Path


def _stored_grid(ds, source: str):
    import tomllib

    from clsas.io.config import grid_table

    return grid_table(tomllib.loads(ds.config), source) if ds.config.strip() else None


def cmd_inspect(args) -> int:
    import clsas
    from clsas.presenting.inspection import draw_inspection, inspect_dataset

    from .common import grid_arg

    ds = clsas.load(args.data)
    stored = _stored_grid(ds, args.data)
    grid = grid_arg(args.grid, args.spacing, stored) if (args.grid or stored is not None) else None
    ins = inspect_dataset(ds, grid)
    print(f"{args.data}: {ds.n_meas} measurements x {ds.n_samples} samples at {ds.fs_hz:g} Hz")
    if grid is not None:
        print(f"  grid: {100 * ins.in_gate_fraction:.0f} % of the echo energy after the direct sound is in its delays")
    for w in ins.warnings:
        print(f"  warning: {w}")
    if not ins.warnings:
        print("  no disagreement found between the geometry and the recordings")
    data = Path(args.data)
    png = Path(args.png) if args.png else data.with_name(data.stem + "-inspect.png")
    print(f"wrote {draw_inspection(ins, png)}")
    return 1 if (args.strict and ins.warnings) else 0


def add_parser(sub) -> None:
    sp = sub.add_parser("inspect", help="draw the transducer paths with the grid and a waterfall of the recordings "
                        "with the predicted arrivals; warn where geometry and data disagree")
    sp.add_argument("data", help="dataset file (HDF5), as imported (before blanking the direct sound)")
    sp.add_argument("--grid", help="x0,x1,y0,y1,z0,z1 in m (default: the dataset's stored [grid], if any)")
    sp.add_argument("--spacing", type=float, default=None, help="grid spacing, m (only its bounds matter here)")
    sp.add_argument("--png", help="picture to write (default: DATA-inspect.png)")
    sp.add_argument("--strict", action="store_true", help="exit with status 1 when there is a warning")
    sp.set_defaults(func=cmd_inspect)
