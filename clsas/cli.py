"""The ``clsas`` command: demo, simulate, reconstruct, limits, devices (acquire, bench)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

log = logging.getLogger("clsas")


@contextmanager
def _bar(desc: str, total: int, enabled: bool = True):
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="stop", disable=not enabled, leave=False) as bar:
        def update(done: int, _total: int) -> None:
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


def _reconstruct(ds, grid, args, progress=True):
    import clsas

    with _bar("backproject", ds.n_meas, progress) as cb:
        return clsas.reconstruct(ds, grid, method=getattr(args, "method", "bp"),
                                 compression=getattr(args, "compression", "matched"),
                                 backend=args.backend, progress=cb)


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
        mip_png(image, out / f"{name}.png", truth, f"{label}: {ds.n_meas} stops, 20-30 kHz, {image.device}")
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
    from clsas.plots import mip_png
    from clsas.scenes import parse_config

    ds = clsas.load(args.data)
    cfg = parse_config(ds.config) if ds.config.strip() else None
    grid = _grid_arg(args.grid, args.spacing, cfg.grid if cfg else None)
    image = _reconstruct(ds, grid, args, not args.quiet)
    out = Path(args.out or Path(args.data).with_name(Path(args.data).stem + "-image.h5"))
    image.save(out)
    if args.verbose and image.plan is not None:
        print(image.plan.describe())
    peaks = image.peaks(args.peaks, min_separation_m=0.03)
    print(f"device: {image.device}; total {image.timings_s['total']:.3f} s")
    for p in peaks:
        x, y, z = p.position_m
        print(f"peak ({x:+.3f}, {y:+.3f}, {z:.3f}) m  |v| = {p.magnitude:.4g}")
    if args.png:
        truth = cfg.scene.image_sources()[0] if cfg else None
        mip_png(image, out.with_suffix(".png"), truth, Path(args.data).name)
        print(f"wrote {out.with_suffix('.png')}")
    print(f"wrote {out}")
    return 0


def cmd_limits(args) -> int:
    import clsas

    lim = clsas.resolution_limits(args.f_start, args.f_stop, args.width, args.height, args.nx, args.ny,
                                  args.range, args.temperature, args.humidity)
    print(lim.report())
    return 0


def cmd_devices(args) -> int:
    from clsas import cl

    rows = cl.list_devices()
    if not rows:
        print("no OpenCL platform found: install pyopencl[pocl] for the PoCL CPU device; "
              "the NumPy backend works without one")
    for r in rows:
        mark = "*" if r.selected else " "
        print(f"{mark} {r.platform} | {r.device} | {r.kind} | {r.compute_units} CUs | "
              f"{r.global_mem_mib} MiB | fp64 {'yes' if r.fp64 else 'no'}")
    if rows:
        print("(* = used by backend='auto'; set PYOPENCL_CTX to choose, e.g. PYOPENCL_CTX=0:0)")
    return 0


def cmd_missing(args) -> int:
    raise NotImplementedError(f"'clsas {args.command}' is not available yet in this release")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clsas", description="In-air synthetic-aperture audio imaging")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--backend", choices=("auto", "opencl", "numpy"), default=None,
                        help="compute backend (default: $CLSAS_BACKEND or auto)")
        sp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
        sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed and skipped")

    d = sub.add_parser("demo", help="simulate and image the paper's two scenes")
    d.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    d.add_argument("--spacing", type=float, default=0.01, help="voxel spacing in m (default 0.01)")
    common(d)
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="simulate a scan from a scene TOML file")
    s.add_argument("scene")
    s.add_argument("out")
    common(s)
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reconstruct", help="image a dataset file")
    r.add_argument("data")
    r.add_argument("--grid", help="x0,x1,y0,y1,z0,z1 in m, e.g. --grid=-0.5,0.5,-0.5,0.5,1,2 "
                   "(default: the dataset's [grid])")
    r.add_argument("--spacing", type=float, help="voxel spacing in m")
    r.add_argument("--method", default="bp", choices=("bp", "bpdn", "cbp-taylor", "cbp-polar"))
    r.add_argument("--compression", default="matched", choices=("matched", "fmcw"))
    r.add_argument("--out", help="image file (default: <data>-image.h5)")
    r.add_argument("--png", action="store_true", help="also write maximum-intensity projections")
    r.add_argument("--peaks", type=int, default=3, help="peaks to print")
    common(r)
    r.set_defaults(func=cmd_reconstruct)

    lim = sub.add_parser("limits", help="resolution limits of a scan configuration")
    lim.add_argument("--f-start", type=float, default=20e3, help="Hz")
    lim.add_argument("--f-stop", type=float, default=30e3, help="Hz")
    lim.add_argument("--width", type=float, default=1.0, help="aperture width, m")
    lim.add_argument("--height", type=float, default=1.0, help="aperture height, m")
    lim.add_argument("--nx", type=int, default=18)
    lim.add_argument("--ny", type=int, default=12)
    lim.add_argument("--range", type=float, default=1.5, help="target range, m")
    lim.add_argument("--temperature", type=float, default=20.0, help="C")
    lim.add_argument("--humidity", type=float, default=50.0, help="%% RH")
    lim.set_defaults(func=cmd_limits)

    dv = sub.add_parser("devices", help="list OpenCL platforms and devices")
    dv.set_defaults(func=cmd_devices)
    for name in ("acquire", "bench"):
        m = sub.add_parser(name, help="(not available yet)")
        m.add_argument("rest", nargs="*")
        m.set_defaults(func=cmd_missing)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if getattr(args, "verbose", False) else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
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
