"""Continuous basis pursuit: CBP-Taylor and the convex CBP-Polar SOCP (cvxpy, positive
amplitudes, Ekanadham et al. 2011), and CBP-Polar refined: BPDN finds the support, then nlopt
moves each echo continuously while the amplitudes are refit (variable projection), splitting,
merging and pruning echoes by the Bayesian information criterion."""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np

from .. import _validate as v
from .atoms import Dictionary
from .bpdn import ShiftOperator, _check, _resolve_lam, bpdn
from .metrics import Echoes

__all__ = ["cbp_taylor", "cbp_polar", "cbp_polar_refined"]

log = logging.getLogger(__name__)


def _positive_only(amplitudes, name):
    if amplitudes != "positive":
        raise ValueError(
            f"{name} is the convex method of Ekanadham et al., which assumes positive amplitudes; "
            f"use method='cbp-polar' (the refined one) for amplitudes={amplitudes!r}"
        )


def _solve(prob, name):
    import cvxpy as cp

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob.solve(solver="CLARABEL")
    except cp.error.SolverError as exc:
        raise RuntimeError(f"{name}: the solver failed ({exc})") from exc
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise RuntimeError(f"{name}: solver status {prob.status}")
    return prob.status, int(prob.solver_stats.num_iters or 0)


def _echoes_from(taus, amps, rel_threshold, method, status, iters, t_start, info):
    keep = amps > rel_threshold * max(amps.max(initial=0.0), 1e-300)
    return Echoes(taus[keep], amps[keep], method, status, iters, time.perf_counter() - t_start, info)


def cbp_taylor(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="positive",
               rel_threshold: float = 1e-3) -> Echoes:
    """CBP-Taylor: ``min |b - F c - G d|^2 + lam sum c`` s.t. ``|d_i| <= c_i`` (G = Delta/2 f')."""
    import cvxpy as cp

    t_start = time.perf_counter()
    _positive_only(amplitudes, "cbp-taylor")
    b = _check(dictionary, b, amplitudes)
    lam, lmax = _resolve_lam(ShiftOperator(dictionary), b, amplitudes, lam, lam_frac)
    F, G = dictionary.taylor()
    c = cp.Variable(dictionary.k, nonneg=True)
    d = cp.Variable(dictionary.k)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(b - F @ c - G @ d) + lam * cp.sum(c)), [cp.abs(d) <= c])
    status, iters = _solve(prob, "cbp-taylor")
    cv, dv = np.maximum(c.value, 0.0), d.value
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(cv > 0, np.clip(dv / cv, -1, 1), 0.0) * dictionary.delta / 2
    return _echoes_from(dictionary.taus + shift, cv, rel_threshold, "cbp-taylor", status, iters, t_start,
                        {"lam": lam, "lam_max": lmax})


def cbp_polar(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="positive",
              rel_threshold: float = 1e-3) -> Echoes:
    """Convex CBP-Polar (SOCP): ``|(u_i, v_i)| <= r c_i``, ``u_i >= r cos(theta) c_i``;
    delay = grid + (Delta/2) atan2(v, u) / theta."""
    import cvxpy as cp

    t_start = time.perf_counter()
    _positive_only(amplitudes, "cbp-polar (convex)")
    b = _check(dictionary, b, amplitudes)
    lam, lmax = _resolve_lam(ShiftOperator(dictionary), b, amplitudes, lam, lam_frac)
    P = dictionary.polar()
    k = dictionary.k
    c, u, w = cp.Variable(k, nonneg=True), cp.Variable(k), cp.Variable(k)
    cons = [cp.SOC(P.r * c, cp.vstack([u, w]), axis=0), u >= P.r * np.cos(P.theta) * c]
    prob = cp.Problem(cp.Minimize(cp.sum_squares(b - P.C @ c - P.U @ u - P.V @ w) + lam * cp.sum(c)), cons)
    status, iters = _solve(prob, "cbp-polar (convex)")
    cv = np.maximum(c.value, 0.0)
    shift = (dictionary.delta / 2) * np.arctan2(w.value, u.value) / P.theta
    return _echoes_from(dictionary.taus + shift, cv, rel_threshold, "cbp-polar-socp", status, iters, t_start,
                        {"lam": lam, "lam_max": lmax, "r": P.r, "theta": P.theta})


# -- refined CBP-Polar: BPDN seed + nlopt ------------------------------------------------------

def _amplitudes(A, b, mode):
    if mode == "positive":
        import scipy.optimize

        return scipy.optimize.nnls(A, b)[0]
    return np.linalg.lstsq(A, b, rcond=None)[0]


class _VarPro:
    """RSS(taus) = |b - A(taus) a*(taus)|^2 with a* the best amplitudes, and its gradient."""

    def __init__(self, atom, b, mode):
        self.atom, self.b, self.mode = atom, b, mode
        self.evals = 0

    def __call__(self, taus, grad=None):
        self.evals += 1
        A = self.atom.matrix(taus)
        a = _amplitudes(A, self.b, self.mode)
        r = self.b - A @ a
        if grad is not None and grad.size:
            dA = self.atom.dmatrix(taus)
            grad[:] = -2 * np.real(np.conj(a) * (dA.conj().T @ r))
        return float(np.vdot(r, r).real)

    def fit(self, taus0, lo, hi, max_eval=300):
        """Delays within [lo, hi] minimising the RSS, from taus0; a roundoff stop keeps the best."""
        import nlopt

        k = len(taus0)
        best = {"f": np.inf, "x": np.array(taus0, float)}

        def obj(x, grad):
            f = self(x, grad)
            if f < best["f"]:
                best["f"], best["x"] = f, x.copy()
            return f

        opt = nlopt.opt(nlopt.LD_LBFGS, k)
        opt.set_lower_bounds(lo)
        opt.set_upper_bounds(hi)
        opt.set_min_objective(obj)
        opt.set_xtol_abs(1e-4 / self.atom.fs)
        opt.set_ftol_rel(1e-12)
        opt.set_maxeval(max_eval)
        status = "optimal"
        try:
            opt.optimize(np.clip(taus0, lo, hi))
        except nlopt.RoundoffLimited:
            status = "roundoff (best point kept)"
        except Exception as exc:  # noqa: BLE001 - nlopt raises its own runtime_error type
            if not np.isfinite(best["f"]):
                raise RuntimeError(f"cbp-polar: nlopt failed before any finite point ({exc!r})") from exc
            status = f"nlopt {type(exc).__name__} (best point kept)"
        taus = best["x"]
        a = _amplitudes(self.atom.matrix(taus), self.b, self.mode)
        return taus, a, best["f"], status


def _clusters(taus, x, rel):
    """Groups of neighbouring active atoms: one seed echo per group (amplitude-weighted delay)."""
    mag = np.abs(x)
    on = np.flatnonzero(mag > rel * max(mag.max(initial=0.0), 1e-300))
    groups, cur = [], []
    for i in on:
        if cur and i > cur[-1] + 1:
            groups.append(cur)
            cur = []
        cur.append(i)
    if cur:
        groups.append(cur)
    return [float(np.average(taus[g], weights=mag[g])) for g in groups], [(taus[g[0]], taus[g[-1]]) for g in groups]


def cbp_polar_refined(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="complex",
                      max_echoes: int = 8, rel_threshold: float = 0.02) -> Echoes:
    """CBP-Polar refined by nlopt, seeded by BPDN; any amplitude model.

    1. BPDN on the grid; each run of neighbouring active atoms seeds one echo.
    2. Variable projection: nlopt (L-BFGS, analytic gradient) moves the delays continuously,
       the amplitudes are the least-squares (or NNLS) fit for the delays.
    3. Model order by BIC, n log(RSS / n) + p K log n (p = 2 real, 3 complex parameters per
       echo): each echo is tried split in two about itself, echoes closer than 1e-3 of a
       sample merge, and echoes below ``rel_threshold`` of the largest are pruned.
    """
    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    atom = dictionary.atom
    # the seed only needs the support: a loose gap is enough
    seed = bpdn(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, tol=1e-3, max_inner=5000)
    taus0, spans = _clusters(dictionary.taus, seed.x, rel_threshold)
    info = {"lam": seed.lam, "seed_echoes": len(taus0), "bpdn_time_s": seed.time_s}
    if not taus0:
        return Echoes([], [], "cbp-polar", "optimal", 0, time.perf_counter() - t_start, info)
    n_real = atom.n * (2 if amplitudes == "complex" else 1)
    p = 3 if amplitudes == "complex" else 2
    t_lo, t_hi = dictionary.taus[0] - dictionary.delta, dictionary.taus[-1] + dictionary.delta
    vp = _VarPro(atom, b, amplitudes)

    def bic(rss, k):
        return n_real * np.log(max(rss, 1e-300) / n_real) + p * k * np.log(n_real)

    def fit(taus):
        taus = np.sort(np.asarray(taus, float))
        lo = np.full(len(taus), t_lo)
        hi = np.full(len(taus), t_hi)
        return vp.fit(taus, lo, hi)

    taus, a, rss, status = fit(taus0)
    score = bic(rss, len(taus))
    width = 1.0 / atom.fs
    improved = True
    while improved and len(taus) < max_echoes:
        improved = False
        best = None
        for k in range(len(taus)):
            for sep in (0.25, 0.5, 1.0, 2.0):
                trial = np.r_[np.delete(taus, k), taus[k] - sep * width, taus[k] + sep * width]
                t2, a2, rss2, st2 = fit(trial)
                s2 = bic(rss2, len(t2))
                if s2 < score - 1e-9 and (best is None or s2 < best[0]):
                    best = (s2, t2, a2, rss2, st2)
        if best is not None:
            score, taus, a, rss, status = best
            improved = True
    # merge echoes that met, prune the negligible, refit
    while len(taus) > 1:
        order = np.argsort(taus)
        taus, a = taus[order], a[order]
        close = np.flatnonzero(np.diff(taus) < 1e-3 * width)
        small = np.flatnonzero(np.abs(a) < rel_threshold * np.abs(a).max())
        if close.size:
            taus = np.delete(taus, close[0] + 1)
        elif small.size:
            taus = np.delete(taus, small[0])
        else:
            break
        taus, a, rss, status = fit(taus)
    if not (np.all(np.isfinite(taus)) and np.all(np.isfinite(a))):
        raise FloatingPointError("cbp-polar: non-finite result")
    info.update(rss=rss, bic=bic(rss, len(taus)), evaluations=vp.evals)
    return Echoes(taus, a, "cbp-polar", status, vp.evals, time.perf_counter() - t_start, info)


def superres(signal, atom_shape, fs_hz: float, *, method: str = "cbp-polar", delta_s: float | None = None,
             lam: float | None = None, lam_frac: float | None = None, amplitudes: str = "complex",
             tau0_s: float = 0.0) -> Echoes:
    """Super-resolve the echoes in one signal.

    Parameters
    ----------
    signal : 1-D array
        Real recording (for ``amplitudes="complex"`` its analytic signal is taken) or an
        analytic signal.
    atom_shape : callable or 1-D array
        The pulse (see :class:`clsas.sparse.Atom`).
    method : {"bpdn", "cbp-taylor", "cbp-polar", "cbp-polar-socp"}
    delta_s : float, optional
        Grid spacing; default half a sample.
    lam, lam_frac : float
        Absolute lam, or a fraction of lam_max (default ``lam_frac=0.05``).
    """
    from ..signals import analytic
    from .atoms import Atom

    v.choice("method", method, ("bpdn", "cbp-taylor", "cbp-polar", "cbp-polar-socp"))
    fs = v.positive("fs_hz", fs_hz)
    x = v.array("signal", signal, ndim=1, allow_complex=True)
    if amplitudes == "complex" and not np.iscomplexobj(x):
        x = analytic(x)
    if amplitudes != "complex" and np.iscomplexobj(x):
        raise ValueError("signal is complex: use amplitudes='complex'")
    atom = Atom(atom_shape, fs, len(x), complex=amplitudes == "complex")
    delta = 0.5 / fs if delta_s is None else v.positive("delta_s", delta_s)
    d = Dictionary(atom, delta, tau0_s)
    if lam is None and lam_frac is None:
        lam_frac = 0.05
    if method == "bpdn":
        t = time.perf_counter()
        res = bpdn(d, x, lam, lam_frac=lam_frac, amplitudes=amplitudes)
        on = np.abs(res.x) > 0
        return Echoes(d.taus[on], res.x[on], "bpdn", res.status, res.iterations, time.perf_counter() - t,
                      {"lam": res.lam, "gap": res.gap, **res.info})
    if method == "cbp-taylor":
        return cbp_taylor(d, x, lam, lam_frac=lam_frac, amplitudes=amplitudes)
    if method == "cbp-polar-socp":
        return cbp_polar(d, x, lam, lam_frac=lam_frac, amplitudes=amplitudes)
    return cbp_polar_refined(d, x, lam, lam_frac=lam_frac, amplitudes=amplitudes)
