"""The noise level of a range profile and the BPDN lam it sets: a detection threshold with a
stated false-alarm rate (pure noise gives no echo), from the signal itself or a known sigma."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from .atoms import Dictionary, whole_atoms
from .bpdn import MODES, ShiftOperator, _check, bpdn, lam_max

__all__ = ["colour_factor", "correlation_sigma", "echo_threshold", "lam_noise", "noise_lam", "noise_sigma"]


def noise_sigma(b) -> float:
    """Robust noise level of a signal mostly made of noise: the median absolute value scaled to
    the Gaussian's sigma (real: |n| median 0.6745 sigma; complex circular, E|n|^2 = sigma^2:
    median sqrt(ln 2) sigma). Echoes covering less than half the window barely move it."""
    b = np.asarray(b)
    med = float(np.median(np.abs(b)))
    return med / np.sqrt(np.log(2.0)) if np.iscomplexobj(b) else med / 0.6744897501960817


def _threshold(k: int, amplitudes: str, false_alarm: float) -> float:
    """The multiple ``t`` of the noise's correlation scale that pure noise's largest correlation
    over ``k`` atoms exceeds with probability at most ``false_alarm`` (a union bound: complex
    circular, P(|g| > t s) = exp(-t^2); real two-sided, positive one-sided Gaussian tails)."""
    from scipy.stats import norm

    p = v.positive("false_alarm", false_alarm)
    if p >= 1:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm!r}")
    k = max(int(k), 1)
    if amplitudes == "complex":
        return float(np.sqrt(np.log(k / p))) if k > p else 0.0
    return float(norm.isf(p / (k if amplitudes == "positive" else 2 * k)))


def correlation_sigma(dictionary: Dictionary, b, amplitudes: str = "real") -> float:
    """Robust scale of the noise in the matched filter ``D^H b`` (its rms per atom for complex
    amplitudes, its standard deviation for real ones): the median of ``|D^H b|`` over the atoms
    that lie whole inside the window, scaled to the Gaussian's. The echoes are compressed there
    to a mainlobe each, so they move it far less than they move the samples' median
    (:func:`noise_sigma`), and coloured or analytic noise is measured as the atoms see it."""
    b = _check(dictionary, b, amplitudes)
    g = ShiftOperator(dictionary).adjoint(b)
    whole = whole_atoms(dictionary)
    if np.count_nonzero(whole) >= 8:
        g = g[whole]
    if amplitudes == "complex":
        return float(np.median(np.abs(g)) / np.sqrt(np.log(2.0)))
    return float(np.median(np.abs(g.real)) / 0.6744897501960817)


def _independent(dictionary: Dictionary) -> float:
    """About how many independent values the median in :func:`correlation_sigma` sees: the
    whole-window atoms' span over the pulse's correlation length (``sum |acf|^2 / acf(0)^2``
    in samples, the autocorrelation's equivalent width)."""
    col = dictionary.atom.matrix(np.array([0.0]))[:, 0]
    acf = np.abs(np.fft.ifft(np.abs(np.fft.fft(col, 2 * len(col))) ** 2))
    length = float(np.sum(acf**2) / acf.max() ** 2) if acf.max() > 0 else 1.0
    whole = whole_atoms(dictionary)
    n = np.count_nonzero(whole) if np.count_nonzero(whole) >= 8 else dictionary.k
    return max(n * dictionary.delta * dictionary.atom.fs / max(length, 1.0), 1.0)


def _deflated_sigma(dictionary: Dictionary, b, A: np.ndarray, amplitudes: str) -> float | None:
    """:func:`correlation_sigma` of ``b`` with the span of ``A``'s columns (fitted atoms) removed,
    each atom's correlation rescaled for what the removal took from it: with ``P`` the projector
    off that span, ``a^H P n`` has the variance ``sigma^2 a^H P a``, not ``sigma^2 |a|^2``, so
    ``|a^H P b| / sqrt(a^H P a / |a|^2)`` has pure noise's scale again. Without the rescaling the
    median falls with every atom fitted (twenty atoms in a 1000-sample gate: 0.3-0.5 of the true
    scale) and a noise level read from the residual is too low. Atoms that the span covers by 80 %
    or more are left out; None if fewer than 8 whole atoms remain."""
    op = ShiftOperator(dictionary)
    q, _ = np.linalg.qr(A)
    r = b - q @ (q.conj().T @ b)
    g = op.adjoint(r)
    cover = np.zeros(dictionary.k)
    for col in q.T:
        cover += np.abs(op.adjoint(col)) ** 2
    whole = whole_atoms(dictionary)
    n2 = dictionary.atom.norm ** 2
    keep = whole & (n2 - cover > 0.2 * n2)
    if np.count_nonzero(keep) < 8:
        return None
    z = g[keep] / np.sqrt((n2 - cover[keep]) / n2)
    if amplitudes == "complex":
        return float(np.median(np.abs(z)) / np.sqrt(np.log(2.0)))
    return float(np.median(np.abs(z.real)) / 0.6744897501960817)


def colour_factor(dictionary: Dictionary, b, A: np.ndarray, rss: float, n_real: float, amplitudes: str) -> float:
    """The order test's correction for noise that is not white, at most 1.

    The test reads twice the log likelihood ratio of one more echo as ``n log(RSS0 / RSS1)``:
    the RSS drop over the noise variance per real degree of freedom, ``RSS / n``. An atom sees
    only the noise in its band: where the noise is coloured into that band (a microphone's or
    a sound card's band-pass), the atoms' own variance, read from the residual's correlations
    (:func:`_deflated_sigma`, the fitted echoes ``A`` removed), is larger than ``RSS / n``, and
    each spurious echo's ratio is inflated by their quotient. Returns
    ``kappa = (RSS / n) / (the atoms' variance)``, by which the test's ``n`` is multiplied
    (1 for white noise: the factor 2 for complex amplitudes makes it so, measured 1.04 +- 0.10
    on real recordings fitted by their real part; 1 for real amplitudes). Only a clear excess counts:
    kappa is raised by three standard errors of the median before it is capped at 1, so white
    noise leaves the test as it was, and noise coloured away from the band never loosens it.
    Measured on a 1000-sample profile with noise band-passed to 18-32 kHz (the chirp 20-30 kHz,
    96 kHz): kappa about 0.4 (0.16 before the allowance for the median's error). With noise
    band-passed to 15-35 kHz, CBP-Polar added spurious echoes to two true ones in 52 of 60
    profiles without it and in 5 with it (BPDN + detect: 49 and 5). ``A`` must hold every echo
    the model has found: echoes left in the residual raise the median as coloured noise does
    (ten echoes filling a gate, five of them weak, read as kappa 0.5), so CBP-Polar and
    :func:`clsas.sparse.detect_echoes` read it after their forward search. ``b`` is the
    (analytic) signal and ``rss`` the fit's residual energy over its ``n_real`` real degrees
    of freedom."""
    s = _deflated_sigma(dictionary, b, A, amplitudes) if A.shape[1] else correlation_sigma(dictionary, b, amplitudes)
    if s is None or not np.isfinite(s) or s <= 0 or rss <= 0:
        return 1.0
    c = 2.0 if amplitudes == "complex" else 1.0  # the same 2 for a real recording's real-part fit
    kappa = c * (rss / n_real) * dictionary.atom.norm**2 / s**2
    spread = 0.72 if amplitudes == "complex" else 1.17
    return float(min(1.0, kappa * (1 + 3 * spread / np.sqrt(_independent(dictionary)))))


def lam_noise(dictionary: Dictionary, b, amplitudes: str = "real", *, false_alarm: float = 0.01,
              refine: int = 5, floor: float = 0.01) -> float:
    """lam at the noise level: twice the correlation that pure noise exceeds on any of the K
    atoms with probability at most ``false_alarm`` (default 1 %), so that BPDN keeps echoes
    and drops noise.

    The noise's correlation scale is :func:`correlation_sigma` of ``b``, then (up to ``refine``
    times) of the residual where the signal is not: BPDN at the current lam, the span of its
    atoms removed and each correlation rescaled for what the removal took
    (:func:`_deflated_sigma`), taken while it falls by a tenth or more (usually one to three fits). Echoes whose chirps
    cover most of the window inflate the first estimate many times; the residual's does not.
    Where the first estimate is at or above lam_max (pure noise, or a gate covered by echoes),
    the fit starts at lam_max / 2 and goes on down while the
    residual's level is under the lam it was fitted at: ten echoes filling the gate reach
    their noise level in three or four fits; on pure noise the first residual's level is still
    above lam_max / 2 (the rescaling keeps it near the first estimate), lam stays at or above
    lam_max and the answer is no echo ("nothing here"). The threshold is raised by one
    standard deviation of the median's relative error, ``0.72 / sqrt(n_eff)`` (Rayleigh; 1.17 for
    real and positive amplitudes, half-normal),
    ``n_eff`` the independent correlations in the window (:func:`_independent`): a scale
    estimated from a short window is often low, and pure noise then crossed a threshold set for
    1 % in 2-3 % of profiles. At least ``floor`` x lam_max (a dynamic range of 40 dB by default:
    a noise-free signal, or one the model does not fit (an impulse, a pulse cut by the window),
    is not fitted down to its rounding errors).
    """
    b = _check(dictionary, b, amplitudes)
    lmax = lam_max(ShiftOperator(dictionary), b, amplitudes)
    # the median's relative standard error: 0.72 / sqrt(n) for |complex Gaussian| (Rayleigh),
    # 1.17 / sqrt(n) for |real Gaussian| (half-normal; with 0.72, 1.5-2 % of pure-noise profiles
    # gave an echo for real and positive amplitudes)
    spread = 0.72 if amplitudes == "complex" else 1.17
    t = _threshold(dictionary.k, amplitudes, false_alarm) * (1 + spread / np.sqrt(_independent(dictionary)))
    lam = 2 * correlation_sigma(dictionary, b, amplitudes) * t
    if isinstance(refine, bool) or not isinstance(refine, (int, np.integer)) or refine < 0:
        raise ValueError(f"refine must be an integer >= 0, got {refine!r}")
    lam_floor = v.non_negative("floor", floor) * lmax
    trial, need = lam, 0.9
    if refine and lam >= lmax:  # the gate may be all echoes: go down from lam_max / 2
        trial, need = 0.5 * lmax, 1.0
    for _ in range(int(refine)):
        if trial >= lmax or trial <= lam_floor:  # below the floor the floor is the answer: no fit
            break
        x = bpdn(dictionary, b, trial, amplitudes=amplitudes, tol=1e-3, max_inner=2000).x
        on = np.flatnonzero(x)
        if not on.size or on.size > dictionary.atom.n // 4:
            break
        s = _deflated_sigma(dictionary, b, dictionary.atom.matrix(dictionary.taus[on], fast=True), amplitudes)
        if s is None:
            break
        new = 2 * s * t
        if new >= need * trial:
            break
        lam, trial, need = new, new, 0.9
    return float(max(lam, lam_floor))


def noise_lam(dictionary: Dictionary, sigma: float, amplitudes: str = "real", *, false_alarm: float = 0.01) -> float:
    """lam at a known noise level: ``sigma`` is the standard deviation per sample of the white
    noise in the real recording (for ``amplitudes="complex"`` the signal is its analytic signal,
    whose correlation with an analytic atom ``a`` has rms ``2 sigma |a|``). See :func:`lam_noise`."""
    sigma = v.non_negative("noise_sigma", sigma)
    v.choice("amplitudes", amplitudes, MODES)
    s_g = (2.0 if amplitudes == "complex" else 1.0) * sigma * dictionary.atom.norm
    return float(2 * s_g * _threshold(dictionary.k, amplitudes, false_alarm))


def _spectral_moment(atom, centred: bool) -> float:
    """Second moment of the atom's power spectrum ``|F(w)|^2`` about its mean (``centred``: the
    envelope of a complex correlation) or about zero (a real correlation's own wiggles), rad^2/s^2."""
    col = atom.matrix(np.array([0.0]))[:, 0]
    power = np.abs(np.fft.fft(col, 2 * len(col))) ** 2
    w = 2 * np.pi * np.fft.fftfreq(len(power), 1.0 / atom.fs)
    total = float(power.sum())
    if total == 0:
        return 0.0
    mean = float(w @ power) / total if centred else 0.0
    return float(((w - mean) ** 2) @ power) / total


def echo_threshold(atom, span_s: float, amplitudes: str = "complex", *, false_alarm: float = 0.01) -> float:
    """The likelihood-ratio threshold for one more echo: the level that the largest ``2 log``
    likelihood ratio of one atom, searched over ``span_s`` of delays with its amplitude fitted,
    exceeds on pure white noise with probability ``false_alarm``.

    The statistic at one delay is chi-square (2 degrees of freedom for a complex amplitude, 1 for
    a real one; a positive one is the one-sided half). Its largest value over the span is bounded
    by the Rice formula, the chance at one point plus the expected number of upcrossings: for a
    complex amplitude ``P(max > t) ~ exp(-t/2) (1 + span sqrt(m2 t / 2 pi))``, ``m2`` the second
    moment of the atom's power spectrum about its mean; for a real one ``2 Q(sqrt t) + span
    sqrt(m2) / pi exp(-t/2)`` with ``m2`` about zero (the carrier's wiggles are upcrossings too),
    halved for a positive one. Measured on 1000 pure-noise profiles of the paper's chirp (96 kHz,
    spans 1.5 and 3.1 ms, complex), the formula is within 20 % of the true rate from 1 % to 15 %;
    for real and positive amplitudes it is an upper bound, 1.2-3 times the measured rate (600
    profiles: the carrier's upcrossings come in clusters).
    Dimensionless, in units of ``2 log`` likelihood ratio (``delta RSS / variance per real sample``).

    Parameters
    ----------
    atom : Atom
    span_s : float
        Length of the delays searched, s (0: one known delay).
    amplitudes : {"positive", "real", "complex"}
    false_alarm : float
        Probability in (0, 1) that pure noise passes the threshold.
    """
    from scipy.optimize import brentq
    from scipy.stats import norm

    span = v.non_negative("span_s", span_s)
    v.choice("amplitudes", amplitudes, MODES)
    p = v.positive("false_alarm", false_alarm)
    if p >= 1:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm!r}")
    if amplitudes == "complex":
        m2 = _spectral_moment(atom, centred=True)

        def rate(t):
            return np.exp(-t / 2) * (1 + span * np.sqrt(m2 * t / (2 * np.pi)))
    else:
        m2 = _spectral_moment(atom, centred=False)
        sides = 1.0 if amplitudes == "positive" else 2.0

        def rate(t):
            return sides * (norm.sf(np.sqrt(t)) + span * np.sqrt(m2) / (2 * np.pi) * np.exp(-t / 2))

    if rate(0.0) <= p:
        return 0.0
    hi = 10.0
    while rate(hi) > p:
        hi *= 2
    return float(brentq(lambda t: rate(t) - p, 0.0, hi, xtol=1e-6))
