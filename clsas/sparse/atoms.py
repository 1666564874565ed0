"""Atoms, shifted-atom dictionaries, Taylor and polar interpolators, coherence (eq. 4).

An :class:`Atom` is a pulse shape f(t) that can be evaluated at any delay on a fixed sampling
grid t_n = n / fs, n = 0..N-1: either a callable (evaluated exactly at t - tau) or a sampled
waveform (shifted by band-limited interpolation: a phase ramp on its spectrum, never by
rounding to whole samples). ``complex=True`` gives the analytic atom (positive frequencies
only), the model for echoes with unknown phase.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import validate as v

__all__ = ["Atom", "absorbed_pulse", "Dictionary", "decaying_exponential", "coherence", "PolarTriple", "pulse_length_s",
           "default_max_echoes", "margin_s", "whole_atoms"]


def decaying_exponential(alpha: float) -> Callable[[np.ndarray], np.ndarray]:
    """The paper's 1-D atom ``1[t >= 0] t exp(-alpha t)`` (section 6), alpha in 1/s."""
    a = v.positive("alpha", alpha)

    def f(t):
        t = np.asarray(t, float)
        return np.where(t >= 0, t * np.exp(-a * np.maximum(t, 0.0)), 0.0)

    f.alpha = a
    return f


class Atom:
    """A pulse shape on the sampling grid ``t_n = n / fs_hz``, n < n_samples.

    Parameters
    ----------
    shape : callable or 1-D array
        ``f(t)`` (t in s, vectorised), or waveform samples starting at t = 0.
    fs_hz : float
        Sample rate of the signals the atom models.
    n_samples : int
        Samples in those signals.
    complex : bool
        Model analytic signals (echoes with unknown phase).
    derivative : callable, optional
        ``f'(t)`` for a callable shape; default a central difference (step 1e-4 / fs).
    centered : bool
        Each delayed atom has its mean over the window removed, as the signal it models had
        (:func:`clsas.superres`'s ``remove_dc``): a pulse with no mean of its own is almost
        unchanged, but one that the window cuts keeps a mean, and removing it from the signal
        alone left a residual that the methods fitted with spurious echoes.
    """

    def __init__(self, shape, fs_hz: float, n_samples: int, *, complex: bool = False, derivative=None,
                 centered: bool = False):
        self.fs = v.positive("fs_hz", fs_hz)
        self.n = v.positive_int("n_samples", n_samples)
        self.complex = bool(complex)
        self.centered = bool(centered)
        self.t = np.arange(self.n) / self.fs
        if callable(shape):
            self._f, self._df = shape, derivative
            self.sampled = None
        else:
            w = v.array("shape", shape, ndim=1)
            if not np.any(w):
                raise ValueError("shape (the atom's waveform) is all zeros")
            self.sampled = w
            # FFT length: the signal window plus the pulse, so no shift inside the window wraps
            m = 1 << int(np.ceil(np.log2(2 * (self.n + len(w)))))
            self._m = m
            spec = np.fft.fft(w, m)
            k = np.fft.fftfreq(m, 1 / self.fs)  # signed frequencies
            if self.complex:
                spec = spec * (2.0 * (k > 0) + 1.0 * (k == 0))
            self._spec, self._freq = spec, k
        self.norm = float(np.linalg.norm(self.matrix(np.array([0.0]))))
        if self.norm == 0:
            raise ValueError("the atom is zero on the sampling grid")

    # -- evaluation ---------------------------------------------------------------------------
    def _analytic_cols(self, cols: np.ndarray) -> np.ndarray:
        import scipy.signal

        return scipy.signal.hilbert(cols, axis=0)

    def matrix(self, taus_s, *, fast: bool = False) -> np.ndarray:
        """(n_samples, K) atoms delayed by ``taus_s`` (s).

        ``fast=True`` (sampled atoms) interpolates a 16x oversampled table of the band-limited
        atom and its derivatives (cubic Hermite) instead of an FFT per column: about 10x faster
        for a few columns, relative error below 1e-6 for a pulse below 0.4 fs.
        """
        taus = np.atleast_1d(np.asarray(taus_s, float))
        if fast and self.sampled is not None:
            return self._hermite(taus, 0)
        if self.sampled is None:
            cols = self._f(self.t[:, None] - taus[None, :])
            return self._center(self._analytic_cols(cols) if self.complex else np.asarray(cols, float))
        ramp = np.exp(-2j * np.pi * np.outer(taus, self._freq))  # (K, m)
        cols = np.fft.ifft(self._spec[None, :] * ramp, axis=1)[:, : self.n].T
        return self._center(cols if self.complex else cols.real)

    def _center(self, cols: np.ndarray) -> np.ndarray:
        return cols - cols.mean(axis=0) if self.centered else cols

    def correlate(self, b: np.ndarray, oversample: int = 4) -> np.ndarray:
        """Correlations ``<atom(tau_j), b>`` at ``tau_j = j / (oversample fs)`` for every j < oversample m.

        One FFT product and a zero-padded inverse FFT (band-limited interpolation): the same
        values as ``matrix(taus).conj().T @ b``, in O(m log m). For a real atom, the analytic
        signal of the correlation (its magnitude is the envelope). Sampled atoms only.
        """
        if self.sampled is None:
            raise ValueError("correlate needs a sampled atom (a waveform), not a function")
        b = v.array("b", b, shape=(self.n,), dtype=None, allow_complex=True)
        if self.centered:  # <P f, b> = <f, P b>
            b = b - b.mean()
        m, big = self._m, oversample * self._m
        k = np.rint(np.fft.fftfreq(m) * m).astype(int)  # signed bin numbers
        z = np.zeros(big, complex)
        z[k % big] = np.conj(self._spec) * np.fft.fft(b, m)
        if not self.complex:
            z[k % big] *= 2.0 * (k > 0) + 1.0 * (k == 0)
        return np.fft.ifft(z) * oversample

    def dmatrix(self, taus_s, *, fast: bool = False) -> np.ndarray:
        """(n_samples, K) derivatives of the delayed atoms with respect to the delay."""
        taus = np.atleast_1d(np.asarray(taus_s, float))
        if fast and self.sampled is not None:
            return -self._hermite(taus, 1)
        if self.sampled is None:
            if self._df is not None:
                cols = -self._df(self.t[:, None] - taus[None, :])
            else:
                h = 1e-4 / self.fs
                cols = (self._f(self.t[:, None] - taus[None, :] - h) - self._f(self.t[:, None] - taus[None, :] + h)) / (
                    2 * h
                )
            return self._center(self._analytic_cols(cols) if self.complex else np.asarray(cols, float))
        ramp = np.exp(-2j * np.pi * np.outer(taus, self._freq)) * (-2j * np.pi * self._freq)[None, :]
        cols = np.fft.ifft(self._spec[None, :] * ramp, axis=1)[:, : self.n].T
        return self._center(cols if self.complex else cols.real)

    _OVERSAMPLE = 16

    def _tables(self):
        """f, f', f'' of the (periodic, band-limited) sampled atom on a grid 16x finer than 1/fs,
        in polyphase order (3, 16, 2 m)."""
        if getattr(self, "_tab", None) is None:
            m, L = self._m, self._OVERSAMPLE
            spec = self._spec.copy()
            half = m // 2
            big = np.zeros(m * L, complex)
            big[:half] = spec[:half]
            big[-half:] = spec[-half:]
            big[half] = big[-half] = 0.5 * spec[half]  # split the Nyquist bin between +/- fs/2
            w = 2j * np.pi * np.fft.fftfreq(m * L, 1 / (self.fs * L))
            tabs = np.stack([np.fft.ifft(big * w**d) * L for d in range(3)])  # (3, m L)
            if not self.complex:
                tabs = tabs.real
            # polyphase: [d, r, q] = table d at point q L + r
            poly = tabs.reshape(3, m, L).transpose(0, 2, 1)
            self._tab = np.ascontiguousarray(np.concatenate([poly, poly], axis=2))  # one period repeated: no wrap
        return self._tab

    def _hermite(self, taus, d):
        return self._hermite_both(taus, d == 0, d == 1)[0 if d == 0 else 1]

    def _hermite_both(self, taus, want_f=True, want_df=True, consistent=False):
        """Cubic Hermite interpolation of the tables at t_n - tau: (f, f') columns.

        ``consistent``: f' is the derivative of the f interpolant itself (one order less
        accurate than the interpolated f' table, about 1e-5 relative), so that a gradient built
        on it is the exact gradient of an objective built on f: L-BFGS's line search otherwise
        meets the 1e-6 disagreement near a minimum and fails ("runtime_error").

        t_n is a whole number of table steps, so the fractional position (and with it the four
        Hermite weights) is one per column; the tables are stored polyphase, (derivative, phase,
        sample), so each column reads a contiguous run of one phase, gathered for all columns at once."""
        poly = self._tables()
        L, m, n = self._OVERSAMPLE, self._m, self.n
        h = 1.0 / (self.fs * L)
        taus = np.atleast_1d(np.asarray(taus, float))
        pos = -taus / h
        j0 = np.floor(pos)
        u = (pos - j0)[:, None]
        u2, u3 = u * u, u * u * u
        w00, w01 = 2 * u3 - 3 * u2 + 1, -2 * u3 + 3 * u2
        w10, w11 = h * (u3 - 2 * u2 + u), h * (u3 - u2)
        q, r = np.divmod(j0.astype(np.int64), L)
        q %= m
        # rows (phase r at sample q + i) and (phase r + 1, i.e. the next table point); n < m and the
        # table holds two periods, so no index wraps
        idx = q[:, None] + np.arange(n)[None, :]  # (K, n)
        r_next = (r + 1) % L
        idx_next = idx + (r + 1 == L)[:, None]
        d_lo, d_hi = (0 if want_f or consistent else 1), (1 if not want_df or consistent else 2)
        a = poly[d_lo:d_hi + 1][:, r[:, None], idx]  # (d, K, n)
        b = poly[d_lo:d_hi + 1][:, r_next[:, None], idx_next]

        def comb(d):  # the Hermite interpolant of derivative d (d and d + 1 in the tables)
            i = d - d_lo
            return (w00 * a[i] + w01 * b[i] + w10 * a[i + 1] + w11 * b[i + 1]).T

        f = self._center(comb(0)) if want_f else None
        if want_df and consistent:  # d/ds of the Hermite interpolant (s = t - tau = (j + u) h)
            df = self._center(((6 * u2 - 6 * u) * (a[0] - b[0]) / h + (3 * u2 - 4 * u + 1) * a[1]
                               + (3 * u2 - 2 * u) * b[1]).T)
        else:
            df = self._center(comb(1)) if want_df else None
        return f, df


@dataclass
class PolarTriple:
    """Polar interpolator of Ekanadham et al. (2011) for one grid spacing.

    The shifts f(t - tau - delta), |delta| <= Delta / 2, lie near an arc of radius ``r`` and
    half-angle ``theta``: f(t - tau - delta) ~ C + r cos(2 theta delta / Delta) U
    + r sin(2 theta delta / Delta) V, with unit vectors U, V and centre C (per atom, columns).
    """

    C: np.ndarray
    U: np.ndarray
    V: np.ndarray
    r: float
    theta: float


class Dictionary:
    """Atoms at delays ``tau_i = tau0 + i * Delta``, i < n_atoms.

    Parameters
    ----------
    atom : Atom
    delta_s : float
        Grid spacing Delta, s.
    tau0_s : float, optional
        First delay (default 0).
    n_atoms : int, optional
        Default: enough to cover the signal window.
    """

    def __init__(self, atom: Atom, delta_s: float, tau0_s: float = 0.0, n_atoms: int | None = None):
        self.atom = atom
        self.delta = v.positive("delta_s", delta_s)
        self.tau0 = v.finite("tau0_s", tau0_s)
        if n_atoms is None:
            n_atoms = int(np.floor((atom.n / atom.fs - self.tau0) / self.delta)) + 1
        self.k = v.positive_int("n_atoms", n_atoms)
        self.taus = self.tau0 + self.delta * np.arange(self.k)

    def matrix(self) -> np.ndarray:
        """(n_samples, n_atoms) shifted atoms."""
        return self.atom.matrix(self.taus)

    def taylor(self) -> tuple[np.ndarray, np.ndarray]:
        """(F, G): the atoms and their delay derivatives scaled by Delta / 2 (CBP-Taylor)."""
        return self.matrix(), (self.delta / 2) * self.atom.dmatrix(self.taus)

    def polar(self) -> PolarTriple:
        """The polar interpolator from the atoms shifted by -Delta/2, 0, +Delta/2."""
        h = self.delta / 2
        fm, f0, fp = self.atom.matrix(self.taus - h), self.atom.matrix(self.taus), self.atom.matrix(self.taus + h)
        d1 = np.median(np.linalg.norm(fp - f0, axis=0))  # chord for the half cell: 2 r sin(theta / 2)
        d2 = np.median(np.linalg.norm(fp - fm, axis=0))  # chord for the cell: 2 r sin(theta)
        cos_half = np.clip(d2 / (2 * d1), -1.0, 1.0)
        theta = float(2 * np.arccos(cos_half))
        if theta < 1e-6:
            raise ValueError(
                f"delta_s={self.delta:g} is too small for a polar interpolator (the shifts do not curve: "
                f"theta={theta:.2g})"
            )
        r = float(d2 / (2 * np.sin(theta)))
        V = (fp - fm) / (2 * r * np.sin(theta))
        U = (f0 - 0.5 * (fp + fm)) / (r * (1 - np.cos(theta)))
        C = f0 - r * U
        return PolarTriple(C, U, V, r, theta)


def coherence(dictionary) -> float:
    """Mutual coherence (eq. 4): the largest ``|<d_k, d_j>| / (|d_k| |d_j|)`` over ``k != j``.

    ``dictionary`` is a :class:`Dictionary` or an (n, K) matrix.

    Parameters
    ----------
    dictionary : Dictionary or numpy.ndarray
        A dictionary of atoms, or an (n, K) matrix whose columns are the atoms.

    Returns
    -------
    float
        Between 0 (orthogonal atoms) and 1.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> clsas.coherence(np.eye(4))
    0.0
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.2)
    >>> D = np.stack([np.roll(np.pad(chirp, (0, 50)), k) for k in range(3)], axis=1)   # 1-sample shifts
    >>> bool(clsas.coherence(D) > 0.5)                   # close atoms are coherent
    True
    """
    D = dictionary.matrix() if isinstance(dictionary, Dictionary) else v.array("dictionary", dictionary, ndim=2)
    if D.shape[1] < 2:
        raise ValueError("dictionary needs at least two atoms for a coherence")
    norms = np.linalg.norm(D, axis=0)
    if np.any(norms == 0):
        raise ValueError("dictionary has an all-zero atom")
    Dn = D / norms
    G = np.abs(Dn.conj().T @ Dn)
    np.fill_diagonal(G, 0.0)
    return float(G.max())


def pulse_length_s(atom: Atom) -> float:
    """The time the atom's energy takes: the fewest samples holding 99 % of it, over fs (cached), s."""
    if getattr(atom, "_pulse_length", None) is None:
        e = np.sort(np.abs(atom.matrix([0.0])[:, 0]) ** 2)[::-1]
        atom._pulse_length = float(np.searchsorted(np.cumsum(e), 0.99 * e.sum()) + 1) / atom.fs
    return atom._pulse_length


def margin_s(atom: Atom, delta_s: float) -> float:
    """The default margin of atoms before a signal's window, s: the pulse length
    (:func:`pulse_length_s`) rounded up to whole grid steps ``delta_s``, so that the grid still
    holds delay 0. An echo that starts up to a pulse before the window is then fitted as one
    truncated echo at its true (negative) delay, not as a swarm of echoes at the window's start."""
    delta = v.positive("delta_s", delta_s)
    return float(np.ceil(pulse_length_s(atom) / delta - 1e-9) * delta)


def whole_atoms(dictionary: Dictionary) -> np.ndarray:
    """(n_atoms,) bool: the atoms whose pulse lies whole inside the window (delay at or after 0
    and at least a pulse length before its end); the noise level is measured on them, since the
    atoms that the window cuts (or a margin before it holds) correlate less with the noise."""
    atom = dictionary.atom
    return (dictionary.taus >= -1e-12 / atom.fs) & (dictionary.taus <= atom.n / atom.fs - pulse_length_s(atom))


def default_max_echoes(dictionary: Dictionary) -> int:
    """The echo cap of one signal: two echoes per pulse length over the dictionary's span of
    delays, at least 8 and at most 32 (a recording's cost grows with it, and clutter or an
    extended target would otherwise add echoes without end)."""
    span = dictionary.taus[-1] - dictionary.taus[0]
    return int(np.clip(np.ceil(2 * span / pulse_length_s(dictionary.atom)), 8, 32))


def absorbed_pulse(pulse, fs_hz: float, path_m: float, *, temperature_c: float = 20.0,
                   humidity_pct: float = 50.0) -> np.ndarray:
    """The pulse after ``path_m`` of air: each frequency attenuated by ISO 9613-1 absorption
    (:func:`clsas.physics.sound.air_absorption_db_per_m`), as :func:`clsas.simulate` applies it
    (``exp(-beta(f) L)``, no delay). Used as an atom (``superres(..., absorbed_pulse(...))``)
    it matches echoes from about that range, which the unabsorbed pulse fits as a pair.

    Parameters
    ----------
    pulse : 1-D array
        The transmitted pulse, sampled at ``fs_hz``.
    path_m : float
        The two-way path (m), e.g. the gate's mean path.
    temperature_c, humidity_pct : float
        The air.
    """
    import scipy.fft

    from ..physics.sound import air_absorption_db_per_m

    x = v.array("pulse", pulse, ndim=1)
    fs = v.positive("fs_hz", fs_hz)
    path = v.non_negative("path_m", path_m)
    n_fft = scipy.fft.next_fast_len(2 * len(x))
    f = scipy.fft.rfftfreq(n_fft, 1 / fs)
    beta = air_absorption_db_per_m(f, temperature_c, humidity_pct) * np.log(10) / 20
    return scipy.fft.irfft(scipy.fft.rfft(x, n_fft) * np.exp(-beta * path), n_fft)[: len(x)]
