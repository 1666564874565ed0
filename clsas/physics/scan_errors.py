"""What a hand-held scan gets wrong, for simulations: motion, air, delays (the truth is kept).

:func:`clsas.simulate` takes these errors (``position_error=``, ``temperature_error_c=``,
``group_delay_s=``, ``timing_jitter_s=``), simulates the recordings with the true values and
states the nominal ones in the dataset, as a real scan would; the true values go to
``Dataset.truth`` so that estimates (:func:`clsas.autofocus`) can be scored.

Hand-like motion (:class:`HandMotion`) is a band-limited random 3-D displacement of the
carriage in time (default 0.2-5 Hz: the sway and drift of a hand holding a phone still; the
8-12 Hz tremor is smaller and left out), sampled at each stop's time. The stop time axis is
``stop index * dwell_s``: the dwell is the time between pings (20 ms by default, about the
round trip to 3 m, the earliest the next chirp can go out). The displacement moves speaker and
microphones together (one rigid carriage), so their distance does not change.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .. import validate as v

__all__ = ["HandMotion", "hand_motion", "stop_index"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HandMotion:
    """Band-limited random 3-D motion of the carriage about its stated path.

    Parameters
    ----------
    rms_m : float
        RMS of the displacement, m: of its 3-D length (each axis gets ``rms_m / sqrt(3)``), or of
        each axis with ``per_axis=True``.
    band_hz : (float, float)
        The motion's frequency band, Hz (flat spectrum inside, nothing outside).
    dwell_s : float
        Time from one stop (ping) to the next, s.
    seed : int
        Seed of the motion's random draw.
    per_axis : bool
        ``rms_m`` is the RMS of each axis rather than of the 3-D length.
    weights : (float, float, float)
        Relative RMS of x, y and z (e.g. ``(1, 1, 0)`` for motion in the aperture's plane only).
    """

    rms_m: float = 0.003
    band_hz: tuple[float, float] = (0.2, 5.0)
    dwell_s: float = 0.02
    seed: int = 0
    per_axis: bool = False
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        v.non_negative("rms_m", self.rms_m)
        lo, hi = (v.non_negative("band_hz", b) for b in np.ravel(self.band_hz)[:2])
        if np.size(self.band_hz) != 2 or not hi > lo:
            raise ValueError(f"band_hz must be (low, high) with high > low >= 0, got {self.band_hz!r}")
        v.positive("dwell_s", self.dwell_s)
        w = v.array("weights", self.weights, shape=(3,))
        if np.any(w < 0) or not np.any(w > 0):
            raise ValueError(f"weights must be >= 0 and not all 0, got {self.weights!r}")

    def stop_times(self, n_stops: int) -> np.ndarray:
        """(n_stops,) time of each stop, s."""
        return np.arange(v.positive_int("n_stops", n_stops)) * float(self.dwell_s)

    def displacements(self, n_stops: int) -> np.ndarray:
        """(n_stops, 3) true minus stated carriage position at each stop, m."""
        return hand_motion(n_stops, self.rms_m, self.band_hz, self.dwell_s, self.seed, per_axis=self.per_axis,
                           weights=self.weights)


def hand_motion(n_stops: int, rms_m: float, band_hz=(0.2, 5.0), dwell_s: float = 0.02, seed: int = 0, *,
                per_axis: bool = False, weights=(1.0, 1.0, 1.0)) -> np.ndarray:
    """(n_stops, 3) band-limited Gaussian displacements at stops ``dwell_s`` apart, m.

    White noise per axis, kept only inside ``band_hz`` (an FFT over a record 4x longer than the
    scan, so the scan is not periodic), scaled to ``rms_m`` exactly (see :class:`HandMotion`).
    A band above the stop rate's Nyquist frequency is cut there, with a warning.
    """
    n = v.positive_int("n_stops", n_stops)
    rms = v.non_negative("rms_m", rms_m)
    dt = v.positive("dwell_s", dwell_s)
    lo, hi = float(band_hz[0]), float(band_hz[1])
    nyq = 0.5 / dt
    if hi > nyq:
        log.warning("hand motion: band up to %g Hz is above the stop rate's Nyquist frequency %g Hz; cut there",
                    hi, nyq)
        hi = nyq
    w = np.asarray(weights, float)
    rng = np.random.default_rng(seed)
    n_rec = 4 * n + 16
    f = np.fft.rfftfreq(n_rec, dt)
    keep = (f >= lo) & (f <= hi)
    if not keep.any():  # a band narrower than the record's frequency step: its nearest bin
        keep[np.argmin(np.abs(f - 0.5 * (lo + hi)))] = True
    spec = (rng.normal(size=(3, len(f))) + 1j * rng.normal(size=(3, len(f)))) * keep
    x = np.fft.irfft(spec, n_rec, axis=1)[:, :n].T  # (n, 3)
    x -= x.mean(axis=0)
    x *= w / np.maximum(np.sqrt(np.mean(x**2, axis=0)), 1e-300)  # each axis to its weight
    if rms == 0:
        return np.zeros((n, 3))
    if per_axis:
        return x * rms
    return x * (rms / np.sqrt(np.mean(np.sum(x**2, axis=1))))


def stop_index(tx_positions: np.ndarray, stage_positions: np.ndarray | None = None) -> np.ndarray:
    """(n_meas,) the stop (ping) each measurement belongs to: consecutive measurements with the
    same carriage position (``stage_positions``, else the speaker's) are one stop."""
    ref = np.asarray(tx_positions if stage_positions is None else stage_positions, float)
    new = np.r_[True, np.any(ref[1:] != ref[:-1], axis=1)]
    return np.cumsum(new) - 1
