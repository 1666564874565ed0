"""``clsas export``: an image file as VTK image data (.vti) or .npy with a JSON sidecar."""

from __future__ import annotations


def cmd_export(args) -> int:
    from clsas.export import export
    from clsas.image import Image

    for path in export(Image.load(args.image), args.out):
        print(f"wrote {path}")
    return 0


def add_parser(sub) -> None:
    ex = sub.add_parser("export", help="write an image file as VTK image data (.vti, ParaView) "
                        "or .npy with a JSON sidecar (napari)")
    ex.add_argument("image", help="image file (HDF5) written by `clsas reconstruct`")
    ex.add_argument("out", help="output file: .vti or .npy")
    ex.set_defaults(func=cmd_export)
