"""Kernel and wall rates of every formation and of the whole ``reconstruct``, on every device.

    python -m bench --rates [N] [--devices P:D ... numpy] [--out DIR]

The scan is the one ``clsas calibrate`` times (:func:`clsas.formation.auto.calibration_case`): a
dense planar scan of N x N stops 5.6 mm apart (default N = 24: 576 measurements onto 22 x 22 x 41
voxels, 1.14e7 voxel-measurement pairs), which bp, ω-k and FFBP all image. On each device (every
OpenCL device whose kernels build, the Oclgrind simulator left out, and the NumPy twins) it times
four steps: ``bp``, ``omega-k`` and ``ffbp`` through :func:`clsas.formation.form` from the same
profiles (compressed once on that device), and ``reconstruct``, the whole
:func:`clsas.reconstruct` with ``formation="bp"`` from the recordings (compression included). Each
step runs once to build, probe and plan, then ``repeats`` times (FFBP's remembered tree forgotten
before each call, so its planning is timed); the medians are reported.

Per call:

- **wall**: the call on the host clock;
- **kernels**: every kernel the call launched, from its OpenCL profiling event (start to end), summed;
- **transfers**: every copy between host and device (``pyopencl.enqueue_copy``) from its profiling
  event, plus the uploads made at buffer creation (:meth:`clsas.cl.Plan.upload`, which have no
  event) on the host clock;
- **host**: the rest of the wall time: host steps (ω-k's FFTs and the tree's planning), checks,
  launches and waits.

The launches and copies are seen by wrapping pyopencl's ``enqueue_nd_range_kernel`` and
``enqueue_copy`` (and ``Plan.upload``) while a step runs; the library is not changed. Where a
queue has no profiling, kernels and transfers are left empty (None) and only the wall rate is given.
On the NumPy twins nothing runs on a device: "kernels" is the time the twins of the kernels take
(bp's sum, ω-k's Stolt step, FFBP's leaves, merges and grid, the compression), from the image's
``timings_s``, and transfers are zero.

Rates are voxel-measurement pairs/s for every step (grid voxels x measurements; for ω-k and FFBP
the rate of bp that would take the same time): kernel rate = pairs / kernel time, wall rate =
pairs / wall. Shares are fractions of the wall time and sum to 1.
"""

from __future__ import annotations

import datetime as dt
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["COLUMNS", "DEFAULT_SIDE", "REPEATS", "STEPS", "Tracer", "devices", "finite_shares", "markdown", "run_rates",
           "table", "write"]

DEFAULT_SIDE = 24
REPEATS = 3
STEPS = ("bp", "omega-k", "ffbp", "reconstruct")
#: the columns of the printed table, in order
COLUMNS = ("device", "step", "wall", "kernel, pairs/s", "wall, pairs/s", "host", "transfers", "kernels")
#: on the NumPy twins, the timings of the steps that are kernels on a device
TWIN_KERNEL_STEPS = {"bp": ("backproject",), "omega-k": ("stolt",), "ffbp": ("ffbp_leaves", "ffbp_merges", "ffbp_grid"),
                     "reconstruct": ("compress", "backproject")}
_SHORT = {"Portable Computing Language": "PoCL", "Intel(R) OpenCL": "Intel OpenCL"}


class Tracer:
    """While entered: the event of every kernel launch and host-device copy pyopencl enqueues, and the
    host time of every :meth:`clsas.cl.Plan.upload` (a buffer made from host data, without event)."""

    def __enter__(self) -> Tracer:
        import pyopencl as cl
        import pyopencl._cl as _cl

        from clsas.cl import Plan

        self.kernels: list = []
        self.copies: list = []
        self.upload_s = 0.0
        self._saved = (cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload)
        copy, launch, upload = self._saved

        def traced_copy(*args, **kwargs):
            evt = copy(*args, **kwargs)
            self.copies.append(evt)
            return evt

        def traced_launch(*args, **kwargs):
            evt = launch(*args, **kwargs)
            self.kernels.append(evt)
            return evt

        def timed_upload(plan, *args, **kwargs):
            t = time.perf_counter()
            buf = upload(plan, *args, **kwargs)
            self.upload_s += time.perf_counter() - t
            return buf

        cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload = traced_copy, traced_launch, timed_upload
        return self

    def __exit__(self, *exc) -> None:
        import pyopencl as cl
        import pyopencl._cl as _cl

        from clsas.cl import Plan

        cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload = self._saved

    def seconds(self) -> tuple[float | None, float | None]:
        """(kernel seconds, transfer seconds) of what was seen; (None, None) where the queue gives no
        profiling times."""
        import pyopencl as cl

        try:
            kernel = sum(_event_s(e) for e in self.kernels)
            transfer = sum(_event_s(e) for e in self.copies if e is not None) + self.upload_s
        except cl.Error as exc:  # PROFILING_INFO_NOT_AVAILABLE where the queue has no profiling
            if "PROFILING" not in str(exc).upper():
                raise
            return None, None
        return kernel, transfer


def _event_s(evt: Any) -> float:
    evt.wait()
    return (evt.profile.end - evt.profile.start) * 1e-9


def devices() -> list[dict]:
    """Every OpenCL device whose kernels build (the Oclgrind simulator left out), then the NumPy twins."""
    from clsas import cl

    rows = cl.list_devices()  # empty without OpenCL: the twins alone
    out = [{"index": r.index, "label": f"{r.index} {_SHORT.get(r.platform, r.platform)} {r.driver.split('_')[0]}",
            "device": r.device, "platform_version": r.platform_version}
           for r in rows if r.builds and "oclgrind" not in r.platform.lower()]
    return [*out, {"index": "numpy", "label": "numpy (twins)", "device": "host", "platform_version": ""}]


def _where(index: str) -> dict:
    return {"backend": "numpy"} if index == "numpy" else {"backend": "opencl", "device": index}


def _call(step: str, ds, prof, grid, where: dict):
    """One call of ``step`` (a function of no argument)."""
    import clsas
    from clsas.formation import form

    if step == "reconstruct":
        return lambda: clsas.reconstruct(ds, grid, formation="bp", **where)
    return lambda: form(prof, grid, step, **where)


def _one(fn: Callable, numpy: bool, step: str) -> dict:
    """Wall, kernel and transfer seconds of one call of ``fn``."""
    from clsas.formation.auto.calibrate import forget_tree

    forget_tree()
    with Tracer() as tr:
        t = time.perf_counter()
        image = fn()
        wall = time.perf_counter() - t
    if numpy:
        kernel, transfer = sum(image.timings_s.get(k, 0.0) for k in TWIN_KERNEL_STEPS[step]), 0.0
    else:
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


def _device_rows(dev: dict, ds, grid, steps, repeats: int, status) -> list[dict]:
    from clsas.formation.auto.calibrate import case_profiles

    where = _where(dev["index"])
    numpy = dev["index"] == "numpy"
    prof = case_profiles(ds, grid, where["backend"] if numpy else _selection(where))
    pairs = grid.size * ds.n_meas
    rows = []
    for step in steps:
        status(f"{dev['label']}: {step}")
        fn = _call(step, ds, prof, grid, where)
        fn()  # builds, probes, plans
        runs = [_one(fn, numpy, step) for _ in range(repeats)]
        rows.append({"device": dev["label"], "index": dev["index"], "step": step, **_row(runs, pairs)})
    return rows


def _selection(where: dict):
    from clsas import cl

    return cl.select(where["backend"], where["device"])


def run_rates(side: int = DEFAULT_SIDE, *, indices: list[str] | None = None, repeats: int = REPEATS,
              steps: tuple[str, ...] = STEPS, status: Callable[[str], None] = lambda s: None) -> dict:
    """Time ``steps`` on the N x N-stop scan on each device (``indices``: ``"P:D"`` or ``"numpy"``;
    default every one :func:`devices` lists). Returns the run: ``rows`` (per device and step: the
    medians ``wall_s``, ``kernel_s``, ``transfer_s``, the rates ``kernel_rate`` and ``wall_rate`` in
    pairs/s, ``shares`` of the wall time: ``host``, ``transfers``, ``kernels``) and what was run."""
    from clsas.formation.auto.calibrate import MIN_SIDE, calibration_case

    if isinstance(side, bool) or not isinstance(side, int) or side < MIN_SIDE:
        raise ValueError(f"--rates: N (stops per side) must be an integer of at least {MIN_SIDE}, got {side!r}")
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats!r}")
    unknown = sorted(set(steps) - set(STEPS))
    if unknown:
        raise ValueError(f"steps: unknown {unknown}; known: {list(STEPS)}")
    found = devices()
    if indices is not None:
        missing = sorted(set(indices) - {d["index"] for d in found})
        if missing:
            raise ValueError(f"--devices: {missing} not among the devices found: {[d['index'] for d in found]}")
        found = [d for d in found if d["index"] in indices]
    ds, grid = calibration_case(side)
    res = {"date": dt.datetime.now().isoformat(timespec="seconds"), "side": side, "measurements": ds.n_meas,
           "grid": list(grid.shape), "pairs": grid.size * ds.n_meas, "repeats": repeats,
           "load_before": list(os.getloadavg()), "devices": found, "rows": []}
    for dev in found:
        res["rows"] += _device_rows(dev, ds, grid, steps, repeats, status)
    res["load_after"] = list(os.getloadavg())
    return res


def _cells(row: dict) -> list[str]:
    from bench.stats import seconds

    s = row["shares"]
    pct = (lambda x: f"{100 * x:.0f} %") if s else (lambda x: "-")
    return [row["device"], row["step"], seconds(row["wall_s"]),
            f"{row['kernel_rate']:.3g}" if row["kernel_rate"] else "-", f"{row['wall_rate']:.3g}",
            pct(s and s["host"]), pct(s and s["transfers"]), pct(s and s["kernels"])]


def _title(res: dict) -> str:
    nx, ny, nz = res["grid"]
    return (f"rates on {res['side']} x {res['side']} stops onto {nx} x {ny} x {nz} voxels ({res['pairs']:.3g} "
            f"voxel-measurement pairs), medians of {res['repeats']} calls after a warm-up; load average "
            f"{res['load_before'][0]:.1f} -> {res['load_after'][0]:.1f}")


def table(res: dict) -> list[str]:
    """The run as aligned text: a title line, then :data:`COLUMNS` and one line per device and step."""
    body = [list(COLUMNS)] + [_cells(r) for r in res["rows"]]
    widths = [max(len(line[i]) for line in body) for i in range(len(COLUMNS))]
    return [_title(res)] + ["  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)).rstrip()
                            for line in body]


def markdown(res: dict) -> list[str]:
    """The run as a Markdown report."""
    from bench.stats import cpu_name

    md = [f"# Kernel and wall rates on {cpu_name()} ({os.cpu_count()} cores), {res['date']}", "",
          "Script: `python -m bench --rates` (`bench/rates.py`; its notes define each column). " + _title(res) + ".",
          "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    md += ["| " + " | ".join(_cells(r)) + " |" for r in res["rows"]]
    return md


def finite_shares(row: dict) -> bool:
    """Whether a row's shares are finite and sum to 1 within 2 % (kernels and transfers fit in the wall)."""
    s = row["shares"]
    return bool(s) and all(math.isfinite(x) and x >= 0 for x in s.values()) and abs(sum(s.values()) - 1) < 0.02


def write(res: dict, out_dir: Path) -> Path:
    """``<date>-rates-<cpu>.{json,md}`` in ``out_dir``; their stem."""
    from bench.report import write_run
    from bench.stats import cpu_name

    return write_run(Path(out_dir), "rates", {**res, "cpu": cpu_name(), "cores": os.cpu_count()}, markdown(res))
