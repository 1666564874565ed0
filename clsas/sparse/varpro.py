"""The variable-projection fit of echo delays: for given delays the amplitudes are the
least-squares (or NNLS) fit, and the residual's energy is minimised over the delays alone
(nlopt's L-BFGS with the analytic gradient), every delay kept inside a gate. Shared by
CBP-Polar refined, the echo detector and the benchmarks' oracle fits; also the helpers around
it (the atom's main-lobe width, the exhaustive two-echo search, the gate, the order test's
degrees of freedom)."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from .atoms import Atom, Dictionary
from .bpdn import real_part_columns, real_part_target

__all__ = ["VarPro", "best_pair", "delay_bounds", "mainlobe_s", "real_dof"]

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


class VarPro:
    """RSS(taus) = |b - A(taus) a*(taus)|^2 with a* the best amplitudes, and its gradient.

    ``real_signal``: ``b`` is the analytic signal of a real recording, and the RSS is that of
    its real part, ``2 |Re(b) - Re(A a)|^2`` (complex amplitudes, real least squares on
    ``[Re a, Im a]``): the analytic RSS in the window's interior, and exact for echoes that the
    window cuts (see :class:`clsas.sparse.bpdn.RealPartOperator`).

    Parameters
    ----------
    atom : Atom
        The echo's shape (its ``matrix`` gives the columns ``A(taus)``, delays in s).
    b : (n_samples,) array
        The signal (analytic for complex amplitudes), in any unit; the RSS is in its unit squared.
    mode : {"positive", "real", "complex"}
        The amplitudes: NNLS for ``"positive"``, else least squares.
    real_signal : bool
        Fit the real part of ``b`` (complex amplitudes only).

    Calling it with delays (and nlopt's gradient array) counts an evaluation (``evals``);
    :meth:`fit` minimises the RSS over sorted delays in a gate, :meth:`rss` evaluates it.
    """

    def __init__(self, atom: Atom, b: np.ndarray, mode: str, real_signal: bool = False):
        self.atom, self.b, self.mode, self.real = atom, b, mode, bool(real_signal)
        self.y = real_part_target(b) if self.real else b
        self.evals = 0

    def fit_columns(self, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(amplitudes, residual) for the atom columns A."""
        if not self.real:
            a = _amplitudes(A, self.b, self.mode)
            return a, self.b - A @ a
        M = real_part_columns(A)
        z = _amplitudes(M, self.y, "real")
        k = A.shape[1]
        return z[:k] + 1j * z[k:], self.y - M @ z

    def __call__(self, taus: np.ndarray, grad: np.ndarray | None = None) -> float:
        """The RSS at ``taus`` (s), the amplitudes refit; ``grad`` (k,) is filled with d RSS / d tau where given."""
        self.evals += 1
        want_grad = grad is not None and grad.size
        if self.atom.sampled is not None:
            A, df = self.atom._hermite_both(taus, True, want_grad, consistent=True)
            dA = -df if want_grad else None  # d/dtau f(t - tau) = -f'(t - tau)
        else:
            A, dA = self.atom.matrix(taus), (self.atom.dmatrix(taus) if want_grad else None)
        a, r = self.fit_columns(A)
        if want_grad:
            if self.real:  # r = sqrt(2) Re(b - A a): d RSS / d tau_k = -2 sqrt(2) Re(a_k dA_k^T r)
                grad[:] = -2 * np.sqrt(2.0) * np.real(a * (dA.T @ r))
            else:
                grad[:] = -2 * np.real(np.conj(a) * (dA.conj().T @ r))
        return float(np.vdot(r, r).real)

    def rss(self, taus: np.ndarray) -> float:
        """The RSS with the amplitudes refit and the delays kept (no evaluation counted)."""
        if not len(taus):
            return float(np.vdot(self.y, self.y).real)
        return float(np.vdot(*(2 * [self.fit_columns(self.atom.matrix(taus, fast=True))[1]])).real)

    def _result(self, taus, status):
        if not len(taus):
            return taus, np.zeros(0), float(np.vdot(self.y, self.y).real), status
        a, r = self.fit_columns(self.atom.matrix(taus, fast=True))
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


def mainlobe_s(atom: Atom) -> float:
    """Half-power half-width of the atom's autocorrelation |<f(t), f(t - s)>|, s (cached on the atom)."""
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


def best_pair(atom: Atom, r: np.ndarray, centre: float, half: float, mode: str,
              n_grid: int = 24) -> tuple[float, float]:
    """The two delays (s) within ``centre +- half`` (s) that best explain the residual ``r``
    (n_samples,) by least squares (real coefficients unless ``mode`` is ``"complex"``): an
    exhaustive search on a grid of step ``half / n_grid``, in closed form from the grid's Gram
    matrix."""
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


def delay_bounds(dictionary: Dictionary, bounds_s: tuple[float, float] | None) -> tuple[float, float]:
    """The gate the delays are kept in, s: ``bounds_s`` (checked: finite, min <= max), else the
    dictionary's first and last delay."""
    if bounds_s is None:
        return float(dictionary.taus[0]), float(dictionary.taus[-1])
    lo, hi = (v.finite("bounds_s", x) for x in bounds_s)
    if hi < lo:
        raise ValueError(f"bounds_s must be (min, max) with min <= max, got {tuple(bounds_s)}")
    return lo, hi


def real_dof(b: np.ndarray, amplitudes: str, real_signal: bool = False) -> int:
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
