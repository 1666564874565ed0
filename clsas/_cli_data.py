"""The ``clsas`` commands for measured data: import, preprocess, compare, export (and the
preprocessing options ``reconstruct --preprocess`` shares)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _preprocess_table(ds, config_path: str | None) -> tuple[dict, str]:
    """The [preprocess] table of a TOML file, else the one stored in the dataset's configuration."""
    import tomllib

    if config_path is not None:
        path = Path(config_path)
        if not path.exists():
            raise FileNotFoundError(f"no preprocessing file at {path}")
        from clsas.config import preprocess_table, read_text

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
    if args.blank_direct:
        opts["blank_direct"] = True
    return opts


def _apply_preprocessing(ds, args, stored: bool):
    from clsas import preprocess as pp

    opts = _preprocess_args(args)
    if opts:
        return pp.apply(ds, **opts), "the command line"
    if stored or args.config is not None:
        table, where = _preprocess_table(ds, args.config)
        if table:
            return pp.from_table(ds, table, where=f"[preprocess] in {where}"), where
    return ds, ""


def cmd_preprocess(args) -> int:
    import clsas

    ds = clsas.load(args.data)
    out, source = _apply_preprocessing(ds, args, stored=True)
    if not source:
        raise ValueError("nothing to do: give steps (--dc, --bandpass, --background, --blank-direct, "
                         "--group-delay-samples) or a [preprocess] table (--config, or stored in the dataset)")
    out.save(args.out)
    steps = out.provenance[len(ds.provenance):]
    print(f"preprocessed {args.data} ({ds.n_meas} measurements) with the steps from {source}:")
    for st in steps:
        detail = ", ".join(f"{k}={val:.4g}" if isinstance(val, float) else f"{k}={val}"
                           for k, val in st.items() if k != "step")
        print(f"  {st['step']}{': ' + detail if detail else ''}")
    print(f"wrote {args.out}; image it with: clsas reconstruct {args.out}")
    return 0


def _box_arg(option: str, text: str | None):
    if text is None:
        return None
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6:
        raise ValueError(f"{option} must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}")
    return (tuple(vals[0:2]), tuple(vals[2:4]), tuple(vals[4:6]))


def cmd_compare(args) -> int:
    from clsas.quality import compare

    res = compare(args.a, args.b, target_box=_box_arg("--box", args.box),
                  clutter_box=_box_arg("--clutter-box", args.clutter_box), peaks=args.peaks)
    print(f"a = {args.a}\nb = {args.b}")
    print(res.report())
    return 0


def _preprocess_options(sp) -> None:
    g = sp.add_argument_group("preprocessing (in this order; default: the [preprocess] table of --config or of "
                              "the dataset's stored configuration)")
    g.add_argument("--group-delay-samples", type=float, metavar="N",
                   help="system (transducer) delay to remove, in samples (t0_s becomes t0_s - N/fs)")
    g.add_argument("--dc", action="store_true", help="subtract each recording's mean")
    g.add_argument("--bandpass", nargs="?", const="chirp", metavar="F_LO,F_HI",
                   help="zero-phase band-pass: the chirp's band (no value) or F_LO,F_HI in Hz")
    g.add_argument("--background", metavar="EMPTY.h5",
                   help="subtract this empty-scene scan (same stops), stretched to the scan's air")
    g.add_argument("--own-background", action="store_true", help="subtract the background stored in the dataset")
    g.add_argument("--align-s", type=float, default=0.0, metavar="S",
                   help="with a background: also align each of its recordings within +-S seconds")
    g.add_argument("--blank-direct", action="store_true",
                   help="zero each recording until the direct speaker-to-microphone sound has passed")
    g.add_argument("--config", metavar="FILE.toml", help="take the steps from this file's [preprocess] table")


def cmd_export(args) -> int:
    from clsas.export import export
    from clsas.imaging.image import Image

    for path in export(Image.load(args.image), args.out):
        print(f"wrote {path}")
    return 0


def cmd_import(args) -> int:
    import clsas.io

    fmt = clsas.io.detect_format(args.source) if args.format == "auto" else args.format
    opts = {}
    if args.waveform_index is not None:
        if fmt != "airsas":
            raise ValueError("--waveform-index is for the airsas format")
        opts["waveform_index"] = args.waveform_index
    ds = clsas.io.import_scan(args.source, format=fmt, background=args.background, **opts)
    ds.save(args.out)
    print(f"imported {args.source} ({fmt}): {ds.n_meas} measurements x {ds.n_samples} samples "
          f"at {ds.fs_hz:g} Hz")
    ch = ds.chirp
    if {"f_start_hz", "f_stop_hz", "duration_s"} <= set(ch):
        print(f"  waveform: LFM {ch['f_start_hz']:g} -> {ch['f_stop_hz']:g} Hz, {ch['duration_s'] * 1e3:g} ms, "
              f"taper {ch.get('taper', 0.0):g} ({len(ds.waveform)} samples)")
    else:
        print(f"  waveform: {len(ds.waveform)} samples ({len(ds.waveform) / ds.fs_hz * 1e3:.3g} ms)")
    t, c, t0 = np.asarray(ds.temperature_c), ds.c_per_meas, ds.t0_s * 1e3
    t0_text = f"{t0[0]:.4g}" if np.ptp(t0) == 0 else f"{t0.min():.4g} to {t0.max():.4g}"
    print(f"  t0: {t0_text} ms; air: {t.min():.1f} to {t.max():.1f} C, c {c.min():.1f} to {c.max():.1f} m/s")
    pos = np.concatenate([ds.tx_positions, ds.rx_positions])
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    print("  aperture (speakers and microphones): " + ", ".join(
        f"{a} {lo[i]:+.3f} to {hi[i]:+.3f}" for i, a in enumerate("xyz")) + " m")
    if ds.background is not None:
        print(f"  background: {args.background} ({ds.background.shape[0]} recordings, stored for subtraction)")
    print(f"wrote {args.out}")
    if fmt == "airsas":  # target frame: the turntable axis is x = y = 0
        r = float(np.min(np.hypot(ds.tx_positions[:, 0], ds.tx_positions[:, 1]))) / 4
        grid = f"{-r:.2f},{r:.2f},{-r:.2f},{r:.2f},0,0"
    else:
        grid = "x0,x1,y0,y1,z0,z1"
    print(f"next: clsas reconstruct {args.out} --grid={grid} --spacing 0.005  (metres, in the dataset's frame)")
    return 0
