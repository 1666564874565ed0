"""``clsas reconstruct``: image a dataset file."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from . import autofocus as af
from .common import add_device_options, box_arg, check_grids_fit, grid_arg, reconstruct_image
from .preprocess import add_preprocess_options, apply_preprocessing


def cmd_reconstruct(args) -> int:
    import clsas
    from clsas.synthesis.scenes import stored_grid_and_truth

    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".svg", ".pdf"):
        raise ValueError(f"--plot: the file must end in .png, .svg or .pdf, got {args.plot!r}")
    af.check_consistency(args)
    ds = clsas.load(args.data)
    partial = _partial_scan(args.data)
    if partial:
        print(f"warning: {partial}", file=sys.stderr)
    stored_grid, truth = stored_grid_and_truth(ds.config)
    grid = grid_arg(args.grid, args.spacing, stored_grid)
    check_grids_fit([grid], args)  # before preprocessing and autofocus, not after them
    ds = _prepared(ds, grid, args)
    out = Path(args.out or Path(args.data).with_name(Path(args.data).stem + "-image.h5"))
    image = _formed_and_saved(ds, grid, args, out)
    if args.verbose and image.plan is not None:
        print(image.plan.describe())
    print(f"device: {image.device}; total {image.timings_s['total']:.3f} s")
    _print_formation_choice(image.provenance.get("formation_auto"))
    if bp_variant_line(image.provenance.get("bp")):
        print(bp_variant_line(image.provenance.get("bp")))
    _print_peaks(image, ds, args.peaks)
    if partial:
        print(f"(imaged from a partial scan: {partial.split(':')[1].split(';')[0].strip()})")
    if args.box is not None:
        from clsas.presenting.quality import tcr_db

        print(f"target-to-clutter ratio in {args.box}: {tcr_db(image, box_arg('--box', args.box)):.1f} dB")
    _write_pictures(image, ds, truth, out, args)
    print(f"wrote {out}")
    return 0


def _prepared(ds, grid, args):
    """``--preprocess`` and ``--autofocus``: the dataset as it is to be imaged."""
    if args.preprocess:
        n_before = len(ds.provenance)
        ds, source = apply_preprocessing(ds, args, stored=True)
        if not source:
            raise ValueError("--preprocess: no steps given and no [preprocess] table in the dataset or --config")
        print(f"preprocessed with the steps from {source}: {', '.join(p['step'] for p in ds.provenance[n_before:])}")
    if args.autofocus:
        ds, _ = af.run_autofocus(ds, grid, args)
    return ds


def _formed_and_saved(ds, grid, args, out: Path):
    """The image, written to ``out``: tile by tile into the file (``--max-memory``, ``--scheduler``, a
    ``.zarr`` store), else formed in memory and saved; either way with the dataset's provenance."""
    import clsas
    from clsas.types.image import source_provenance

    if args.max_memory is not None or args.scheduler is not None or out.suffix.lower() == ".zarr":
        image = _reconstruct_tiled(ds, grid, args, out)
        return clsas.pipeline.tiling.update_attrs(image, source_provenance(ds, args.data),
                                                  compression=args.compression)
    image = reconstruct_image(ds, grid, args, not args.quiet)
    image.provenance.update(source_provenance(ds, args.data), compression=args.compression)
    image.save(out, overwrite=True)  # checked against --overwrite before any work
    return image


def _print_formation_choice(auto: dict | None) -> None:
    """What ``formation="auto"`` chose and why, with each measured check against bp."""
    if not auto:
        return
    print(f"formation: {auto['formation']} (auto, error target {auto['max_error_db']:g} dB: {auto['reason']})")
    for c in auto.get("checks", []):
        err, up = (f"{float(c[k]):.1f}" for k in ("error_db", "upper_db"))  # "inf" is stored as a string
        print(f"  measured {c['formation']} against bp on {c['voxels']} voxels (a stride of {c['stride']}): "
              f"{err} dB (upper bound {up} dB): " + ("kept" if c["kept"] else "over the target, not kept"))


def bp_variant_line(record: dict | None) -> str:
    """The line ``clsas reconstruct`` prints for bp's kernel variant (``image.provenance["bp"]``,
    :func:`clsas.formation.bp.variant_record`) where it is less exact than the plain float kernel:
    the variant, its shape, its stated bound and the allowance; ``""`` for the exact ones."""
    if not record or not record.get("error_bound"):
        return ""
    bound = float(record["error_bound"])
    return (f"bp kernel: {record['variant']} ({record['shape']}), stated error against the float64 twin at most "
            f"{bound:.2g} of the peak ({20 * np.log10(bound):.0f} dB), allowed {record['max_error_db']:g} dB")


def _print_peaks(image, ds, n: int) -> None:
    """The ``n`` strongest peaks, each with a note where it may be a grating lobe of a stronger one."""
    from clsas.compression import center_frequency
    from clsas.formation.lobes import grating_lobe_notes

    peaks = image.peaks(n, min_separation_m=0.03)
    notes = grating_lobe_notes(peaks, ds.tx_positions, ds.rx_positions, center_frequency(ds.waveform, ds.fs_hz),
                               float(np.mean(ds.c_mps)))
    for p, note in zip(peaks, notes, strict=True):
        x, y, z = p.position_m
        print(f"peak ({x:+.3f}, {y:+.3f}, {z:.3f}) m  |v| = {p.magnitude:.4g}" + (f"  [{note}]" if note else ""))


def _write_pictures(image, ds, truth, out: Path, args) -> None:
    """``--png`` (beside ``out``) and ``--plot FILE``: the image's picture, the truth and scene marked."""
    if not (args.png or args.plot):
        return
    from clsas.synthesis.scenes import stored_scene

    kw = dict(truth_m=truth, scene=stored_scene(ds.config), aperture=ds, dynamic_range_db=args.dynamic_range)
    for pic in ([out.with_suffix(".png")] if args.png else []) + ([Path(args.plot)] if args.plot else []):
        image.plot(pic, **kw)
        print(f"wrote {pic}")


def _reconstruct_tiled(ds, grid, args, out: Path):
    """``--max-memory`` / ``--scheduler``: the grid formed tile by tile into ``out`` (resumable)."""
    import clsas

    from .common import formation_options, stage_bar

    with stage_bar(not args.quiet) as cb:
        return clsas.reconstruct(ds, grid, method=args.method, compression=args.compression, backend=args.backend,
                                 device=args.device, progress=cb, force=args.force, formation=args.formation,
                                 formation_options=formation_options(args.formation_option) or None, out=out,
                                 max_memory=args.max_memory, client=args.scheduler, max_error_db=args.max_error_db)


def _partial_scan(path) -> str:
    """A warning for a scan file that ``clsas acquire`` did not finish, else ``""``."""
    import h5py

    with h5py.File(path, "r") as f:
        if "complete" not in f.attrs or bool(f.attrs["complete"]):
            return ""
        planned = int(f.attrs.get("n_stops_planned", 0))
        done = len(np.unique(f["stop_index"][()])) if "stop_index" in f else 0
    return (f"partial scan: {done} of {planned} stops were taken; the image lacks the rest "
            f"(continue it with: clsas acquire RIG.toml {path} --resume)")


def add_parser(sub) -> None:
    from clsas.formation import FORMATIONS
    from clsas.formation.auto import DEFAULT_MAX_ERROR_DB
    from clsas.pipeline.reconstruction import methods

    r = sub.add_parser("reconstruct", help="image a dataset file")
    r.add_argument("data", help="dataset file (HDF5, from clsas simulate, acquire, import or preprocess)")
    r.add_argument("--grid", help="x0,x1,y0,y1,z0,z1 in m, e.g. --grid=-0.5,0.5,-0.5,0.5,1,2 "
                   "(default: the dataset's [grid])")
    r.add_argument("--spacing", type=float, help="voxel spacing in m")
    r.add_argument("--method", default="bp", choices=methods(),
                   help="bp: matched filter + backprojection (default); bpdn, cbp-taylor, cbp-polar: each recording "
                   "super-resolved first (needs the sparse extra)")
    r.add_argument("--compression", default="matched", choices=("matched", "fmcw"),
                   help="matched filter (default), or FMCW dechirp (only for echoes that arrive while the chirp plays)")
    r.add_argument("--out", help="image file (default: <data>-image.h5); a .zarr store is written tile by tile "
                   "(needs the zarr extra)")
    r.add_argument("--max-memory", metavar="SIZE",
                   help="form the image tile by tile into --out (a chunked HDF5 file, read lazily afterwards) with "
                   "this process's memory under SIZE, e.g. 2GB; an interrupted run given again resumes")
    r.add_argument("--scheduler", metavar="ADDRESS",
                   help="form the tiles on the Dask cluster at ADDRESS (tcp://host:8786; needs the distributed "
                   "extra), streaming them into --out")
    r.add_argument("--png", action="store_true", help="also write the picture as <out>.png")
    r.add_argument("--plot", metavar="FILE",
                   help="write the picture (projections and slices through the peak) to FILE: .png, .svg or .pdf")
    r.add_argument("--dynamic-range", type=float, default=40.0, metavar="DB",
                   help="the picture's floor, dB below the peak (default 40)")
    r.add_argument("--peaks", type=int, default=3, help="peaks to print")
    r.add_argument("--force", action="store_true", help="image even if the grid does not seem to fit in memory")
    r.add_argument("--box", help="target box x0,x1,y0,y1,z0,z1 in m: print the target-to-clutter ratio")
    r.add_argument("--preprocess", action="store_true",
                   help="preprocess first: the steps below, else the [preprocess] table of --config or the dataset")
    r.add_argument("--formation", default="auto", choices=FORMATIONS.names(),
                   help="how the profiles become an image: auto (default: the fastest whose predicted error meets "
                   "--max-error-db, said in the log and kept in the image file), bp (exact backprojection), omega-k "
                   "(planar uniform apertures, much faster), ... (see docs/guide/fast-formation.md)")
    r.add_argument("--max-error-db", type=float, default=None, metavar="DB",
                   help="the largest error against exact backprojection allowed: the target of --formation auto "
                   f"(default {DEFAULT_MAX_ERROR_DB:g}), and, where given, what bp's kernel (chosen or named) may "
                   "trade for speed (half-precision records, the range expansion; default: exact)")
    r.add_argument("--formation-option", action="append", metavar="KEY=VALUE",
                   help="an option of the formation, e.g. --formation-option upsample=2 (repeatable)")
    add_preprocess_options(r)
    r.add_argument("--autofocus", action="store_true",
                   help="estimate motion, sound speed and delay from the scan first (see clsas autofocus)")
    af.add_autofocus_options(r)
    add_device_options(r)
    r.set_defaults(func=cmd_reconstruct)
