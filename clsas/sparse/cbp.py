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
from .bpdn import ShiftOperator, _check, _resolve_lam, bpdn, lam_noise
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
    """CBP-Taylor: ``min |b - F c - G d|^2 + lam sum c`` s.t. ``|d_i| <= c_i`` (G = Delta/2 f').

    ``amplitudes="positive"`` is Ekanadham et al.'s convex program. For signed or complex
    amplitudes (echoes of unknown phase) the same idea is kept convex with a bound ``t_i``:
    ``min |b - F c - G d|^2 + lam sum t`` s.t. ``|c_i| <= t_i``, ``|d_i| <= t_i``; the shift is
    ``Re(d_i / c_i) Delta / 2``, clipped to the cell. This relaxation lets d's phase differ
    from c's, so it is looser than the positive program; refined CBP-Polar has no such gap.
    """
    import cvxpy as cp

    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    lam, lmax = _resolve_lam(ShiftOperator(dictionary), b, amplitudes, lam, lam_frac)
    F, G = dictionary.taylor()
    k = dictionary.k
    if amplitudes == "positive":
        c = cp.Variable(k, nonneg=True)
        d = cp.Variable(k)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(b - F @ c - G @ d) + lam * cp.sum(c)), [cp.abs(d) <= c])
    else:
        cplx = amplitudes == "complex"
        c, d, t = cp.Variable(k, complex=cplx), cp.Variable(k, complex=cplx), cp.Variable(k, nonneg=True)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(b - F @ c - G @ d) + lam * cp.sum(t)),
                          [cp.abs(c) <= t, cp.abs(d) <= t])
    status, iters = _solve(prob, "cbp-taylor")
    cv, dv = np.asarray(c.value), np.asarray(d.value)
    if amplitudes == "positive":
        cv = np.maximum(cv.real, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.abs(cv) > 0, np.real(dv / np.where(np.abs(cv) > 0, cv, 1)), 0.0)
    shift = np.clip(ratio, -1, 1) * dictionary.delta / 2
    mag = np.abs(cv)
    keep = mag > rel_threshold * max(mag.max(initial=0.0), 1e-300)
    return Echoes(dictionary.taus[keep] + shift[keep], cv[keep], "cbp-taylor", status, iters,
                  time.perf_counter() - t_start, {"lam": lam, "lam_max": lmax})


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
    G = A.conj().T @ A
    if np.linalg.cond(G) < 1e10:  # the normal equations: K x K, much cheaper than an SVD of A
        return np.linalg.solve(G, A.conj().T @ b)
    return np.linalg.lstsq(A, b, rcond=None)[0]


class _VarPro:
    """RSS(taus) = |b - A(taus) a*(taus)|^2 with a* the best amplitudes, and its gradient."""

    def __init__(self, atom, b, mode):
        self.atom, self.b, self.mode = atom, b, mode
        self.evals = 0

    def __call__(self, taus, grad=None):
        self.evals += 1
        want_grad = grad is not None and grad.size
        if self.atom.sampled is not None:
            A, df = self.atom._hermite_both(taus, True, want_grad)
            dA = -df if want_grad else None  # d/dtau f(t - tau) = -f'(t - tau)
        else:
            A, dA = self.atom.matrix(taus), (self.atom.dmatrix(taus) if want_grad else None)
        a = _amplitudes(A, self.b, self.mode)
        r = self.b - A @ a
        if want_grad:
            grad[:] = -2 * np.real(np.conj(a) * (dA.conj().T @ r))
        return float(np.vdot(r, r).real)

    def fit(self, taus0, lo, hi, min_gap=0.0, max_eval=300):
        """Sorted delays in [lo, hi], neighbours at least ``min_gap`` apart, minimising the RSS
        from taus0. The variables are the first delay and the gaps (bounds only, for L-BFGS-B
        style box constraints), so two echoes cannot collapse onto one another into the
        degenerate atom-plus-derivative limit. A roundoff stop keeps the best point found."""
        import nlopt

        taus0 = np.sort(np.asarray(taus0, float))
        k = len(taus0)
        x0 = np.r_[np.clip(taus0[:1], lo, hi), np.maximum(np.diff(taus0), min_gap)]
        best = {"f": np.inf, "x": x0.copy()}

        def obj(x, grad):
            g = np.empty(k) if grad.size else None
            f = self(np.cumsum(x), g)
            if grad.size:
                grad[:] = np.cumsum(g[::-1])[::-1]  # d/dx_j = sum over delays at or after j
            if f < best["f"]:
                best["f"], best["x"] = f, x.copy()
            return f

        opt = nlopt.opt(nlopt.LD_LBFGS, k)
        opt.set_lower_bounds(np.r_[lo, np.full(k - 1, min_gap)])
        opt.set_upper_bounds(np.r_[hi, np.full(k - 1, max(hi - lo, min_gap))])
        opt.set_min_objective(obj)
        opt.set_xtol_abs(1e-4 / self.atom.fs)
        opt.set_ftol_rel(1e-12)
        opt.set_maxeval(max_eval)
        status = "optimal"
        try:
            opt.optimize(x0)
        except nlopt.RoundoffLimited:
            status = "roundoff (best point kept)"
        except Exception as exc:  # noqa: BLE001 - nlopt raises its own runtime_error type
            if not np.isfinite(best["f"]):
                raise RuntimeError(f"cbp-polar: nlopt failed before any finite point ({exc!r})") from exc
            status = f"nlopt {type(exc).__name__} (best point kept)"
        taus = np.cumsum(best["x"])
        a = _amplitudes(self.atom.matrix(taus, fast=True), self.b, self.mode)
        return taus, a, best["f"], status


def _mainlobe_s(atom) -> float:
    """Half-power half-width of the atom's autocorrelation |<f(t), f(t - s)>|, s (cached)."""
    if getattr(atom, "_mainlobe", None) is None:
        step = 1.0 / (8 * atom.fs)
        f0 = atom.matrix([0.0])[:, 0]
        e0 = float(np.vdot(f0, f0).real)
        width = atom.n / atom.fs
        for start in range(1, 8 * atom.n, 64):
            shifts = step * np.arange(start, start + 64)
            acf = np.abs(atom.matrix(shifts).conj().T @ f0)
            below = np.flatnonzero(acf < 0.5 * e0)
            if below.size:
                width = float(shifts[below[0]])
                break
        atom._mainlobe = width
    return atom._mainlobe


def _best_pair(atom, r, centre, half, mode, n_grid=24):
    """The two delays within centre +- half that best explain r by least squares: an exhaustive
    search on a grid of step half / n_grid, in closed form from the grid's Gram matrix."""
    grid = centre + half * np.arange(-n_grid, n_grid + 1) / n_grid
    F = atom.matrix(grid, fast=True)
    G = F.conj().T @ F
    c = F.conj().T @ r
    if mode != "complex":
        G, c = G.real, c.real
    g = np.real(np.diag(G))
    det = g[:, None] * g[None, :] - np.abs(G) ** 2
    num = (g[None, :] * np.abs(c[:, None]) ** 2 + g[:, None] * np.abs(c[None, :]) ** 2
           - 2 * np.real(np.conj(c[:, None]) * G * c[None, :]))
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(det > 1e-9 * np.outer(g, g), num / det, -np.inf)
    gain = np.triu(gain, 1) + np.tril(np.full_like(gain, -np.inf))
    i, j = np.unravel_index(int(np.argmax(gain)), gain.shape)
    return float(grid[i]), float(grid[j])


def _clusters(taus, x, rel, max_groups):
    """Groups of neighbouring active atoms: one seed echo per group (amplitude-weighted delay),
    the ``max_groups`` groups of largest total magnitude, in delay order."""
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
    weight = [mag[g].sum() for g in groups]
    keep = sorted(np.argsort(weight)[::-1][:max_groups])
    return [float(np.average(taus[groups[i]], weights=mag[groups[i]])) for i in keep]


def cbp_polar_refined(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="complex",
                      max_echoes: int = 8, rel_threshold: float = 0.02) -> Echoes:
    """CBP-Polar refined by nlopt, seeded by BPDN; any amplitude model.

    1. BPDN on the grid (lam: given, else :func:`lam_noise`); each run of neighbouring
       active atoms seeds one echo (the ``max_echoes`` strongest runs).
    2. Variable projection: nlopt (L-BFGS, analytic gradient) moves the delays continuously,
       the amplitudes are the least-squares (or NNLS) fit for the delays.
    3. Model order by BIC, n log(RSS / n) + p K log n_e (p = 2 real, 3 complex parameters per
       echo; n_e the real samples one pulse covers, 99 % of its energy): each echo is tried
       split in two about itself (exhaustive pair search); then each echo is tried removed;
       echoes below ``rel_threshold`` of the largest are pruned. Neighbouring delays stay at
       least 1/16 of the matched filter's half-power half-width apart.
    """
    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    atom = dictionary.atom
    if lam is None and lam_frac is None:
        lam = lam_noise(dictionary, b, amplitudes)
    # the seed only needs the support: a loose gap is enough
    seed = bpdn(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, tol=1e-3, max_inner=5000)
    taus0 = _clusters(dictionary.taus, seed.x, rel_threshold, max_echoes)
    info = {"lam": seed.lam, "seed_echoes": len(taus0), "bpdn_time_s": seed.time_s}
    if not taus0:
        return Echoes([], [], "cbp-polar", "optimal", 0, time.perf_counter() - t_start, info)
    n_real = atom.n * (2 if amplitudes == "complex" else 1)
    p = 3 if amplitudes == "complex" else 2
    # an echo's parameters are informed by the samples its pulse covers, not the whole window
    f0 = np.abs(atom.matrix([0.0])[:, 0]) ** 2
    n_eff = int(np.searchsorted(np.cumsum(np.sort(f0)[::-1]), 0.99 * f0.sum()) + 1)
    penalty = p * np.log(n_eff * (2 if amplitudes == "complex" else 1))
    t_lo, t_hi = dictionary.taus[0] - dictionary.delta, dictionary.taus[-1] + dictionary.delta
    vp = _VarPro(atom, b, amplitudes)

    def bic(rss, k):
        return n_real * np.log(max(rss, 1e-300) / n_real) + penalty * k

    half = _mainlobe_s(atom)
    min_gap = half / 16

    def fit(taus):
        return vp.fit(taus, t_lo, t_hi, min_gap)

    taus, a, rss, status = fit(taus0)
    score = bic(rss, len(taus))
    improved = True
    while improved and len(taus) < max_echoes:
        improved = False
        best = None
        for k in range(len(taus)):
            # split echo k: the best pair (exhaustive search) for what the others leave over
            others = np.delete(np.arange(len(taus)), k)
            r = b - atom.matrix(taus[others], fast=True) @ a[others] if others.size else b
            trial = np.r_[taus[others], _best_pair(atom, r, taus[k], half, amplitudes)]
            t2, a2, rss2, st2 = fit(trial)
            s2 = bic(rss2, len(t2))
            if s2 < score - 1e-9 and (best is None or s2 < best[0]):
                best = (s2, t2, a2, rss2, st2)
        if best is not None:
            score, taus, a, rss, status = best
            improved = True
    # backward: drop the echo whose removal improves the BIC most, while one does
    while len(taus) > 1:
        best = None
        for k in range(len(taus)):
            t2, a2, rss2, st2 = fit(np.delete(taus, k))
            s2 = bic(rss2, len(t2))
            if s2 < score - 1e-9 and (best is None or s2 < best[0]):
                best = (s2, t2, a2, rss2, st2)
        if best is None:
            break
        score, taus, a, rss, status = best
    # prune the negligible, refit
    while len(taus) > 1:
        small = np.flatnonzero(np.abs(a) < rel_threshold * np.abs(a).max())
        if not small.size:
            break
        taus, a, rss, status = fit(np.delete(taus, small[0]))
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
        Absolute lam, or a fraction of lam_max; default :func:`clsas.sparse.lam_noise`, the
        noise level estimated from the signal.
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
        lam = lam_noise(d, x, amplitudes)
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
