"""L1 reconstruction on the image-domain Gram model (``method="l1-psf"``): the cheap path to ``"l1"``.

For a scan over a small scene the Gram operator ``A^H A`` is close to a convolution with clsas's
point-spread function ``g = A^H A e_c`` (:func:`clsas.inverse.psf.point_spread`, here not
normalised, so it keeps the Gram's scale). The objective of ``"l1"``,

    0.5 ||A x - b||^2 + lam ||x||_1  =  0.5 x^H (A^H A) x - Re(x^H A^H b) + lam ||x||_1 + const,

then becomes, with ``A^H A`` replaced by the convolution ``G x = g * x`` and ``A^H b`` the
backprojection ``y``,

    F(x) = 0.5 Re(x^H G x) - Re(x^H y) + lam ||x||_1,

which monotone FISTA minimises with each iteration two FFTs on the grid (zero-padded to twice its
size or more, a fast FFT length, against wrap-around) instead of a projection and a backprojection.
``G``'s transfer function is that of ``g`` made Hermitian (``(g(r) + conj(g(-r))) / 2``, so its FFT
is real) and clipped at 0 (so ``G`` is positive semi-definite and ``F`` convex); the step size is
``1 / max H`` (no power iteration). The weight is the noise-level rule of
:mod:`clsas.inverse.methods` with one noise draw (one backprojection of noise); since ``F``'s
gradient at 0 is ``-y``, ``x = 0`` exactly when ``|y| <= lam`` everywhere, as for ``"l1"``. Option
``polish`` (default 0) then runs that many iterations of ``"l1"``'s FISTA with the real operator
from the Gram solution (step size ``1 / max H`` again: the monotone variant rejects a step that
would raise the objective).

Cost: one backprojection (``y``), one backprojection of a point echo (the PSF; the echo itself is
projected from a one-voxel grid, nearly free), one compression and backprojection of noise, and one
projection and backprojection per polishing iteration. Limit: the model holds where the PSF barely
changes over the grid (a turntable scan around a small scene, as AirSAS); on a short line aperture
near the scene it does not, and the solution can fit the data worse than the backprojection (the
tests show both). The inner products are elementwise, not BLAS: with the OpenCL CPU device's threads
busy, BLAS's own threads made them about 100 times slower in measurement.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy import fft
from scipy.fft import next_fast_len

from .. import cl as _cl
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from ..types.image import Image
from ..types.profiles import Profiles
from . import solvers
from .methods import MODEL_METHODS, _say, check_options, noise_weight, operator_for

__all__ = ["GramModel", "fista_gram", "gram_psf"]

log = logging.getLogger(__name__)


class GramModel:
    """The convolution ``x -> g * x`` on a grid of ``shape``, by FFT on a zero-padded grid.

    Parameters
    ----------
    psf : complex array of ``shape``
        The Gram's column at the centre voxel ``(n // 2, ...)`` (its scale kept).
    """

    def __init__(self, psf: np.ndarray) -> None:
        psf = np.asarray(psf, np.complex128)
        if psf.ndim != 3 or not np.all(np.isfinite(psf)):
            raise ValueError(f"psf must be a finite 3-D array, got shape {psf.shape}")
        self.shape = psf.shape
        self.pad = tuple(next_fast_len(2 * n) if n > 1 else 1 for n in psf.shape)
        kernel = np.zeros(self.pad, np.complex128)
        kernel[tuple(slice(0, n) for n in psf.shape)] = psf
        kernel = np.roll(kernel, [-(n // 2) for n in psf.shape], axis=(0, 1, 2))
        mirrored = np.conj(np.roll(np.flip(kernel, axis=(0, 1, 2)), 1, axis=(0, 1, 2)))
        H = np.maximum(fft.fftn(0.5 * (kernel + mirrored)).real, 0.0)
        self.lipschitz = float(H.max())
        self._axes = tuple(a for a, n in enumerate(psf.shape) if n > 1) or (0,)
        self._fshape = tuple(self.pad[a] for a in self._axes)
        self._H = H.reshape(self._fshape).astype(np.float32)  # single precision: the model is approximate anyway

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``g * x`` for a grid-shaped complex ``x`` (the Gram model, positive semi-definite)."""
        sq = np.asarray(x, np.complex64).reshape([self.shape[a] for a in self._axes])
        X = fft.fftn(sq, self._fshape)
        X *= self._H
        out = fft.ifftn(X, overwrite_x=True)[tuple(slice(0, self.shape[a]) for a in self._axes)]
        return out.astype(np.complex128).reshape(self.shape)


def fista_gram(G: GramModel, y: np.ndarray, lam: float, x0: np.ndarray | None = None, *, max_iter: int = 200,
               tol: float = 1e-4, progress=None) -> solvers.SolveResult:
    """Monotone FISTA for ``0.5 Re(x^H G x) - Re(x^H y) + lam ||x||_1`` (module docstring).

    Parameters
    ----------
    G : GramModel
    y : complex array of ``G.shape``: the backprojection ``A^H b``.
    lam : float
        L1 weight (>= 0), units of ``y``.
    x0 : complex array of ``G.shape``, optional (default 0).
    max_iter : int
        At most this many iterations (two FFTs each).
    tol : float
        Stop when the step ``||z - y_k||`` falls to ``tol ||x||``.
    progress : callable(done, total), optional

    Returns
    -------
    SolveResult (``x`` flattened; ``n_forward``/``n_adjoint`` 0: no projection is run).
    """
    y = np.asarray(y, np.complex128)
    if y.shape != G.shape:
        raise ValueError(f"y must have the Gram model's shape {G.shape}, got {y.shape}")
    x = np.zeros(G.shape, np.complex128) if x0 is None else np.asarray(x0, np.complex128).reshape(G.shape)
    if lam < 0 or not np.isfinite(lam):
        raise ValueError(f"lam must be finite and >= 0, got {lam}")
    L = 1.0001 * G.lipschitz
    if L <= 0:
        return solvers.SolveResult(x.ravel(), 0, [], "zero")

    def objective(xx, gxx):
        return 0.5 * _dot(xx, gxx) - _dot(xx, y) + lam * float(np.abs(xx).sum())

    gx = G.apply(x)
    f = objective(x, gx)
    hist, stopped, it = [f], "max_iter", 0
    v, gv, t = x.copy(), gx.copy(), 1.0
    for it in range(1, max_iter + 1):
        w = v - (gv - y) / L
        mag = np.abs(w)
        z = w * (np.maximum(mag - lam / L, 0.0) / np.where(mag > 0, mag, 1.0))
        gz = G.apply(z)
        fz = objective(z, gz)
        x_old, gx_old = x, gx
        if fz <= f:
            x, gx, f = z, gz, fz
        t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
        c1, c2 = t / t_new, (t - 1) / t_new
        step = np.sqrt(_dot(z - v, z - v))
        v = x + c1 * (z - x) + c2 * (x - x_old)
        gv = gx + c1 * (gz - gx) + c2 * (gx - gx_old)
        t = t_new
        hist.append(f)
        if progress is not None:
            progress(it, max_iter)
        nx = np.sqrt(max(_dot(x, x), _dot(z, z)))
        if nx == 0:
            stopped = "zero"
            break
        if it > 1 and step <= tol * nx:
            stopped = "tolerance"
            break
    return solvers.SolveResult(x.ravel(), it, hist, stopped)


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``Re(a^H b)`` of two complex arrays (elementwise, not BLAS: BLAS's threads contend with the
    OpenCL CPU device's and made this 100x slower in measurement)."""
    a, b = np.ascontiguousarray(a).view(np.float64), np.ascontiguousarray(b).view(np.float64)
    return float(np.multiply(a, b).sum())


def _point_echo(dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection,
                pulse: bool, beam: str | None = None, beam_floor_db: float = -12.0) -> np.ndarray:
    """``A e_c``: the profiles of a unit point at the grid's centre voxel, projected through a
    one-voxel operator (the same projector, a tiny fraction of a full projection's cost)."""
    c = [n // 2 for n in grid.shape]
    one = VoxelGrid(grid.x_m[c[0]: c[0] + 1], grid.y_m[c[1]: c[1] + 1], grid.z_m[c[2]: c[2] + 1])
    return operator_for(dataset, profiles, one, selection, pulse, beam, beam_floor_db).matvec(np.ones(1, np.complex128))


@MODEL_METHODS.register("l1-psf")
def gram_psf(dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection,
             progress=None, **options) -> Image:
    """``method="l1-psf"``: L1 on the PSF-convolution model of the Gram, then ``polish`` exact
    iterations (default 0; module docstring). Options: ``lam``, ``noise_std``, ``max_iter`` (Gram
    iterations, default 300), ``tol`` (default 1e-3, as ``"l1"``'s), ``polish``, ``seed``."""
    o = check_options(options)
    t0 = time.perf_counter()
    A = operator_for(dataset, profiles, grid, selection, o["pulse"], o["beam"], o["beam_floor_db"])
    b = A.data
    bp = A.rmatvec(b).reshape(grid.shape)
    G = GramModel(A.rmatvec(_point_echo(dataset, profiles, grid, selection, o["pulse"], o["beam"],
                                                  o["beam_floor_db"])).reshape(grid.shape))
    lam, sigma = o["lam"], None
    if lam is None:
        lam, sigma = noise_weight(A, dataset, profiles, noise_std=o["noise_std"], n_draws=1,
                                  delta=o["delta"], seed=o["seed"])
    t_setup = time.perf_counter() - t0
    den = _dot(bp, G.apply(bp))
    x0 = bp * (_dot(bp, bp) / den) if den > 0 and o["warm_start"] == "bp" else None
    res = fista_gram(G, bp, lam, x0, max_iter=o["max_iter"] or 300, tol=o["tol"], progress=_say("l1-psf", progress))
    t_gram = time.perf_counter() - t0 - t_setup
    x, polish = res.x, None
    if o["polish"] and np.any(x):
        polish = solvers.fista(A, b, x, lam_l1=lam, lipschitz=G.lipschitz, max_iter=o["polish"], tol=o["tol"])
        x = polish.x
    log.info("l1-psf: %d Gram iterations (%s), %d polishing, %d A and %d A^H on %s", res.iterations,
             res.stopped, polish.iterations if polish else 0, A.n_forward, A.n_adjoint, A.backend)
    info = {"solver": "fista-gram", "iterations": res.iterations, "stopped": res.stopped,
            "objective_gram": [float(f) for f in res.objective],
            "polish_iterations": polish.iterations if polish else 0,
            "objective": [float(f) for f in polish.objective] if polish else [],
            "n_forward": A.n_forward, "n_adjoint": A.n_adjoint, "noise_sigma": sigma, "tol": o["tol"],
            "lam_l1": lam, "lam_tv": 0.0, "lipschitz": G.lipschitz}
    timings = {"setup": t_setup, "gram": t_gram, "polish": time.perf_counter() - t0 - t_setup - t_gram}
    sel = A.selection
    return Image(x.reshape(grid.shape), grid, "l1-psf", sel.kind, sel.device, timings, provenance={"inverse": info})
