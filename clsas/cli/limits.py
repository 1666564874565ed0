"""``clsas limits``: resolution limits of a scan configuration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_LIMITS_DEFAULTS = {"f_start": 20e3, "f_stop": 30e3, "width": 1.0, "height": 1.0, "nx": 18, "ny": 12, "range": 1.5,
                    "temperature": 20.0, "humidity": 50.0}


def _limits_from_file(path: str) -> dict:
    """The limits' inputs from a scene or rig file: [chirp], [aperture], [air], and the range
    from the [grid]'s centre (else the reflectors' mean) to the aperture's plane."""
    import tomllib

    from clsas.io.config import kind_of, read_text

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
        from clsas.synthesis.scenes import parse_config

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
    if (args.f_start is not None or args.f_stop is not None) and values["f_start"] > values["f_stop"]:
        raise ValueError(f"--f-start {values['f_start']:g} Hz is above --f-stop {values['f_stop']:g} Hz: give the "
                         "chirp's band low to high (a down-chirp has the same limits as the up-chirp over its band)")
    if args.config is not None:
        print(f"from {args.config} (flags override): " + ", ".join(f"{k}={values[k]:g}" for k in _LIMITS_DEFAULTS))
    lim = clsas.resolution_limits(values["f_start"], values["f_stop"], values["width"], values["height"],
                                  values["nx"], values["ny"], values["range"], values["temperature"],
                                  values["humidity"])
    print(lim.report())
    return 0


def add_parser(sub) -> None:
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
