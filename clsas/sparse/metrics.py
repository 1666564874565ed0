"""Echo lists, the paper's error (eq. 5) with optimal matching, success and RMSE, and the
Cramer-Rao bound for K echoes of a known atom in white noise."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from .. import validate as v

__all__ = ["Echoes", "DelayError", "delay_error", "crb_delays"]


@dataclass
class Echoes:
    """Echoes found in one signal: delays (s) and amplitudes (real or complex), plus how.

    ``status`` says how the solver ended (``"optimal"``, ``"roundoff (best point kept)"``, ...;
    ``"fallback: <reason>"`` where the method failed on this signal). ``fallback`` is True where
    the sparse method failed and the recording was imaged by its matched filter instead (then
    there are no echoes). ``capped`` is True where the method had more echoes than its
    ``max_echoes`` and kept the strongest.

    Parameters
    ----------
    delays_s : numpy.ndarray
        (k,) delays, s.
    amplitudes : numpy.ndarray
        (k,) amplitudes (real or complex), in the signal's units.
    method, status : str
        The method that found them and how it ended.
    iterations : int
        Solver iterations.
    time_s : float
        Wall time, s.
    info : dict
        Method-specific details.
    fallback, capped : bool
        See above.

    Examples
    --------
    >>> import numpy as np
    >>> from clsas.sparse import Echoes
    >>> truth = Echoes(np.array([1.0e-3, 1.06e-3]), np.array([1.0, 0.8]))
    >>> truth.delays_s.size
    2
    """

    delays_s: np.ndarray
    amplitudes: np.ndarray
    method: str = ""
    status: str = "optimal"
    iterations: int = 0
    time_s: float = 0.0
    info: dict = field(default_factory=dict)
    fallback: bool = False
    capped: bool = False

    def __post_init__(self):
        self.delays_s = np.atleast_1d(np.asarray(self.delays_s, float))
        self.amplitudes = np.atleast_1d(np.asarray(self.amplitudes))
        if self.delays_s.shape != self.amplitudes.shape:
            raise ValueError("delays_s and amplitudes must have the same length")
        order = np.argsort(self.delays_s)
        self.delays_s, self.amplitudes = self.delays_s[order], self.amplitudes[order]

    def __len__(self) -> int:
        return len(self.delays_s)

    def signal(self, atom) -> np.ndarray:
        """The signal these echoes predict on ``atom``'s sampling grid."""
        if len(self) == 0:
            return np.zeros(atom.n, complex if atom.complex else float)
        return atom.matrix(self.delays_s) @ self.amplitudes


@dataclass
class DelayError:
    """Result of :func:`delay_error`. Units: delays in s, amplitudes in the signal's units."""

    total: float  # eq. 5: sum over matched echoes of (|tau~ - tau| a~)^2 + ||b - b~||^2 (+ penalties)
    delay_term: float  # sum (|tau~ - tau| |a~|)^2 over matched pairs, s^2 x amplitude^2
    fit_term: float  # ||b - b~||^2, amplitude^2
    penalty: float  # (window x |a|)^2 for every unmatched true or estimated echo
    pairs: list  # (index of estimate, index of truth)
    delay_errors_s: np.ndarray  # tau~ - tau of the matched pairs
    success: bool  # every true echo matched within tol_s, and no extra echo
    rmse_s: float  # over the matched pairs (nan if none)


def delay_error(estimate: Echoes, truth: Echoes, signal=None, atom=None, *, tol_s: float | None = None,
                window_s: float | None = None) -> DelayError:
    """The paper's error (eq. 5) with the optimal (Hungarian) matching of estimated to true delays.

    ``signal`` (the measured b) and ``atom`` give the fit term ||b - b~||^2; without them it is 0.
    One without the other is refused.
    When the counts differ, each unmatched echo adds ``(window_s |a|)^2``, the delay term of an
    echo placed a whole window away (``window_s`` defaults to the atom's window, else the span
    of all delays). ``success`` needs every true echo matched within ``tol_s`` and no extra one.

    Parameters
    ----------
    estimate, truth : Echoes
        The estimated and the true echoes.
    signal : numpy.ndarray, optional
        The measured signal, for the fit term (with ``atom``).
    atom : Atom or numpy.ndarray, optional
        The pulse, for the fit term (with ``signal``).
    tol_s : float, optional
        A true echo is found when an estimate is within this, s.
    window_s : float, optional
        The window length of the count penalty, s.

    Returns
    -------
    DelayError
        The error, its delay and fit terms, the matching, ``success`` and the RMSE.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> from clsas.sparse import Echoes
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.2)
    >>> x = np.zeros(600)
    >>> x[100:100 + chirp.size] += chirp                   # two echoes 6 samples apart
    >>> x[106:106 + chirp.size] += 0.8 * chirp
    >>> x += 0.05 * np.random.default_rng(0).standard_normal(x.size)
    >>> echoes = clsas.superres(x, chirp, fs)            # CBP-Polar, complex amplitudes
    >>> truth = Echoes(np.array([100, 106]) / fs, np.array([1.0, 0.8]))
    >>> bool(clsas.delay_error(echoes, truth, tol_s=0.25 / 10e3).success)
    True
    """
    _refuse_one_of_signal_and_atom(signal, atom)
    est_t, tru_t = estimate.delays_s, truth.delays_s
    window_s = _count_window(window_s, atom, est_t, tru_t)
    pairs = _optimal_pairs(est_t, tru_t)
    d = np.array([est_t[i] - tru_t[j] for i, j in pairs])
    delay_term = float(sum((abs(est_t[i] - tru_t[j]) * abs(estimate.amplitudes[i])) ** 2 for i, j in pairs))
    penalty = _count_penalty(estimate, truth, pairs, window_s)
    fit = 0.0
    if signal is not None and atom is not None:
        fit = float(np.sum(np.abs(np.asarray(signal) - estimate.signal(atom)) ** 2))
    tol = np.inf if tol_s is None else v.positive("tol_s", tol_s)
    success = (len(est_t) == len(tru_t)) and bool(np.all(np.abs(d) <= tol)) if len(tru_t) else len(est_t) == 0
    rmse = float(np.sqrt(np.mean(d**2))) if d.size else float("nan")
    return DelayError(delay_term + fit + penalty, delay_term, fit, penalty, pairs, d, success, rmse)


def _refuse_one_of_signal_and_atom(signal, atom) -> None:
    """The fit term needs both the measured signal and the atom, or neither."""
    if (signal is None) != (atom is None):
        given, missing = ("signal", "atom") if atom is None else ("atom", "signal")
        raise ValueError(f"delay_error: {given} was given without {missing}; the fit term ||b - b~||^2 needs "
                         "both (the measured signal and the atom that models it), or neither")


def _count_window(window_s: float | None, atom, est_t: np.ndarray, tru_t: np.ndarray) -> float:
    """The window of the count penalty, s: ``window_s``, else the atom's window, else the span of all delays."""
    if window_s is not None:
        return window_s
    if atom is not None:
        return atom.n / atom.fs
    allt = np.r_[est_t, tru_t]
    return float(np.ptp(allt)) if allt.size else 0.0


def _optimal_pairs(est_t: np.ndarray, tru_t: np.ndarray) -> list[tuple[int, int]]:
    """``(estimate, truth)`` index pairs of the matching with the least total delay difference (Hungarian)."""
    if not (len(est_t) and len(tru_t)):
        return []
    rows, cols = scipy.optimize.linear_sum_assignment(np.abs(est_t[:, None] - tru_t[None, :]))
    return list(zip(rows.tolist(), cols.tolist(), strict=True))


def _count_penalty(estimate: Echoes, truth: Echoes, pairs: list, window_s: float) -> float:
    """``(window_s |a|)^2`` summed over the echoes of either list left unmatched by ``pairs``."""
    un_est = set(range(len(estimate.delays_s))) - {i for i, _ in pairs}
    un_tru = set(range(len(truth.delays_s))) - {j for _, j in pairs}
    return float(sum((window_s * abs(estimate.amplitudes[i])) ** 2 for i in un_est)
                 + sum((window_s * abs(truth.amplitudes[j])) ** 2 for j in un_tru))


def crb_delays(atom, delays_s, amplitudes, noise_sigma: float) -> np.ndarray:
    """Cramer-Rao bound (s^2) on each delay of K echoes of ``atom`` in white noise.

    Real atom: parameters (tau_k, a_k), noise N(0, sigma^2) per sample. Complex (analytic) atom:
    parameters (tau_k, Re a_k, Im a_k), the unknown-phase case, circular noise with
    E|n|^2 = sigma^2 per sample. The bound is the diagonal of the inverse Fisher information.
    """
    sigma = v.positive("noise_sigma", noise_sigma)
    taus = np.atleast_1d(np.asarray(delays_s, float))
    a = np.atleast_1d(np.asarray(amplitudes))
    A, dA = atom.matrix(taus), atom.dmatrix(taus)
    if atom.complex:
        cols = [dA * a[None, :], A, 1j * A]  # d mu / d tau_k, d Re a_k, d Im a_k
        psi = np.concatenate(cols, axis=1)
        fisher = (2 / sigma**2) * np.real(psi.conj().T @ psi)
    else:
        psi = np.concatenate([dA * a[None, :].real, A], axis=1)
        fisher = (1 / sigma**2) * psi.T @ psi
    try:
        inv = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.full(len(taus), np.inf)
    return np.diag(inv)[: len(taus)].copy()
