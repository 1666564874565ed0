"""Kernel and wall rates of every formation and of the whole ``reconstruct``, on every device.

What ``clsas bench`` runs and prints. The scan is the one ``clsas calibrate`` times
(:func:`clsas.formation.auto.calibrate.calibration_case`): a dense planar scan of N x N stops
5.6 mm apart (default N = 24: 576 measurements onto 22 x 22 x 41 voxels, 1.14e7
voxel-measurement pairs), which bp, ω-k and FFBP all image. On each device (every OpenCL device
whose kernels build, the Oclgrind simulator left out, and the NumPy twins) it times four steps:
``bp``, ``omega-k`` and ``ffbp`` through :func:`clsas.formation.form` from the same profiles
(compressed once on that device), and ``reconstruct``, the whole :func:`clsas.reconstruct` with
``formation="bp"`` from the recordings (compression included). Each step runs once to build,
probe and plan, then ``repeats`` times (FFBP's remembered tree forgotten before each call, so its
planning is timed); the medians are reported.

Per call:

- **wall**: the call on the host clock;
- **kernels**: every kernel the call launched, from its OpenCL profiling event (start to end), summed;
- **transfers**: every copy between host and device from its profiling event, plus the uploads
  made at buffer creation (:meth:`clsas.cl.Plan.upload`, which have no event) on the host clock;
- **host**: the rest of the wall time: host steps (ω-k's FFTs and the tree's planning), checks,
  launches and waits.

The launches and copies are seen by :class:`clsas.cl.Tracer` while a step runs. Where a queue has
no profiling, kernels and transfers are left empty (None) and only the wall rate is given. On the
NumPy twins nothing runs on a device: "kernels" is the time the twins of the kernels take (bp's
sum, ω-k's Stolt step, FFBP's leaves, merges and grid, the compression), from the image's
``timings_s``, and transfers are zero.

Rates are voxel-measurement pairs/s for every step (grid voxels x measurements; for ω-k and FFBP
the rate of bp that would take the same time): kernel rate = pairs / kernel time, wall rate =
pairs / wall. Shares are fractions of the wall time and sum to 1.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import platform
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["COLUMNS", "DEFAULT_SIZE", "REPEATS", "STEPS", "cpu_name", "devices", "finite_shares", "markdown",
           "measure_rates", "table", "write"]

DEFAULT_SIZE = 24
REPEATS = 3
STEPS = ("bp", "omega-k", "ffbp", "reconstruct")
#: the columns of the printed table, in order
COLUMNS = ("device", "step", "wall", "kernel, pairs/s", "wall, pairs/s", "host", "transfers", "kernels")
#: on the NumPy twins, the timings of the steps that are kernels on a device
TWIN_KERNEL_STEPS = {"bp": ("backproject",), "omega-k": ("stolt",), "ffbp": ("ffbp_leaves", "ffbp_merges", "ffbp_grid"),
                     "reconstruct": ("compress", "backproject")}
_SHORT = {"Portable Computing Language": "PoCL", "Intel(R) OpenCL": "Intel OpenCL"}


def devices() -> list[dict]:
    """Every OpenCL device whose kernels build (the Oclgrind simulator left out), then the NumPy
    twins; each as ``index`` (``"P:D"`` or ``"numpy"``), ``label``, ``device`` and
    ``platform_version``."""
    from ..cl import list_devices

    rows = list_devices()  # empty without OpenCL: the twins alone
    out = [{"index": r.index, "label": f"{r.index} {_SHORT.get(r.platform, r.platform)} {r.driver.split('_')[0]}",
            "device": r.device, "platform_version": r.platform_version}
           for r in rows if r.builds and "oclgrind" not in r.platform.lower()]
    return [*out, {"index": "numpy", "label": "numpy (twins)", "device": "host", "platform_version": ""}]


def _where(index: str) -> dict:
    return {"backend": "numpy"} if index == "numpy" else {"backend": "opencl", "device": index}


def _call(step: str, ds, prof, grid, where: dict) -> Callable[[], Any]:
    """One call of ``step`` (a function of no argument)."""
    from ..formation import form
    from ..pipeline.reconstruction import reconstruct

    if step == "reconstruct":
        return lambda: reconstruct(ds, grid, formation="bp", **where)
    return lambda: form(prof, grid, step, **where)


def _one(fn: Callable[[], Any], numpy: bool, step: str) -> dict:
    """Wall, kernel and transfer seconds of one call of ``fn``."""
    from ..cl import Tracer
    from ..formation.auto.calibrate import forget_tree

    forget_tree()
    if numpy:
        t = time.perf_counter()
        image = fn()
        wall = time.perf_counter() - t
        kernel = sum(image.timings_s.get(k, 0.0) for k in TWIN_KERNEL_STEPS[step])
        return {"wall_s": wall, "kernel_s": kernel, "transfer_s": 0.0}
    with Tracer() as tr:
        t = time.perf_counter()
        fn()
        wall = time.perf_counter() - t
    kernel, transfer = tr.seconds()
    return {"wall_s": wall, "kernel_s": kernel, "transfer_s": transfer}


def _row(runs: list[dict], pairs: int) -> dict:
    """The medians of ``runs``, the rates and the shares of the wall time."""
    wall = float(np.median([r["wall_s"] for r in runs]))
    row: dict = {"wall_s": wall, "wall_rate": pairs / wall, "runs": runs}
    if any(r["kernel_s"] is None for r in runs):
        return {**row, "kernel_s": None, "transfer_s": None, "kernel_rate": None, "shares": None}
    kernel = float(np.median([r["kernel_s"] for r in runs]))
    transfer = float(np.median([r["transfer_s"] for r in runs]))
    k, t = kernel / wall, transfer / wall
    return {**row, "kernel_s": kernel, "transfer_s": transfer, "kernel_rate": pairs / kernel if kernel > 0 else None,
            "shares": {"host": max(0.0, 1.0 - k - t), "transfers": t, "kernels": k}}


def _device_rows(dev: dict, ds, grid, steps: tuple[str, ...], repeats: int,
                 status: Callable[[str], None]) -> list[dict]:
    """The rows of one device: each step built once, then timed ``repeats`` times."""
    from ..cl import select
    from ..formation.auto.calibrate import case_profiles

    where = _where(dev["index"])
    numpy = dev["index"] == "numpy"
    status(f"{dev['label']}: compress (the formations' profiles)")
    prof = case_profiles(ds, grid, "numpy" if numpy else select(where["backend"], where["device"]))
    pairs = grid.size * ds.n_meas
    rows = []
    for i, step in enumerate(steps, 1):
        status(f"{dev['label']}: step {i} of {len(steps)}: {step}")
        fn = _call(step, ds, prof, grid, where)
        fn()  # builds, probes, plans
        runs = [_one(fn, numpy, step) for _ in range(repeats)]
        rows.append({"device": dev["label"], "index": dev["index"], "step": step, **_row(runs, pairs)})
    return rows


def _check_request(size: Any, repeats: Any, steps: Any) -> None:
    from ..formation.auto.calibrate import MIN_SIDE

    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < MIN_SIDE:
        raise ValueError(f"size: stops per side must be an integer of at least {MIN_SIDE}, got {size!r}")
    if isinstance(repeats, bool) or not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise ValueError(f"repeats: must be an integer of at least 1, got {repeats!r}")
    if isinstance(steps, str) or not steps:
        raise ValueError(f"steps: must be a non-empty sequence of names out of {list(STEPS)}, got {steps!r}")
    unknown = sorted(set(steps) - set(STEPS))
    if unknown:
        raise ValueError(f"steps: unknown {unknown}; known: {list(STEPS)}")


def _chosen(indices: Any) -> list[dict]:
    """The devices of :func:`devices` that ``indices`` names (all where None)."""
    found = devices()
    if indices is None:
        return found
    if isinstance(indices, str) or not all(isinstance(i, str) for i in indices) or not indices:
        raise ValueError(f"devices: must be a non-empty list of 'P:D' numbers or 'numpy', got {indices!r}")
    missing = sorted(set(indices) - {d["index"] for d in found})
    if missing:
        raise ValueError(f"devices: {missing} not among the devices found: {[d['index'] for d in found]}")
    return [d for d in found if d["index"] in indices]


def measure_rates(size: int = DEFAULT_SIZE, *, devices: list[str] | None = None, repeats: int = REPEATS,
                  steps: tuple[str, ...] = STEPS, status: Callable[[str], None] | None = None) -> dict:
    """Time ``steps`` on the ``size`` x ``size``-stop scan on each device.

    Parameters
    ----------
    size : int
        Stops per side of the scan (at least 8).
    devices : list of str, optional
        ``"P:D"`` numbers (as ``clsas devices`` lists them) or ``"numpy"``; default every device
        :func:`devices` lists.
    repeats : int
        Timed calls per step, after one untimed call.
    steps : tuple of str
        Out of :data:`STEPS`.
    status : callable, optional
        Called with a progress line naming the device and the step before each one.

    Returns
    -------
    dict
        ``rows`` (per device and step: the medians ``wall_s``, ``kernel_s``, ``transfer_s``, the
        rates ``kernel_rate`` and ``wall_rate`` in pairs/s, ``shares`` of the wall time: ``host``,
        ``transfers``, ``kernels``; ``runs``, every call's seconds) and what was run: ``side``,
        ``measurements``, ``grid``, ``pairs``, ``repeats``, ``devices``, the load average before and
        after.
    """
    from ..formation.auto.calibrate import calibration_case

    _check_request(size, repeats, steps)
    found = _chosen(devices)
    status = status or (lambda line: None)
    ds, grid = calibration_case(int(size))
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "side": int(size), "measurements": ds.n_meas,
           "grid": list(grid.shape), "pairs": grid.size * ds.n_meas, "repeats": int(repeats),
           "load_before": list(os.getloadavg()), "devices": found, "rows": []}
    for dev in found:
        res["rows"] += _device_rows(dev, ds, grid, tuple(steps), int(repeats), status)
    res["load_after"] = list(os.getloadavg())
    return res


def _seconds(t: float) -> str:
    """A run time: milliseconds under 0.1 s, else seconds."""
    return f"{t * 1e3:.3g} ms" if t < 0.1 else f"{t:.2f} s"


def _cells(row: dict) -> list[str]:
    s = row["shares"]
    pct = (lambda x: f"{100 * x:.0f} %") if s else (lambda x: "-")
    return [row["device"], row["step"], _seconds(row["wall_s"]),
            f"{row['kernel_rate']:.3g}" if row["kernel_rate"] else "-", f"{row['wall_rate']:.3g}",
            pct(s and s["host"]), pct(s and s["transfers"]), pct(s and s["kernels"])]


def _title(res: dict) -> str:
    nx, ny, nz = res["grid"]
    return (f"rates on {res['side']} x {res['side']} stops onto {nx} x {ny} x {nz} voxels ({res['pairs']:.3g} "
            f"voxel-measurement pairs), medians of {res['repeats']} calls after a warm-up; load average "
            f"{res['load_before'][0]:.1f} -> {res['load_after'][0]:.1f}")


def table(res: dict) -> list[str]:
    """The run of :func:`measure_rates` as aligned text: a title line, then :data:`COLUMNS` and one
    line per device and step."""
    body = [list(COLUMNS)] + [_cells(r) for r in res["rows"]]
    widths = [max(len(line[i]) for line in body) for i in range(len(COLUMNS))]
    return [_title(res)] + ["  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)).rstrip()
                            for line in body]


def cpu_name() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo), else what the platform module says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def markdown(res: dict) -> list[str]:
    """The run of :func:`measure_rates` as a Markdown report."""
    md = [f"# Kernel and wall rates on {cpu_name()} ({os.cpu_count()} cores), {res['date']}", "",
          "Command: `clsas bench` (`clsas/presenting/rates.py`; its notes define each column). " + _title(res) + ".",
          "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    md += ["| " + " | ".join(_cells(r)) + " |" for r in res["rows"]]
    return md


def finite_shares(row: dict) -> bool:
    """Whether a row's shares are finite and sum to 1 within 2 % (kernels and transfers fit in the wall)."""
    s = row["shares"]
    return bool(s) and all(math.isfinite(x) and x >= 0 for x in s.values()) and abs(sum(s.values()) - 1) < 0.02


def write(res: dict, out_dir: str | Path) -> Path:
    """Write ``<date>-rates-<cpu>.json`` (the run, with the CPU and its cores) and ``.md`` (:func:`markdown`)
    in ``out_dir`` (made where missing); returns their common stem."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"out_dir: {out_dir} exists and is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    cpu = cpu_name()
    stem = out_dir / f"{dt.date.today()}-rates-{re.sub(r'[^A-Za-z0-9]+', '-', cpu).strip('-')[:40]}"
    stem.with_suffix(".json").write_text(json.dumps({**res, "cpu": cpu, "cores": os.cpu_count()}, indent=1,
                                                    default=str))
    stem.with_suffix(".md").write_text("\n".join(markdown(res)) + "\n")
    return stem
