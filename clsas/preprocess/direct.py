"""The direct speaker-to-microphone sound: the clock taken from it, and its blanking."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from ..types.dataset import Dataset
from ._base import _check_ds, _step, log

__all__ = ["blank_direct", "clock_from_direct"]


def blank_direct(ds: Dataset, *, guard_s: float | None = None, taper_s: float | None = None) -> Dataset:
    """Zero each recording up to the end of the direct speaker-to-microphone sound.

    The direct path arrives at ``|tx - rx| / c`` after the transmit start and lasts one
    waveform; samples up to that end plus ``guard_s`` become 0, then a raised-cosine taper of
    ``taper_s`` brings the recording back (no step for the matched filter to ring on).

    Parameters
    ----------
    guard_s : float, optional
        Extra time blanked after the direct sound's end, s; default a tenth of the waveform.
    taper_s : float, optional
        Length of the taper, s; default a tenth of the waveform.
    """
    ds = _check_ds(ds)
    wave_s = len(ds.waveform) / ds.fs_hz
    guard = 0.1 * wave_s if guard_s is None else v.non_negative("guard_s", guard_s)
    taper = 0.1 * wave_s if taper_s is None else v.non_negative("taper_s", taper_s)
    direct = np.linalg.norm(ds.tx_positions - ds.rx_positions, axis=1) / ds.c_per_meas
    end = (direct + wave_s + guard - ds.t0_s) * ds.fs_hz  # blank samples before this index
    n_taper = max(1, int(round(taper * ds.fs_hz)))
    k = np.arange(ds.n_samples)[None, :]
    ramp = np.clip((k - end[:, None]) / n_taper, 0.0, 1.0)
    gain = 0.5 * (1 - np.cos(np.pi * ramp))
    sig = ds.signals * gain
    bg = None if ds.background is None else ds.background * gain
    return ds.replace(signals=sig, background=bg,
                      provenance=_step(ds, "blank_direct", guard_s=guard, taper_s=taper,
                                       max_blanked_s=float(end.max() / ds.fs_hz)))


def clock_from_direct(ds: Dataset, *, max_delay_s: float = 5e-4, min_snr_db: float = 15.0) -> Dataset:
    """Set the clock (``t0_s``) from the direct speaker-to-microphone sound of the scan itself.

    The direct sound travels the stated ``|tx - rx|`` and arrives ``|tx - rx| / c - t0``
    after sample 0 (:func:`clsas.focus.direct.direct_arrivals` finds it to a fraction of a
    sample). One shift, the median over the recordings where it is found, is added to every
    ``t0_s``: a common ``t0_s`` stays common, and an attached background (on the same
    samples) stays aligned. Run it before the direct sound is subtracted (background) or
    blanked, and after filtering (:func:`apply` runs it after DC removal and band-pass).

    What it assumes: the stated speaker-microphone spacing is right, and the direct path (off
    the transducers' axes) is delayed by the chain as the echoes are. What it finds on the
    public AirSAS scans is in the own-data guide (docs/guide/own-data.md).

    Raises
    ------
    ValueError
        The direct sound was not found in most recordings (too weak, already blanked, or
        ``t0_s`` more than ``max_delay_s`` off).
    """
    from ..focus.direct import direct_arrivals

    ds = _check_ds(ds)
    found = direct_arrivals(ds, max_delay_s=v.positive("max_delay_s", max_delay_s), min_snr_db=min_snr_db)
    if not found.found:
        raise ValueError(f"clock_from_direct: the direct sound was not found in most recordings (in "
                         f"{int(found.detected.sum())} of {ds.n_meas}, {min_snr_db:g} dB above the rest, within "
                         f"{max_delay_s * 1e6:.0f} us of where t0_s puts it): run it before background subtraction "
                         "and blanking")
    est = found.distance_m / ds.c_per_meas - found.arrival_s
    d = (est - ds.t0_s)[found.detected]
    shift = float(np.median(d))
    spread = float(np.median(np.abs(d - shift)))
    log.info("clock from the direct sound: t0_s %+.2f us (found in %d of %d recordings, spread %.2f us)",
             shift * 1e6, int(found.detected.sum()), ds.n_meas, spread * 1e6)
    return ds.replace(t0_s=ds.t0_s + shift,
                      provenance=_step(ds, "direct_clock", shift_s=shift, spread_s=spread,
                                       found=int(found.detected.sum())))
