"""What several commands share: progress bars, the grid and box options, the device options, simulating a scene
and imaging a dataset with the command's flags."""

from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def progress_bar(desc: str, total: int, enabled: bool = True):
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="stop", disable=not enabled, leave=False) as bar:
        def update(done: int, _total: int) -> None:
            if bar.total != _total:  # a formation counts its own steps (ω-k: spatial-frequency columns)
                bar.total = _total
            bar.update(done - bar.n)

        yield update


def grid_arg(text: str | None, spacing: float | None, fallback):
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


def box_arg(option: str, text: str | None):
    if text is None:
        return None
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6:
        raise ValueError(f"{option} must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}")
    return (tuple(vals[0:2]), tuple(vals[2:4]), tuple(vals[4:6]))


def simulate_scene(cfg, progress=True):
    import clsas

    with progress_bar("simulate", cfg.aperture.n_meas, progress) as cb:
        return clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=cfg.snr_db,
                              seed=cfg.seed, chirp=cfg.chirp, config=cfg.text, progress=cb)


def formation_options(items: list[str] | None) -> dict:
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


def reconstruct_image(ds, grid, args, progress=True):
    import clsas

    formation = getattr(args, "formation", "bp")
    options = formation_options(getattr(args, "formation_option", None)) or None
    with progress_bar("backproject" if formation == "bp" else formation, ds.n_meas, progress) as cb:
        return clsas.reconstruct(ds, grid, method=getattr(args, "method", "bp"),
                                 compression=getattr(args, "compression", "matched"),
                                 backend=args.backend, device=getattr(args, "device", None), progress=cb,
                                 force=getattr(args, "force", False), formation=formation,
                                 formation_options=options)


def add_device_options(sp) -> None:
    """``--backend``, ``--device``, ``-q`` and ``-v``: what every imaging command takes."""
    from clsas.cl import BACKENDS

    sp.add_argument("--backend", choices=BACKENDS, default=None,
                    help="compute backend (default: $CLSAS_BACKEND or auto)")
    sp.add_argument("--device", default=None, metavar="P:D",
                    help="OpenCL platform:device numbers from `clsas devices` (default: $PYOPENCL_CTX or the best)")
    sp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed and skipped")
