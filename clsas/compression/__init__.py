"""Pulse compression: recordings -> complex baseband range profiles over a gated delay window.

One dispatcher, :func:`compress`, over a NumPy twin (``numpy.py``, float64, the
specification) and an OpenCL plan (``opencl.py``, float32).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .. import cl as _cl
from .. import validate as v
from ..physics.signals import analytic
from ..registry import Registry
from ..types.dataset import Dataset
from ..types.profiles import Profiles, center_frequency
from . import compress_numpy as twin
from .compress_opencl import FftMatchedPlan, FmcwPlan, MatchedFilterPlan, layout_key, table_key
from .layout import FftLayout, fft_layout

__all__ = ["COMPRESSIONS", "Profiles", "compress", "center_frequency", "profile_decimation"]

log = logging.getLogger(__name__)

# name -> compression(signals, wave, fs, t0, fc, gate, selection, *, lag_step, algorithm, chirp) -> Profiles;
# each registers itself below where it is defined
COMPRESSIONS: Registry[Callable[..., Profiles]] = Registry("compression", "method")


def compress(data: Dataset | np.ndarray, waveform: np.ndarray | None = None, fs_hz: float | None = None, *,
             method: str = "matched", gate_s: tuple[float, float] | None = None, t0_s: float | np.ndarray | None = None,
             fc_hz: float | None = None, chirp: dict | None = None, lag_step: int | None = None,
             algorithm: str = "auto", backend: str | _cl.Selection | None = None, device: Any = None) -> Profiles:
    """Pulse-compress recordings into complex baseband range profiles.

    Parameters
    ----------
    data : Dataset or (n_meas, n_samples) array
        Recordings. A Dataset brings its own waveform, sample rate, t0, chirp and positions.
    waveform : (n_wave,) array, optional
        Transmitted signal (needed when ``data`` is an array).
    fs_hz : float, optional
        Sample rate, Hz (needed when ``data`` is an array).
    method : str
        A registered compression (:data:`COMPRESSIONS`). ``"matched"``: correlation with the
        analytic transmit waveform. ``"fmcw"``: mix with the transmitted chirp and Fourier transform
        (paper, section 4; needs the chirp and a common ``t0``; echoes that arrive while it plays).
    gate_s : (min, max), optional
        Delays after the transmit start that the profiles must cover, s; only those lags are
        computed. Default: the whole recording.
    t0_s : float or (n_meas,) array, optional
        Time of sample 0 after the transmit start, s (default: the dataset's, else 0).
    fc_hz : float, optional
        Baseband rotation frequency; default the waveform's power-weighted mean frequency.
    chirp : dict, optional
        ``f_start_hz``, ``f_stop_hz``, ``duration_s`` (for ``"fmcw"``; default the dataset's).
    lag_step : int, optional
        Matched filter only: profile sample spacing in recording samples, a power of two.
        Baseband profiles are band-limited, so they need not keep the recording's rate; the
        default (:func:`profile_decimation`) is the largest step at which the linear
        interpolation of backprojection still loses < 0.5 dB at the band edge.
    algorithm : {"auto", "fft", "direct"}
        Matched filter on OpenCL: FFT with frequency-domain decimation, or direct correlation
        (cheaper for short references); ``"auto"`` picks the one with fewer operations. Both
        compute the same profile (the twin's), which is a direct correlation.
    backend : {"auto", "opencl", "numpy"}, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"``: OpenCL where a device exists and its kernel
        variant builds, else the NumPy twin with one warning; ``"opencl"`` raises instead. Or a
        :class:`clsas.cl.Selection` resolved by the caller (its request is kept; ``device`` None).
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
        The OpenCL device (default: ``PYOPENCL_CTX``, else the preferred one).

    Returns
    -------
    Profiles
    """
    compression = COMPRESSIONS.choose(method)
    signals, wave, fs, t0, chirp, positions = _checked_recordings(data, waveform, fs_hz, t0_s, chirp)
    fc = _carrier(wave, fs, fc_hz)
    gate = _gate(gate_s, t0, signals.shape[1], fs)
    v.choice("algorithm", algorithm, ("auto", "fft", "direct"))
    lag_step = _lag_step(lag_step, method, wave, fs, fc)
    sel = _cl.select(backend, device)
    t_start = time.perf_counter()
    prof = compression(signals, wave, fs, t0, fc, gate, sel, lag_step=lag_step, algorithm=algorithm, chirp=chirp)
    return prof.with_fields(timings_s={**prof.timings_s, "compress": time.perf_counter() - t_start}, **positions)


def _checked_recordings(data, waveform, fs_hz, t0_s, chirp):
    """(signals (n_meas, n_samples) floats, waveform, fs, t0 per measurement, chirp, positions):
    the arguments, a Dataset's own where not given, checked."""
    signals, waveform, fs_hz, t0_s, chirp, positions = _inputs(data, waveform, fs_hz, t0_s, chirp)
    signals = v.array("signals", signals, ndim=2, dtype=None)
    if not np.issubdtype(signals.dtype, np.floating):
        signals = signals.astype(np.float64)
    fs = v.positive("fs_hz", fs_hz)
    wave = v.array("waveform", waveform, ndim=1)
    t0 = np.broadcast_to(np.asarray(0.0 if t0_s is None else t0_s, float), (len(signals),)).copy()
    v.array("t0_s", t0)
    return signals, wave, fs, t0, chirp, positions


def _lag_step(lag_step: int | None, method: str, wave: np.ndarray, fs: float, fc: float) -> int:
    """``lag_step`` checked (a power of two), else :func:`profile_decimation`'s for the matched
    filter and 1 for the other compressions."""
    if lag_step is None:
        lag_step = profile_decimation(wave, fs, fc) if method == "matched" else 1
    lag_step = v.positive_int("lag_step", lag_step)
    if lag_step & (lag_step - 1):
        raise ValueError(f"lag_step must be a power of two, got {lag_step}")
    return lag_step


def _inputs(data, waveform, fs_hz, t0_s, chirp):
    """(signals, waveform, fs_hz, t0_s, chirp, positions): a Dataset's own, where not given."""
    if not isinstance(data, Dataset):
        if waveform is None or fs_hz is None:
            raise ValueError("waveform and fs_hz are required when data is an array")
        return data, waveform, fs_hz, t0_s, chirp, {}
    positions = dict(tx_positions=data.tx_positions, rx_positions=data.rx_positions, c_mps=data.c_mps,
                     beams=data.beams)
    return (data.signals, data.waveform if waveform is None else waveform, data.fs_hz if fs_hz is None else fs_hz,
            data.t0_s if t0_s is None else t0_s, data.chirp if chirp is None else chirp, positions)


def _carrier(wave: np.ndarray, fs: float, fc_hz: float | None) -> float:
    """``fc_hz`` checked (below Nyquist), else the waveform's power-weighted mean frequency."""
    fc = center_frequency(wave, fs) if fc_hz is None else v.non_negative("fc_hz", fc_hz)
    if fc >= fs / 2:
        raise ValueError(f"fc_hz={fc:g} is at or above the Nyquist frequency {fs / 2:g}")
    return fc


def _gate(gate_s, t0: np.ndarray, n_samples: int, fs: float) -> tuple[float, float]:
    """The delays to cover: ``gate_s`` checked, else the whole recording."""
    if gate_s is None:
        return (float(t0.min()), float(t0.max() + (n_samples - 1) / fs))
    gate = tuple(v.array("gate_s", gate_s, shape=(2,)))
    if gate[1] < gate[0]:
        raise ValueError(f"gate_s must be (min, max) with min <= max, got {gate_s}")
    return gate


# linear interpolation of a baseband profile loses at most 0.5 dB at the band edge when the
# edge lies within this fraction of the profile's sample rate (sinc(0.186) = 0.944 = -0.5 dB)
INTERP_EDGE_FRACTION = 0.186


def profile_decimation(waveform: np.ndarray, fs_hz: float, fc_hz: float) -> int:
    """Largest power-of-two lag step D for baseband profiles of ``waveform``.

    Two conditions: linear interpolation of the profile costs < 0.5 dB at the waveform's
    -20 dB band edges (``edge offset from fc <= 0.186 fs / D``), and the D-fold narrower band
    kept around ``fc_hz`` holds the waveform's spectrum down to -60 dB.
    """
    n = 1 << int(np.ceil(np.log2(max(64, 8 * len(waveform)))))
    spec = np.abs(np.fft.rfft(waveform, n))
    f = np.fft.rfftfreq(n, 1 / fs_hz)
    peak = spec.max()
    if peak <= 0:
        raise ValueError("waveform is all zeros")
    band20 = f[spec >= 0.1 * peak]
    band60 = f[spec >= 1e-3 * peak]
    edge20 = max(band20.max() - fc_hz, fc_hz - band20.min())
    edge60 = max(band60.max() - fc_hz, fc_hz - band60.min())
    d = 1
    while INTERP_EDGE_FRACTION * fs_hz / (2 * d) >= edge20 and fs_hz / (4 * d) >= edge60:
        d *= 2
    return d


@COMPRESSIONS.register("matched")
def _matched(signals, wave, fs, t0, fc, gate, sel, lag_step, algorithm, chirp=None) -> Profiles:
    n_meas, n_samples = signals.shape
    n_ref, d = len(wave), lag_step
    lag_lo = int(np.floor(np.min((gate[0] - t0) * fs))) - 1
    lag_hi = int(np.ceil(np.max((gate[1] - t0) * fs))) + 1
    lag0 = d * (lag_lo // d)  # a multiple of D, so the FFT path's lags fall on its grid
    n_lags = max(2, -(-(lag_hi - lag0) // d) + 1)
    # read only the samples the gated lags need: the gate plus the pulse length. The slice
    # starts at lag0 (or 0, or the last samples) and keeps lag0 - s_lo a multiple of D
    s_lo = min(max(lag0, 0), lag0 + d * ((n_samples - 1 - lag0) // d))
    lag_read = lag0 - s_lo
    s_hi = max(s_lo + 1, min(n_samples, s_lo + lag_read + d * (n_lags - 1) + n_ref))
    signals = signals[:, s_lo:s_hi]
    ref_a = analytic(wave)
    ref_conj = np.conj(ref_a)
    k = np.arange(n_lags)
    rot = np.exp(-2j * np.pi * ((fc * d * k / fs) % 1.0))
    rot0 = np.exp(-2j * np.pi * ((fc * (t0 + lag0 / fs)) % 1.0))
    total = n_samples + n_ref - 1
    log.info(
        "matched filter: %d lags of %d (%.0f %% skipped by the range gate), lag step %d",
        n_lags * d, total, 100 * max(0.0, 1 - n_lags * d / total), d,
    )
    timings = {}
    plan = None
    if sel.opencl:
        layout = None
        if algorithm != "direct":
            layout = fft_layout(ref_a, fs, fc, 0, signals.shape[1], lag_read, d, n_lags, rot)
        if algorithm == "auto":
            algorithm = choose_algorithm(sel.cl_device, n_meas, n_lags, n_ref, layout)
        n_in = signals.shape[1]
        if algorithm == "fft":
            key = (n_meas, n_in, layout_key(layout))
            plan, sel = sel.plan(lambda q: _cl.reused(q, "matched_fft", key, lambda q: FftMatchedPlan(
                n_meas, n_in, layout, rot0, queue=q)))
        else:
            key = table_key(n_meas, n_in, ref_conj, lag_read, n_lags, rot, d)
            plan, sel = sel.plan(lambda q: _cl.reused(q, "matched_filter", key, lambda q: MatchedFilterPlan(
                n_meas, n_in, ref_conj, lag_read, n_lags, rot, rot0, d, queue=q)))
    rows = out = None
    if plan is not None:
        plan.set_rot0(rot0)  # a plan reused from an earlier call was built with its t0
        rows = plan.enqueue(signals)  # left on the device: read when the host asks for Profiles.data
        timings["compress_kernel"] = plan.last_kernel_s
        log.info("matched filter on OpenCL: %s algorithm, VEC=%d", algorithm, plan.vec)
    else:
        out = twin.matched_filter(signals, ref_conj, lag_read, n_lags, rot, rot0, d)
    return Profiles(out, t0 + lag0 / fs, d / fs, fc, "matched", sel.kind, timings_s=timings, device=sel.device,
                    on_device=rows)


def choose_algorithm(device: Any, n_meas: int, n_lags: int, n_ref: int, layout: FftLayout) -> str:
    """``"fft"`` or ``"direct"`` for the OpenCL matched filter on ``device``.

    Work: the direct kernel does ``n_lags * n_ref`` complex multiply-adds per recording, the
    FFT ``~5 (N log2 N + N' log2 N')``; the FFT must be cheaper by that count. Parallelism:
    the FFT kernel runs one work-item per VEC recordings, the direct kernel one per VEC lags of
    every recording. On a CPU the count alone decides: measured on a 2-core AMD EPYC (PoCL,
    VEC=8, the demo's 480-sample chirp, 284 gated lags), the FFT kernel took 0.11 / 0.07 / 0.34 /
    1.9 ms for 2 / 8 / 32 / 216 recordings against 0.17 / 0.62 / 1.3 / 8.7 ms direct, so even a
    single work-item wins. A GPU needs thousands of work-items in flight, so there the FFT is
    chosen only with at least 256 of its work-items per compute unit (a rule from occupancy,
    not yet measured on a GPU); otherwise the direct kernel.
    """
    n, nd = layout.n_fft, layout.n_fft >> (layout.log2_n - layout.log2_nd)
    fft_cost = 5 * (n * layout.log2_n + nd * layout.log2_nd)
    if fft_cost >= 2 * n_lags * n_ref:
        return "direct"
    if _cl.is_cpu(device):
        return "fft"
    per_cu = 256
    items = -(-n_meas // 4)  # at the GPU width
    return "fft" if items >= per_cu * device.max_compute_units else "direct"


@COMPRESSIONS.register("fmcw")
def _fmcw(signals, wave, fs, t0, fc, gate, sel, lag_step=1, algorithm="auto", chirp=None) -> Profiles:
    chirp = chirp or {}
    missing = [k for k in ("f_start_hz", "f_stop_hz", "duration_s") if k not in chirp]
    if missing:
        raise ValueError(f"method='fmcw' needs chirp parameters; chirp lacks {', '.join(missing)}")
    f1 = v.non_negative("chirp['f_start_hz']", chirp["f_start_hz"])
    f2 = v.non_negative("chirp['f_stop_hz']", chirp["f_stop_hz"])
    T = v.positive("chirp['duration_s']", chirp["duration_s"])
    if np.ptp(t0) > 0.1 / fs:
        raise ValueError("method='fmcw' needs the same t0_s for every measurement")
    t00 = float(t0[0])
    if t00 < 0:
        raise ValueError(f"method='fmcw' needs t0_s >= 0, got {t00:g}")
    n_samples = signals.shape[1]
    n_mix = min(n_samples, int(np.floor((T - t00) * fs)))
    if n_mix < 2:
        raise ValueError("method='fmcw': the recording does not overlap the transmitted chirp")
    # an echo at delay tau is mixed only while the chirp still plays: over [tau, T)
    if gate[0] >= T:
        raise ValueError(
            f"method='fmcw': the gated echoes arrive {gate[0] * 1e3:.3g}-{gate[1] * 1e3:.3g} ms after the transmit "
            f"start, after the {T * 1e3:.3g} ms chirp has ended, so there is nothing to mix. FMCW serves delays "
            f"below {T * 1e3:.3g} ms (well below: half the chirp gives half the bandwidth); use "
            "compression='matched' (or a longer chirp)"
        )
    if gate[1] > 0.5 * T:
        log.warning("fmcw: echoes later than %.3g ms (half the %.3g ms chirp) overlap less than half the chirp; "
                    "their range resolution is at least 2x coarser, and past %.3g ms they vanish; "
                    "compression='matched' does not have this limit", 0.5e3 * T, 1e3 * T, 1e3 * T)
    slope = (f2 - f1) / T
    t = t00 + np.arange(n_mix) / fs
    ref = np.exp(-2j * np.pi * (f1 * t + 0.5 * slope * t**2)) * np.hanning(n_mix)
    n_lags = max(2, int(np.ceil((gate[1] - gate[0]) * fs)) + 1)
    taus = gate[0] + np.arange(n_lags) / fs
    t_c = t00 + 0.5 * (n_mix - 1) / fs
    rvp = np.exp(2j * np.pi * (((f1 + slope * t_c - fc) * taus - 0.5 * slope * taus**2) % 1.0))
    log.info("fmcw: %d delays from %.3f to %.3f ms, %d samples mixed", n_lags, 1e3 * taus[0], 1e3 * taus[-1], n_mix)
    timings = {}
    key = table_key(signals.shape[0], n_samples, ref, slope, fs, taus, rvp)
    plan, sel = sel.plan(lambda q: _cl.reused(q, "fmcw_dechirp", key, lambda q: FmcwPlan(
        signals.shape[0], n_samples, ref, slope, fs, taus, rvp, queue=q)))
    rows = out = None
    if plan is not None:
        rows = plan.enqueue(signals)  # left on the device: read when the host asks for Profiles.data
        timings["compress_kernel"] = plan.last_kernel_s
    else:
        out = twin.fmcw_dechirp(signals, ref, slope, fs, taus, rvp)
    tau0 = np.full(signals.shape[0], taus[0])
    return Profiles(out, tau0, 1 / fs, fc, "fmcw", sel.kind, timings_s=timings, device=sel.device,
                    on_device=rows)
