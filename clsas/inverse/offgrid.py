"""Off-grid reflectors (``method="offgrid"``): point reflectors' positions and complex amplitudes as
continuous variables, by a sliding Frank-Wolfe / ADCG loop (Boyd, Schiebinger and Recht 2017) seeded
by the grid solution: the paper's continuous-basis idea applied in space rather than in delay.

Model: the profile of a unit reflector at ``p`` in measurement ``m`` is the compressed pulse at the
bistatic delay, ``P(tau0_m + k dtau - tau_m(p)) exp(-j 2 pi fc tau_m(p))``, with ``P`` clsas's own
compressed pulse at the recording rate, band-limited upsampled 8 times and linearly interpolated
(no grid in the positions), times the spherical spreading ``1 / (r_tx r_rx)`` (normalised at the
grid's centre) and ISO 9613-1 air absorption over the grid centre's mean path (it tilts the
spectrum): each a 1-2 % model error if left out, more than the noise after compression. The loop:

1. seeds: the local maxima of the L1 grid image (``method="l1"``) within -10 dB of its peak;
2. fit all positions jointly (``scipy.optimize.least_squares``, Levenberg-Marquardt; amplitudes by
   linear least squares at each step: variable projection), clipped to the grid's box; an axis of
   one voxel stays where it is;
3. drop reflectors whose amplitude fell under the noise-level weight, merge ones closer than a
   tenth of the range resolution;
4. backproject the residual: if its largest value is over the noise-level weight
   (:func:`clsas.inverse.noise_weight`) and fewer than ``max_reflectors`` are found, add a reflector
   there and go to 2; else stop.

The image returned puts each reflector's amplitude on its nearest voxel; ``image.provenance
["inverse"]["reflectors"]`` and :func:`reflector_peaks` give the continuous positions as
:class:`clsas.types.image.Peak` objects (strongest first), like :meth:`clsas.Image.peaks`.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy.optimize import least_squares

from .. import cl as _cl
from ..physics.beam import pair_weights
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from ..types.image import Image, Peak
from ..types.profiles import Profiles
from .methods import MODEL_METHODS, _solve, check_options, noise_weight, operator_for
from .operator import ImagingOperator, compressed_pulse

__all__ = ["PointModel", "reflector_peaks"]

log = logging.getLogger(__name__)


class PointModel:
    """Profiles of point reflectors at continuous positions, for the geometry of ``A``."""

    def __init__(self, A: ImagingOperator, waveform: np.ndarray, fs_hz: float, up: int = 8,
                 temperature_c: float = 20.0, humidity_pct: float = 50.0):
        self.A = A
        centre = np.array([np.mean(a) for a in (A.grid.x_m, A.grid.y_m, A.grid.z_m)])
        r_tx, r_rx = np.linalg.norm(centre - A.tx, axis=1), np.linalg.norm(centre - A.rx, axis=1)
        self.r0 = float(np.mean(r_tx * r_rx))
        echo = _absorbed(waveform, fs_hz, float(np.mean(r_tx + r_rx)), temperature_c, humidity_pct)
        base = compressed_pulse(waveform, fs_hz, 1.0 / fs_hz, A.fc, echo=echo)
        n = len(base)
        spec = np.fft.fft(base)
        padded = np.zeros(n * up, np.complex128)
        half = n // 2
        padded[: half + 1], padded[-(n - half - 1):] = spec[: half + 1], spec[half + 1:]
        self.fine = np.fft.ifft(padded) * up  # sample i at (i / up - half) / fs_hz from the echo
        self.dt = 1.0 / (fs_hz * up)
        self.offset = half * up  # index of zero delay
        self.lags = np.arange(A.n_lags) * A.dtau

    def columns(self, positions: np.ndarray) -> np.ndarray:
        """(n_meas * n_lags, K) profiles of unit reflectors at ``positions`` (K, 3), m."""
        A = self.A
        pos = np.atleast_2d(positions)
        r_tx = np.linalg.norm(pos[:, None] - A.tx[None], axis=2)  # (K, n_meas)
        r_rx = np.linalg.norm(pos[:, None] - A.rx[None], axis=2)
        path = r_tx + r_rx
        tau = path / np.broadcast_to(A.c, (A.n_meas,))[None]
        u = (A.tau0[None, :, None] + self.lags[None, None] - tau[..., None]) / self.dt + self.offset
        i0 = np.floor(u).astype(np.int64)
        w = u - i0
        ok = (i0 >= 0) & (i0 < len(self.fine) - 1)
        i0c = np.clip(i0, 0, len(self.fine) - 2)
        val = np.where(ok, (1 - w) * self.fine[i0c] + w * self.fine[i0c + 1], 0)
        spread = self.r0 / np.maximum(r_tx * r_rx, 1e-6)  # spherical spreading, 1 at the grid's centre
        if A.weights is not None:  # the operator's beam weights, the same pair by pair
            bw = A.weights
            spread = spread * np.stack([pair_weights(bw.luts, A.tx[m], A.rx[m], bw.tx_dir[m], bw.rx_dir[m], pos,
                                                     bw.gate) for m in range(A.n_meas)], axis=1)
        val = val * (spread * np.exp(-2j * np.pi * A.fc * tau))[..., None]
        return val.reshape(len(pos), -1).T


def _absorbed(waveform: np.ndarray, fs_hz: float, path_m: float, temperature_c: float,
              humidity_pct: float) -> np.ndarray:
    """The waveform after ISO 9613-1 air absorption over ``path_m`` (its shape changes: higher
    frequencies lose more)."""
    from ..physics.sound import air_absorption_db_per_m

    n = len(waveform)
    f = np.fft.rfftfreq(2 * n, 1 / fs_hz)
    beta = air_absorption_db_per_m(np.maximum(f, 1.0), temperature_c, humidity_pct) * np.log(10) / 20
    return np.fft.irfft(np.fft.rfft(waveform, 2 * n) * np.exp(-beta * path_m), 2 * n)[:n]


def _fit(model: PointModel, b: np.ndarray, positions: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Joint least-squares fit of the positions (amplitudes projected out; Levenberg-Marquardt over
    the axes the grid spans, the result clipped to its box)."""
    K = len(positions)
    free = hi - lo > 1e-12
    start = np.clip(positions, lo, hi)

    def place(flat):
        pos = start.copy()
        pos[:, free] = flat.reshape(K, -1)
        return pos

    def residual(flat):
        M = model.columns(place(flat))
        alpha = np.linalg.lstsq(M, b, rcond=None)[0]
        r = b - M @ alpha
        return np.concatenate([r.real, r.imag])

    sol = least_squares(residual, start[:, free].ravel(), x_scale=1e-3, diff_step=1e-6,
                        max_nfev=10 * (free.sum() * K + 1), method="lm")
    pos = np.clip(place(sol.x), lo, hi)
    M = model.columns(pos)
    alpha = np.linalg.lstsq(M, b, rcond=None)[0]
    return pos, alpha, b - M @ alpha


def refine(A: ImagingOperator, model: PointModel, b: np.ndarray, seeds: np.ndarray, lam: float, *,
           max_reflectors: int = 8, merge_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, int]:
    """The ADCG loop (module docstring). Returns positions (K, 3), amplitudes (K,), rounds."""
    g = A.grid
    lo = np.array([g.x_m.min(), g.y_m.min(), g.z_m.min()])
    hi = np.array([g.x_m.max(), g.y_m.max(), g.z_m.max()])
    pos = np.asarray(seeds, float).reshape(-1, 3)[:max_reflectors]
    alpha = np.zeros(0, complex)
    points = g.points()
    rounds = 0
    for _ in range(max_reflectors + 1):
        rounds += 1
        if len(pos):
            pos, alpha, r = _fit(model, b, pos, lo, hi)
            col = np.linalg.norm(model.columns(pos), axis=0)
            keep = np.abs(alpha) * col ** 2 >= lam  # as strong as the L1 weight lets a voxel be
            pos, alpha = pos[keep], alpha[keep]
            pos, alpha = _merge(pos, alpha, merge_m)
            r = b - model.columns(pos) @ alpha if len(pos) else b
        else:
            r = b
        corr = np.abs(A.rmatvec(r))
        if corr.max() <= lam or len(pos) >= max_reflectors:
            break
        pos = np.vstack([pos, points[np.argmax(corr)]])
    return pos, alpha, rounds


def _merge(pos: np.ndarray, alpha: np.ndarray, merge_m: float):
    if len(pos) < 2 or merge_m <= 0:
        return pos, alpha
    order = np.argsort(-np.abs(alpha))
    kept: list[int] = []
    for i in order:
        if all(np.linalg.norm(pos[i] - pos[j]) >= merge_m for j in kept):
            kept.append(i)
    return pos[kept], alpha[kept]


def reflector_peaks(image: Image) -> list[Peak]:
    """The off-grid reflectors of an ``method="offgrid"`` image as Peaks (strongest first)."""
    refl = image.provenance.get("inverse", {}).get("reflectors")
    if refl is None:
        raise ValueError("image has no off-grid reflectors (make it with method='offgrid')")
    out = []
    for r in refl:
        p = np.asarray(r["position_m"], float)
        out.append(Peak(p, _nearest(image.grid, p), float(r["magnitude"])))
    return out


def _nearest(grid: VoxelGrid, p: np.ndarray) -> tuple[int, int, int]:
    return tuple(int(np.argmin(np.abs(ax - c))) for ax, c in zip((grid.x_m, grid.y_m, grid.z_m), p, strict=True))


@MODEL_METHODS.register("offgrid")
def offgrid(dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection, progress=None,
            **options) -> Image:
    """``method="offgrid"``: the L1 grid image, then the ADCG refinement (module docstring)."""
    o = check_options(options)
    t0 = time.perf_counter()
    seed_image = _solve("l1", dataset, profiles, grid, selection, progress, options)
    A = operator_for(dataset, profiles, grid, selection, o["pulse"], o["beam"], o["beam_floor_db"])
    lam = o["lam"]
    if lam is None:
        lam = noise_weight(A, dataset, profiles, noise_std=o["noise_std"], n_draws=o["n_draws"], delta=o["delta"],
                           seed=o["seed"])[0]
    max_reflectors = o["max_reflectors"]
    peaks = seed_image.peaks(max_reflectors)
    top = peaks[0].magnitude if peaks else 0.0
    seeds = [p.position_m for p in peaks if p.magnitude > 0 and p.magnitude >= 0.3 * top]
    model = PointModel(A, dataset.waveform, dataset.fs_hz, temperature_c=float(np.mean(dataset.temperature_c)),
                       humidity_pct=float(np.mean(dataset.humidity_pct)))
    c = float(np.mean(A.c))
    merge = 0.1 * c * profiles.dtau_s  # a tenth of a lag of path
    pos, alpha, rounds = refine(A, model, A.data, np.array(seeds).reshape(-1, 3), lam,
                                max_reflectors=max_reflectors, merge_m=merge)
    order = np.argsort(-np.abs(alpha))
    pos, alpha = pos[order], alpha[order]
    values = np.zeros(grid.shape, np.complex128)
    for p, a in zip(pos, alpha, strict=True):
        values[_nearest(grid, p)] += a
    info = {**seed_image.provenance["inverse"], "solver": "l1 + adcg", "rounds": rounds,
            "reflectors": [{"position_m": p.tolist(), "amplitude": [a.real, a.imag], "magnitude": abs(a)}
                           for p, a in zip(pos, alpha, strict=True)]}
    sel = A.selection
    return Image(values, grid, "offgrid", sel.kind, sel.device, {"solve": time.perf_counter() - t0},
                 provenance={"inverse": info})
