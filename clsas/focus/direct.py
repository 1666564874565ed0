"""The direct speaker-to-microphone sound: its arrival gives the delay (and c, given distances).

The direct sound travels ``|tx - rx|`` (fixed on a rigid carriage, whatever the hand does) and
arrives ``|tx - rx| / c - t0`` after sample 0. Its arrival, measured to a small fraction of a
sample, therefore gives each recording's true ``t0`` once ``c`` is known; where the
speaker-to-microphone distances differ enough (several microphones), ``c`` and a common ``t0``
together.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..physics.signals import analytic
from ..types.dataset import Dataset

__all__ = ["DirectPath", "direct_arrivals"]

log = logging.getLogger(__name__)


@dataclass
class DirectPath:
    """Arrivals of the direct sound.

    Attributes
    ----------
    found : bool
        The direct sound was detected in enough recordings (``min_fraction``).
    arrival_s : (n_meas,) time of the arrival after sample 0, s (NaN where not detected).
    detected : (n_meas,) bool
    snr_db : (n_meas,) peak of the matched filter in the search window over the RMS outside it, dB.
    distance_m : (n_meas,) ``|tx - rx|`` (stated), m.
    """

    found: bool
    arrival_s: np.ndarray
    detected: np.ndarray
    snr_db: np.ndarray
    distance_m: np.ndarray

    def t0_s(self, c_mps: np.ndarray, fallback_s: np.ndarray) -> np.ndarray:
        """(n_meas,) ``t0`` from the arrivals at ``c_mps``; ``fallback_s`` where not detected
        (shifted by the detected recordings' median correction)."""
        t0 = self.distance_m / c_mps - self.arrival_s
        if not self.detected.any():
            return np.asarray(fallback_s, float).copy()
        shift = float(np.median((t0 - fallback_s)[self.detected]))
        return np.where(self.detected, t0, fallback_s + shift)

    def fit_c(self, min_spread_m: float = 0.02) -> tuple[float, float] | None:
        """``(c, t0)`` from ``arrival = d / c - t0`` over recordings with distances spread by at
        least ``min_spread_m``; None where they do not differ enough."""
        d, a = self.distance_m[self.detected], self.arrival_s[self.detected]
        if len(d) < 3 or np.ptp(d) < min_spread_m:
            return None
        coef, *_ = np.linalg.lstsq(np.c_[d, -np.ones_like(d)], a, rcond=None)
        if coef[0] <= 0:
            return None
        return float(1 / coef[0]), float(coef[1])


def direct_arrivals(ds: Dataset, *, max_delay_s: float = 5e-4, min_snr_db: float = 15.0,
                    min_fraction: float = 0.8, oversample: int = 16) -> DirectPath:
    """Find the direct sound in each recording within ``±max_delay_s`` of where the stated
    ``t0_s`` and ``c_mps`` put it.

    The recording is matched-filtered with the analytic waveform, interpolated ``oversample``
    times (band-limited, by zero padding) and the envelope's peak located by a parabola through
    its three highest samples. Detected where that peak stands ``min_snr_db`` above the filter's
    RMS outside the search window.
    """
    fs = ds.fs_hz
    d = np.linalg.norm(ds.tx_positions - ds.rx_positions, axis=1)
    expect = d / ds.c_per_meas - ds.t0_s  # s after sample 0
    n_wave = len(ds.waveform)
    last = int(np.ceil((expect.max() + max_delay_s) * fs)) + n_wave + 8
    n_seg = int(min(ds.n_samples, max(last, 4 * n_wave)))
    n = 1 << int(np.ceil(np.log2(n_seg + n_wave)))
    seg = ds.signals[:, :n_seg].astype(np.float64)
    spec = np.fft.fft(seg, n, axis=1) * np.conj(np.fft.fft(analytic(ds.waveform), n))[None, :]
    spec[:, n // 2:] = 0  # the analytic filter keeps positive frequencies only
    # band-limited interpolation: zero-pad the spectrum oversample times
    up = np.zeros((ds.n_meas, n * oversample), np.complex128)
    up[:, : n // 2] = spec[:, : n // 2]
    env = np.abs(np.fft.ifft(up, axis=1))[:, : n_seg * oversample]
    lag_s = np.arange(env.shape[1]) / (fs * oversample)
    arrival = np.full(ds.n_meas, np.nan)
    snr = np.full(ds.n_meas, -np.inf)
    for m in range(ds.n_meas):
        win = np.abs(lag_s - expect[m]) <= max_delay_s
        if not win.any():
            continue
        k = int(np.flatnonzero(win)[np.argmax(env[m, win])])
        out = env[m, ~win]
        rms = float(np.sqrt(np.mean(out**2))) if out.size else 0.0
        snr[m] = 20 * np.log10(env[m, k] / max(rms, 1e-300))
        if 0 < k < env.shape[1] - 1:
            y0, y1, y2 = env[m, k - 1], env[m, k], env[m, k + 1]
            den = y0 - 2 * y1 + y2
            frac = 0.5 * (y0 - y2) / den if den < 0 else 0.0
            arrival[m] = (k + frac) / (fs * oversample)
    detected = np.isfinite(arrival) & (snr >= min_snr_db)
    found = bool(detected.mean() >= min_fraction)
    log.info("direct sound: detected in %d of %d recordings (median %.1f dB)", int(detected.sum()), ds.n_meas,
             float(np.median(snr[np.isfinite(snr)])) if np.isfinite(snr).any() else float("nan"))
    return DirectPath(found, arrival, detected, snr, d)
