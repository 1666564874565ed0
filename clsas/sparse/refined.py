"""CBP-Polar refined: BPDN finds the support, then nlopt moves each echo continuously while the
amplitudes are refit (variable projection), splitting, merging and pruning echoes by the
Bayesian information criterion. Every delay it tries stays inside the bounds it is given (the
recording's gate), however the data look."""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np

from .. import _validate as v
from .atoms import Dictionary, default_max_echoes, pulse_length_s
from .bpdn import ShiftOperator, _check, bpdn, group_atoms, real_part_columns, real_part_target
from .metrics import Echoes
from .noise import _threshold, colour_factor, echo_threshold, lam_noise

__all__ = ["cbp_polar_refined"]

RSS_FLOOR = 0.25  # of the noise RSS that lam stands for (see cbp_polar_refined)
log = logging.getLogger(__name__)

_W_MIN = 1e-9  # lower bound of a slack fraction: 0 would let every weight vanish at once
_NLOPT_STATUS = {1: "optimal", 2: "optimal", 3: "optimal", 4: "optimal", 5: "max_eval (best point kept)",
                 6: "max_time (best point kept)"}


def _amplitudes(A, b, mode):
    if mode == "positive":
        import scipy.optimize

        return scipy.optimize.nnls(A, b)[0]
    import scipy.linalg

    AH = A.conj().T
    G = AH @ A
    try:  # the normal equations: K x K, much cheaper than an SVD of A, while well conditioned
        c, lower = scipy.linalg.cho_factor(G, check_finite=False)
        d = np.abs(np.diag(c))
        if d.min() ** 2 > 1e-10 * d.max() ** 2:
            return scipy.linalg.cho_solve((c, lower), AH @ b, check_finite=False)
    except np.linalg.LinAlgError:
        pass
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _feasible(taus, lo: float, hi: float, min_gap: float) -> tuple[np.ndarray, float]:
    """Sorted delays moved into ``[lo, hi]`` with neighbours at least ``min_gap`` apart.

    Returns the compressed delays ``z_j = tau_j - j min_gap`` (non-decreasing, within
    ``[lo, lo + free]``) and the free length ``free = hi - lo - (k - 1) min_gap``. Where more
    echoes are asked for than fit (``k min_gap`` beyond the gate), the later echo of the
    closest pair is dropped until they fit: fewer echoes, never a failure.
    """
    taus = np.asarray(taus, float)
    taus = np.sort(np.clip(taus[np.isfinite(taus)], lo, hi))
    k_max = int(np.floor((hi - lo) / min_gap + 1e-9)) + 1 if min_gap > 0 else len(taus)
    while len(taus) > k_max:
        j = int(np.argmin(np.diff(taus)))
        taus = np.delete(taus, j + 1)
    k = len(taus)
    free = max(hi - lo - (k - 1) * min_gap, 0.0)
    z = np.maximum.accumulate(np.clip(taus - min_gap * np.arange(k), lo, lo + free))
    return z, free


class _VarPro:
    """RSS(taus) = |b - A(taus) a*(taus)|^2 with a* the best amplitudes, and its gradient.

    ``real_signal``: ``b`` is the analytic signal of a real recording, and the RSS is that of
    its real part, ``2 |Re(b) - Re(A a)|^2`` (complex amplitudes, real least squares on
    ``[Re a, Im a]``): the analytic RSS in the window's interior, and exact for echoes that the
    window cuts (see :class:`clsas.sparse.bpdn.RealPartOperator`)."""

    def __init__(self, atom, b, mode, real_signal: bool = False):
        self.atom, self.b, self.mode, self.real = atom, b, mode, bool(real_signal)
        self.y = real_part_target(b) if self.real else b
        self.evals = 0

    def _fit(self, A):
        """(amplitudes, residual) for the atom columns A."""
        if not self.real:
            a = _amplitudes(A, self.b, self.mode)
            return a, self.b - A @ a
        M = real_part_columns(A)
        z = _amplitudes(M, self.y, "real")
        k = A.shape[1]
        return z[:k] + 1j * z[k:], self.y - M @ z

    def __call__(self, taus, grad=None):
        self.evals += 1
        want_grad = grad is not None and grad.size
        if self.atom.sampled is not None:
            A, df = self.atom._hermite_both(taus, True, want_grad, consistent=True)
            dA = -df if want_grad else None  # d/dtau f(t - tau) = -f'(t - tau)
        else:
            A, dA = self.atom.matrix(taus), (self.atom.dmatrix(taus) if want_grad else None)
        a, r = self._fit(A)
        if want_grad:
            if self.real:  # r = sqrt(2) Re(b - A a): d RSS / d tau_k = -2 sqrt(2) Re(a_k dA_k^T r)
                grad[:] = -2 * np.sqrt(2.0) * np.real(a * (dA.T @ r))
            else:
                grad[:] = -2 * np.real(np.conj(a) * (dA.conj().T @ r))
        return float(np.vdot(r, r).real)

    def rss(self, taus):
        """The RSS with the amplitudes refit and the delays kept (no evaluation counted)."""
        if not len(taus):
            return float(np.vdot(self.y, self.y).real)
        return float(np.vdot(*(2 * [self._fit(self.atom.matrix(taus, fast=True))[1]])).real)

    def _result(self, taus, status):
        if not len(taus):
            return taus, np.zeros(0), float(np.vdot(self.y, self.y).real), status
        a, r = self._fit(self.atom.matrix(taus, fast=True))
        return taus, a, float(np.vdot(r, r).real), status

    def fit(self, taus0, lo: float, hi: float, min_gap: float = 0.0, max_eval: int = 300):
        """Sorted delays in ``[lo, hi]``, neighbours at least ``min_gap`` apart, minimising the
        RSS from ``taus0`` (moved into those bounds first). Returns (taus, amplitudes, rss, status).

        Parametrisation: the k echoes split the free length ``hi - lo - (k - 1) min_gap`` into
        k + 1 slacks (before the first echo, between neighbours beyond the minimum gap, after
        the last), written as normalised weights ``w_i / sum(w)``, each weight in
        ``[1e-9, 1]``. A box in w is exactly the set of sorted delays in the gate with the
        minimum gaps, so L-BFGS (fast here, with its box bounds) cannot leave the gate or
        collapse two echoes into the degenerate atom-plus-derivative limit, and every
        evaluation is of a feasible point. Bounding the first delay and each gap instead does
        not bound their sum (delays left the gate and the next start point fell outside
        nlopt's bounds); SLSQP or MMA take the linear constraints but only approximately at
        the intermediate points, and cost more per step. A roundoff stop or a stalled line
        search keeps the best point; nlopt failing before any finite point raises RuntimeError.
        """
        import nlopt

        z0, free = _feasible(taus0, lo, hi, min_gap)
        k = len(z0)
        offsets = lo + min_gap * np.arange(k)
        if k == 0 or free <= 1e-6 / self.atom.fs:
            return self._result(np.clip(offsets + (z0 - lo), lo, hi), "optimal")
        w0 = np.clip(np.diff(np.r_[lo, z0, lo + free]) / free, _W_MIN, 1.0)

        def taus_of(w):
            return offsets + free * np.cumsum(w[:k]) / w.sum()

        best = {"f": np.inf, "x": w0.copy()}

        def obj(w, grad):
            g = np.empty(k) if grad.size else None
            taus = taus_of(w)
            f = self(taus, g)
            if grad.size:
                s = w.sum()
                tail = np.r_[np.cumsum(g[::-1])[::-1], 0.0]  # sum of g_j over echoes j >= i
                grad[:] = free / s * tail - free * float(g @ np.cumsum(w[:k])) / s**2
            if np.isfinite(f) and f < best["f"]:
                best["f"], best["x"] = f, w.copy()
            return f

        opt = nlopt.opt(nlopt.LD_LBFGS, k + 1)
        opt.set_lower_bounds(np.full(k + 1, _W_MIN))
        opt.set_upper_bounds(np.ones(k + 1))
        opt.set_min_objective(obj)
        opt.set_xtol_abs(1e-4 / (self.atom.fs * free))
        opt.set_ftol_rel(1e-12)
        opt.set_maxeval(max_eval)
        try:
            opt.optimize(w0)
            status = _NLOPT_STATUS.get(opt.last_optimize_result(), f"nlopt result {opt.last_optimize_result()}")
        except nlopt.RoundoffLimited:
            status = "roundoff (best point kept)"
        except Exception as exc:  # noqa: BLE001 - nlopt raises its own runtime_error and invalid_argument types
            name = _nlopt_name(exc)
            if not np.isfinite(best["f"]):
                raise RuntimeError(f"cbp-polar: nlopt {name} before any finite point") from exc
            # L-BFGS's generic failure is its line search finding no descent, typically at a
            # minimum already (a start on the optimum); any other error is reported as such
            status = "stalled (best point kept)" if name == "runtime_error" else f"nlopt {name} (best point kept)"
        return self._result(np.clip(taus_of(best["x"]), lo, hi), status)


def _nlopt_name(exc: BaseException) -> str:
    """``invalid_argument``, ``runtime_error``...: the C++ exception's name where nlopt says it."""
    name = type(exc).__name__
    text = repr(exc)
    for cxx in ("invalid_argument", "runtime_error", "bad_alloc", "forced_stop", "roundoff_limited"):
        if cxx in text:
            return cxx
    return name


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


def _bounds(dictionary, bounds_s):
    if bounds_s is None:
        return float(dictionary.taus[0]), float(dictionary.taus[-1])
    lo, hi = (v.finite("bounds_s", x) for x in bounds_s)
    if hi < lo:
        raise ValueError(f"bounds_s must be (min, max) with min <= max, got {tuple(bounds_s)}")
    return lo, hi


def _real_dof(b: np.ndarray, amplitudes: str, real_signal: bool = False) -> int:
    """The real degrees of freedom of the noise in ``b``, the ``n`` of the order test's
    ``n log(RSS / n)``: one per sample for a real signal; two per sample for a complex one
    (proper complex noise, e.g. I/Q at baseband), but one for an analytic signal (the
    analytic signal of a real recording: no energy at negative frequencies, its imaginary part
    the Hilbert transform of its real part). Counting two there doubled every likelihood ratio,
    and the order test admitted echoes at far more than its stated false-alarm rate.
    ``real_signal``: the real part is what is fitted, one per sample whatever ``b`` holds."""
    n = len(b)
    if real_signal or amplitudes != "complex" or n < 4:
        return n
    power = np.abs(np.fft.fft(b)) ** 2
    negative = float(power[n // 2 + 1:].sum())
    return n if negative <= 1e-6 * float(power.sum()) else 2 * n


def _rss_floor(dictionary: Dictionary, lam: float, amplitudes: str) -> float:
    """``RSS_FLOOR`` (a quarter) of the noise RSS that ``lam`` stands for, in ``b``'s units squared
    (``lam = 2 t s_g``, ``t`` the 1 % threshold of :func:`lam_noise`, ``s_g`` the noise's rms
    correlation with an atom). The order test counts no residual below it, so a noise-free or
    mis-modelled signal is not chased to its rounding errors by cancelling pairs. A quarter, not
    all of it: lam is set above the noise (lam_noise raises its threshold for the scale's
    estimation error), and a floor at the noise RSS itself hid weak echoes (ratio 0.1: their fit
    lowers the RSS by a few per cent, all of it under the floor)."""
    atom = dictionary.atom
    n_real = atom.n * (2 if amplitudes == "complex" else 1)
    s_g = lam / (2 * max(_threshold(dictionary.k, amplitudes, 0.01), 1e-3))
    return max(RSS_FLOOR * n_real * (s_g / ((2.0 if amplitudes == "complex" else 1.0) * atom.norm)) ** 2, 1e-300)


def cbp_polar_refined(dictionary: Dictionary, b, lam=None, *, lam_frac=None, amplitudes="complex",
                      max_echoes: int | None = None, rel_threshold: float = 0.02,
                      bounds_s: tuple[float, float] | None = None, real_signal: bool = False,
                      false_alarm: float = 0.01) -> Echoes:
    """CBP-Polar refined by nlopt, seeded by BPDN; any amplitude model.

    1. BPDN on the grid (lam: given, else :func:`lam_noise`); each run of neighbouring
       active atoms seeds one echo, the ``max_echoes`` strongest runs.
    2. Variable projection: nlopt (L-BFGS, analytic gradient) moves the delays continuously
       within ``bounds_s`` (default the dictionary's span), the amplitudes are the
       least-squares (or NNLS) fit for the delays.
    3. Model order by a likelihood-ratio test at a stated false-alarm rate: the score
       n log(RSS / n) + t K (n the noise's real degrees of freedom, :func:`_real_dof`;
       ``n log(RSS0 / RSS1)`` is twice the log likelihood ratio of two fits with the noise
       variance unknown) with ``t`` the level
       that the best of one more echo anywhere in the bounds exceeds on pure noise with
       probability ``false_alarm`` (:func:`clsas.sparse.noise.echo_threshold`, the Rice
       formula over the bounds' span). So an echo is added only where its likelihood ratio
       passes that test and kept only while it still does. The three echoes whose pulses
       leave the most residual energy are tried split in two about themselves (exhaustive
       pair search), and one echo is tried added where the residual correlates most with
       an atom, up to ``max_echoes``; then each echo is tried removed (the three that cost
       the least with only the amplitudes refit are refit in full); echoes below
       ``rel_threshold`` of the largest are pruned. Before the backward pass the test's ``n``
       is scaled by :func:`clsas.sparse.noise.colour_factor` (at most 1), read from what the
       forward search leaves: noise coloured into the atoms' band inflates every spurious
       echo's likelihood ratio, and this takes the inflation back. (A BIC penalty, p log n_e per echo on the
       samples one pulse covers, was used before: 17.9 for complex amplitudes whatever the
       span, about a 1.3 % rate on a 3.1 ms gate and 0.6 % on a 1.5 ms one, 10.5 for real
       ones, about 40 % on 1.3 ms.)
       Neighbouring delays stay at least 1/16 of the matched filter's half-power half-width
       apart; a trial fit that fails is skipped, and so is one whose echoes hold more than four
       times the signal's energy (cancelling pairs). The score counts no residual below a quarter
       of the noise RSS that ``lam`` stands for (a noise-free signal is not fitted down to rounding errors).

    ``max_echoes`` defaults to :func:`clsas.sparse.atoms.default_max_echoes` (two per pulse
    length over the span); ``capped`` on the result says that the seeds were more than it or
    the forward search (splits and additions) reached it. ``false_alarm`` (default 1 %, the
    rate of :func:`lam_noise`'s first detection) is the chance per profile that the order test
    admits an echo that is not there; raising it finds more weak echoes and more spurious ones.

    ``real_signal=True`` (complex amplitudes): ``b`` is the analytic signal of a real
    recording; BPDN and every fit then fit its real part (the same RSS in the window's interior;
    exact for echoes cut by the window, which the analytic fit models only to -20 to -25 dB,
    so that the order test added echoes to explain the rest), and the noise has ``n`` real
    degrees of freedom.
    """
    t_start = time.perf_counter()
    b = _check(dictionary, b, amplitudes)
    atom = dictionary.atom
    max_echoes = default_max_echoes(dictionary) if max_echoes is None else v.positive_int("max_echoes", max_echoes)
    t_lo, t_hi = _bounds(dictionary, bounds_s)
    # each echo must pass a likelihood-ratio test at the stated false-alarm rate (validated up front)
    penalty = echo_threshold(atom, t_hi - t_lo, amplitudes, false_alarm=false_alarm)
    if lam is None and lam_frac is None:
        lam = lam_noise(dictionary, b, amplitudes)
    # the seed only needs the support: a loose gap is enough
    seed = bpdn(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, tol=1e-3, max_inner=5000,
                real_signal=real_signal)
    half = _mainlobe_s(atom)
    delays, _, weight = group_atoms(dictionary, seed.x, rel_threshold=rel_threshold)
    capped = len(delays) > max_echoes
    taus0 = np.sort(delays[np.argsort(weight)[::-1][:max_echoes]])
    info = {"lam": seed.lam, "seed_echoes": len(delays), "bpdn_time_s": seed.time_s, "max_echoes": max_echoes,
            "bounds_s": (t_lo, t_hi), "order_threshold": penalty}
    if not len(taus0):
        return Echoes([], [], "cbp-polar", "optimal", 0, time.perf_counter() - t_start, info)
    n_real = _real_dof(b, amplitudes, real_signal)
    n_eff = int(round(pulse_length_s(atom) * atom.fs))
    vp = _VarPro(atom, b, amplitudes, real_signal)
    min_gap = half / 16

    rss_floor = _rss_floor(dictionary, seed.lam, amplitudes)
    info["rss_floor"] = rss_floor
    energy_cap = 4.0 * float(np.vdot(b, b).real)

    n_dof = float(n_real)  # the order test's degrees of freedom: n_real, less for coloured noise

    def score_of(rss, k):
        return n_dof * np.log(max(rss, rss_floor) / n_real) + penalty * k

    def fit(taus):
        return vp.fit(taus, t_lo, t_hi, min_gap)

    def rss_at(taus):  # the amplitudes refit, the delays kept
        return vp.rss(np.clip(np.sort(taus), t_lo, t_hi))

    def best_of(trials, score, n_try=3):
        """The trial with the lowest score below ``score``, or None. The trials are ranked by
        their score with only the amplitudes refit; the ``n_try`` best are fitted in full (each
        full fit costs ~100 RSS evaluations); failed fits are skipped."""
        trials = list(trials)
        approx = [score_of(rss_at(t), len(t)) for t in trials]
        best = None
        for i in np.argsort(approx, kind="stable")[:n_try]:
            trial = trials[i]
            try:
                t2, a2, rss2, st2 = fit(trial)
            except RuntimeError as exc:
                log.debug("cbp-polar: a trial fit failed (%s)", exc)
                continue
            if energy(a2) > energy_cap:
                continue  # cancelling pairs: echoes far stronger than the signal they explain
            s2 = score_of(rss2, len(t2))
            if s2 < score - 1e-9 and (best is None or s2 < best[0]):
                best = (s2, t2, a2, rss2, st2)
        return best

    pulse_n = max(1, n_eff)

    def splits(taus, a, n_try=3):
        """Each echo split in two, for the ``n_try`` echoes whose pulses leave the most residual
        energy (the others' splits would rarely win, and each costs a pair search)."""
        A = atom.matrix(taus, fast=True)
        resid = np.abs(b - A @ a) ** 2
        start = np.clip(np.round(taus * atom.fs).astype(int), 0, atom.n - 1)
        csum = np.r_[0.0, np.cumsum(resid)]
        local = csum[np.minimum(start + pulse_n, atom.n)] - csum[start]
        for k in np.sort(np.argsort(local, kind="stable")[::-1][:n_try]):
            # split echo k: the best pair (exhaustive search) for what the others leave over
            others = np.delete(np.arange(len(taus)), k)
            r = b - A[:, others] @ a[others] if others.size else b
            yield np.r_[taus[others], _best_pair(atom, r, taus[k], half, amplitudes)]

    op = ShiftOperator(dictionary)
    in_bounds = (dictionary.taus >= t_lo) & (dictionary.taus <= t_hi)

    def additions(taus, a):
        """One more echo where the residual correlates most with an atom (an echo the seeds
        missed, away from every echo found, which no split reaches)."""
        g = op.adjoint(b - atom.matrix(taus, fast=True) @ a)
        score_g = np.where(in_bounds, g.real if amplitudes == "positive" else np.abs(g), -np.inf)
        cand = dictionary.taus[int(np.argmax(score_g))]
        if np.isfinite(score_g.max()) and np.min(np.abs(taus - cand)) > half:
            yield np.r_[taus, cand]

    taus, a, rss, status = fit(taus0)

    def energy(amps):
        return float(np.sum(np.abs(amps) ** 2)) * atom.norm**2

    # seeds that fit as cancelling pairs: drop the echo the fit misses least, until they do not
    while len(taus) > 1 and energy(a) > energy_cap:
        taus, a, rss, status = min((fit(np.delete(taus, k)) for k in range(len(taus))), key=lambda f: f[2])
    score = score_of(rss, len(taus))
    while len(taus) < max_echoes:
        best = best_of(itertools.chain(splits(taus, a), additions(taus, a)), score)
        if best is None:
            break
        score, taus, a, rss, status = best
        capped = capped or len(taus) >= max_echoes
    # noise coloured into the atoms' band: read from what the model leaves (every echo it has
    # found removed, so echoes cannot pass for noise), the test scaled for it, then the backward pass
    kappa = colour_factor(dictionary, b, atom.matrix(taus), rss, n_real, amplitudes)
    n_dof = kappa * n_real
    info["colour_factor"] = kappa
    score = score_of(rss, len(taus))
    # backward: drop the echo whose removal improves the score most, while one does
    while len(taus) > 1:
        best = best_of((np.delete(taus, k) for k in range(len(taus))), score)
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
    info.update(rss=rss, score=score_of(rss, len(taus)), evaluations=vp.evals)
    return Echoes(taus, a, "cbp-polar", status, vp.evals, time.perf_counter() - t_start, info, capped=capped)
