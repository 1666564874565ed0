"""Debiasing and detection at fixed delays: echoes found on a grid (BPDN's) with their amplitudes
refit by least squares, then echoes added where the residual says so and dropped where it does
not, each by the likelihood-ratio test at a stated false-alarm rate that CBP-Polar's order step
uses (:func:`clsas.sparse.noise.echo_threshold`). No delay moves: this is the cheap half of
CBP-Polar's model-order search, for BPDN, whose l1 penalty both shrinks the amplitudes and sits
at the first echo's detection threshold, so weak echoes next to strong ones fall under it."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from .atoms import Dictionary
from .bpdn import MODES, ShiftOperator, _check
from .noise import colour_factor, echo_threshold
from .refined import rss_floor
from .varpro import VarPro, delay_bounds, mainlobe_s, real_dof

__all__ = ["detect_echoes"]


def detect_echoes(dictionary: Dictionary, b, delays_s, amplitudes: str = "complex", *, lam: float,
                  false_alarm: float = 0.01, max_echoes: int = 32, bounds_s: tuple[float, float] | None = None,
                  polish_steps: int = 3, real_signal: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """Least-squares amplitudes at ``delays_s`` (polished), then the echo count by likelihood-ratio tests.

    The score ``n log(RSS / n) + t K`` (``n`` the noise's real degrees of freedom, ``K`` echoes, ``t`` =
    :func:`clsas.sparse.noise.echo_threshold` over the bounds' span at ``false_alarm``) is lowered
    one echo at a time: drops, then additions where the residual correlates most with an atom away
    from every echo kept, up to ``max_echoes``, then drops again. An echo is thus kept only while
    its own likelihood ratio against the noise passes the test at the stated rate.

    Parameters
    ----------
    dictionary : Dictionary
        The grid of candidate delays (s) and the atom.
    b : (n_samples,) array
        The signal (analytic for ``amplitudes="complex"``).
    delays_s : (n,) array
        The echoes' delays to start from, s (e.g. BPDN's grouped echoes).
    amplitudes : {"positive", "real", "complex"}
    lam : float
        The lam the delays were found at, in ``b``'s units: the RSS is counted no lower than
        a quarter of the noise RSS that it stands for.
    false_alarm : float
        Chance per profile that pure noise adds an echo, in (0, 1).
    max_echoes : int
        No additions beyond this many echoes.
    bounds_s : (float, float), optional
        Delays searched for additions, s; default the dictionary's span.
    polish_steps : int
        Gauss-Newton steps on the delays per fit, before the amplitudes' least squares (NNLS for
        ``"positive"``): a grid delay a tenth of a sample off leaves a strong echo's residual above
        a weak echo's, which the additions would explain by spurious echoes (0: the delays stay
        where they are given, the additions on the grid).
    real_signal : bool
        ``b`` (complex amplitudes) is the analytic signal of a real recording: every fit is of
        its real part, as :func:`clsas.sparse.refined.cbp_polar_refined` does (exact for echoes
        cut by the window), and the noise has ``n`` real degrees of freedom.

    Returns
    -------
    delays_s, amplitudes : (K,) arrays
        Sorted delays (s) and their least-squares amplitudes (``b``'s units).
    info : dict
        ``order_threshold``, the ``dropped`` and ``added`` counts, the final ``rss``, the noise's
        ``colour_factor``.
    """
    b, taus, lam, max_echoes, real = _checked_inputs(dictionary, b, delays_s, amplitudes, lam, max_echoes,
                                                     polish_steps, real_signal)
    lo, hi = delay_bounds(dictionary, bounds_s)
    t = echo_threshold(dictionary.atom, hi - lo, amplitudes, false_alarm=false_alarm)
    order = _Detector(dictionary, b, amplitudes, real, lam, (lo, hi), t, polish_steps)
    taus, a, rss, n_drop, added = order.search(taus, max_echoes)
    kappa = order.colour_noise(taus, rss)
    if added or kappa < 1:  # the score changed with the noise's degrees of freedom: drop again
        taus, a, rss, _, more = order.drop(taus, a, rss, order.score(rss, len(taus)))
        n_drop += more
    return taus, a, {"order_threshold": t, "dropped": n_drop, "added": added, "rss": rss, "colour_factor": kappa}


def _checked_inputs(dictionary: Dictionary, b, delays_s, amplitudes: str, lam: float, max_echoes: int,
                    polish_steps: int, real_signal: bool) -> tuple[np.ndarray, np.ndarray, float, int, bool]:
    """:func:`detect_echoes`'s inputs checked: ``(b, delays, lam, max_echoes, real)``, ``real``
    where the fits are of ``b``'s real part."""
    v.choice("amplitudes", amplitudes, MODES)
    b = _check(dictionary, b, amplitudes)
    taus = v.array("delays_s", np.asarray(delays_s, float).reshape(-1), ndim=1)
    lam = v.non_negative("lam", lam)
    max_echoes = v.positive_int("max_echoes", max_echoes)
    if isinstance(polish_steps, bool) or not isinstance(polish_steps, (int, np.integer)) or polish_steps < 0:
        raise ValueError(f"polish_steps must be an integer >= 0, got {polish_steps!r}")
    if not isinstance(real_signal, (bool, np.bool_)):
        raise TypeError(f"real_signal must be True or False, got {real_signal!r}")
    return b, taus, lam, max_echoes, bool(real_signal) and amplitudes == "complex"


class _Detector:
    """The fits and stages of :func:`detect_echoes` on one profile ``b``: a fit polishes the
    delays (Gauss-Newton) and refits the amplitudes, returning ``(taus, amplitudes, rss)``; the
    score is the order test's; :meth:`drop` and :meth:`add` lower it one echo at a time."""

    def __init__(self, dictionary: Dictionary, b: np.ndarray, amplitudes: str, real: bool, lam: float,
                 bounds: tuple[float, float], t: float, polish_steps: int):
        atom = dictionary.atom
        self.dictionary, self.atom, self.b, self.amplitudes = dictionary, atom, b, amplitudes
        self.lo, self.hi = bounds
        self.t, self.polish_steps = t, polish_steps
        self.n_real = real_dof(b, amplitudes, real)
        self.vp = VarPro(atom, b, amplitudes, real)  # the fits, CBP-Polar's (the real part where ``real``)
        # the polish's joint fit of atoms and derivative atoms: unconstrained least squares
        self.joint = VarPro(atom, b, "complex" if amplitudes == "complex" else "real", real)
        self.floor = rss_floor(dictionary, lam, amplitudes) if lam > 0 else 1e-300
        self.half = mainlobe_s(atom)
        self.step_max = 0.25 * self.half
        self.n_dof = float(self.n_real)  # less for coloured noise (colour_factor, set after the first fit)
        self.op = ShiftOperator(dictionary)
        self.in_bounds = (dictionary.taus >= self.lo) & (dictionary.taus <= self.hi)

    def polish(self, ts: np.ndarray) -> np.ndarray:
        """Up to ``polish_steps`` Gauss-Newton steps on the delays ``ts``: each echo's atom and
        its derivative atom fitted together, the delay moved by their ratio, at most a quarter of
        the matched filter's half-power half-width per step."""
        atom = self.atom
        for _ in range(self.polish_steps):
            A, D = atom.matrix(ts, fast=True), atom.dmatrix(ts, fast=True)
            coef = self.joint.fit_columns(np.hstack([A, D]))[0]
            amp, dd = coef[: len(ts)], coef[len(ts):]
            step = np.zeros(len(ts))
            ok = np.abs(amp) > 0
            step[ok] = np.real(dd[ok] / amp[ok])
            ts = np.sort(np.clip(ts + np.clip(step, -self.step_max, self.step_max), self.lo, self.hi))
            if np.max(np.abs(step)) < 1e-4 / atom.fs:
                break
        return ts

    def fit(self, ts):
        if not len(ts):
            return ts, np.zeros(0, complex if self.amplitudes == "complex" else float), self.vp.rss(ts)
        ts = self.polish(np.sort(ts))
        a, r = self.vp.fit_columns(self.atom.matrix(ts, fast=True))
        return ts, a, float(np.vdot(r, r).real)

    def score(self, rss: float, k: int) -> float:
        return self.n_dof * np.log(max(rss, self.floor) / self.n_real) + self.t * k

    def search(self, taus: np.ndarray, max_echoes: int):
        """The order search from the delays ``taus``: drops, then additions up to ``max_echoes``;
        returns the fit ``(taus, amplitudes, rss)`` and the numbers dropped and added."""
        fitted = self.fit(taus)
        cur = self.score(fitted[2], len(fitted[0]))
        *fitted, cur, n_drop = self.drop(*fitted, cur)
        *fitted, cur, added = self.add(*fitted, cur, max_echoes)
        return *fitted, n_drop, added

    def colour_noise(self, taus: np.ndarray, rss: float) -> float:
        """The noise coloured into the atoms' band, read from what the model at ``taus`` leaves
        (CBP-Polar's rule): sets the score's degrees of freedom and returns the colour factor."""
        kappa = colour_factor(self.dictionary, self.b, self.atom.matrix(taus), rss, self.n_real, self.amplitudes)
        self.n_dof = kappa * self.n_real
        return kappa

    def drop(self, ts, a, rss, cur):
        """Drop the echo whose removal lowers the score most, while one does; returns the fit,
        its score and the number dropped."""
        dropped = 0
        while len(ts):
            best = min((self.fit(np.delete(ts, j)) for j in range(len(ts))),
                       key=lambda f: self.score(f[2], len(f[0])))
            s = self.score(best[2], len(best[0]))
            if s >= cur - 1e-9:
                break
            (ts, a, rss), cur, dropped = best, s, dropped + 1
        return ts, a, rss, cur, dropped

    def add(self, taus, a, rss, cur, max_echoes: int):
        """Add an echo at the grid delay where the residual correlates most with an atom, away
        from every echo kept (more than the matched filter's half-power half-width), while that
        lowers the score, up to ``max_echoes``; returns the fit, its score and the number added."""
        grid, b = self.dictionary.taus, self.b
        added = 0
        while len(taus) < max_echoes:
            g = self.op.adjoint(b - self.atom.matrix(taus, fast=True) @ a if len(taus) else b)
            c = g.real if self.amplitudes == "positive" else np.abs(g)
            free = self.in_bounds.copy()
            for tau in taus:
                free &= np.abs(grid - tau) > self.half
            if not free.any():
                break
            t2, a2, rss2 = self.fit(np.r_[taus, grid[int(np.argmax(np.where(free, c, -np.inf)))]])
            s2 = self.score(rss2, len(t2))
            if s2 >= cur - 1e-9:
                break
            taus, a, rss, cur, added = t2, a2, rss2, s2, added + 1
        return taus, a, rss, cur, added
