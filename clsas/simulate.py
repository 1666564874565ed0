"""Forward model: scene + aperture + waveform -> Dataset."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from . import _validate as v
from .dataset import Dataset
from .geometry import Aperture, Scene
from .physics import air_absorption_db_per_m, speed_of_sound

__all__ = ["simulate"]

log = logging.getLogger(__name__)


def simulate(
    scene: Scene,
    aperture: Aperture,
    waveform: np.ndarray,
    fs_hz: float,
    *,
    n_samples: int | None = None,
    t0_s: float | np.ndarray = 0.0,
    snr_db: float | None = None,
    seed: int | None = 0,
    absorption: bool = True,
    chirp: dict | None = None,
    config: str = "",
    temperature_c: float | np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Dataset:
    """Simulate the recordings of a scan.

    Every reflector (and its first-order mirror image in each wall) returns the waveform
    delayed by its bistatic path over ``c``, scaled by its amplitude, spherical spreading
    ``1 / (r_tx r_rx)`` and ISO 9613-1 air absorption over the path, evaluated per frequency.
    Delays are exact (applied as phase ramps in the frequency domain, not rounded to samples).

    Parameters
    ----------
    scene : Scene
    aperture : Aperture
    waveform : (n_wave,) array
        Transmitted signal sampled at ``fs_hz``, starting at the transmit time.
    fs_hz : float
        Sample rate, Hz.
    n_samples : int, optional
        Samples per recording; default covers the farthest echo plus the waveform.
    t0_s : float or (n_meas,) array
        Time of sample 0 after the transmit start, s (latency of the recording).
    snr_db : float, optional
        Add white Gaussian noise whose power is the mean echo power over the whole dataset
        divided by ``10^(snr_db/10)``; ``None`` adds no noise.
    seed : int, optional
        Seed of the noise generator.
    absorption : bool
        Apply air absorption.
    chirp, config : stored in the dataset's attributes.
    temperature_c : float or (n_meas,) array, optional
        Air temperature during each measurement (default the scene's): air that changes
        during a scan gives each measurement its own speed of sound. Absorption uses the
        mean temperature. The dataset records it (and so its ``c_mps`` per measurement).
    progress : callable(done, total), optional
        Called after each block of measurements.

    Returns
    -------
    Dataset
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a clsas.Scene, got {type(scene).__name__}")
    if not isinstance(aperture, Aperture):
        raise TypeError(f"aperture must be a clsas.Aperture, got {type(aperture).__name__}")
    fs = v.positive("fs_hz", fs_hz)
    wave = v.array("waveform", waveform, ndim=1)
    n_meas = aperture.n_meas
    t0 = np.broadcast_to(np.asarray(t0_s, dtype=float), (n_meas,)).copy()
    v.array("t0_s", t0)
    if snr_db is not None:
        snr_db = v.finite("snr_db", snr_db)
    if temperature_c is None:
        temperature_c = scene.temperature_c
    elif np.ndim(temperature_c):
        temperature_c = v.array("temperature_c", temperature_c, shape=(n_meas,))
    c = np.broadcast_to(np.asarray(speed_of_sound(temperature_c), float), (n_meas,))
    t_mean = float(np.mean(temperature_c))

    src, amp = scene.image_sources()
    tx, rx = aperture.tx_positions, aperture.rx_positions
    r_tx = np.linalg.norm(src[None, :, :] - tx[:, None, :], axis=2)  # (n_meas, k)
    r_rx = np.linalg.norm(src[None, :, :] - rx[:, None, :], axis=2)
    path = r_tx + r_rx
    gain = amp[None, :] / np.maximum(r_tx * r_rx, 1e-6)
    if scene.wall_echo:
        for wall in scene.walls:
            p = np.linalg.norm(wall.mirror(tx) - rx, axis=1)[:, None]
            path = np.concatenate([path, p], axis=1)
            gain = np.concatenate([gain, wall.reflectivity / np.maximum(p, 1e-6)], axis=1)
    delay = path / c[:, None] - t0[:, None]  # delay into the recording, s
    if n_samples is None:
        n_samples = int(np.ceil((delay.max(initial=0.0) * fs) + len(wave))) + 16
    n_samples = v.positive_int("n_samples", n_samples)

    # long enough that no echo (early or late) wraps around into the kept samples
    span = max(n_samples, delay.max(initial=0.0) * fs) + max(0.0, -delay.min(initial=0.0)) * fs
    import scipy.fft

    n_fft = scipy.fft.next_fast_len(int(np.ceil(span)) + len(wave) + 16)
    spec = scipy.fft.rfft(wave, n_fft)
    freqs = scipy.fft.rfftfreq(n_fft, 1 / fs)
    keep = np.abs(spec) > 1e-7 * np.abs(spec).max(initial=0.0)  # only bins with energy
    spec_k, f_k = spec[keep], freqs[keep]
    log.debug("simulate: %d sources, %d of %d frequency bins", src.shape[0], keep.sum(), len(freqs))
    beta = (
        air_absorption_db_per_m(f_k, t_mean, scene.humidity_pct) * np.log(10) / 20
        if absorption
        else np.zeros_like(f_k)
    )

    signals = np.zeros((n_meas, n_samples), dtype=np.float64)
    block = max(1, int(2e7 // max(1, path.shape[1] * len(f_k))))
    for start in range(0, n_meas, block):
        sl = slice(start, min(n_meas, start + block))
        # (b, k, f): gain * exp(-beta L) * exp(-j 2 pi f delay)
        expo = -path[sl, :, None] * beta[None, None, :] - 2j * np.pi * delay[sl, :, None] * f_k
        h = np.einsum("bk,bkf->bf", gain[sl], np.exp(expo))
        full = np.zeros((h.shape[0], len(freqs)), dtype=np.complex128)
        full[:, keep] = h * spec_k
        signals[sl] = scipy.fft.irfft(full, n_fft, axis=1)[:, :n_samples]
        if progress is not None:
            progress(sl.stop, n_meas)

    if snr_db is not None:
        rng = np.random.default_rng(seed)
        p_sig = float(np.mean(signals**2))
        sigma = np.sqrt(p_sig / 10 ** (snr_db / 10)) if p_sig > 0 else 0.0
        signals += rng.normal(0.0, sigma, signals.shape)

    return Dataset(
        signals=signals,
        tx_positions=tx,
        rx_positions=rx,
        fs_hz=fs,
        waveform=wave,
        t0_s=t0,
        temperature_c=temperature_c,
        humidity_pct=scene.humidity_pct,
        stage_positions=aperture.stage_positions,
        chirp=chirp or {},
        config=config,
    )
