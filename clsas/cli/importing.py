"""``clsas import``: measured recordings (a WAV/CSV folder, the AirSAS layout, a UFF file) into a dataset file."""

from __future__ import annotations

import numpy as np

from ..types.dataset import SOUND_SPEED_STEP


def cmd_import(args) -> int:
    import clsas.io

    fmt = clsas.io.detect_format(args.source) if args.format == "auto" else args.format
    opts = {}
    if args.waveform_index is not None:
        if fmt != "airsas":
            raise ValueError("--waveform-index is for the airsas format")
        opts["waveform_index"] = args.waveform_index
    if getattr(args, "radius_m", None) is not None:
        if fmt != "airsas":
            raise ValueError("--radius-m is for the airsas format")
        opts["radius_m"] = args.radius_m
    ds = clsas.io.import_scan(args.source, format=fmt, background=args.background, **opts)
    ds.save(args.out, overwrite=True)  # checked against --overwrite before any work
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
    steps = [p for p in ds.provenance if p.get("step") == SOUND_SPEED_STEP]
    source = steps[-1]["c_mps_source"] if steps else "as the files state it"
    print(f"  t0: {t0_text} ms; air: {t.min():.1f} to {t.max():.1f} C, c {c.min():.1f} to {c.max():.1f} m/s "
          f"({source})")
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
    print(f"look first: clsas inspect {args.out} --grid={grid}  (paths, recordings, warnings)")
    print(f"next: clsas reconstruct {args.out} --grid={grid} --spacing 0.005  (metres, in the dataset's frame)")
    return 0


def add_parser(sub) -> None:
    from clsas.io import IMPORTERS

    im = sub.add_parser("import", help="import measured recordings (" + "; ".join(
        f"{name}: {imp.summary}" for name, imp in IMPORTERS.items()) + ")")
    im.add_argument("source", help="the scan's folder (or file: .uff)")
    im.add_argument("out", help="dataset file to write (HDF5)")
    im.add_argument("--format", choices=("auto", *IMPORTERS), default="auto",
                    help="layout of SOURCE (default: auto)")
    im.add_argument("--background", metavar="FOLDER", help="the empty-scene scan, same layout and stops")
    im.add_argument("--waveform-index", type=int, help="airsas: which interleaved waveform (0-based)")
    im.add_argument("--radius-m", type=float, metavar="R",
                    help="airsas: put the transducers R metres from the turntable axis (SysParams.csv's directions "
                         "and heights kept)")
    im.set_defaults(func=cmd_import)
