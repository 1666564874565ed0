"""``clsas preprocess`` (DC, band-pass, background, direct-path blanking, group delay) and the
preprocessing options ``reconstruct --preprocess`` shares."""

from __future__ import annotations

from pathlib import Path


def _preprocess_table(ds, config_path: str | None) -> tuple[dict, str]:
    """The [preprocess] table of a TOML file, else the one stored in the dataset's configuration."""
    import tomllib

    if config_path is not None:
        path = Path(config_path)
        if not path.exists():
            raise FileNotFoundError(f"no preprocessing file at {path}")
        from clsas.io.config import preprocess_table, read_text

        try:
            cfg = tomllib.loads(read_text(path, "preprocessing"))
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path} is not valid TOML: {exc}") from None
        if "preprocess" in cfg:
            cfg["preprocess"] = preprocess_table(cfg, str(path))  # its keys checked, with a suggestion
        where = f"{path}"
        bg = cfg.get("preprocess", {}).get("background") if isinstance(cfg.get("preprocess"), dict) else None
        # a background file named in the table is relative to the table's file
        if isinstance(bg, str) and not Path(bg).is_absolute():
            cfg["preprocess"]["background"] = str(path.parent / bg)
        elif isinstance(bg, dict) and isinstance(bg.get("path"), str) and not Path(bg["path"]).is_absolute():
            bg["path"] = str(path.parent / bg["path"])
    else:
        cfg = tomllib.loads(ds.config) if ds.config.strip() else {}
        where = "the dataset's stored configuration"
    table = cfg.get("preprocess")
    if table is None:
        return {}, where
    if not isinstance(table, dict):
        raise ValueError(f"[preprocess] in {where} must be a table")
    return table, where


def _preprocess_args(args) -> dict:
    """preprocess.apply() arguments from the command-line flags."""
    opts: dict = {}
    if args.group_delay_samples is not None:
        opts["group_delay_samples"] = args.group_delay_samples
    if getattr(args, "direct_clock", False):
        opts["direct_clock"] = True
    if args.dc:
        opts["dc"] = True
    if args.bandpass is not None:
        if args.bandpass == "chirp":
            opts["bandpass"] = True
        else:
            try:
                lo, hi = (float(x) for x in args.bandpass.split(","))
            except ValueError:
                raise ValueError(f"--bandpass must be 'chirp' or F_LO,F_HI in Hz, got {args.bandpass!r}") from None
            opts["bandpass"] = (lo, hi)
    if args.background is not None:
        opts["background"] = {"path": args.background, "align_s": args.align_s}
    elif args.own_background:
        opts["background"] = {"align_s": args.align_s}
    if getattr(args, "common", None):
        opts["common"] = args.common
    if args.blank_direct:
        opts["blank_direct"] = True
    return opts


def apply_preprocessing(ds, args, stored: bool):
    from clsas import preprocess as pp

    opts = _preprocess_args(args)
    if isinstance(opts.get("bandpass"), tuple):
        _check_band(opts["bandpass"], pp.chirp_band(ds))
    if opts:
        return pp.apply(ds, **opts), "the command line"
    if stored or args.config is not None:
        table, where = _preprocess_table(ds, args.config)
        if table:
            return pp.from_table(ds, table, where=f"[preprocess] in {where}"), where
    return ds, ""


def _check_band(band: tuple[float, float], chirp: tuple[float, float]) -> None:
    """Refuse a ``--bandpass`` band that misses the transmitted one (it would remove every echo)."""
    lo, hi = band
    if not lo < hi:
        raise ValueError(f"--bandpass F_LO,F_HI needs F_LO < F_HI, got {lo:g},{hi:g}")
    if hi <= chirp[0] or lo >= chirp[1]:
        raise ValueError(f"--bandpass {lo:g},{hi:g} Hz is outside the chirp's band {chirp[0]:g}-{chirp[1]:g} Hz: "
                         "it would remove every echo (give a band that covers the chirp's, or --bandpass alone "
                         "for the chirp's own)")


def add_preprocess_options(sp) -> None:
    g = sp.add_argument_group("preprocessing (in this order; default: the [preprocess] table of --config or of "
                              "the dataset's stored configuration)")
    g.add_argument("--group-delay-samples", type=float, metavar="N",
                   help="system (transducer) delay to remove, in samples (t0_s becomes t0_s - N/fs)")
    g.add_argument("--dc", action="store_true", help="subtract each recording's mean")
    g.add_argument("--bandpass", nargs="?", const="chirp", metavar="F_LO,F_HI",
                   help="zero-phase band-pass: the chirp's band (no value) or F_LO,F_HI in Hz")
    g.add_argument("--direct-clock", action="store_true",
                   help="set t0 from the direct speaker-to-microphone sound of the scan itself (one shift)")
    g.add_argument("--background", metavar="EMPTY.h5",
                   help="subtract this empty-scene scan (same stops), stretched to the scan's air")
    g.add_argument("--own-background", action="store_true", help="subtract the background stored in the dataset")
    g.add_argument("--align-s", type=float, default=0.0, metavar="S",
                   help="with a background: also align each of its recordings within +-S seconds")
    g.add_argument("--common", nargs="?", const="mean", choices=("mean", "median"),
                   help="subtract what every recording shares at each delay (mean, or median): the "
                        "turntable's and the room's rings; removes wanted signal on static planar scans")
    g.add_argument("--blank-direct", action="store_true",
                   help="zero each recording until the direct speaker-to-microphone sound has passed")
    g.add_argument("--config", metavar="FILE.toml", help="take the steps from this file's [preprocess] table")


def cmd_preprocess(args) -> int:
    import clsas

    ds = clsas.load(args.data)
    out, source = apply_preprocessing(ds, args, stored=True)
    if not source:
        raise ValueError("nothing to do: give steps (--dc, --bandpass, --background, --common, --blank-direct, "
                         "--group-delay-samples) or a [preprocess] table (--config, or stored in the dataset)")
    out.save(args.out, overwrite=True)  # checked against --overwrite before any work
    steps = out.provenance[len(ds.provenance):]
    print(f"preprocessed {args.data} ({ds.n_meas} measurements) with the steps from {source}:")
    for st in steps:
        detail = ", ".join(f"{k}={val:.4g}" if isinstance(val, float) else f"{k}={val}"
                           for k, val in st.items() if k != "step")
        print(f"  {st['step']}{': ' + detail if detail else ''}")
    print(f"wrote {args.out}; image it with: clsas reconstruct {args.out}")
    return 0


def add_parser(sub) -> None:
    pre = sub.add_parser("preprocess", help="DC, band-pass, background subtraction, direct-path blanking, "
                         "group delay: write a new dataset file")
    pre.add_argument("data", help="dataset file (HDF5)")
    pre.add_argument("out", help="dataset file to write")
    add_preprocess_options(pre)
    pre.set_defaults(func=cmd_preprocess)
