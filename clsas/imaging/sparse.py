"""Super-resolved range profiles for imaging: each recording's echoes are found by sparse
recovery (BPDN, CBP-Taylor or refined CBP-Polar) on the analytic transmit waveform, then
rendered as narrow pulses into baseband profiles that backprojection takes as it takes the
matched filter's."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from .. import _validate as v
from ..compress import Profiles, center_frequency
from ..dataset import Dataset
from ..signals import analytic

__all__ = ["superres_profiles"]

log = logging.getLogger(__name__)

SPARSE_METHODS = ("bpdn", "cbp-taylor", "cbp-polar")


def _echoes(method, x, atom, delta, tau0, n_atoms, lam, lam_frac):
    from ..sparse import Dictionary, Echoes, bpdn, cbp_polar_refined, cbp_taylor, lam_noise

    d = Dictionary(atom, delta, tau0, n_atoms)
    if lam is None and lam_frac is None:
        lam = lam_noise(d, x, "complex")
    if method == "bpdn":
        res = bpdn(d, x, lam, lam_frac=lam_frac, amplitudes="complex", tol=1e-4)  # ample for an image
        on = np.abs(res.x) > 0
        return Echoes(d.taus[on], res.x[on], "bpdn", res.status, res.iterations, res.time_s)
    if method == "cbp-taylor":
        return cbp_taylor(d, x, lam, lam_frac=lam_frac, amplitudes="complex")
    return cbp_polar_refined(d, x, lam, lam_frac=lam_frac, amplitudes="complex")


def superres_profiles(
    dataset: Dataset,
    gates_s: np.ndarray,
    method: str = "cbp-polar",
    *,
    delta_s: float | None = None,
    lam: float | None = None,
    lam_frac: float | None = None,
    render_width_s: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Profiles, list]:
    """Super-resolve every recording of ``dataset`` within its delay gate.

    Parameters
    ----------
    gates_s : (n_meas, 2) array
        Delays after the transmit start to search, per measurement, s.
    method : {"bpdn", "cbp-taylor", "cbp-polar"}
        Complex amplitudes (echoes have unknown phase): BPDN on the grid; CBP-Taylor in its
        complex form (``|c_i|, |d_i| <= t_i``); CBP-Polar refined by nlopt.
    delta_s : float, optional
        Dictionary spacing; default one sample.
    lam, lam_frac : float, optional
        Absolute lam or a fraction of lam_max; default the noise level of each recording
        (:func:`clsas.sparse.lam_noise`).
    render_width_s : float, optional
        Each echo becomes a Gaussian pulse of this standard deviation in the profile (default
        0.05 / B, B the waveform's -20 dB bandwidth); the profile step is a quarter of it.

    Returns
    -------
    (Profiles, list of Echoes)
        The rendered profiles (baseband at the waveform's centre frequency, all rows on one
        delay grid) and the echoes of each measurement (delays after the transmit start).
    """
    from ..sparse import Atom

    v.choice("method", method, SPARSE_METHODS)
    fs = dataset.fs_hz
    wave = dataset.waveform
    gates = v.array("gates_s", gates_s, shape=(dataset.n_meas, 2))
    if np.any(gates[:, 1] < gates[:, 0]):
        raise ValueError("gates_s rows must be (min, max) with min <= max")
    delta = 1.0 / fs if delta_s is None else v.positive("delta_s", delta_s)
    fc = center_frequency(wave, fs)
    if render_width_s is None:
        spec = np.abs(np.fft.rfft(wave, 8 * len(wave)))
        f = np.fft.rfftfreq(8 * len(wave), 1 / fs)
        band = f[spec >= 0.1 * spec.max()]
        render_width_s = 0.05 / max(band.max() - band.min(), fs / len(wave))
    width = v.positive("render_width_s", render_width_s)
    t0 = np.zeros(dataset.n_meas) if dataset.t0_s is None else np.asarray(dataset.t0_s, float)
    n_wave = len(wave)
    echoes = []
    t_start = time.perf_counter()
    for m in range(dataset.n_meas):
        # the samples that echoes from the gate can reach, and the delays (from that first sample)
        s_lo = max(0, int(np.floor((gates[m, 0] - t0[m]) * fs)) - 2)
        s_hi = min(dataset.n_samples, int(np.ceil((gates[m, 1] - t0[m]) * fs)) + n_wave + 2)
        if s_hi - s_lo < 2:
            echoes.append(None)
            continue
        x = analytic(np.asarray(dataset.signals[m, s_lo:s_hi], float))
        atom = Atom(wave, fs, s_hi - s_lo, complex=True)
        tau0 = gates[m, 0] - t0[m] - s_lo / fs
        n_atoms = max(2, int(np.ceil((gates[m, 1] - gates[m, 0]) / delta)) + 1)
        e = _echoes(method, x, atom, delta, tau0, n_atoms, lam, lam_frac)
        e.delays_s = e.delays_s + t0[m] + s_lo / fs  # after the transmit start
        echoes.append(e)
        if progress is not None:
            progress(m + 1, dataset.n_meas)
    found = [e for e in echoes if e is not None]
    log.info("%s: %d echoes in %d recordings, %.2f s", method, sum(len(e) for e in found), dataset.n_meas,
             time.perf_counter() - t_start)
    # render: one common delay grid spanning every gate, a Gaussian of sigma = width per echo
    dtau = width / 4
    lo, hi = float(gates[:, 0].min()) - 4 * width, float(gates[:, 1].max()) + 4 * width
    n_lags = int(np.ceil((hi - lo) / dtau)) + 1
    data = np.zeros((dataset.n_meas, n_lags), np.complex128)
    reach = int(np.ceil(5 * width / dtau))
    for m, e in enumerate(echoes):
        for tau, a in zip(e.delays_s if e is not None else [], e.amplitudes if e is not None else [], strict=True):
            k0 = int(round((tau - lo) / dtau))
            ks = np.arange(max(0, k0 - reach), min(n_lags, k0 + reach + 1))
            g = np.exp(-0.5 * ((lo + ks * dtau - tau) / width) ** 2)
            data[m, ks] += a * np.exp(-2j * np.pi * fc * tau) * g
    prof = Profiles(data, np.full(dataset.n_meas, lo), dtau, fc, method, "numpy",
                    tx_positions=dataset.tx_positions, rx_positions=dataset.rx_positions, c_mps=dataset.c_mps,
                    timings_s={"superres": time.perf_counter() - t_start})
    return prof, [e if e is not None else _empty() for e in echoes]


def _empty():
    from ..sparse import Echoes

    return Echoes([], [])
