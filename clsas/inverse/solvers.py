"""Solvers of the model-based reconstruction: CGLS (least squares with early stopping) and monotone
FISTA (an L1 prior on |x|, isotropic total variation of |x|, or both).

Written here rather than taken from a library: scipy has least squares (``lsqr``) but no proximal
solvers, and its ``lsqr`` takes no callback (no progress, no stopping by the discrepancy principle);
PyLops/PyProximal would add two dependencies for about a hundred lines. Every solver takes any
:class:`scipy.sparse.linalg.LinearOperator` (``matvec``/``rmatvec``), complex.

Objective of :func:`fista` for complex ``x`` (the priors act on the magnitude):

    F(x) = 0.5 ||A x - b||^2 + lam_l1 sum_v |x_v| + lam_tv TV(|x|),
    TV(u) = sum_v sqrt(sum_d (u[v + e_d] - u[v])^2)   (isotropic, voxel units, axes longer than 1).

The L1 prox is exact (complex soft threshold). With TV, the prox of ``lam_tv TV(|.|) + lam_l1 |.|``
is taken on the magnitude with the phase kept (TV denoising of |z| by Beck and Teboulle's fast
gradient projection, then soft threshold and clip at 0): exact for a real non-negative image, a
magnitude prior in the manner of Cetin and Karl's feature-enhanced SAR imaging for a complex one.
The monotone variant keeps the lower objective, so F never rises.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse.linalg import LinearOperator

from .. import validate as v

__all__ = ["SolveResult", "cgls", "fista", "tv", "tv_prox"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None] | None


@dataclass(frozen=True)
class SolveResult:
    """A solver's answer.

    Attributes
    ----------
    x : (n,) complex128 solution.
    iterations : int
        Iterations run.
    objective : list of float
        The objective after each iteration (CGLS: 0.5 ||A x - b||^2).
    stopped : str
        Why it stopped (``"tolerance"``, ``"discrepancy"``, ``"max_iter"``, ``"zero"``).
    n_forward, n_adjoint : int
        Applications of ``A`` and ``A^H``.
    """

    x: np.ndarray
    iterations: int
    objective: list = field(default_factory=list)
    stopped: str = "max_iter"
    n_forward: int = 0
    n_adjoint: int = 0


def _check(A, b, x0, max_iter, tol):
    if not isinstance(A, LinearOperator):
        raise TypeError(f"A must be a scipy.sparse.linalg.LinearOperator, got {type(A).__name__}")
    b = np.asarray(b, np.complex128).ravel()
    if b.shape != (A.shape[0],):
        raise ValueError(f"b must have {A.shape[0]} values, got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("b must be finite (no NaN or Inf)")
    if x0 is None:
        x0 = np.zeros(A.shape[1], np.complex128)
    x0 = np.asarray(x0, np.complex128).ravel()
    if x0.shape != (A.shape[1],) or not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 must be {A.shape[1]} finite values, got shape {x0.shape}")
    return b, x0, v.positive_int("max_iter", max_iter), v.positive("tol", tol)


def cgls(A: LinearOperator, b: np.ndarray, x0: np.ndarray | None = None, *, max_iter: int = 30,
         tol: float = 1e-3, residual_norm: float | None = None, progress: Progress = None) -> SolveResult:
    """Least squares ``min ||A x - b||`` by conjugate gradients on the normal equations (CGLS).

    One ``A`` and one ``A^H`` per iteration. Stops after ``max_iter``; when ``||A^H r||`` falls
    below ``tol`` times its start; or, given ``residual_norm`` (the expected ``||noise||``), when
    ``||r||`` falls to it (the discrepancy principle: fitting further fits the noise).
    """
    b, x, max_iter, tol = _check(A, b, x0, max_iter, tol)
    if residual_norm is not None:
        residual_norm = v.non_negative("residual_norm", residual_norm)
    r = b - A.matvec(x)
    s = A.rmatvec(r)
    p = s.copy()
    gamma0 = gamma = float(np.vdot(s, s).real)
    hist, stopped, it = [0.5 * float(np.vdot(r, r).real)], "max_iter", 0
    nf, na = 1, 1
    if gamma0 == 0:
        return SolveResult(x, 0, hist, "zero", nf, na)
    for it in range(1, max_iter + 1):
        q = A.matvec(p)
        alpha = gamma / float(np.vdot(q, q).real)
        x = x + alpha * p
        r = r - alpha * q
        s = A.rmatvec(r)
        nf, na = nf + 1, na + 1
        gamma_new = float(np.vdot(s, s).real)
        hist.append(0.5 * float(np.vdot(r, r).real))
        if progress is not None:
            progress(it, max_iter)
        if residual_norm is not None and np.sqrt(2 * hist[-1]) <= residual_norm:
            stopped = "discrepancy"
            break
        if np.sqrt(gamma_new / gamma0) < tol:
            stopped = "tolerance"
            break
        p = s + (gamma_new / gamma) * p
        gamma = gamma_new
    return SolveResult(x, it, hist, stopped, nf, na)


def _grad(u: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """Forward differences along ``axes`` (0 at the far edge), stacked on a new first axis."""
    g = np.zeros((len(axes), *u.shape))
    for i, a in enumerate(axes):
        d = np.diff(u, axis=a)
        sl = [slice(None)] * u.ndim
        sl[a] = slice(0, u.shape[a] - 1)
        g[i][tuple(sl)] = d
    return g


def _div(p: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """The negative adjoint of :func:`_grad`."""
    out = np.zeros(p.shape[1:])
    for i, a in enumerate(axes):
        pi = p[i]
        n = pi.shape[a]
        d = np.zeros_like(pi)
        first = [slice(None)] * pi.ndim
        first[a] = 0
        d[tuple(first)] = np.take(pi, 0, axis=a)
        mid = [slice(None)] * pi.ndim
        mid[a] = slice(1, n - 1)
        d[tuple(mid)] = np.diff(pi, axis=a)[tuple([slice(None)] * a + [slice(0, n - 2)])]
        last = [slice(None)] * pi.ndim
        last[a] = n - 1
        d[tuple(last)] = -np.take(pi, n - 2, axis=a)
        out += d
    return out


def _axes(shape: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(a for a, n in enumerate(shape) if n > 1)


def tv(u: np.ndarray) -> float:
    """Isotropic total variation of a real array (voxel units, over its axes longer than 1)."""
    axes = _axes(u.shape)
    if not axes:
        return 0.0
    return float(np.sqrt((_grad(u, axes) ** 2).sum(0)).sum())


def tv_prox(u: np.ndarray, weight: float, n_iter: int = 30) -> np.ndarray:
    """``argmin_w 0.5 ||w - u||^2 + weight TV(w)`` for a real array (Beck and Teboulle's fast gradient
    projection on the dual, ``n_iter`` steps)."""
    axes = _axes(u.shape)
    if weight <= 0 or not axes:
        return u.copy()
    p = np.zeros((len(axes), *u.shape))
    q, t = p.copy(), 1.0
    step = 1.0 / (4.0 * len(axes) * weight)
    for _ in range(n_iter):
        g = _grad(u + weight * _div(q, axes), axes)
        p_new = q + step * g * weight
        p_new /= np.maximum(1.0, np.sqrt((p_new ** 2).sum(0)))
        t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
        q = p_new + ((t - 1) / t_new) * (p_new - p)
        p, t = p_new, t_new
    return u + weight * _div(p, axes)


def _prox(z: np.ndarray, shape: tuple[int, ...], l1: float, tvw: float, n_inner: int) -> np.ndarray:
    """Prox of ``l1 |.| + tvw TV(|.|)`` at ``z`` (step folded into the weights)."""
    mag = np.abs(z)
    if tvw > 0:
        m = tv_prox(mag.reshape(shape), tvw, n_inner).ravel()
    else:
        m = mag
    m = np.maximum(m - l1, 0.0)
    phase = np.where(mag > 0, z / np.where(mag > 0, mag, 1.0), 0.0)
    return m * phase


def fista(A: LinearOperator, b: np.ndarray, x0: np.ndarray | None = None, *, lam_l1: float = 0.0,
          lam_tv: float = 0.0, shape: tuple[int, ...] | None = None, lipschitz: float | None = None,
          max_iter: int = 50, tol: float = 1e-3, tv_iter: int = 30, progress: Progress = None) -> SolveResult:
    """Monotone FISTA for ``0.5 ||A x - b||^2 + lam_l1 ||x||_1 + lam_tv TV(|x|)`` (module docstring).

    Parameters
    ----------
    A : LinearOperator
        Complex, (n_data, n_vox).
    b : (n_data,) complex data.
    x0 : (n_vox,) complex start (e.g. the scaled backprojection), default 0.
    lam_l1, lam_tv : float
        Weights (>= 0) of the L1 and TV priors, in the units of ``A^H b``.
    shape : tuple of int
        The image's shape (for TV; default ``(n_vox,)``).
    lipschitz : float, optional
        ``||A||^2`` (default: power iteration, 8 ``A^H A`` from ``x0``).
    max_iter : int
        At most this many iterations (one ``A`` and one ``A^H`` each).
    tol : float
        Stop when the proximal-gradient step ``||z_k - y_k||`` falls to ``tol ||x_k||``.
    tv_iter : int
        Steps of the inner TV prox.
    progress : callable(done, total), optional
    """
    b, x, max_iter, tol = _check(A, b, x0, max_iter, tol)
    lam_l1, lam_tv = v.non_negative("lam_l1", lam_l1), v.non_negative("lam_tv", lam_tv)
    shape = tuple(shape) if shape is not None else (A.shape[1],)
    if int(np.prod(shape)) != A.shape[1]:
        raise ValueError(f"shape {shape} does not hold {A.shape[1]} voxels")
    tv_iter = v.positive_int("tv_iter", tv_iter)
    L = 1.02 * (v.positive("lipschitz", lipschitz) if lipschitz is not None else _norm2(A, start=x))

    def objective(xx, axx):
        r = axx - b
        val = 0.5 * float(np.vdot(r, r).real) + lam_l1 * float(np.abs(xx).sum())
        return val + (lam_tv * tv(np.abs(xx).reshape(shape)) if lam_tv else 0.0)

    ax = A.matvec(x)
    f = objective(x, ax)
    hist, nf, na = [f], 1, 0
    y, ay, t = x.copy(), ax.copy(), 1.0
    stopped, it = "max_iter", 0
    for it in range(1, max_iter + 1):
        y_prev = y
        z = _prox(y - A.rmatvec(ay - b) / L, shape, lam_l1 / L, lam_tv / L, tv_iter)
        az = A.matvec(z)
        nf, na = nf + 1, na + 1
        fz = objective(z, az)
        x_old, ax_old = x, ax
        if fz <= f:
            x, ax, f = z, az, fz
        t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
        c1, c2 = t / t_new, (t - 1) / t_new
        y = x + c1 * (z - x) + c2 * (x - x_old)
        ay = ax + c1 * (az - ax) + c2 * (ax - ax_old)
        t = t_new
        hist.append(f)
        if progress is not None:
            progress(it, max_iter)
        nx = np.linalg.norm(x)
        if nx == 0 and np.linalg.norm(z) == 0:
            stopped = "zero"
            break
        if np.linalg.norm(z - y_prev) <= tol * max(nx, np.linalg.norm(z)) and it > 1:
            stopped = "tolerance"
            break
    return SolveResult(x, it, hist, stopped, nf, na)


def _norm2(A: LinearOperator, n_iter: int = 8, start: np.ndarray | None = None) -> float:
    """``||A||^2`` by power iteration on ``A^H A``, from ``start`` (the warm start, near the top
    singular vector: few steps) plus a little noise, else from noise."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=A.shape[1]) + 1j * rng.normal(size=A.shape[1])
    if start is not None and np.linalg.norm(start) > 0:
        x = start / np.linalg.norm(start) + 1e-3 * x / np.linalg.norm(x)
    s = 0.0
    for _ in range(n_iter):
        x /= np.linalg.norm(x)
        x = A.rmatvec(A.matvec(x))
        s = float(np.linalg.norm(x))
    return s
