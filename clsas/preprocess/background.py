"""The empty-scene scan: attached to a dataset, put on its time axis (stretched for another air)
and subtracted stop by stop."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from ..types.dataset import Dataset
from ._base import _check_ds, _step, log

__all__ = ["attach_background", "subtract_background"]


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
