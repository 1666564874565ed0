"""The model-based methods ``reconstruct(method=...)`` takes: ``"ls"``, ``"l1"``, ``"tv"``, ``"l1-tv"``
(solvers on :class:`~clsas.inverse.ImagingOperator`), ``"psf"`` (image-domain deconvolution) and
``"l1-psf"`` (L1 on the PSF-convolution model of the Gram, :mod:`clsas.inverse.gram`), each
registered in :data:`MODEL_METHODS`.

Weights from the noise level (when ``lam`` is not given)
--------------------------------------------------------
The noise of the profiles is taken as complex Gaussian with per-sample standard deviation
``sigma``: from ``noise_std`` (of the recordings) through the compression, else estimated from the
whole recordings' matched-filter profiles (every lag, not only the grid's gate) as
``median|p| / sqrt(ln 2)`` (exact for pure noise, an overestimate where echoes fill
more than half the samples: the conservative side). ``n_draws`` noise profile sets with that
``sigma`` (white recordings through the same compression) give the mean power of ``A^H noise`` per
voxel, smoothed over the grid (Gaussian, 2 voxels); ``s`` is the square root of its largest value.
The L1 weight is ``lam = s sqrt(ln(n_vox / delta))`` with ``delta = 0.05``: by the union bound,
pure noise leaves ``|A^H b| < lam`` everywhere, so the L1 solution is 0 (no reflector), in at
least 95 % of draws. TV takes ``lam_tv = tv_ratio * lam`` (default ``tv_ratio`` 0.5), L1+TV both.
Least squares stops by the discrepancy principle, at ``||A x - b|| = 1.05 sigma sqrt(n_data)``.

Transducer beams
----------------
Options ``beam`` and ``beam_floor_db`` are bp's (:func:`clsas.backproject`): the operator weights
every voxel-measurement pair by the profiles' two-way beam in both the forward projection and the
backprojection (so ``A^H`` stays the exact adjoint); default ``"limited"`` where the dataset carries
directional beams, else ``"none"`` -- the choice bp makes for the same dataset.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.beam import BEAM_MODES
from ..physics.geometry import VoxelGrid
from ..registry import Registry
from ..types.dataset import Dataset
from ..types.image import Image
from ..types.profiles import Profiles
from . import solvers
from .operator import ImagingOperator, compressed_pulse

__all__ = ["INVERSE_OPTIONS", "MODEL_METHODS", "noise_weight"]

log = logging.getLogger(__name__)

#: model-based methods by name: ``fn(dataset, profiles, grid, selection, progress, **options) -> Image``
MODEL_METHODS: Registry = Registry("model-based method", "method")

#: options ``reconstruct(..., inverse={...})`` takes, and their defaults
INVERSE_OPTIONS = {
    "lam": None, "lam_tv": None, "tv_ratio": 0.5, "noise_std": None, "max_iter": None, "tol": 1e-3,
    "warm_start": "bp", "pulse": True, "tv_iter": 30, "n_draws": 4, "delta": 0.05, "seed": 0,
    "psf_snr_db": 20.0, "max_reflectors": 8, "beam": None, "beam_floor_db": -12.0, "polish": 0,
}


def check_options(options: dict | None) -> dict:
    """The options with defaults filled in, each checked (ValueError/TypeError naming it)."""
    if options is None:
        options = {}
    if not isinstance(options, dict):
        raise TypeError(f"inverse must be a dict of options, got {type(options).__name__}")
    unknown = set(options) - set(INVERSE_OPTIONS)
    if unknown:
        raise ValueError(f"inverse: unknown option(s) {sorted(unknown)}; known: {sorted(INVERSE_OPTIONS)}")
    o = {**INVERSE_OPTIONS, **options}
    for key in ("lam", "lam_tv", "noise_std"):
        if o[key] is not None:
            o[key] = v.non_negative(f"inverse['{key}']", o[key])
    o["tv_ratio"] = v.non_negative("inverse['tv_ratio']", o["tv_ratio"])
    if o["max_iter"] is not None:
        o["max_iter"] = v.positive_int("inverse['max_iter']", o["max_iter"])
    o["tol"] = v.positive("inverse['tol']", o["tol"])
    o["warm_start"] = v.choice("inverse['warm_start']", o["warm_start"], ("bp", "zero"))
    if not isinstance(o["pulse"], bool):
        raise TypeError(f"inverse['pulse'] must be True or False, got {o['pulse']!r}")
    o["tv_iter"] = v.positive_int("inverse['tv_iter']", o["tv_iter"])
    o["n_draws"] = v.positive_int("inverse['n_draws']", o["n_draws"])
    o["delta"] = v.positive("inverse['delta']", o["delta"])
    if o["delta"] >= 1:
        raise ValueError(f"inverse['delta'] must be in (0, 1), got {o['delta']}")
    if not isinstance(o["seed"], (int, np.integer)) or isinstance(o["seed"], bool):
        raise TypeError(f"inverse['seed'] must be an int, got {o['seed']!r}")
    o["psf_snr_db"] = v.finite("inverse['psf_snr_db']", o["psf_snr_db"])
    o["max_reflectors"] = v.positive_int("inverse['max_reflectors']", o["max_reflectors"])
    if o["beam"] is not None:
        o["beam"] = v.choice("inverse['beam']", o["beam"], BEAM_MODES)
    o["beam_floor_db"] = v.finite("inverse['beam_floor_db']", o["beam_floor_db"])
    if isinstance(o["polish"], bool) or not isinstance(o["polish"], int | np.integer) or o["polish"] < 0:
        raise TypeError(f"inverse['polish'] must be an int >= 0, got {o['polish']!r}")
    return o


def operator_for(dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection,
                 pulse: bool = True, beam: str | None = None, beam_floor_db: float = -12.0) -> ImagingOperator:
    """The imaging operator of ``profiles``' geometry on ``grid`` (with the dataset's compressed pulse),
    weighting pairs by the profiles' beams as bp would (``beam`` None: ``"limited"`` for directional
    beams, else ``"none"``)."""
    h = compressed_pulse(dataset.waveform, dataset.fs_hz, profiles.dtau_s, profiles.fc_hz) if pulse else None
    return ImagingOperator(profiles, grid, pulse=h, backend=selection, beam=beam, beam_floor_db=beam_floor_db)


def noise_sigma(dataset: Dataset, profiles: Profiles, noise_std: float | None, rng,
                backend: Any = "numpy") -> tuple[float, np.ndarray]:
    """Per-sample noise std of the profiles, and one unit-variance noise profile set (module docstring)."""
    from ..compression import compress

    noise = rng.normal(size=dataset.signals.shape)
    step = max(1, int(round(profiles.dtau_s * dataset.fs_hz)))
    gate = (float(profiles.tau0_s.min()), float(profiles.tau0_s.max() + (profiles.n_lags - 1) * profiles.dtau_s))
    unit = compress(noise, dataset.waveform, dataset.fs_hz, gate_s=gate, t0_s=dataset.t0_s, fc_hz=profiles.fc_hz,
                    lag_step=step, backend=backend).data
    unit = _fit_lags(unit, profiles.n_lags)
    per_sample = float(np.sqrt(np.mean(np.abs(unit) ** 2)))
    if noise_std is not None:
        sigma = noise_std * per_sample
    else:  # the whole recording's profiles: mostly lags without echoes
        full = compress(dataset, fc_hz=profiles.fc_hz, lag_step=step, backend=backend).data
        sigma = float(np.median(np.abs(full)) / np.sqrt(np.log(2)))
    return sigma, unit / per_sample


def _fit_lags(a: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((a.shape[0], n), np.complex128)
    k = min(n, a.shape[1])
    out[:, :k] = a[:, :k]
    return out


def noise_weight(A: ImagingOperator, dataset: Dataset, profiles: Profiles, *, noise_std: float | None = None,
                 n_draws: int = 2, delta: float = 0.05, seed: int = 0) -> tuple[float, float]:
    """``(lam, sigma)``: the L1 weight that leaves pure noise without a reflector in ``1 - delta`` of
    draws, and the profiles' per-sample noise std (module docstring)."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    sigma, unit = noise_sigma(dataset, profiles, noise_std, rng, A.selection)
    power = np.zeros(A.shape[1])
    for i in range(n_draws):
        if i:
            unit = noise_sigma(dataset, profiles, 1.0, rng, A.selection)[1]
        power += np.abs(A.rmatvec(sigma * unit.ravel())) ** 2 / n_draws
    shape = A.grid.shape
    smooth = gaussian_filter(power.reshape(shape), [2.0 if n > 1 else 0.0 for n in shape], mode="nearest")
    s = float(np.sqrt(smooth.max()))
    return s * float(np.sqrt(np.log(A.shape[1] / delta))), sigma


def warm_start(A: ImagingOperator, b: np.ndarray) -> np.ndarray:
    """The backprojection ``A^H b`` scaled to fit the data best (one ``A^H``, one ``A``)."""
    x = A.rmatvec(b)
    ax = A.matvec(x)
    den = float(np.vdot(ax, ax).real)
    return x * (np.vdot(ax, b) / den) if den > 0 else x


def _solve(kind: str, dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection,
           progress: Callable[[int, int], None] | None, options: dict) -> Image:
    o = check_options(options)
    t0 = time.perf_counter()
    A = operator_for(dataset, profiles, grid, selection, o["pulse"], o["beam"], o["beam_floor_db"])
    b = A.data
    lam, sigma = o["lam"], None
    if lam is None or kind == "ls":
        lam_rule, sigma = noise_weight(A, dataset, profiles, noise_std=o["noise_std"], n_draws=o["n_draws"],
                                       delta=o["delta"], seed=o["seed"])
        lam = lam_rule if lam is None else lam
    t_weight = time.perf_counter() - t0
    x0 = warm_start(A, b) if o["warm_start"] == "bp" else None
    say = _say(kind, progress)
    if kind == "ls":
        res = solvers.cgls(A, b, x0, max_iter=o["max_iter"] or 30, tol=o["tol"],
                           residual_norm=1.05 * sigma * np.sqrt(len(b)), progress=say)
        weights = {}
    else:
        lam_l1 = lam if kind in ("l1", "l1-tv") else 0.0
        lam_tv = (o["lam_tv"] if o["lam_tv"] is not None else o["tv_ratio"] * lam) if kind in ("tv", "l1-tv") else 0.0
        res = solvers.fista(A, b, x0, lam_l1=lam_l1, lam_tv=lam_tv, shape=grid.shape, max_iter=o["max_iter"] or 50,
                            tol=o["tol"], tv_iter=o["tv_iter"], progress=say)
        weights = {"lam_l1": lam_l1, "lam_tv": lam_tv}
    log.info("%s: %d iterations (%s), %d A and %d A^H on %s", kind, res.iterations, res.stopped,
             A.n_forward, A.n_adjoint, A.backend)
    info = {"solver": "cgls" if kind == "ls" else "fista", "iterations": res.iterations, "stopped": res.stopped,
            "objective": [float(f) for f in res.objective], "n_forward": A.n_forward, "n_adjoint": A.n_adjoint,
            "noise_sigma": sigma, "tol": o["tol"], **weights}
    timings = {"weight": t_weight, "solve": time.perf_counter() - t0 - t_weight}
    sel = A.selection
    return Image(res.x.reshape(grid.shape), grid, kind, sel.kind, sel.device, timings,
                 provenance={"inverse": info})


def _say(kind: str, progress):
    def say(done: int, total: int) -> None:
        log.debug("%s: iteration %d/%d", kind, done, total)
        if progress is not None:
            progress(done, total)
    return say


for _name in ("ls", "l1", "tv", "l1-tv"):
    MODEL_METHODS.register(_name, lambda ds, prof, grid, sel, progress=None, _k=_name, **opts:
                           _solve(_k, ds, prof, grid, sel, progress, opts))


def model_reconstruct(method: str, dataset: Dataset, profiles: Profiles, grid: VoxelGrid,
                      selection: _cl.Selection, progress: Callable[[int, int], None] | None = None,
                      options: dict | None = None) -> Image:
    """Run the registered model-based ``method`` (the pipeline's entry)."""
    fn = MODEL_METHODS.choose(method)
    image = fn(dataset, profiles, grid, selection, progress=progress, **(options or {}))
    return replace(image, method=method)


