"""``clsas simulate``: a scan simulated from a scene TOML file."""

from __future__ import annotations

from .common import add_device_options, simulate_scene


def cmd_simulate(args) -> int:
    from clsas.synthesis.scenes import load_config

    cfg = load_config(args.scene)
    ds = simulate_scene(cfg, not args.quiet)
    ds.save(args.out, overwrite=True)  # checked against --overwrite before any work
    print(f"wrote {args.out}: {ds.n_meas} measurements x {ds.n_samples} samples at {ds.fs_hz:g} Hz")
    return 0


def add_parser(sub) -> None:
    s = sub.add_parser("simulate", help="simulate a scan from a scene TOML file")
    s.add_argument("scene", help="scene file (TOML: [chirp], [aperture], [air], [noise], [[points]], [grid])")
    s.add_argument("out", help="dataset file to write (HDF5)")
    add_device_options(s)
    s.set_defaults(func=cmd_simulate)
