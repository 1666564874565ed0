"""``clsas demo``: simulate and image the paper's two scenes."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .common import add_device_options, check_grids_fit, reconstruct_image, simulate_scene


def cmd_demo(args) -> int:
    import clsas
    from clsas.synthesis.scenes import demo_configs, parse_config
    from clsas.types.pictures import mip_png

    configs = {name: parse_config(text) for name, text in demo_configs(args.spacing).items()}
    check_grids_fit([cfg.grid for cfg in configs.values()], args)  # every scene, before the first one starts
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(clsas.resolution_limits(20e3, 30e3, 1.0, 1.0, 18, 12, range_m=1.5).report())
    print()
    for name, cfg in configs.items():
        t = time.perf_counter()
        ds = simulate_scene(cfg, not args.quiet)
        t_sim = time.perf_counter() - t
        ds.save(out / f"{name}.h5", overwrite=True)  # the demo's own folder, rewritten each run
        image = reconstruct_image(ds, cfg.grid, args, not args.quiet)
        image.save(out / f"{name}-image.h5", overwrite=True)
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


def add_parser(sub) -> None:
    d = sub.add_parser("demo", help="simulate and image the paper's two scenes")
    d.add_argument("--out", default="demo-out", help="output folder (default: demo-out)")
    d.add_argument("--spacing", type=float, default=0.01, help="voxel spacing in m (default 0.01)")
    d.add_argument("--force", action="store_true", help="image even if the grid does not seem to fit in memory")
    add_device_options(d)
    d.set_defaults(func=cmd_demo)
