"""A look at a dataset before imaging it: where the transducers are against the grid, a
waterfall of the recordings with the arrivals the geometry predicts, and warnings where the
geometry and the data disagree.

:func:`inspect_dataset` computes everything (no drawing); :func:`draw_inspection` draws it
(matplotlib, imported there). What is checked:

- the direct speaker-to-microphone sound: found where ``|tx - rx| / c - t0_s`` says
  (:func:`clsas.focus.direct.direct_arrivals`)? Early or late by more than an eighth of a
  period at the band's centre (or half a sample) means the delay or the spacing is off; by
  about a group delay the provenance records, that delay removed twice or not at all;
- the echoes: does the energy of the matched-filtered recordings after the direct sound fall
  inside the delays of the grid (the grid's range gate, per measurement)? Little of it there
  means the grid is not where the target is, or positions are in the wrong frame or unit;
- the recordings: clipped samples (many samples at the extreme value).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..physics.geometry import VoxelGrid
from ..types import sanity
from ..types.dataset import Dataset

__all__ = ["Inspection", "draw_inspection", "inspect_dataset"]

log = logging.getLogger(__name__)


@dataclass
class Inspection:
    """What :func:`inspect_dataset` found.

    Attributes
    ----------
    envelope_db : (n_meas, n_samples) matched-filter envelope, dB re its maximum.
    time_s : (n_samples,) time of each sample after the transmit start for measurement 0, s
        (``t0_s[0] + k / fs``).
    direct_predicted_s, direct_measured_s : (n_meas,) arrival of the direct sound after the
        transmit start (stated geometry; measured, NaN where not found), s.
    gate_s : (n_meas, 2) the grid's nearest and farthest bistatic delay per measurement, s
        (None without a grid).
    in_gate_fraction : float
        Share of the envelope's energy after the direct sound that lies in the gate (NaN
        without a grid).
    warnings : list of str
    """

    envelope_db: np.ndarray
    time_s: np.ndarray
    t0_s: np.ndarray
    direct_predicted_s: np.ndarray
    direct_measured_s: np.ndarray
    gate_s: np.ndarray | None
    in_gate_fraction: float
    tx_positions: np.ndarray
    rx_positions: np.ndarray
    grid_bounds_m: np.ndarray | None
    warnings: list = field(default_factory=list)


def _envelope(ds: Dataset) -> np.ndarray:
    """|matched filter| of each recording, aligned so that sample k is an echo at t0 + k / fs."""
    return sanity.envelope(ds, np.arange(ds.n_meas))


def _direct_check(ds: Dataset, warnings: list) -> tuple[np.ndarray, np.ndarray]:
    from ..focus.direct import direct_arrivals
    from ..preprocess import chirp_band

    pred = np.linalg.norm(ds.tx_positions - ds.rx_positions, axis=1) / ds.c_per_meas
    wave_s = len(ds.waveform) / ds.fs_hz
    found = direct_arrivals(ds, max_delay_s=max(5e-4, 3 * wave_s))
    meas = np.where(found.detected, found.arrival_s + ds.t0_s, np.nan)
    if not found.found:
        warnings.append(f"the direct sound was not found near where the geometry puts it "
                        f"({np.median(pred) * 1e6:.1f} us after the transmit start) in most recordings: "
                        "blanked already, or t0_s or the positions are far off")
        return pred, meas
    off = float(np.nanmedian(meas - pred))
    f_lo, f_hi = chirp_band(ds)
    tol = max(0.125 / (0.5 * (f_lo + f_hi)), 0.5 / ds.fs_hz)  # an eighth of a period at the centre
    stated = [float(p["group_delay_samples"]) for p in ds.provenance if "group_delay_samples" in p]
    stated += [float(p["delay_s"]) * ds.fs_hz for p in ds.provenance if p.get("step") == "group_delay"
               and "delay_s" in p]
    if abs(off) * ds.fs_hz > 10 and any(abs(abs(off) * ds.fs_hz - g) < 2 for g in stated):
        warnings.append(f"the direct sound arrives {off * 1e6:+.1f} us ({off * ds.fs_hz:+.2f} samples) from where "
                        "t0_s and the geometry put it, about the group delay the provenance records: removed "
                        "twice (or not at all)?")
    elif abs(off) > tol:
        path = off * float(np.median(ds.c_per_meas)) * 1e3
        warnings.append(f"the direct sound arrives {off * 1e6:+.1f} us ({off * ds.fs_hz:+.2f} samples) from where "
                        f"t0_s and the geometry put it: the group delay or the speaker-microphone spacing is off "
                        f"(as path: {path:+.1f} mm; an eighth of a period is {tol * 1e6:.1f} us)")
    return pred, meas


def inspect_dataset(ds: Dataset, grid: VoxelGrid | None = None, *, min_in_gate: float = 0.2) -> Inspection:
    """Check a dataset against its geometry (see the module docstring).

    Parameters
    ----------
    ds : Dataset
        As imported (before the direct sound is blanked: it is the clock's check).
    grid : VoxelGrid, optional
        The grid to be imaged: its range gate is drawn and checked against the echoes.
    min_in_gate : float
        Warn when less than this share of the echo energy after the direct sound is in the gate.

    Returns
    -------
    Inspection
    """
    if not isinstance(ds, Dataset):
        raise TypeError(f"ds must be a clsas.Dataset, got {type(ds).__name__}")
    if grid is not None and not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    warnings: list[str] = []
    env = _envelope(ds)
    env_db = 20 * np.log10(np.maximum(env / max(float(env.max()), 1e-300), 1e-6))
    pred, meas = _direct_check(ds, warnings)
    t = ds.t0_s[:, None] + np.arange(ds.n_samples)[None, :] / ds.fs_hz
    gate, frac, bounds = None, float("nan"), None
    if grid is not None:
        gate = sanity.grid_delays(ds, grid)
        frac = sanity.echo_share_in_grid(ds, grid, env=env)
        bounds = np.array([[ax[0], ax[-1]] for ax in (grid.x_m, grid.y_m, grid.z_m)])
        if np.isfinite(frac) and frac < min_in_gate:
            warnings.append(f"only {100 * frac:.0f} % of the echo energy after the direct sound falls in the grid's "
                            f"delays; {sanity.likely_cause(ds, grid)}")
    peak = np.abs(ds.signals).max(axis=1, keepdims=True)
    at_peak = (np.abs(ds.signals) >= 0.999 * peak).sum(axis=1)
    if np.mean(at_peak >= 4) > 0.1:
        warnings.append(f"{int(np.sum(at_peak >= 4))} recordings hold 4 or more samples at their extreme value: "
                        "clipped?")
    for w in warnings:
        log.warning("inspect: %s", w)
    return Inspection(env_db, t[0], ds.t0_s.copy(), pred, meas, gate, frac, ds.tx_positions.copy(),
                      ds.rx_positions.copy(), bounds, warnings)


def draw_inspection(ins: Inspection, path: str | Path, *, dynamic_range_db: float = 40.0) -> Path:
    """Draw the transducers' paths with the grid (top and side view) and the waterfall with the
    predicted arrivals over it; write the picture to ``path`` (PNG, PDF, ... by its suffix)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    fig = Figure(figsize=(15, 4.8))  # drawn through its own canvas: the caller's backend is left as it is
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1, 1, 1.6]})
    for k, (i, j, name) in enumerate(((0, 1, "top (x, y)"), (0, 2, "side (x, z)"))):
        ax[k].plot(ins.tx_positions[:, i], ins.tx_positions[:, j], ".", ms=2, label="speaker")
        ax[k].plot(ins.rx_positions[:, i], ins.rx_positions[:, j], ".", ms=2, label="microphone")
        if ins.grid_bounds_m is not None:
            (a0, a1), (b0, b1) = ins.grid_bounds_m[i], ins.grid_bounds_m[j]
            ax[k].add_patch(Rectangle((a0, b0), a1 - a0, max(b1 - b0, 1e-3), fill=False, color="k", lw=1))
        ax[k].set_aspect("equal", adjustable="datalim")
        ax[k].set_title(name)
        ax[k].set_xlabel("xyz"[i] + " (m)")
        ax[k].set_ylabel("xyz"[j] + " (m)")
    ax[0].legend(fontsize=7, loc="upper right")
    n = ins.envelope_db.shape[0]
    rel = (ins.t0_s - ins.t0_s[0]) * 1e3
    ext = (ins.time_s[0] * 1e3, ins.time_s[-1] * 1e3, n - 0.5, -0.5)
    ax[2].imshow(ins.envelope_db, aspect="auto", extent=ext, vmin=-dynamic_range_db, vmax=0, cmap="gray_r")
    rows = np.arange(n)
    ax[2].plot(ins.direct_predicted_s * 1e3 - rel, rows, "r-", lw=0.8, label="direct sound (geometry)")
    ax[2].plot(ins.direct_measured_s * 1e3 - rel, rows, "c.", ms=1.5, label="direct sound (measured)")
    if ins.gate_s is not None:
        for col, lab in ((0, "grid: nearest"), (1, "grid: farthest")):
            ax[2].plot(ins.gate_s[:, col] * 1e3 - rel, rows, "--", lw=0.8, label=lab)
    ax[2].set_xlabel("time after the transmit start (ms, measurement 0's axis)")
    ax[2].set_ylabel("measurement")
    ax[2].legend(fontsize=7, loc="lower right")
    ax[2].set_title("matched-filter envelope (dB)")
    if ins.warnings:
        fig.suptitle("\n".join(ins.warnings), fontsize=7, color="darkred")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path
