"""Preprocessing of measured recordings: DC removal, band-pass, background subtraction,
removal of what every recording shares, direct-path blanking, group-delay removal.

Each step takes a :class:`~clsas.dataset.Dataset` and returns a new one (the input is not
changed) whose ``provenance`` ends with a record of the step and its parameters, so an image
file can say what was done to its data. :func:`preprocess` runs several steps in a fixed,
sensible order and is what the ``[preprocess]`` table of a scene or preprocessing file and
``clsas preprocess`` call::

    ds = clsas.preprocess.apply(ds, dc=True, bandpass=True, background=empty_scan,
                          blank_direct=True, group_delay_s=62.33 / ds.fs_hz)

The order is: group delay (it only moves ``t0_s``), DC, band-pass, the clock from the direct
sound (it only moves ``t0_s``), background subtraction,
shared-clutter removal (:func:`remove_common`), direct-path blanking. Band-passing before
subtracting means the same filter is applied to the background recordings (they are filtered
with the scan).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from . import validate as v
from .dataset import Dataset

__all__ = [
    "COMMON_STATISTICS", "PREPROCESS_KEYS", "apply", "attach_background", "bandpass", "blank_direct",
    "chirp_band", "clock_from_direct", "from_table", "remove_common", "remove_dc", "remove_delay",
    "subtract_background",
]

log = logging.getLogger(__name__)

# keys of a [preprocess] table and of apply()'s keyword arguments
PREPROCESS_KEYS = ("group_delay_s", "group_delay_samples", "direct_clock", "dc", "bandpass", "background",
                   "common", "blank_direct")

#: what :func:`remove_common` subtracts at each delay
COMMON_STATISTICS = ("mean", "median")


def _check_ds(ds: Any) -> Dataset:
    if not isinstance(ds, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(ds).__name__}")
    return ds


def _step(ds: Dataset, name: str, **params) -> list[dict]:
    clean = {k: (float(p) if isinstance(p, np.floating | float) else p) for k, p in params.items()}
    return [*ds.provenance, {"step": name, **clean}]


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


def attach_background(ds: Dataset, background: Dataset | np.ndarray) -> Dataset:
    """The dataset with ``background`` (the empty scene at the same stops) as its own.

    A Dataset must have the same sample rate and measurement count. Its recordings are put on
    this dataset's time axis through both ``t0_s`` (which must both count from the sound
    leaving the speaker: remove a group delay from both first) and stretched by the ratio of
    the two speeds of sound, so that a static echo recorded in cooler or warmer air lines up
    with the scan's. Later steps (DC, band-pass, blanking) then treat scan and background alike.
    """
    ds = _check_ds(ds)
    if isinstance(background, Dataset):
        if background.n_meas != ds.n_meas:
            raise ValueError(f"background has {background.n_meas} measurements, the scan {ds.n_meas}: "
                             "they must be the same stops in the same order")
        if abs(background.fs_hz - ds.fs_hz) > 1e-9 * ds.fs_hz:
            raise ValueError(f"background fs_hz={background.fs_hz:g} differs from the scan's {ds.fs_hz:g}")
        # the same echo path arrives at p / c: stretch the background to the scan's air
        scale = ds.c_per_meas / background.c_per_meas
        bg = _on_time_axis(background.signals, background.t0_s, ds.t0_s, ds.fs_hz, ds.n_samples, scale,
                           ds.waveform)
        if np.any(np.abs(scale - 1) > 1e-12):
            log.info("background: stretched to the scan's air (speed of sound ratio %.5f to %.5f)",
                     scale.min(), scale.max())
    else:
        bg = v.array("background", background, ndim=2)
        if bg.shape[0] != ds.n_meas:
            raise ValueError(f"background has {bg.shape[0]} recordings, the scan {ds.n_meas}")
        bg = _fit_length(bg, ds.n_samples)
    return ds.replace(background=bg)


def subtract_background(ds: Dataset, background: Dataset | np.ndarray | None = None, *,
                        align_s: float = 0.0, fit_gain: bool = False, label: str | None = None) -> Dataset:
    """Subtract the empty scene's recordings, stop by stop.

    Parameters
    ----------
    background : Dataset or (n_meas, n_samples) array, optional
        The empty-scene scan at the same stops (same measurement count and order); default
        the dataset's own ``background``. A Dataset must have the same sample rate and its
        recordings are brought to this dataset's ``t0_s`` by whole samples.
    align_s : float
        If > 0, each background recording is first shifted (by a fraction of a sample, in
        the frequency domain) by the delay within ``+-align_s`` that best matches the
        recording: static clutter moves a little when the air warms between the two scans.
    fit_gain : bool
        Also scale each background recording by its least-squares gain.
    label : str, optional
        Where the background came from, for the provenance (e.g. its file name).

    Returns
    -------
    Dataset
        With the background subtracted and ``background`` cleared (recorded in the provenance).
    """
    ds = _check_ds(ds)
    source = "dataset.background"
    if background is not None:
        source = "background dataset" if isinstance(background, Dataset) else "background array"
        ds = attach_background(ds, background)
    elif ds.background is None:
        raise ValueError("subtract_background: the dataset has no background scan; pass background=")
    if label is not None:
        source = str(label)
    bg = ds.background
    align = v.non_negative("align_s", align_s)
    shifts = np.zeros(ds.n_meas)
    if align > 0:
        bg, shifts = _align(ds.signals, bg, ds.fs_hz, align)
    gains = np.ones(ds.n_meas)
    if fit_gain:
        num = np.einsum("ij,ij->i", ds.signals, bg)
        den = np.einsum("ij,ij->i", bg, bg)
        gains = np.where(den > 0, num / np.where(den > 0, den, 1), 1.0)
        bg = bg * gains[:, None]
    before = float(np.sqrt(np.mean(ds.signals**2)))
    out = ds.signals - bg
    after = float(np.sqrt(np.mean(out**2)))
    log.info("background subtracted: RMS %.3g -> %.3g (%.1f dB)", before, after,
             20 * np.log10(max(after, 1e-300) / max(before, 1e-300)))
    prov = _step(ds, "background", source=source, align_s=align, fit_gain=bool(fit_gain),
                 max_shift_s=float(np.abs(shifts).max()), rms_before=before, rms_after=after)
    return ds.replace(signals=out, background=None, provenance=prov)


def _fit_length(x: np.ndarray, n: int) -> np.ndarray:
    if x.shape[1] >= n:
        return x[:, :n]
    return np.pad(x, ((0, 0), (0, n - x.shape[1])))


def _upsampled(x: np.ndarray, up: int) -> tuple[np.ndarray, int]:
    import scipy.fft

    nf = scipy.fft.next_fast_len(len(x) + 64)
    return scipy.fft.irfft(scipy.fft.rfft(x, nf), nf * up) * up, nf


def _on_time_axis(sig, t0_from, t0_to, fs, n, scale, waveform=None) -> np.ndarray:
    """Recordings with sample 0 at ``t0_from``, evaluated at the times ``t0_to + j / fs``
    with their echoes moved from delay ``tau`` to ``tau / scale`` (per row).

    Whole-sample shifts with no stretch are copied exactly. Otherwise the row is stretched in
    time (upsampled 8 times by FFT, interpolated linearly: error below -40 dB up to 0.4 fs),
    which moves every echo to its new delay but also squeezes each echo's waveform by
    ``scale``; a filter ``W(f) / W_s(f)`` (W the waveform's spectrum, W_s the squeezed
    waveform's, Wiener-regularised) then restores the waveform, so each echo is exactly the
    transmitted waveform at its new delay.
    """

    out = np.zeros((sig.shape[0], n))
    up = 8
    wave_fine = None if waveform is None else _upsampled(waveform, up)[0]  # the same for every row
    for m in range(sig.shape[0]):
        k = (t0_to[m] - t0_from[m]) * fs  # sample of sig at our sample 0
        if abs(scale[m] - 1) < 1e-12 and abs(k - round(k)) < 1e-6:
            k = int(round(k))
            lo, hi = max(0, k), min(sig.shape[1], k + n)
            if hi > lo:
                out[m, lo - k : hi - k] = sig[m, lo:hi]
            continue
        fine, nf = _upsampled(sig[m], up)
        want = ((t0_to[m] + np.arange(n) / fs) * scale[m] - t0_from[m]) * fs * up
        out[m] = np.interp(want, np.arange(nf * up), fine, left=0.0, right=0.0)
        out[m, want > (sig.shape[1] - 1) * up] = 0.0
        if waveform is not None and abs(scale[m] - 1) >= 1e-12:
            out[m] = _unsqueeze(out[m], waveform, wave_fine, scale[m], up)
    return out


def _unsqueeze(x: np.ndarray, waveform: np.ndarray, fine: np.ndarray, scale: float, up: int) -> np.ndarray:
    """Filter ``x``, whose echoes are ``w(scale t)``, so that they become ``w(t)`` (``fine``:
    the waveform upsampled ``up`` times)."""
    import scipy.fft

    k = np.arange(int(np.ceil(len(waveform) / scale)) + 1)
    squeezed = np.interp(k * scale * up, np.arange(len(fine)), fine, left=0.0, right=0.0)
    nf = scipy.fft.next_fast_len(len(x) + 2 * len(squeezed) + 16)
    W = scipy.fft.rfft(waveform, nf)
    Ws = scipy.fft.rfft(squeezed, nf)
    p = np.abs(Ws) ** 2
    h = W * np.conj(Ws) / (p + 1e-4 * p.max())
    return scipy.fft.irfft(scipy.fft.rfft(x, nf) * h, nf)[: len(x)]


def _align(sig, bg, fs, max_shift_s):
    """Shift each background row by the delay within +-max_shift_s maximising its correlation
    with the recording (parabolic peak on an 8x upsampled cross-correlation)."""
    import scipy.fft

    n = sig.shape[1]
    nf = scipy.fft.next_fast_len(2 * n)
    S, B = scipy.fft.rfft(sig, nf, axis=1), scipy.fft.rfft(bg, nf, axis=1)
    up = 8
    xc = scipy.fft.irfft(S * np.conj(B), nf * up, axis=1)  # lag l / up samples at index l
    k = int(np.ceil(max_shift_s * fs * up))
    lags = np.r_[np.arange(0, k + 1), np.arange(-k, 0)]
    win = xc[:, lags % (nf * up)]
    i = np.argmax(win, axis=1)
    shift = lags[i].astype(float)
    # parabolic refinement where both neighbours exist
    for m, j in enumerate(i):
        jm, jp = (j - 1) % len(lags), (j + 1) % len(lags)
        if abs(lags[jm] - lags[j]) == 1 and abs(lags[jp] - lags[j]) == 1:
            a, b, c = win[m, jm], win[m, j], win[m, jp]
            den = a - 2 * b + c
            if den < 0:
                shift[m] += 0.5 * (a - c) / den * np.sign(lags[jp] - lags[j])
    shift_s = shift / (up * fs)
    f = scipy.fft.rfftfreq(nf, 1 / fs)
    shifted = scipy.fft.irfft(B * np.exp(-2j * np.pi * f[None, :] * shift_s[:, None]), nf, axis=1)[:, :n]
    return shifted, shift_s


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


def remove_common(ds: Dataset, statistic: str = "mean") -> Dataset:
    """Subtract what every recording shares: the mean (or median) over the measurements at
    each delay.

    On a turntable, the room, the turntable's rim and the fixture turn with nothing (or turn
    into themselves): their echoes are the same in every ping, while the target's move from
    ping to ping. An empty-scene scan removes most of them, but not what changed between the
    two scans (the air, a cable, the level); the shared part left is what draws rings centred
    on the axis. The same holds for a fixed rig where the target moves relative to the
    transducers.

    What it also removes (an honest note): any part of the wanted echo that is the same in
    every recording. On a turntable that is a reflector on the axis (its range never changes)
    and the rotation-invariant part of a target centred on it (a disc, a ring about the axis);
    on a planar scan of a target in front of the aperture, the target's echo changes slowly
    from stop to stop, so much of it is shared and subtracted (``tests/test_preprocess_common.py``
    measures both). Use it for turntable scans and rigs where the target moves; not for a
    planar scan of a static scene.

    Parameters
    ----------
    statistic : {"mean", "median"}
        The estimate of the shared part: the mean is linear (an image of the result is the
        image minus the image of the shared part); the median ignores a target that appears
        in fewer than half of the recordings at that delay (it is not linear).

    Notes
    -----
    All recordings must start at the same time (one ``t0_s``), or "the same delay" would mean
    different samples. The air may differ from ping to ping (``temperature_c`` per
    measurement): a shared echo at path p then arrives at p/c of each ping, which this
    sample-wise estimate does not follow (0.1 % of c moves an echo at 1.7 m by 5 us).
    The background (if still attached) is treated alike.
    """
    ds = _check_ds(ds)
    v.choice("statistic", statistic, COMMON_STATISTICS)
    if ds.n_meas < 2:
        raise ValueError(f"remove_common needs at least 2 recordings, the dataset has {ds.n_meas}")
    spread = float(np.ptp(ds.t0_s)) * ds.fs_hz
    if spread > 1e-3:
        raise ValueError(f"remove_common: the recordings start at different times (t0_s spans {spread:.3g} "
                         "samples); the shared part is taken sample by sample, so they must share one t0_s")
    stat = np.mean if statistic == "mean" else np.median

    def strip(x: np.ndarray) -> np.ndarray:
        return x - stat(x, axis=0, keepdims=True)

    before = float(np.sqrt(np.mean(ds.signals**2)))
    sig = strip(ds.signals)
    after = float(np.sqrt(np.mean(sig**2)))
    log.info("shared part (%s over %d recordings) removed: RMS %.3g -> %.3g", statistic, ds.n_meas, before, after)
    bg = None if ds.background is None else strip(ds.background)
    return ds.replace(signals=sig, background=bg,
                      provenance=_step(ds, "common", statistic=statistic, rms_before=before, rms_after=after))


def clock_from_direct(ds: Dataset, *, max_delay_s: float = 5e-4, min_snr_db: float = 15.0) -> Dataset:
    """Set the clock (``t0_s``) from the direct speaker-to-microphone sound of the scan itself.

    The direct sound travels the stated ``|tx - rx|`` and arrives ``|tx - rx| / c - t0``
    after sample 0 (:func:`clsas.focus.direct.direct_arrivals` finds it to a fraction of a
    sample). One shift, the median over the recordings where it is found, is added to every
    ``t0_s``: a common ``t0_s`` stays common, and an attached background (on the same
    samples) stays aligned. Run it before the direct sound is subtracted (background) or
    blanked, and after filtering (:func:`apply` runs it after DC removal and band-pass).

    What it assumes: the stated speaker-microphone spacing is right, and the direct path (off
    the transducers' axes) is delayed by the chain as the echoes are. On the AirSAS scans it
    moves ``t0_s`` by +11.0 us (20k) and +14.6 us (5k) from ``Group Delay`` (docs/guide/own-data.md, "Your own
    data").

    Raises
    ------
    ValueError
        The direct sound was not found in most recordings (too weak, already blanked, or
        ``t0_s`` more than ``max_delay_s`` off).
    """
    from .focus.direct import direct_arrivals

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


# apply() takes arguments named like the steps; these names reach the step functions
_bandpass_step = bandpass
_blank_step = blank_direct
_clock_step = clock_from_direct


def apply(ds: Dataset, *, group_delay_s: float | None = None, group_delay_samples: float | None = None,
               direct_clock: bool = False, dc: bool = False, bandpass: bool | dict | tuple = False,
               background: bool | str | Dataset | np.ndarray | dict | None = None,
               common: bool | str = False, blank_direct: bool | dict = False) -> Dataset:
    """Several preprocessing steps in their natural order (see the module docstring).

    Parameters
    ----------
    group_delay_s, group_delay_samples : float, optional
        System delay to remove (:func:`remove_delay`), in seconds or in samples.
    direct_clock : bool
        :func:`clock_from_direct`, after DC removal and band-pass (on the filtered recordings,
        before the background subtraction removes the direct sound; an attached background,
        on the same samples, keeps its alignment).
    dc : bool
        :func:`remove_dc`.
    bandpass : bool, (f_lo_hz, f_hi_hz) or dict
        :func:`bandpass`; ``True`` for the chirp's band, a pair for a given band, a dict for
        its keyword arguments.
    background : True, path, Dataset, array or dict, optional
        :func:`subtract_background`: ``True`` uses the dataset's own ``background``; a path
        names an HDF5 dataset file of the empty scene; a dict holds ``path`` (or nothing, for
        the own background) and the keyword arguments ``align_s``, ``fit_gain``. A given
        background is attached first (:func:`attach_background`), so the group delay, DC and
        band-pass steps treat it as they treat the scan.
    common : bool or {"mean", "median"}
        :func:`remove_common` (``True``: the mean), after the background subtraction.
    blank_direct : bool or dict
        :func:`blank_direct`, with a dict for its keyword arguments.

    Examples
    --------
    >>> from clsas import preprocess as pp
    >>> from clsas.synthetic import turntable_scan
    >>> scan = turntable_scan(30)
    >>> clean = pp.apply(scan.dataset, group_delay_samples=62.33, dc=True, bandpass=True,
    ...                  background=scan.background, blank_direct=True)
    >>> clean.signals.shape == scan.dataset.signals.shape
    True
    """
    ds = _check_ds(ds)
    src, bg_opts = _background_source(ds, background)
    if group_delay_s is not None and group_delay_samples is not None:
        raise ValueError("give group_delay_s or group_delay_samples, not both")
    if group_delay_samples is not None:
        group_delay_s = v.finite("group_delay_samples", group_delay_samples) / ds.fs_hz
    if group_delay_s is not None:
        ds = remove_delay(ds, group_delay_s)
    if background is not None and background is not False and src is not True:
        if isinstance(src, Dataset) and group_delay_s is not None:
            src = remove_delay(src, group_delay_s)  # the same rig, the same delay
        ds = attach_background(ds, src)
    if _flag("dc", dc):
        ds = remove_dc(ds)
    ds = _bandpass_option(ds, bandpass)
    if _flag("direct_clock", direct_clock):  # on the filtered recordings; the background moves with them
        ds = _clock_step(ds)
    if background is not None and background is not False:
        ds = subtract_background(ds, **bg_opts)
    if isinstance(common, str):
        ds = remove_common(ds, common)
    elif _flag("common", common):
        ds = remove_common(ds)
    if isinstance(blank_direct, dict):
        ds = _blank_step(ds, **_only(blank_direct, "blank_direct", ("guard_s", "taper_s")))
    elif _flag("blank_direct", blank_direct):
        ds = _blank_step(ds)
    return ds


def _background_source(ds: Dataset, background) -> tuple[Any, dict]:
    """apply()'s ``background``: (True for the dataset's own, a Dataset, an array, or None;
    subtract_background's keyword arguments). A path is loaded here."""
    if background is None or background is False:
        return None, {}
    # the empty scene goes through the same steps as the scan: attach it first
    bg_opts: dict = {}
    src = background
    if isinstance(background, dict):
        bg_opts = _only(background, "background", ("path", "align_s", "fit_gain"))
        src = bg_opts.pop("path", True)
    if isinstance(src, str):
        from .dataset import load

        bg_opts["label"] = src
        src = load(src)
    elif isinstance(src, Dataset):
        bg_opts["label"] = "background dataset"
    if src is True and ds.background is None:
        raise ValueError("background=True: the dataset has no background scan of its own")
    return src, bg_opts


def _bandpass_option(ds: Dataset, bandpass) -> Dataset:
    """apply()'s ``bandpass``: True, (f_lo_hz, f_hi_hz) or a dict of options."""
    if isinstance(bandpass, tuple | list):
        if len(bandpass) != 2:
            raise ValueError(f"bandpass must be (f_lo_hz, f_hi_hz), got {bandpass!r}")
        return _bandpass_step(ds, *bandpass)
    if isinstance(bandpass, dict):
        return _bandpass_step(ds, **_only(bandpass, "bandpass", ("f_lo_hz", "f_hi_hz", "margin_hz", "transition_hz")))
    return _bandpass_step(ds) if _flag("bandpass", bandpass) else ds


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be true or false here, got {value!r}")
    return bool(value)


def _only(opts: dict, name: str, allowed: tuple[str, ...]) -> dict:
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}")
    return dict(opts)


def from_table(ds: Dataset, table: dict, *, where: str = "[preprocess]") -> Dataset:
    """Apply a ``[preprocess]`` TOML table (keys as :func:`apply`'s arguments)."""
    if not isinstance(table, dict):
        raise ValueError(f"{where} must be a table")
    unknown = sorted(set(table) - set(PREPROCESS_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(PREPROCESS_KEYS)}")
    args = dict(table)
    if isinstance(args.get("bandpass"), list):
        args["bandpass"] = tuple(args["bandpass"])
    return apply(ds, **args)
