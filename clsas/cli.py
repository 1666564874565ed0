"""The ``clsas`` command: demo, simulate, reconstruct, limits, devices, acquire, bench; the commands
for measured data (import, preprocess, compare, export) are in ``_cli_data.py``, ``devices``
in ``_cli_devices.py``, ``acquire`` and ``bench`` in ``_cli_run.py``, ``autofocus`` in ``_cli_autofocus.py``."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import _cli_autofocus as _autofocus
from ._cli_data import (
    _apply_preprocessing,
    _box_arg,
    _preprocess_options,
    cmd_compare,
    cmd_export,
    cmd_import,
    cmd_preprocess,
)
from ._cli_devices import cmd_devices
from ._cli_run import cmd_acquire, cmd_bench

log = logging.getLogger("clsas")


@contextmanager
def _bar(desc: str, total: int, enabled: bool = True):
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="stop", disable=not enabled, leave=False) as bar:
        def update(done: int, _total: int) -> None:
            if bar.total != _total:  # a formation counts its own steps (ω-k: spatial-frequency columns)
                bar.total = _total
            bar.update(done - bar.n)

        yield update


def _grid_arg(text: str | None, spacing: float | None, fallback):
    import clsas

    if text is None:
        if fallback is None:
            raise ValueError("--grid is required (the dataset stores no [grid] configuration)")
        if spacing is None:
            return fallback
        b = fallback.bounds()
        return clsas.VoxelGrid.from_bounds(tuple(b[0]), tuple(b[1]), tuple(b[2]), spacing)
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"--grid must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}") from None
    if len(vals) != 6:
        raise ValueError(f"--grid must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}")
    return clsas.VoxelGrid.from_bounds(tuple(vals[0:2]), tuple(vals[2:4]), tuple(vals[4:6]), spacing or 0.01)


def _simulate(cfg, progress=True):
    import clsas

    with _bar("simulate", cfg.aperture.n_meas, progress) as cb:
        return clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=cfg.snr_db,
                              seed=cfg.seed, chirp=cfg.chirp, config=cfg.text, progress=cb)


def _formation_options(items: list[str] | None) -> dict:
    """``KEY=VALUE`` pairs; values read as TOML scalars (numbers, true/false, "text"), else as text."""
    import tomllib

    out = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--formation-option must be KEY=VALUE, got {item!r}")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out[key.strip()] = value
    return out


def _reconstruct(ds, grid, args, progress=True):
    import clsas

    formation = getattr(args, "formation", "bp")
    options = _formation_options(getattr(args, "formation_option", None)) or None
    with _bar("backproject" if formation == "bp" else formation, ds.n_meas, progress) as cb:
        return clsas.reconstruct(ds, grid, method=getattr(args, "method", "bp"),
                                 compression=getattr(args, "compression", "matched"),
                                 backend=args.backend, device=getattr(args, "device", None), progress=cb,
                                 force=getattr(args, "force", False), formation=formation,
                                 formation_options=options)


def cmd_demo(args) -> int:
    import clsas
    from clsas.plots import mip_png
    from clsas.scenes import demo_configs, parse_config

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(clsas.resolution_limits(20e3, 30e3, 1.0, 1.0, 18, 12, range_m=1.5).report())
    print()
    for name, text in demo_configs(args.spacing).items():
        cfg = parse_config(text)
        t = time.perf_counter()
        ds = _simulate(cfg, not args.quiet)
        t_sim = time.perf_counter() - t
        ds.save(out / f"{name}.h5")
        image = _reconstruct(ds, cfg.grid, args, not args.quiet)
        image.save(out / f"{name}-image.h5")
        truth = cfg.scene.image_sources()[0]
        label = "mannequin in front" if name == "front" else "mannequin around the corner (mirror image)"
        mip_png(image, out / f"{name}.png", truth, f"{label}: {ds.n_meas} stops, 20-30 kHz, {image.device}",
                scene=cfg.scene, aperture=ds)
        peak = image.peaks(1)[0].position_m
        nearest = np.min(np.linalg.norm(truth - peak, axis=1))
        ts = image.timings_s
        print(f"[{name}] {label}")
        print(f"  grid {'x'.join(map(str, cfg.grid.shape))} = {cfg.grid.size} voxels; "
              f"{ds.n_meas} measurements x {ds.n_samples} samples")
        print(f"  device: {image.device}")
        print(f"  simulate {t_sim:.2f} s | compress {ts.get('compress', 0):.3f} s | "
              f"backproject {ts.get('backproject', 0):.3f} s "
              f"({cfg.grid.size * ds.n_meas / max(ts.get('backproject', 1e-9), 1e-9):.3g} pairs/s)")
        print(f"  brightest voxel at ({peak[0]:+.3f}, {peak[1]:+.3f}, {peak[2]:.3f}) m, "
              f"{nearest * 100:.1f} cm from the nearest true (image) reflector")
        print(f"  wrote {out / (name + '.h5')}, {out / (name + '-image.h5')}, {out / (name + '.png')}")
    return 0


def cmd_simulate(args) -> int:
    from clsas.scenes import load_config

    cfg = load_config(args.scene)
    ds = _simulate(cfg, not args.quiet)
    ds.save(args.out)
    print(f"wrote {args.out}: {ds.n_meas} measurements x {ds.n_samples} samples at {ds.fs_hz:g} Hz")
    return 0


def cmd_reconstruct(args) -> int:
    import clsas
    from clsas.scenes import stored_grid_and_truth

    if args.plot and Path(args.plot).suffix.lower() not in (".png", ".svg", ".pdf"):
        raise ValueError(f"--plot: the file must end in .png, .svg or .pdf, got {args.plot!r}")
    ds = clsas.load(args.data)
    partial = _partial_scan(args.data)
    if partial:
        print(f"warning: {partial}", file=sys.stderr)
    stored_grid, truth = stored_grid_and_truth(ds.config)
    grid = _grid_arg(args.grid, args.spacing, stored_grid)
    if args.preprocess:
        n_before = len(ds.provenance)
        ds, source = _apply_preprocessing(ds, args, stored=True)
        if not source:
            raise ValueError("--preprocess: no steps given and no [preprocess] table in the dataset or --config")
        print(f"preprocessed with the steps from {source}: {', '.join(p['step'] for p in ds.provenance[n_before:])}")
    if args.autofocus:
        from ._cli_autofocus import run_autofocus

        ds, _ = run_autofocus(ds, grid, args)
    image = _reconstruct(ds, grid, args, not args.quiet)
    from clsas.imaging.image import source_provenance

    image.provenance.update(source_provenance(ds, args.data), compression=args.compression)
    out = Path(args.out or Path(args.data).with_name(Path(args.data).stem + "-image.h5"))
    image.save(out)
    if args.verbose and image.plan is not None:
        print(image.plan.describe())
    peaks = image.peaks(args.peaks, min_separation_m=0.03)
    print(f"device: {image.device}; total {image.timings_s['total']:.3f} s")
    from clsas.compression import center_frequency
    from clsas.imaging.lobes import grating_lobe_notes

    notes = grating_lobe_notes(peaks, ds.tx_positions, ds.rx_positions, center_frequency(ds.waveform, ds.fs_hz),
                               float(np.mean(ds.c_mps)))
    for p, note in zip(peaks, notes, strict=True):
        x, y, z = p.position_m
        print(f"peak ({x:+.3f}, {y:+.3f}, {z:.3f}) m  |v| = {p.magnitude:.4g}" + (f"  [{note}]" if note else ""))
    if partial:
        print(f"(imaged from a partial scan: {partial.split(':')[1].split(';')[0].strip()})")
    if args.box is not None:
        from clsas.quality import tcr_db

        print(f"target-to-clutter ratio in {args.box}: {tcr_db(image, _box_arg('--box', args.box)):.1f} dB")
    if args.png or args.plot:
        from clsas.plots import stored_scene

        kw = dict(truth_m=truth, scene=stored_scene(ds.config), aperture=ds, dynamic_range_db=args.dynamic_range)
        for pic in ([out.with_suffix(".png")] if args.png else []) + ([Path(args.plot)] if args.plot else []):
            image.plot(pic, **kw)
            print(f"wrote {pic}")
    print(f"wrote {out}")
    return 0


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


_LIMITS_DEFAULTS = {"f_start": 20e3, "f_stop": 30e3, "width": 1.0, "height": 1.0, "nx": 18, "ny": 12, "range": 1.5,
                    "temperature": 20.0, "humidity": 50.0}


def _limits_from_file(path: str) -> dict:
    """The limits' inputs from a scene or rig file: [chirp], [aperture], [air], and the range
    from the [grid]'s centre (else the reflectors' mean) to the aperture's plane."""
    import tomllib

    from clsas.config import kind_of, read_text

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no scene or rig file at {p}")
    text = read_text(p, "scene or rig")
    try:
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p} is not a TOML scene or rig file: {exc}") from None
    # the whole file is checked as what it is (unknown keys refused, with a suggestion)
    if kind_of(cfg) == "rig":
        from clsas.rig import parse_rig_config

        parse_rig_config(text, source=str(p))
    else:
        from clsas.scenes import parse_config

        parse_config(text, source=str(p))
    out = {}
    keys = {"chirp": {"f_start_hz": "f_start", "f_stop_hz": "f_stop"},
            "aperture": {"width_m": "width", "height_m": "height", "nx": "nx", "ny": "ny"},
            "air": {"temperature_c": "temperature", "humidity_pct": "humidity"}}
    for table, names in keys.items():
        t = cfg.get(table, {})
        if not isinstance(t, dict):
            raise ValueError(f"{p}: [{table}] must be a table")
        for key, arg in names.items():
            if key in t:
                out[arg] = t[key]
    z0 = (cfg.get("aperture", {}).get("center_m") or [0.0, 0.0, 0.0])[2]
    grid = cfg.get("grid")
    if isinstance(grid, dict) and "z_m" in grid:
        out["range"] = abs(0.5 * (grid["z_m"][0] + grid["z_m"][1]) - z0)
    elif cfg.get("points"):
        out["range"] = abs(float(np.mean([pt["position_m"][2] for pt in cfg["points"]])) - z0)
    return out


def cmd_limits(args) -> int:
    import clsas

    values = dict(_LIMITS_DEFAULTS)
    if args.config is not None:
        values.update(_limits_from_file(args.config))
    values.update({k: getattr(args, k) for k in _LIMITS_DEFAULTS if getattr(args, k) is not None})
    if args.config is not None:
        print(f"from {args.config} (flags override): " + ", ".join(f"{k}={values[k]:g}" for k in _LIMITS_DEFAULTS))
    lim = clsas.resolution_limits(values["f_start"], values["f_stop"], values["width"], values["height"],
                                  values["nx"], values["ny"], values["range"], values["temperature"],
                                  values["humidity"])
    print(lim.report())
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clsas", description="In-air synthetic-aperture audio imaging")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--backend", choices=("auto", "opencl", "numpy"), default=None,
                        help="compute backend (default: $CLSAS_BACKEND or auto)")
        sp.add_argument("--device", default=None, metavar="P:D",
                        help="OpenCL platform:device numbers from `clsas devices` (default: $PYOPENCL_CTX or the best)")
        sp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
        sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed and skipped")

    d = sub.add_parser("demo", help="simulate and image the paper's two scenes")
    d.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    d.add_argument("--spacing", type=float, default=0.01, help="voxel spacing in m (default 0.01)")
    d.add_argument("--force", action="store_true", help="image even if the grid does not seem to fit in memory")
    common(d)
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="simulate a scan from a scene TOML file")
    s.add_argument("scene", help="scene file (TOML: [chirp], [aperture], [air], [noise], [[points]], [grid])")
    s.add_argument("out", help="dataset file to write (HDF5)")
    common(s)
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reconstruct", help="image a dataset file")
    r.add_argument("data", help="dataset file (HDF5, from clsas simulate, acquire, import or preprocess)")
    r.add_argument("--grid", help="x0,x1,y0,y1,z0,z1 in m, e.g. --grid=-0.5,0.5,-0.5,0.5,1,2 "
                   "(default: the dataset's [grid])")
    r.add_argument("--spacing", type=float, help="voxel spacing in m")
    r.add_argument("--method", default="bp", choices=("bp", "bpdn", "cbp-taylor", "cbp-polar"),
                   help="bp: matched filter + backprojection (default); bpdn, cbp-taylor, cbp-polar: each recording "
                   "super-resolved first (needs the sparse extra)")
    r.add_argument("--compression", default="matched", choices=("matched", "fmcw"),
                   help="matched filter (default), or FMCW dechirp (only for echoes that arrive while the chirp plays)")
    r.add_argument("--out", help="image file (default: <data>-image.h5)")
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
    from clsas.formation import FORMATIONS

    r.add_argument("--formation", default="bp", choices=tuple(FORMATIONS),
                   help="how the profiles become an image: bp (exact backprojection, default), omega-k (planar uniform "
                   "apertures, much faster), ... (see README: Fast image formation)")
    r.add_argument("--formation-option", action="append", metavar="KEY=VALUE",
                   help="an option of the formation, e.g. --formation-option upsample=2 (repeatable)")
    _preprocess_options(r)
    r.add_argument("--autofocus", action="store_true",
                   help="estimate motion, sound speed and delay from the scan first (see clsas autofocus)")
    _autofocus.add_autofocus_options(r)
    common(r)
    r.set_defaults(func=cmd_reconstruct)
    _autofocus.add_parser(sub, common)

    pre = sub.add_parser("preprocess", help="DC, band-pass, background subtraction, direct-path blanking, "
                         "group delay: write a new dataset file")
    pre.add_argument("data", help="dataset file (HDF5)")
    pre.add_argument("out", help="dataset file to write")
    _preprocess_options(pre)
    pre.set_defaults(func=cmd_preprocess)

    lim = sub.add_parser("limits", help="resolution limits of a scan configuration")
    lim.add_argument("config", nargs="?", help="a scene or rig TOML file to take the chirp, aperture, air and "
                     "range from (flags override it)")
    lim.add_argument("--f-start", type=float, help="chirp start, Hz (default 20000)")
    lim.add_argument("--f-stop", type=float, help="chirp stop, Hz (default 30000)")
    lim.add_argument("--width", type=float, help="aperture width, m (default 1)")
    lim.add_argument("--height", type=float, help="aperture height, m (default 1)")
    lim.add_argument("--nx", type=int, help="stops along x (default 18)")
    lim.add_argument("--ny", type=int, help="stops along y (default 12)")
    lim.add_argument("--range", type=float, help="target range, m (default 1.5; from a file: the grid's centre)")
    lim.add_argument("--temperature", type=float, help="air temperature, C (default 20)")
    lim.add_argument("--humidity", type=float, help="relative humidity, %% (default 50)")
    lim.set_defaults(func=cmd_limits)

    cmp_ = sub.add_parser("compare", help="compare two images on the same grid: correlation, peak offsets, TCR")
    cmp_.add_argument("a", help="image file (HDF5, from clsas reconstruct)")
    cmp_.add_argument("b", help="image file on the same grid")
    cmp_.add_argument("--box", help="target box x0,x1,y0,y1,z0,z1 in m: report each image's target-to-clutter "
                      "ratio (peak in the box / RMS outside it), e.g. --box=-0.05,0.05,-0.05,0.05,0,0")
    cmp_.add_argument("--clutter-box", help="x0,x1,y0,y1,z0,z1 in m: measure the clutter here (less the target box)")
    cmp_.add_argument("--peaks", type=int, default=3, help="strongest peaks to match between the images (default 3)")
    cmp_.set_defaults(func=cmd_compare)

    dv = sub.add_parser("devices", help="list OpenCL devices, audio devices and serial ports")
    dv.add_argument("--opencl-only", action="store_true", help="only the OpenCL devices")
    dv.add_argument("--variants", action="store_true",
                    help="check (or read the stored verdicts of) each kernel's vector width on the device")
    dv.add_argument("--device", default=None, help="P:D: the device for --variants (default: the one auto uses)")
    dv.add_argument("--clear-cache", action="store_true",
                    help="forget the stored kernel-variant verdicts (they are probed again on next use)")
    dv.set_defaults(func=cmd_devices)

    a = sub.add_parser("acquire", help="run a scan on a rig (or an emulated one) described by rig.toml")
    a.add_argument("config", nargs="?", help="rig configuration (TOML)")
    a.add_argument("out", nargs="?", help="dataset file to write (HDF5)")
    a.add_argument("--resume", action="store_true", help="continue the file at its first missing stop")
    a.add_argument("--simulate", nargs="?", const="all", default=None, choices=("all", "stage", "audio"),
                   help="all (the default when given alone): emulated GRBL stage and simulated microphone hearing "
                   "the [simulate] scene; stage: the emulated stage with the real sound card; audio: the real "
                   "stage (stage.port) with the simulated microphone")
    a.add_argument("--fault", help="with --simulate: inject faults, e.g. alarm@5, reset@2, error@3, drop-ok@2, "
                   "disconnect@4 "
                   "(at the N-th move)")
    a.add_argument("--sample-config", action="store_true", help="print a commented rig.toml and exit")
    a.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    a.add_argument("-v", "--verbose", action="store_true", help="log the stage dialogue and retries")
    a.set_defaults(func=cmd_acquire)
    im = sub.add_parser("import", help="import measured recordings (a WAV/CSV folder or the AirSAS layout)")
    im.add_argument("source", help="the scan's folder")
    im.add_argument("out", help="dataset file to write (HDF5)")
    im.add_argument("--format", choices=("auto", "folder", "airsas"), default="auto",
                    help="layout of SOURCE (default: auto)")
    im.add_argument("--background", metavar="FOLDER", help="the empty-scene scan, same layout and stops")
    im.add_argument("--waveform-index", type=int, help="airsas: which interleaved waveform (0-based)")
    im.set_defaults(func=cmd_import)
    ex = sub.add_parser("export", help="write an image file as VTK image data (.vti, ParaView) "
                        "or .npy with a JSON sidecar (napari)")
    ex.add_argument("image", help="image file (HDF5) written by `clsas reconstruct`")
    ex.add_argument("out", help="output file: .vti or .npy")
    ex.set_defaults(func=cmd_export)

    b = sub.add_parser("bench", help="benchmarks: kernels against their peers, scaling, error against run time")
    b.add_argument("--full", action="store_true", help="the full set (tens of minutes on a 2-core CPU)")
    b.add_argument("--out", default="bench/results", help="results folder (default: bench/results)")
    b.add_argument("--scheduler", help="address of a Dask scheduler for the sweeps and tiles (default: a local "
                   "cluster of 2 workers with --full)")
    b.add_argument("--dask", action="store_true", help="run the Dask part in the quick set too")
    b.add_argument("--no-plots", action="store_true", help="no PNG")
    b.add_argument("--formation", nargs="*", metavar="NAME", default=None,
                   help="run only the image-formation benchmark, for these registered formations (default all; bp, "
                   "the reference, always runs)")
    b.add_argument("--scale", type=float, default=None,
                   help="with --formation: size of the dense planar case (1 = 128 x 128 stops, 256 x 256 x 128 "
                   "voxels; default 1 with --full, else 0.25)")
    b.add_argument("--cases", nargs="+", choices=("demo", "dense", "circular"), default=None,
                   help="with --formation: which cases (default all)")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    b.add_argument("-v", "--verbose", action="store_true", help="log details")
    b.set_defaults(func=cmd_bench)
    for sp in sub.choices.values():  # what every command takes, before or after its name
        opts = sp._option_string_actions
        sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks")
        if "-q" not in opts:
            sp.add_argument("-q", "--quiet", action="store_true", help="no progress output")
        if "-v" not in opts:
            sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.debug = getattr(args, "debug", False)
    logging.basicConfig(level=logging.INFO if getattr(args, "verbose", False) else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "quiet", False):
        # the first run on a machine checks each kernel variant in a child process: say so
        logging.getLogger("clsas.cl.variants").setLevel(logging.INFO)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("clsas: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the CLI turns every error into one line
        if args.debug:
            raise
        print(f"clsas {args.command}: error: {exc}".splitlines()[0], file=sys.stderr)
        return 2 if isinstance(exc, ValueError | TypeError | FileNotFoundError) else 1


if __name__ == "__main__":
    sys.exit(main())
