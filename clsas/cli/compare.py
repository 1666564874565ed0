"""``clsas compare``: two images on the same grid: correlation, peak offsets, TCR."""

from __future__ import annotations

from .common import box_arg


def cmd_compare(args) -> int:
    from clsas.presenting.quality import compare

    res = compare(args.a, args.b, target_box=box_arg("--box", args.box),
                  clutter_box=box_arg("--clutter-box", args.clutter_box), peaks=args.peaks)
    print(f"a = {args.a}\nb = {args.b}")
    print(res.report())
    return 0


def add_parser(sub) -> None:
    cmp_ = sub.add_parser("compare", help="compare two images on the same grid: correlation, peak offsets, TCR")
    cmp_.add_argument("a", help="image file (HDF5, from clsas reconstruct)")
    cmp_.add_argument("b", help="image file on the same grid")
    cmp_.add_argument("--box", help="target box x0,x1,y0,y1,z0,z1 in m: report each image's target-to-clutter "
                      "ratio (peak in the box / RMS outside it), e.g. --box=-0.05,0.05,-0.05,0.05,0,0")
    cmp_.add_argument("--clutter-box", help="x0,x1,y0,y1,z0,z1 in m: measure the clutter here (less the target box)")
    cmp_.add_argument("--peaks", type=int, default=3, help="strongest peaks to match between the images (default 3)")
    cmp_.set_defaults(func=cmd_compare)
