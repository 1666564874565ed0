"""Filters and the time axis: DC removal, band-pass to the chirp's band, a known group delay."""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import validate as v
from ..types.dataset import Dataset
from ._base import _check_ds, _step

__all__ = ["bandpass", "chirp_band", "remove_dc", "remove_delay"]


def remove_dc(ds: Dataset) -> Dataset:
    """Subtract each recording's mean (and the background's, if the dataset has one)."""
    ds = _check_ds(ds)
    sig = ds.signals - ds.signals.mean(axis=1, keepdims=True)
    bg = None if ds.background is None else ds.background - ds.background.mean(axis=1, keepdims=True)
    return ds.replace(signals=sig, background=bg, provenance=_step(ds, "dc"))


def chirp_band(ds: Dataset) -> tuple[float, float]:
    """The transmitted band, Hz: the chirp's start and stop frequencies if the dataset has
    them, else where the waveform's spectrum is within 20 dB of its peak."""
    ch = ds.chirp or {}
    if "f_start_hz" in ch and "f_stop_hz" in ch:
        f1, f2 = float(ch["f_start_hz"]), float(ch["f_stop_hz"])
        return min(f1, f2), max(f1, f2)
    n = 8 * len(ds.waveform)
    spec = np.abs(np.fft.rfft(ds.waveform, n))
    f = np.fft.rfftfreq(n, 1 / ds.fs_hz)
    if spec.max() <= 0:
        raise ValueError("the dataset's waveform is all zeros: give the band as f_lo_hz, f_hi_hz")
    band = f[spec >= 0.1 * spec.max()]
    return float(band.min()), float(band.max())


def _band_response(n: int, fs: float, f_lo: float, f_hi: float, transition: float) -> np.ndarray:
    """Zero-phase band-pass gain on the rfft bins of length n: 1 inside [f_lo, f_hi], raised-
    cosine edges ``transition`` Hz wide outside it, 0 beyond."""
    f = np.fft.rfftfreq(n, 1 / fs)
    g = np.zeros_like(f)
    g[(f >= f_lo) & (f <= f_hi)] = 1.0
    if transition > 0:
        lo = (f < f_lo) & (f > f_lo - transition)
        g[lo] = 0.5 * (1 + np.cos(np.pi * (f_lo - f[lo]) / transition))
        hi = (f > f_hi) & (f < f_hi + transition)
        g[hi] = 0.5 * (1 + np.cos(np.pi * (f[hi] - f_hi) / transition))
    return g


def bandpass(ds: Dataset, f_lo_hz: float | None = None, f_hi_hz: float | None = None, *,
             margin_hz: float | None = None, transition_hz: float | None = None) -> Dataset:
    """Zero-phase band-pass to the chirp's band (FFT filter, raised-cosine edges).

    Parameters
    ----------
    f_lo_hz, f_hi_hz : float, optional
        Pass band, Hz; default :func:`chirp_band` widened by ``margin_hz`` on each side.
    margin_hz : float, optional
        Default 5 % of the band's width.
    transition_hz : float, optional
        Width of each raised-cosine edge, Hz; default 10 % of the band's width. A smooth
        edge keeps the filter's impulse response short (no ringing into the image).
    """
    ds = _check_ds(ds)
    lo0, hi0 = chirp_band(ds)
    width = hi0 - lo0
    margin = 0.05 * width if margin_hz is None else v.non_negative("margin_hz", margin_hz)
    f_lo = max(0.0, lo0 - margin) if f_lo_hz is None else v.non_negative("f_lo_hz", f_lo_hz)
    f_hi = hi0 + margin if f_hi_hz is None else v.positive("f_hi_hz", f_hi_hz)
    if f_hi <= f_lo:
        raise ValueError(f"f_hi_hz ({f_hi:g}) must be above f_lo_hz ({f_lo:g})")
    if f_hi > ds.fs_hz / 2:
        raise ValueError(f"f_hi_hz={f_hi:g} is above the Nyquist frequency {ds.fs_hz / 2:g}")
    trans = 0.1 * (f_hi - f_lo) if transition_hz is None else v.non_negative("transition_hz", transition_hz)
    import scipy.fft

    # pad so that the filter's (short) impulse response does not wrap around the record
    n = scipy.fft.next_fast_len(ds.n_samples + int(4 * ds.fs_hz / max(trans, ds.fs_hz / ds.n_samples)) + 16)
    g = _band_response(n, ds.fs_hz, f_lo, f_hi, trans)

    def filt(x):
        return scipy.fft.irfft(scipy.fft.rfft(x, n, axis=1) * g, n, axis=1)[:, : x.shape[1]]

    bg = None if ds.background is None else filt(ds.background)
    return ds.replace(signals=filt(ds.signals), background=bg,
                      provenance=_step(ds, "bandpass", f_lo_hz=f_lo, f_hi_hz=f_hi, transition_hz=trans))


def remove_delay(ds: Dataset, delay_s: float | np.ndarray) -> Dataset:
    """Remove a known system delay (transducer and converter group delay) from the time axis.

    A recording whose sound is ``delay_s`` late (the chain delays it) has its sample 0 at
    ``t0_s - delay_s`` after the sound truly left: ``t0_s`` is lowered by ``delay_s`` (and may
    become negative); the samples are not moved.
    """
    ds = _check_ds(ds)
    if np.ndim(delay_s):
        d = v.array("delay_s", delay_s, shape=(ds.n_meas,))
        rec: Any = {"mean_s": float(d.mean()), "per_measurement": True}
    else:
        d = v.finite("delay_s", delay_s)
        rec = {"delay_s": d}
    return ds.replace(t0_s=ds.t0_s - d, provenance=_step(ds, "group_delay", **rec))
