"""The request against the data, before any work: does the grid hold the echoes at all?

A grid typed in millimetres (``VoxelGrid.from_bounds((-400, 400), ..., 10)``), positions in the
wrong unit or frame, or a grid beside the target image nothing but noise, silently. Every entry
point that images a grid (``reconstruct`` with any method and formation, ``autofocus``, the
command line, ``inspect``) asks :func:`check_grid_against_data` first:

- no voxel's delay within any recording's time span: the grid cannot be imaged from these
  recordings; refused (``ValueError`` naming ``grid``) with the likely cause;
- under :data:`MIN_SHARE` of the echo energy after the direct sound with delays inside the grid's:
  a warning naming the share and the likely cause (units, frame), kept in the result.

The share is computed as ``clsas inspect`` computes it (the matched filter's envelope, on at most
:data:`MAX_RECORDINGS` recordings spread over the scan, so it costs a fraction of a compression).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..physics.geometry import VoxelGrid
from .dataset import Dataset

__all__ = ["MAX_RECORDINGS", "MIN_SHARE", "GridCheck", "band_hz", "check_grid_against_data", "echo_share_in_grid",
           "envelope", "grid_corners", "grid_delays", "likely_cause", "pulse_width_s"]

log = logging.getLogger(__name__)

MIN_SHARE = 0.2  # warn below this share of the echo energy in the grid's delays
MAX_RECORDINGS = 64  # recordings the share is computed on, spread over the scan


@dataclass(frozen=True)
class GridCheck:
    """What :func:`check_grid_against_data` found: the echo energy's share in the grid's delays
    (NaN where the recordings hold no echo energy after the direct sound), and the warnings."""

    share: float
    warnings: tuple[str, ...] = ()


def grid_corners(grid: VoxelGrid) -> np.ndarray:
    """(8, 3) the corners of the grid's box, m."""
    ends = [(ax[0], ax[-1]) for ax in (grid.x_m, grid.y_m, grid.z_m)]
    return np.array(np.meshgrid(*ends, indexing="ij"), float).reshape(3, -1).T


def grid_delays(ds: Dataset, grid: VoxelGrid, rows: np.ndarray | None = None) -> np.ndarray:
    """(n, 2) bounds of the bistatic delay from each measurement (``rows``) to the grid's box, s:
    at least the speaker's and the microphone's distances to the box, at most the farthest corner's
    (a sum of distances is convex, so its largest value over a box is at a corner). No voxel is
    formed: a grid typed in millimetres may hold 1e9 of them."""
    rows = np.arange(ds.n_meas) if rows is None else rows
    corners = grid_corners(grid)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    tx, rx, c = ds.tx_positions[rows], ds.rx_positions[rows], ds.c_per_meas[rows]

    def to_box(p):
        return np.linalg.norm(p - np.clip(p, lo, hi), axis=1)

    far = (np.linalg.norm(corners[None] - tx[:, None], axis=2) + np.linalg.norm(corners[None] - rx[:, None], axis=2))
    return np.c_[(to_box(tx) + to_box(rx)) / c, far.max(axis=1) / c]


def band_hz(ds: Dataset) -> tuple[float, float]:
    """The waveform's band: the lowest and highest frequency where its spectrum is within 10 dB
    of its peak, Hz."""
    spec = np.abs(np.fft.rfft(ds.waveform, 4 * len(ds.waveform)))
    f = np.fft.rfftfreq(4 * len(ds.waveform), 1 / ds.fs_hz)
    band = f[spec >= 10 ** (-10 / 20) * spec.max()]
    return float(band.min()), float(band.max())


def pulse_width_s(ds: Dataset) -> float:
    """The compressed pulse's width, about 1 / bandwidth (:func:`band_hz`), s."""
    lo, hi = band_hz(ds)
    return 1.0 / max(hi - lo, ds.fs_hz / len(ds.waveform))


def envelope(ds: Dataset, rows: np.ndarray) -> np.ndarray:
    """|matched filter| of the recordings ``rows``: sample k is an echo at t0 + k / fs."""
    from ..physics.signals import analytic

    n = ds.n_samples + len(ds.waveform)
    nf = 1 << int(np.ceil(np.log2(n)))
    spec = np.fft.fft(ds.signals[rows], nf, axis=1) * np.conj(np.fft.fft(analytic(ds.waveform), nf))[None, :]
    spec[:, nf // 2:] = 0
    return np.abs(np.fft.ifft(spec, axis=1))[:, : ds.n_samples] * 2


def echo_share_in_grid(ds: Dataset, grid: VoxelGrid, rows: np.ndarray | None = None,
                       env: np.ndarray | None = None) -> float:
    """The share of the echo energy after the direct sound whose delays fall inside the grid's
    (NaN where there is none), on the recordings ``rows`` (default all); ``env``: their
    :func:`envelope`, where the caller has it already.

    The direct sound and its range sidelobes (a chirp's length and a fifth after its arrival) are
    left out, except where the grid's own delays begin earlier: a target closer than half a
    chirp's length of sound still counts."""
    rows = np.arange(ds.n_meas) if rows is None else rows
    env = envelope(ds, rows) if env is None else env
    t = ds.t0_s[rows, None] + np.arange(ds.n_samples)[None, :] / ds.fs_hz
    direct = np.linalg.norm(ds.tx_positions[rows] - ds.rx_positions[rows], axis=1) / ds.c_per_meas[rows]
    gate = grid_delays(ds, grid, rows)
    pad = pulse_width_s(ds)  # an echo from a voxel spreads over the compressed pulse (a plane's gate is thin)
    after = t > np.minimum(direct + 1.2 * len(ds.waveform) / ds.fs_hz, gate[:, 0] - pad)[:, None]
    inside = (t >= gate[:, :1] - pad) & (t <= gate[:, 1:] + pad)
    energy = float((env[after] ** 2).sum())
    return float((env[after & inside] ** 2).sum() / energy) if energy > 0 else float("nan")


def likely_cause(ds: Dataset, grid: VoxelGrid) -> str:
    """The grid's and the positions' extents, and the likely cause of a grid that misses the data."""
    ext = np.array([[ax[0], ax[-1]] for ax in (grid.x_m, grid.y_m, grid.z_m)])
    span = float(np.max(np.abs(ext)))
    pos = float(np.max(np.abs(np.r_[ds.tx_positions, ds.rx_positions])))
    reach = 0.5 * float(np.max(ds.t0_s) + ds.n_samples / ds.fs_hz) * float(np.max(ds.c_per_meas))
    text = (f"the grid reaches {span:.3g} m from the origin, the transducers {pos:.3g} m, and the recordings "
            f"hear echoes out to about {reach:.3g} m")
    if span > 20 * max(reach, pos, 1e-9):
        return text + ": is the grid in millimetres? (clsas works in metres)"
    if pos > 20 * max(reach, span, 1e-9):
        return text + ": are the positions in millimetres? (clsas works in metres)"
    return text + ": is the grid where the target is, and are the positions in metres in its frame?"


def check_grid_against_data(ds: Dataset, grid: VoxelGrid, *, where: str = "reconstruct",
                            min_share: float = MIN_SHARE) -> GridCheck:
    """Check that ``grid`` can be imaged from ``ds``'s recordings, before any work.

    Raises ``ValueError`` naming ``grid`` where no voxel's delay falls within any recording's time
    span; returns the echo energy's share in the grid's delays, with a warning (logged, and for the
    caller to keep in its result) below ``min_share``.
    """
    if not isinstance(ds, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(ds).__name__}")
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    rows = np.unique(np.linspace(0, ds.n_meas - 1, min(ds.n_meas, MAX_RECORDINGS)).round().astype(int))
    gate = grid_delays(ds, grid, rows)
    start = ds.t0_s[rows]
    end = start + ds.n_samples / ds.fs_hz
    pad = pulse_width_s(ds)
    if not np.any((gate[:, 1] + pad >= start) & (gate[:, 0] - pad <= end)):
        raise ValueError(f"grid: no voxel's echo delay ({gate.min() * 1e3:.4g} to {gate.max() * 1e3:.4g} ms) "
                         f"falls within the recordings ({start.min() * 1e3:.4g} to {end.max() * 1e3:.4g} ms): "
                         f"{likely_cause(ds, grid)}")
    share = echo_share_in_grid(ds, grid, rows)
    warnings = ()
    if np.isfinite(share) and share < min_share:
        warnings = (f"{where}: only {100 * share:.0f} % of the echo energy after the direct sound falls in the "
                    f"grid's delays; {likely_cause(ds, grid)}",)
        for w in warnings:
            log.warning("%s", w)
    return GridCheck(share, warnings)
