"""``clsas export``: an image file as VTK image data (.vti) or .npy with a JSON sidecar; a dataset
file as UFF channel data (.uff)."""

from __future__ import annotations

from pathlib import Path


def cmd_export(args) -> int:
    if Path(args.out).suffix.lower() == ".uff":
        import clsas
        import clsas.io

        print(f"wrote {clsas.io.export_uff(clsas.load(args.image), args.out, overwrite=args.overwrite)}")
        return 0
    from clsas.presenting.export import export
    from clsas.types.image import Image

    for path in export(Image.load(args.image), args.out):
        print(f"wrote {path}")
    return 0


def add_parser(sub) -> None:
    ex = sub.add_parser("export", help="write an image file as VTK image data (.vti, ParaView) "
                        "or .npy with a JSON sidecar (napari), or a dataset file as UFF channel data (.uff, "
                        "USTB / pyuff-ustb)")
    ex.add_argument("image", help="image file (HDF5) written by `clsas reconstruct`; for .uff, a dataset file")
    ex.add_argument("out", help="output file: .vti or .npy (an image), .uff (a dataset)")
    ex.set_defaults(func=cmd_export)
