"""CBP-Polar refined: BPDN finds the support, then nlopt moves each echo continuously while the
amplitudes are refit (variable projection), splitting, merging and pruning echoes by a
likelihood-ratio test at a stated false-alarm rate. Every delay it tries stays inside the bounds
it is given (the recording's gate), however the data look."""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np

from .. import validate as v
from .atoms import Dictionary, default_max_echoes, pulse_length_s
from .bpdn import ShiftOperator, _check, bpdn, group_atoms
from .metrics import Echoes
from .noise import _threshold, colour_factor, echo_threshold, lam_noise
from .varpro import VarPro, best_pair, delay_bounds, mainlobe_s, real_dof

__all__ = ["cbp_polar_refined", "rss_floor", "RSS_FLOOR"]

RSS_FLOOR = 0.25  # of the noise RSS that lam stands for (see cbp_polar_refined)
log = logging.getLogger(__name__)

def rss_floor(dictionary: Dictionary, lam: float, amplitudes: str) -> float:
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
       n log(RSS / n) + t K (n the noise's real degrees of freedom, :func:`real_dof`; ``n log(RSS0 /
       RSS1)`` is twice the log likelihood ratio of two fits with the noise variance unknown) with
       ``t`` the level that the best of one more echo anywhere in the bounds exceeds on pure noise
       with probability ``false_alarm`` (:func:`clsas.sparse.noise.echo_threshold`, the Rice formula
       over the bounds' span). So an echo is added only where its likelihood ratio passes that test
       and kept only while it still does. The three echoes whose pulses leave the most residual
       energy are tried split in two about themselves (exhaustive pair search), and one echo is
       tried added where the residual correlates most with an atom, up to ``max_echoes``; then each
       echo is tried removed (the three that cost the least with only the amplitudes refit are refit
       in full); echoes below ``rel_threshold`` of the largest are pruned. Before the backward pass
       the test's ``n`` is scaled by :func:`clsas.sparse.noise.colour_factor` (at most 1), read from
       what the forward search leaves: noise coloured into the atoms' band inflates every spurious
       echo's likelihood ratio, and this takes the inflation back. The score counts no residual
       below a quarter of the noise RSS that ``lam`` stands for (a noise-free signal is not fitted
       down to rounding errors).

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
    max_echoes = default_max_echoes(dictionary) if max_echoes is None else v.positive_int("max_echoes", max_echoes)
    t_lo, t_hi = delay_bounds(dictionary, bounds_s)
    # each echo must pass a likelihood-ratio test at the stated false-alarm rate (validated up front)
    penalty = echo_threshold(dictionary.atom, t_hi - t_lo, amplitudes, false_alarm=false_alarm)
    seed, taus0, n_seeds = _bpdn_seeds(dictionary, b, lam, lam_frac, amplitudes, real_signal, rel_threshold,
                                       max_echoes)
    info = {"lam": seed.lam, "seed_echoes": n_seeds, "bpdn_time_s": seed.time_s, "max_echoes": max_echoes,
            "bounds_s": (t_lo, t_hi), "order_threshold": penalty}
    if not len(taus0):
        return Echoes([], [], "cbp-polar", "optimal", 0, time.perf_counter() - t_start, info)
    search = _OrderSearch(dictionary, b, amplitudes, real_signal, (t_lo, t_hi), penalty, mainlobe_s(dictionary.atom),
                          rss_floor(dictionary, seed.lam, amplitudes))
    info["rss_floor"] = search.floor
    (taus, a, rss, status), capped, info["colour_factor"] = search.run(taus0, max_echoes, n_seeds > max_echoes,
                                                                       rel_threshold)
    if not (np.all(np.isfinite(taus)) and np.all(np.isfinite(a))):
        raise FloatingPointError("cbp-polar: non-finite result")
    info.update(rss=rss, score=search.score_of(rss, len(taus)), evaluations=search.vp.evals)
    return Echoes(taus, a, "cbp-polar", status, search.vp.evals, time.perf_counter() - t_start, info, capped=capped)


def _bpdn_seeds(dictionary: Dictionary, b: np.ndarray, lam, lam_frac, amplitudes: str, real_signal: bool,
                rel_threshold: float, max_echoes: int):
    """BPDN's answer on the grid (lam: given, else :func:`lam_noise`), the sorted delays of the
    ``max_echoes`` strongest runs of neighbouring active atoms (one echo each), and the number of runs."""
    if lam is None and lam_frac is None:
        lam = lam_noise(dictionary, b, amplitudes)
    # the seed only needs the support: a loose gap is enough
    seed = bpdn(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, tol=1e-3, max_inner=5000,
                real_signal=real_signal)
    delays, _, weight = group_atoms(dictionary, seed.x, rel_threshold=rel_threshold)
    return seed, np.sort(delays[np.argsort(weight)[::-1][:max_echoes]]), len(delays)


class _OrderSearch:
    """The model-order search of :func:`cbp_polar_refined` on one profile ``b``: the full and the
    amplitude-only fits, the order test's score, and its stages (cancelling seeds dropped, the
    forward search, the test rescaled for coloured noise, the backward pass, the pruning). A fit
    is the tuple ``(taus, amplitudes, rss, status)`` of :meth:`VarPro.fit`. Neighbouring delays
    stay at least 1/16 of the matched filter's half-power half-width apart; a trial fit that fails
    is skipped, and so is one whose echoes hold more than four times the signal's energy
    (cancelling pairs)."""

    def __init__(self, dictionary: Dictionary, b: np.ndarray, amplitudes: str, real_signal: bool,
                 bounds: tuple[float, float], penalty: float, half: float, floor: float):
        atom = dictionary.atom
        self.dictionary, self.atom, self.b, self.amplitudes = dictionary, atom, b, amplitudes
        self.t_lo, self.t_hi = bounds
        self.penalty, self.half, self.floor = penalty, half, floor
        self.n_real = real_dof(b, amplitudes, real_signal)
        self.pulse_n = max(1, int(round(pulse_length_s(atom) * atom.fs)))
        self.vp = VarPro(atom, b, amplitudes, real_signal)
        self.min_gap = half / 16
        self.energy_cap = 4.0 * float(np.vdot(b, b).real)
        self.n_dof = float(self.n_real)  # the order test's degrees of freedom: n_real, less for coloured noise
        self.op = ShiftOperator(dictionary)
        self.in_bounds = (dictionary.taus >= self.t_lo) & (dictionary.taus <= self.t_hi)

    def run(self, taus0: np.ndarray, max_echoes: int, capped: bool, rel_threshold: float):
        """The stages from the seeds ``taus0``: the fit without cancelling seeds, the forward
        search (``capped``: set where it reaches ``max_echoes``), the test rescaled for coloured
        noise, the backward pass and the pruning; returns the fit, ``capped`` and the colour factor."""
        fitted = self.drop_cancelling(self.fit(taus0))
        fitted, capped = self.forward(fitted, max_echoes, capped)
        kappa = self.recolour(fitted)
        return self.prune(self.backward(fitted), rel_threshold), capped, kappa

    def score_of(self, rss: float, k: int) -> float:
        return self.n_dof * np.log(max(rss, self.floor) / self.n_real) + self.penalty * k

    def fit(self, taus):
        return self.vp.fit(taus, self.t_lo, self.t_hi, self.min_gap)

    def rss_at(self, taus) -> float:  # the amplitudes refit, the delays kept
        return self.vp.rss(np.clip(np.sort(taus), self.t_lo, self.t_hi))

    def energy(self, amps) -> float:
        return float(np.sum(np.abs(amps) ** 2)) * self.atom.norm**2

    def best_of(self, trials, score: float, n_try: int = 3):
        """The trial with the lowest score below ``score`` as ``(score, taus, a, rss, status)``, or
        None. The trials are ranked by their score with only the amplitudes refit; the ``n_try``
        best are fitted in full (each full fit costs ~100 RSS evaluations); failed fits are skipped."""
        trials = list(trials)
        approx = [self.score_of(self.rss_at(t), len(t)) for t in trials]
        best = None
        for i in np.argsort(approx, kind="stable")[:n_try]:
            trial = trials[i]
            try:
                t2, a2, rss2, st2 = self.fit(trial)
            except RuntimeError as exc:
                log.debug("cbp-polar: a trial fit failed (%s)", exc)
                continue
            if self.energy(a2) > self.energy_cap:
                continue  # cancelling pairs: echoes far stronger than the signal they explain
            s2 = self.score_of(rss2, len(t2))
            if s2 < score - 1e-9 and (best is None or s2 < best[0]):
                best = (s2, t2, a2, rss2, st2)
        return best

    def splits(self, taus, a, n_try: int = 3):
        """Each echo split in two, for the ``n_try`` echoes whose pulses leave the most residual
        energy (the others' splits would rarely win, and each costs a pair search)."""
        atom, b = self.atom, self.b
        A = atom.matrix(taus, fast=True)
        resid = np.abs(b - A @ a) ** 2
        start = np.clip(np.round(taus * atom.fs).astype(int), 0, atom.n - 1)
        csum = np.r_[0.0, np.cumsum(resid)]
        local = csum[np.minimum(start + self.pulse_n, atom.n)] - csum[start]
        for k in np.sort(np.argsort(local, kind="stable")[::-1][:n_try]):
            # split echo k: the best pair (exhaustive search) for what the others leave over
            others = np.delete(np.arange(len(taus)), k)
            r = b - A[:, others] @ a[others] if others.size else b
            yield np.r_[taus[others], best_pair(atom, r, taus[k], self.half, self.amplitudes)]

    def additions(self, taus, a):
        """One more echo where the residual correlates most with an atom (an echo the seeds
        missed, away from every echo found, which no split reaches)."""
        g = self.op.adjoint(self.b - self.atom.matrix(taus, fast=True) @ a)
        score_g = np.where(self.in_bounds, g.real if self.amplitudes == "positive" else np.abs(g), -np.inf)
        cand = self.dictionary.taus[int(np.argmax(score_g))]
        if np.isfinite(score_g.max()) and np.min(np.abs(taus - cand)) > self.half:
            yield np.r_[taus, cand]

    def drop_cancelling(self, fitted):
        """Seeds that fit as cancelling pairs: drop the echo the fit misses least, until they do not."""
        taus, a, rss, status = fitted
        while len(taus) > 1 and self.energy(a) > self.energy_cap:
            taus, a, rss, status = min((self.fit(np.delete(taus, k)) for k in range(len(taus))), key=lambda f: f[2])
        return taus, a, rss, status

    def forward(self, fitted, max_echoes: int, capped: bool):
        """Splits and additions while one passes the order test, up to ``max_echoes``; returns
        the fit and ``capped`` (also set when the search reached ``max_echoes``)."""
        taus, a, rss, status = fitted
        score = self.score_of(rss, len(taus))
        while len(taus) < max_echoes:
            best = self.best_of(itertools.chain(self.splits(taus, a), self.additions(taus, a)), score)
            if best is None:
                break
            score, taus, a, rss, status = best
            capped = capped or len(taus) >= max_echoes
        return (taus, a, rss, status), capped

    def recolour(self, fitted) -> float:
        """Noise coloured into the atoms' band: read from what the model leaves (every echo it
        has found removed, so echoes cannot pass for noise), the test scaled for it. Returns the
        factor (at most 1)."""
        taus, _, rss, _ = fitted
        kappa = colour_factor(self.dictionary, self.b, self.atom.matrix(taus), rss, self.n_real, self.amplitudes)
        self.n_dof = kappa * self.n_real
        return kappa

    def backward(self, fitted):
        """Drop the echo whose removal improves the score most, while one does."""
        taus, a, rss, status = fitted
        score = self.score_of(rss, len(taus))
        while len(taus) > 1:
            best = self.best_of((np.delete(taus, k) for k in range(len(taus))), score)
            if best is None:
                break
            score, taus, a, rss, status = best
        return taus, a, rss, status

    def prune(self, fitted, rel_threshold: float):
        """Echoes below ``rel_threshold`` of the largest removed one at a time, each time refit."""
        taus, a, rss, status = fitted
        while len(taus) > 1:
            small = np.flatnonzero(np.abs(a) < rel_threshold * np.abs(a).max())
            if not small.size:
                break
            taus, a, rss, status = self.fit(np.delete(taus, small[0]))
        return taus, a, rss, status
