"""Basis pursuit denoising (eq. 3): ``min_x ||b - D x||^2 + lam ||x||_1``.

Two solvers: :func:`bpdn_cvxpy`, the reference (a conic solver through cvxpy), and
:func:`bpdn`, a working set solved by FISTA with a Newton polish (:mod:`clsas.sparse.gram`),
or feature-sign search for real amplitudes, stopped on a certified duality gap.
Its operator applies the shifted-atom dictionary by FFT: with Delta = T / P (P atoms per
sample) the dictionary is a convolution of the atom with the coefficients upsampled by P, so
``D x`` and ``D^H r`` cost one FFT of length P * M each (M the signal FFT length).

Amplitude models: ``"positive"`` (x >= 0, the paper's), ``"real"``, ``"complex"`` (analytic
atoms and signal, |x_i| the modulus).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .. import validate as v
from .atoms import Dictionary
from .gram import fista_gram

__all__ = ["BpdnResult", "RealPartOperator", "ShiftOperator", "bpdn", "bpdn_cvxpy", "group_atoms", "lam_max",
           "real_part_target"]

log = logging.getLogger(__name__)
MODES = ("positive", "real", "complex")


@dataclass
class BpdnResult:
    x: np.ndarray
    objective: float
    lam: float
    status: str
    iterations: int
    gap: float = 0.0
    time_s: float = 0.0
    info: dict = field(default_factory=dict)


class ShiftOperator:
    """``D x`` and ``D^H r`` for a :class:`Dictionary`, by FFT where Delta * fs = 1/P, else dense."""

    def __init__(self, dictionary: Dictionary):
        self.d = dictionary
        atom = dictionary.atom
        self.n, self.k, self.complex = atom.n, dictionary.k, atom.complex
        self.centered = atom.centered
        p = 1.0 / (dictionary.delta * atom.fs)
        self.p = int(round(p))
        self.fft = atom.sampled is not None and self.p >= 1 and abs(p - self.p) < 1e-9 * max(1.0, p)
        if self.fft:
            m = atom._m
            mp = m * self.p
            if self.k > mp:
                self.fft = False
        if self.fft:
            self.m, self.mp = m, mp
            # spectrum of the atom delayed by tau0, on the signed bins of length m
            self.spec = atom._spec * np.exp(-2j * np.pi * atom._freq * dictionary.tau0)
            kk = np.fft.fftfreq(m, 1 / m).astype(int)  # signed bin index
            self.bins = kk % mp  # where bin k of the signal sits in the length-mp DFT of x
        else:
            self.D = dictionary.matrix()
            self.DH = self.D.conj().T

    def forward(self, x: np.ndarray) -> np.ndarray:
        if not self.fft:
            return self.D @ x
        X = np.fft.fft(x, self.mp)[self.bins]
        y = np.fft.ifft(self.spec * X)[: self.n]
        if not self.complex:
            y = y.real
        return y - y.mean() if self.centered else y

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        if not self.fft:
            return self.DH @ r
        if self.centered:  # P is symmetric: D_c^H r = D^H (P r)
            r = r - r.mean()
        R = np.fft.fft(r, self.m)
        Z = np.zeros(self.mp, complex)
        Z[self.bins] = np.conj(self.spec) * R
        g = np.fft.ifft(Z)[: self.k] * (self.mp / self.m)
        return g if self.complex else g.real

    def norm2(self, iters: int = 50, seed: int = 0) -> float:
        """||D||^2 by power iteration (an upper estimate: x 1.02)."""
        rng = np.random.default_rng(seed)
        x = rng.normal(size=self.k) + (1j * rng.normal(size=self.k) if self.complex else 0)
        s = 0.0
        for _ in range(iters):
            x = self.adjoint(self.forward(x))
            s = np.linalg.norm(x)
            if s == 0:
                return 1.0
            x = x / s
        return 1.02 * float(s)


class RealPartOperator:
    """``sqrt(2) Re(D x)`` and its adjoint ``sqrt(2) D^H s`` (s real): complex amplitudes of
    analytic atoms fitted to the real part of an analytic signal ``b``, i.e. to the real
    recording itself (:func:`real_part_target`).

    BPDN on ``real_part_target(b)`` with it is the complex problem in the interior of the
    window (an analytic residual holds as much energy in its imaginary part as in its real
    part, hence the sqrt(2): lam and the residual's scale stay the same), and it is exact for
    echoes that the window cuts, whose analytic signal, taken over the window, is not the cut
    analytic atom."""

    def __init__(self, op: ShiftOperator):
        if not op.complex:
            raise ValueError("RealPartOperator needs complex (analytic) atoms")
        self.op, self.d, self.n, self.k, self.complex, self.fft = op, op.d, op.n, op.k, True, op.fft

    def forward(self, x: np.ndarray) -> np.ndarray:
        return np.sqrt(2.0) * self.op.forward(x).real

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        return np.sqrt(2.0) * self.op.adjoint(np.asarray(r, float).astype(complex))


def real_part_target(b: np.ndarray) -> np.ndarray:
    """What :class:`RealPartOperator` fits for an analytic signal ``b``: ``sqrt(2) Re(b)``."""
    return np.sqrt(2.0) * np.asarray(b).real


def real_part_columns(D: np.ndarray) -> np.ndarray:
    """(n, 2K) real matrix of :class:`RealPartOperator` on K analytic columns: coefficients
    stacked as ``[Re x, Im x]``."""
    return np.sqrt(2.0) * np.hstack([D.real, -D.imag])


def _check(dictionary, b, amplitudes):
    v.choice("amplitudes", amplitudes, MODES)
    if not isinstance(dictionary, Dictionary):
        raise TypeError("dictionary must be a clsas.sparse.Dictionary")
    if (amplitudes == "complex") != dictionary.atom.complex:
        raise ValueError("amplitudes='complex' needs a complex (analytic) atom, and only it does")
    b = v.array("b", b, ndim=1, allow_complex=amplitudes == "complex")
    if len(b) != dictionary.atom.n:
        raise ValueError(f"b has {len(b)} samples, the atom's grid {dictionary.atom.n}")
    return b


def lam_max(op: ShiftOperator, b: np.ndarray, amplitudes: str) -> float:
    """Smallest lam for which x = 0 is the BPDN solution: 2 max D^H b (by the model's norm)."""
    g = op.adjoint(b)
    if amplitudes == "positive":
        return float(max(0.0, 2 * np.max(g.real)))
    return float(2 * np.max(np.abs(g)))


def _objective(r, x, lam):
    return float(np.vdot(r, r).real + lam * np.abs(x).sum())


def _gap(op, b, r, x, lam, amplitudes):
    """Duality gap of the BPDN objective at x (residual r = b - D x); >= the suboptimality."""
    g = op.adjoint(r)
    dual_norm = np.max(g.real) if amplitudes == "positive" else np.max(np.abs(g))
    lp = lam / 2
    s = 1.0 if dual_norm <= lp else lp / dual_norm
    theta = s * r
    primal = 0.5 * np.vdot(r, r).real + lp * np.abs(x).sum()
    dual = 0.5 * np.vdot(b, b).real - 0.5 * np.vdot(b - theta, b - theta).real
    return float(2 * max(0.0, primal - dual))


def _resolve_lam(op, b, amplitudes, lam, lam_frac):
    lmax = lam_max(op, b, amplitudes)
    if (lam is None) == (lam_frac is None):
        raise ValueError("give exactly one of lam (absolute) and lam_frac (a fraction of lam_max)")
    if lam is None:
        lam = v.non_negative("lam_frac", lam_frac) * lmax
    else:
        lam = v.non_negative("lam", lam)
    return lam, lmax


def _best_on_the_way(Da, b, lam, xa, theta) -> np.ndarray:
    """Feature-sign search's step on the active atoms ``Da``: the least-squares solution for the
    signs ``theta``, or the best point on the way to it where a coefficient changes sign."""
    lp = lam / 2
    G = Da.T @ Da
    c = Da.T @ b
    try:
        x_new = np.linalg.solve(G, c - lp * theta)
    except np.linalg.LinAlgError:
        x_new = np.linalg.lstsq(G, c - lp * theta, rcond=None)[0]

    def f(z):
        return float(z @ G @ z - 2 * c @ z + lam * np.abs(z).sum())

    # candidate points: the full step and every zero crossing on the way
    d = x_new - xa
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = -xa / d
    ts = ts[(ts > 0) & (ts < 1) & np.isfinite(ts)]
    best_t, best_f = 1.0, f(x_new)
    for t in ts:
        fz = f(xa + t * d)
        if fz < best_f:
            best_t, best_f = t, fz
    return xa + best_t * d


def _feature_sign(dictionary, op, b, lam, amplitudes, max_iter, deadline=np.inf):
    """Exact BPDN for real or positive amplitudes by feature-sign search (Lee et al., NIPS 2006).

    The active set grows from the atom that most violates optimality (found with the FFT
    adjoint over all atoms); on it, the signed least-squares step is followed by a line search
    over the points where a coefficient changes sign. Finite; returns (x, iterations).
    """
    lp = lam / 2
    x = np.zeros(dictionary.k)
    active = np.zeros(0, int)
    theta = np.zeros(0)
    it = 0
    r = b.copy()
    while it < max_iter and time.perf_counter() <= deadline:
        it += 1
        g = op.adjoint(r).real  # D^T r: lam / 2 * sign(x) on the support at the optimum
        g_off = g.copy()
        g_off[active] = 0.0
        cand = g_off if amplitudes == "positive" else np.abs(g_off)
        i = int(np.argmax(cand))
        on_ok = True
        if active.size:
            on_ok = np.max(np.abs(g[active] - lp * theta)) <= 1e-9 * max(lp, np.abs(g).max())
        if on_ok:
            if cand[i] <= lp * (1 + 1e-9):
                break  # optimal
            active = np.append(active, i)
            theta = np.append(theta, np.sign(g[i]) if amplitudes == "real" else 1.0)
        Da = dictionary.atom.matrix(dictionary.taus[active])
        xa = _best_on_the_way(Da, b, lam, x[active], theta)
        xa[np.abs(xa) <= 1e-14 * max(1.0, np.abs(xa).max())] = 0.0
        if amplitudes == "positive":
            xa = np.maximum(xa, 0.0)
        x[active] = xa
        keep = xa != 0
        x[active[~keep]] = 0.0
        active, theta = active[keep], np.sign(xa[keep])
        r = b - (Da[:, keep] @ xa[keep] if keep.any() else 0.0)
    return x, it


def _unpair(z, k):
    return z[:k] + 1j * z[k:]


def bpdn(
    dictionary: Dictionary,
    b,
    lam: float | None = None,
    *,
    lam_frac: float | None = None,
    amplitudes: str = "positive",
    tol: float = 1e-7,
    max_outer: int = 30,
    max_inner: int = 100000,
    max_time_s: float | None = None,
    real_signal: bool = False,
) -> BpdnResult:
    """Fast BPDN, stopped at a certified duality gap <= ``tol`` x the objective.

    Real and positive amplitudes: feature-sign search, an exact active-set method whose full
    gradient ``D^T r`` is one FFT. Complex amplitudes: a working set, solved by FISTA (with
    adaptive restart) on its Gram matrix and polished by Newton's method on the support FISTA
    finds (:func:`clsas.sparse.gram.fista_gram`); the atoms that violate optimality join the set. Either
    way the duality gap over all atoms certifies the end.
    ``lam`` is absolute, or ``lam_frac`` a fraction of lam_max (at or above lam_max the answer
    is exactly zero). ``max_time_s``: a time budget; where it runs out the best point so far is
    returned with its certified gap (``gap``), status ``"max_time"``. ``status`` is
    ``"optimal"``, ``"max_iter"`` or ``"max_time"``.
    ``real_signal=True`` (complex amplitudes only): ``b`` is the analytic signal of a real
    recording, and its real part is fitted (:class:`RealPartOperator`): the same problem in the
    window's interior, exact for echoes cut by the window's edges.
    """
    t_start = time.perf_counter()
    deadline = np.inf if max_time_s is None else t_start + v.positive("max_time_s", max_time_s)
    b = _check(dictionary, b, amplitudes)
    op = ShiftOperator(dictionary)
    if real_signal:
        if amplitudes != "complex":
            raise ValueError("real_signal=True is for amplitudes='complex' (a real signal's analytic signal)")
        op, b = RealPartOperator(op), real_part_target(b)
    lam, lmax = _resolve_lam(op, b, amplitudes, lam, lam_frac)
    dtype = complex if amplitudes == "complex" else float
    x = np.zeros(dictionary.k, dtype)
    info = {"lam_max": lmax, "fft": op.fft, "real_signal": bool(real_signal)}
    if lam >= lmax:
        return BpdnResult(x, _objective(b, x, lam), lam, "optimal", 0, 0.0, time.perf_counter() - t_start, info)
    if amplitudes != "complex":
        return _bpdn_feature_sign(dictionary, op, b, lam, amplitudes, tol, deadline, t_start, info)
    return _bpdn_working_set(dictionary, op, b, lam, tol, max_outer, max_inner, deadline, real_signal,
                             t_start, info)


def _bpdn_feature_sign(dictionary, op, b, lam, amplitudes, tol, deadline, t_start, info) -> BpdnResult:
    """:func:`bpdn` for real and positive amplitudes: the feature-sign search, then its gap."""
    x, n_it = _feature_sign(dictionary, op, b, lam, amplitudes, max_iter=20 * dictionary.k + 100,
                              deadline=deadline)
    r = b - op.forward(x)
    f = _objective(r, x, lam)
    gap = _gap(op, b, r, x, lam, amplitudes)
    status = ("optimal" if gap <= tol * max(f, 1e-300)
              else "max_time" if time.perf_counter() > deadline else "max_iter")
    if status != "optimal":
        log.warning("bpdn: feature-sign search ended with relative gap %.2g", gap / max(f, 1e-300))
    info.update(algorithm="feature-sign", support=int(np.count_nonzero(x)))
    return BpdnResult(x, f, lam, status, n_it, gap, time.perf_counter() - t_start, info)


#: atoms added to the working set at a time (the strongest violators of optimality)
_GROWTH = 20


def _restricted_problem(cols, b, x, work, real_signal) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """The working set's normal equations for :func:`fista_gram`: ``(D^H D, D^H b, mode, start)``;
    for a real signal the columns are each atom's [Re, Im] pair, whose modulus is penalised."""
    if real_signal:
        cols = real_part_columns(cols)
        mode, x0 = "pairs", np.r_[x[work].real, x[work].imag]
    else:
        mode, x0 = "complex", x[work]
    return cols.conj().T @ cols, cols.conj().T @ b, mode, x0


def _residual_objective_gap(op, b, x, lam) -> tuple[np.ndarray, float, float]:
    """The residual, the objective and the duality gap over all atoms at ``x``."""
    r = b - op.forward(x)
    return r, _objective(r, x, lam), _gap(op, b, r, x, lam, "complex")


def _grown(dictionary, work: np.ndarray, cols: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The working set with the atoms ``new`` (not in it) added, kept sorted, and its columns
    (only the new atoms are computed)."""
    order = np.argsort(np.r_[work, new], kind="stable")
    cols = np.concatenate([cols, dictionary.atom.matrix(dictionary.taus[new])], axis=1)
    return np.r_[work, new][order], cols[:, order]


def _bpdn_working_set(dictionary, op, b, lam, tol, max_outer, max_inner, deadline, real_signal, t_start,
                      info) -> BpdnResult:
    """:func:`bpdn` for complex amplitudes: FISTA on a working set of atoms, grown by the atoms
    that violate optimality (20 at a time), until the duality gap over all atoms certifies it."""
    x = np.zeros(dictionary.k, complex)
    lp = lam / 2
    score = np.abs(op.adjoint(b))
    work = np.flatnonzero(score > lp)
    work = np.sort(work[np.argsort(score[work])[::-1][:_GROWTH]])
    status, gap, inner, outer = "max_iter", np.inf, 0, 0
    bb = float(np.vdot(b, b).real)
    tol_inner = tol / 10
    cols = dictionary.atom.matrix(dictionary.taus[work])  # the working set's atoms, kept as it grows
    while outer < max_outer:
        outer += 1
        Gw, cw, mode, x0 = _restricted_problem(cols, b, x, work, real_signal)
        xw, n_in = fista_gram(Gw, cw, bb, lam, mode, x0, tol / 10, max_inner, deadline)
        inner += n_in
        x[:] = 0
        x[work] = _unpair(xw, len(work)) if real_signal else xw
        r, f, gap = _residual_objective_gap(op, b, x, lam)
        if gap <= tol * max(f, 1e-300):
            status = "optimal"
            break
        if time.perf_counter() > deadline:
            status = "max_time"
            break
        score = np.abs(op.adjoint(r))
        viol = np.setdiff1d(np.flatnonzero(score > lp * (1 + tol)), work)
        if viol.size == 0:  # the set is right, the restricted solve was not tight enough
            tol_inner = tol_inner / 10
            xw, n_in = fista_gram(Gw, cw, bb, lam, mode, xw, tol_inner, max_inner, deadline)
            inner += n_in
            x[work] = _unpair(xw, len(work)) if real_signal else xw
            r, f, gap = _residual_objective_gap(op, b, x, lam)
            if gap <= tol * max(f, 1e-300):
                status = "optimal"
                break
            continue
        work, cols = _grown(dictionary, work, cols, viol[np.argsort(score[viol])[::-1][:_GROWTH]])
    if not np.all(np.isfinite(x)):
        raise FloatingPointError("BPDN diverged (non-finite coefficients); check the dictionary and b")
    r = b - op.forward(x)
    f = _objective(r, x, lam)
    if status != "optimal":
        log.warning("bpdn: stopped after %d outer iterations with relative gap %.2g", outer, gap / max(f, 1e-300))
    info.update(algorithm="working-set FISTA", outer_iterations=outer, working_set=int(len(work)))
    return BpdnResult(x, f, lam, status, inner, gap, time.perf_counter() - t_start, info)


def bpdn_cvxpy(
    dictionary: Dictionary, b, lam: float | None = None, *, lam_frac: float | None = None,
    amplitudes: str = "positive", solver: str | None = None,
) -> BpdnResult:
    """Reference BPDN through cvxpy (Clarabel by default). Same arguments as :func:`bpdn`."""
    import cvxpy as cp

    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    op = ShiftOperator(dictionary)
    lam, lmax = _resolve_lam(op, b, amplitudes, lam, lam_frac)
    D = dictionary.matrix()
    if amplitudes == "complex":
        x = cp.Variable(dictionary.k, complex=True)
    else:
        x = cp.Variable(dictionary.k, nonneg=amplitudes == "positive")
    prob = cp.Problem(cp.Minimize(cp.sum_squares(b - D @ x) + lam * cp.sum(cp.abs(x))))
    try:
        prob.solve(solver=solver or "CLARABEL")
    except cp.error.SolverError as exc:
        raise RuntimeError(f"bpdn_cvxpy: the solver failed ({exc})") from exc
    if prob.status not in ("optimal", "optimal_inaccurate") or x.value is None:
        raise RuntimeError(f"bpdn_cvxpy: solver status {prob.status}")
    xv = np.asarray(x.value)
    if amplitudes == "positive":
        xv = np.maximum(xv, 0.0)
    r = b - D @ xv
    stats = prob.solver_stats
    return BpdnResult(xv, _objective(r, xv, lam), lam, prob.status, int(stats.num_iters or 0), 0.0,
                      time.perf_counter() - t_start, {"lam_max": lmax, "solver": stats.solver_name})


def group_atoms(dictionary: Dictionary, x: np.ndarray, *, rel_threshold: float = 0.0,
                max_run: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Echoes from a grid solution: one per run of neighbouring active atoms.

    A smeared echo (off the grid, or a pulse that differs from the atom, as on measured data)
    comes out of BPDN as a few neighbouring atoms; read as separate echoes they render as a
    streak, read as one they render as one pulse.

    Parameters
    ----------
    dictionary : Dictionary
    x : (K,) array
        Coefficients on the dictionary's grid (real or complex).
    rel_threshold : float
        Atoms with ``|x|`` at or below this fraction of the largest are inactive.
    max_run : int, optional
        Runs longer than this many atoms are cut into equal pieces no longer than it (an
        extended reflector stays several echoes).

    Returns
    -------
    delays_s, amplitudes, weights : (n_echoes,) arrays
        Per run: the ``|x|``-weighted mean delay; the amplitude of one atom there that best
        fits the run's signal (its projection, ``<f(tau), sum_i x_i f(tau_i)> / |f(tau)|^2``,
        the norm on the window, so that an echo cut by the window keeps its amplitude:
        what the matched filter reads at that delay, scaled to an amplitude, so the carrier
        phase between the run's atoms is accounted for); and the sum of ``|x|``.
    """
    x = np.asarray(x)
    taus = dictionary.taus
    mag = np.abs(x)
    on = np.flatnonzero(mag > max(v.non_negative("rel_threshold", rel_threshold) * mag.max(initial=0.0), 0.0))
    runs = np.split(on, np.flatnonzero(np.diff(on) > 1) + 1) if on.size else []
    if max_run is not None:
        max_run = v.positive_int("max_run", max_run)
        runs = [piece for r in runs for piece in np.array_split(r, -(-len(r) // max_run))]
    delays = np.array([np.average(taus[r], weights=mag[r]) for r in runs])
    amps = np.zeros(len(runs), dtype=x.dtype)
    atom = dictionary.atom
    for j, r in enumerate(runs):
        if len(r) == 1:
            amps[j] = x[r[0]]
            continue
        f = atom.matrix(np.r_[delays[j], taus[r]], fast=True)
        # over the column's own energy: an atom the window cuts holds less than |f|^2
        proj = np.vdot(f[:, 0], f[:, 1:] @ x[r]) / max(np.vdot(f[:, 0], f[:, 0]).real, 1e-300)
        amps[j] = proj if np.iscomplexobj(amps) else proj.real
    weights = np.array([mag[r].sum() for r in runs])
    return delays, amps, weights
