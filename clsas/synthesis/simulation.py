"""Forward model: scene + aperture + waveform -> Dataset."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from .. import validate as v
from ..physics.beam import Beams
from ..physics.geometry import Aperture, Scene
from ..physics.scan_errors import HandMotion
from ..physics.sound import air_absorption_db_per_m, speed_of_sound
from ..physics.specular import Surface
from ..types.dataset import Dataset

__all__ = ["simulate"]

log = logging.getLogger(__name__)


def simulate(scene: Scene, aperture: Aperture, waveform: np.ndarray, fs_hz: float, *, n_samples: int | None = None,
             t0_s: float | np.ndarray = 0.0, snr_db: float | None = None, seed: int | None = 0, absorption: bool = True,
             chirp: dict | None = None, config: str = "", temperature_c: float | np.ndarray | None = None,
             progress: Callable[[int, int], None] | None = None,
             position_error: float | HandMotion | np.ndarray | None = None, temperature_error_c: float = 0.0,
             group_delay_s: float = 0.0, timing_jitter_s: float = 0.0, direct_gain: float | None = None,
             beams: Beams | None = None, surfaces: Sequence[Surface] = (), c_mps: float | None = None) -> Dataset:
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
        Air temperature during each measurement (default the scene's): air that changes during a
        scan gives each measurement its own speed of sound (at the scene's humidity). Absorption
        uses the mean temperature. The dataset records both (so the same ``c_mps`` per measurement).
    progress : callable(done, total), optional
        Called after each block of measurements.
    position_error : float, HandMotion or array, optional
        The carriage was not where the dataset says (:mod:`clsas.physics.scan_errors`): a
        :class:`~clsas.scan_errors.HandMotion` (band-limited 3-D jitter in time), a float (its
        RMS in m with the default band and dwell, seeded by ``seed``), or the true-minus-stated
        displacements, (n_stops, 3) or (n_meas, 3) m. Speaker and microphones move together.
        The dataset states the aperture's positions and gets the stop times as ``timestamps``.
    temperature_error_c : float
        The air was this much warmer than the dataset states (``temperature_c``), °C.
    group_delay_s : float
        A delay of the sound the dataset does not know about (transducers, converters), s:
        the true ``t0_s`` is the stated one minus this.
    timing_jitter_s : float
        RMS of a random extra delay per stop (seeded by ``seed``), s.
    direct_gain : float, optional
        Add the direct speaker-to-microphone sound, with amplitude ``direct_gain / |tx - rx|``
        (a reflector of amplitude a at ranges r1, r2 returns ``a / (r1 r2)``); None: none.
    beams, surfaces, c_mps : directional transducers, specular facets, another medium (see :data:`EXTRAS`).

    Any of the errors above stores the truth in ``Dataset.truth``: ``tx_positions``, ``rx_positions``,
    ``position_error_m`` (true minus stated, per measurement), ``t0_s``, ``group_delay_s``,
    ``timing_jitter_s`` (per measurement), ``temperature_c``, ``c_mps``, ``stop_time_s`` and ``stop_index``.

    Returns
    -------
    Dataset
    """
    fs, wave, t0, snr_db, temperature_c = _checked(scene, aperture, fs_hz, waveform, t0_s, snr_db, temperature_c)
    err = _errors(aperture, seed, position_error, temperature_error_c, group_delay_s, timing_jitter_s)
    true_temp, c, t0_true = _true_air_and_t0(temperature_c, t0, err, aperture.n_meas, c_mps, scene.humidity_pct)
    tx, rx, path, gain, n_sources, shaping = _echoes(scene, aperture, err, direct_gain, beams, surfaces, c)
    delay = path / c[:, None] - t0_true[:, None]  # delay into the recording, s
    n_samples = v.positive_int("n_samples", _n_samples(delay, fs, len(wave)) if n_samples is None else n_samples)
    signals = _recordings(wave, fs, path, gain, delay, n_samples, n_sources,
                          scene.humidity_pct, float(np.mean(true_temp)) if absorption and c_mps is None else None,
                          progress, shaping)
    _add_noise(signals, snr_db, seed)
    return Dataset(signals, aperture.tx_positions, aperture.rx_positions, fs, wave, t0_s=t0, c_mps=c_mps, beams=beams,
                   temperature_c=temperature_c, humidity_pct=scene.humidity_pct, chirp=chirp or {}, config=config,
                   stage_positions=aperture.stage_positions, timestamps=err["stop_time_s"] if err["moved"] else None,
                   truth=_truth(err, tx, rx, t0_true, true_temp, c) if err["any"] else {})


def _checked(scene, aperture, fs_hz, waveform, t0_s, snr_db, temperature_c):
    """:func:`simulate`'s scene, aperture, rate, waveform, t0, SNR and temperature checked:
    (fs, waveform, t0 per measurement, snr_db, temperature_c)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a clsas.Scene, got {type(scene).__name__}")
    if not isinstance(aperture, Aperture):
        raise TypeError(f"aperture must be a clsas.Aperture, got {type(aperture).__name__}")
    fs = v.sampling_rate("fs_hz", fs_hz)
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
    return fs, wave, t0, snr_db, temperature_c


def _true_air_and_t0(temperature_c, t0: np.ndarray, err: dict, n_meas: int, c_mps: float | None = None,
                     humidity_pct: float = 50.0):
    """The true air temperature (the stated one plus the error), °C, its speed of sound per
    measurement at ``humidity_pct`` (the scene's, which the dataset carries), m/s (``c_mps`` for
    another medium), and the true t0 per measurement (less the unknown delays), s."""
    true_temp = np.asarray(temperature_c, float) + err["temperature_error_c"]
    c = np.broadcast_to(np.asarray(speed_of_sound(true_temp, humidity_pct), float), (n_meas,))
    if c_mps is not None:
        if err["temperature_error_c"]:
            raise ValueError("temperature_error_c applies to air; it cannot go with c_mps")
        c = np.full(n_meas, v.positive("c_mps", c_mps))
    return true_temp, c, t0 - err["group_delay_s"] - err["timing_jitter_s"]


def _n_samples(delay: np.ndarray, fs: float, n_wave: int) -> int:
    """The default recording length: the latest echo's delay (s) plus the waveform and 16 samples."""
    return int(np.ceil((delay.max(initial=0.0) * fs) + n_wave)) + 16


def _truth(err: dict, tx: np.ndarray, rx: np.ndarray, t0_true: np.ndarray, true_temp, c: np.ndarray) -> dict:
    """``Dataset.truth`` of a scan simulated with errors (see :func:`simulate`)."""
    return {"tx_positions": tx, "rx_positions": rx, "position_error_m": err["position_error_m"],
            "t0_s": t0_true, "group_delay_s": err["group_delay_s"], "timing_jitter_s": err["timing_jitter_s"],
            "temperature_c": true_temp if np.ndim(true_temp) else float(true_temp),
            "c_mps": c.copy(), "stop_time_s": err["stop_time_s"], "stop_index": err["stop_index"],
            "errors": err["spec"]}


def _paths(scene: Scene, aperture: Aperture, displacement_m: np.ndarray, direct_gain: float | None):
    """The true speaker and microphone positions (the aperture's moved by ``displacement_m``),
    every echo's two-way path (n_meas, n_echoes), m, and its amplitude (spreading, wall
    reflectivity, direct sound), and the number of (image) sources: the reflectors and their
    mirror images first, then each wall's echo (where ``scene.wall_echo``), then the direct sound."""
    if direct_gain is not None:
        direct_gain = v.non_negative("direct_gain", direct_gain)
    tx, rx = aperture.tx_positions + displacement_m, aperture.rx_positions + displacement_m
    src, amp = scene.image_sources()
    r_tx = np.linalg.norm(src[None, :, :] - tx[:, None, :], axis=2)  # (n_meas, k)
    r_rx = np.linalg.norm(src[None, :, :] - rx[:, None, :], axis=2)
    path = r_tx + r_rx
    gain = amp[None, :] / np.maximum(r_tx * r_rx, 1e-6)
    if scene.wall_echo:
        for wall in scene.walls:
            p = np.linalg.norm(wall.mirror(tx) - rx, axis=1)[:, None]
            path = np.concatenate([path, p], axis=1)
            gain = np.concatenate([gain, wall.reflectivity / np.maximum(p, 1e-6)], axis=1)
    if direct_gain:
        p = np.linalg.norm(tx - rx, axis=1)[:, None]
        path = np.concatenate([path, p], axis=1)
        gain = np.concatenate([gain, direct_gain / np.maximum(p, 1e-6)], axis=1)
    return tx, rx, path, gain, src.shape[0]


def _recordings(wave: np.ndarray, fs: float, path: np.ndarray, gain: np.ndarray, delay: np.ndarray, n_samples: int,
                n_sources: int, humidity_pct: float, absorption_temperature_c: float | None,
                progress: Callable[[int, int], None] | None, shaping: _Shaping | None = None) -> np.ndarray:
    """(n_meas, n_samples) the noise-free recordings: each echo the waveform delayed by
    ``delay`` (s, exact: a phase ramp per frequency), scaled by ``gain`` and absorbed over
    ``path`` (m) at ``absorption_temperature_c`` (None: no absorption), summed in blocks of
    measurements (``progress`` after each); ``shaping`` multiplies each echo's spectrum (beams,
    facets)."""
    import scipy.fft

    n_meas = len(path)
    # long enough that no echo (early or late) wraps around into the kept samples
    span = max(n_samples, delay.max(initial=0.0) * fs) + max(0.0, -delay.min(initial=0.0)) * fs
    n_fft = scipy.fft.next_fast_len(int(np.ceil(span)) + len(wave) + 16)
    spec = scipy.fft.rfft(wave, n_fft)
    freqs = scipy.fft.rfftfreq(n_fft, 1 / fs)
    floor = 1e-7 if shaping is None else 1e-5  # -100 dB where every echo's spectrum is shaped
    keep = np.abs(spec) > floor * np.abs(spec).max(initial=0.0)  # only bins with energy
    spec_k, f_k = spec[keep], freqs[keep]
    log.debug("simulate: %d sources, %d of %d frequency bins", n_sources, keep.sum(), len(freqs))
    beta = (
        air_absorption_db_per_m(f_k, absorption_temperature_c, humidity_pct) * np.log(10) / 20
        if absorption_temperature_c is not None
        else np.zeros_like(f_k)
    )
    signals = np.zeros((n_meas, n_samples), dtype=np.float64)
    budget = 2e7 if shaping is None else 6e6  # (b, k, f) complex elements per block
    block = max(1, int(budget // max(1, path.shape[1] * len(f_k))))
    for start in range(0, n_meas, block):
        sl = slice(start, min(n_meas, start + block))
        # (b, k, f): gain * exp(-beta L) * exp(-j 2 pi f delay)
        expo = -path[sl, :, None] * beta[None, None, :] - 2j * np.pi * delay[sl, :, None] * f_k
        resp = np.exp(expo)
        if shaping is not None:
            resp *= shaping(sl, f_k)
        h = np.einsum("bk,bkf->bf", gain[sl], resp)
        full = np.zeros((h.shape[0], len(freqs)), dtype=np.complex128)
        full[:, keep] = h * spec_k
        signals[sl] = scipy.fft.irfft(full, n_fft, axis=1)[:, :n_samples]
        if progress is not None:
            progress(sl.stop, n_meas)
    return signals


def _add_noise(signals: np.ndarray, snr_db: float | None, seed: int | None) -> None:
    """Add white Gaussian noise at ``snr_db`` below the mean signal power, in place (None: none)."""
    if snr_db is None:
        return
    rng = np.random.default_rng(seed)
    p_sig = float(np.mean(signals**2))
    sigma = np.sqrt(p_sig / 10 ** (snr_db / 10)) if p_sig > 0 else 0.0
    signals += rng.normal(0.0, sigma, signals.shape)


def _errors(aperture: Aperture, seed, position_error, temperature_error_c, group_delay_s, timing_jitter_s) -> dict:
    """The true-minus-stated errors per measurement (see :func:`simulate`)."""
    n, k = aperture.n_meas, aperture.mics_per_stop
    n_stops = n // k
    stops = np.repeat(np.arange(n_stops), k)
    spec: dict = {}
    motion = HandMotion(float(position_error), seed=0 if seed is None else int(seed)) \
        if isinstance(position_error, int | float) and not isinstance(position_error, bool) else position_error
    if motion is None:
        disp = np.zeros((n_stops, 3))
        times = np.arange(n_stops) * HandMotion().dwell_s
    elif isinstance(motion, HandMotion):
        disp = motion.displacements(n_stops)
        times = motion.stop_times(n_stops)
        spec["position_error"] = {"rms_m": motion.rms_m, "band_hz": list(motion.band_hz), "dwell_s": motion.dwell_s,
                                  "seed": motion.seed, "per_axis": motion.per_axis, "weights": list(motion.weights)}
    else:
        disp = v.array("position_error", motion, shape=(None, 3))
        if len(disp) == n and k > 1:
            if np.any(disp.reshape(n_stops, k, 3) != disp[::k, None, :]):
                raise ValueError("position_error: the microphones of one stop must move with it (one rigid carriage)")
            disp = disp[::k]
        if len(disp) != n_stops:
            raise ValueError(f"position_error must have shape ({n_stops}, 3) or ({n}, 3), got {disp.shape}")
        times = np.arange(n_stops) * HandMotion().dwell_s
        spec["position_error"] = {"given": True}
    dt = v.finite("temperature_error_c", temperature_error_c)
    gd = v.finite("group_delay_s", group_delay_s)
    tj = v.non_negative("timing_jitter_s", timing_jitter_s)
    jitter = np.zeros(n_stops)
    if tj > 0:
        jitter = np.random.default_rng([0 if seed is None else int(seed), 14]).normal(0.0, tj, n_stops)
    spec.update(temperature_error_c=dt, group_delay_s=gd, timing_jitter_s=tj)
    moved = motion is not None
    return {"position_error_m": disp[stops], "stop_time_s": times[stops], "stop_index": stops,
            "temperature_error_c": dt, "group_delay_s": gd, "timing_jitter_s": jitter[stops], "spec": spec,
            "moved": moved, "any": moved or dt != 0 or gd != 0 or tj > 0}


EXTRAS = """simulate's keywords for directional transducers, specular surfaces and other media.

beams : clsas.physics.beam.Beams, optional
    Directional transducers: every echo (reflectors, mirror images, facets, wall echoes, the
    direct sound) is scaled by the speaker's pattern toward where the sound leaves and the
    microphone's toward where it arrives from, at each frequency (a piston's beam narrows with
    frequency). The dataset records them. None: omnidirectional.
surfaces : sequence of clsas.physics.specular.Surface
    Specular surfaces (flat facets with their Kirchhoff lobe, :mod:`clsas.physics.specular`).
c_mps : float, optional
    A medium other than air (e.g. 1480 for water): this speed of sound for every measurement,
    stored in the dataset, and no air absorption. Not with ``temperature_error_c``.
"""


def _echoes(scene, aperture, err, direct_gain, beams, surfaces, c):
    """:func:`_paths` plus the specular facets' echoes, and the shaping of every echo's spectrum
    (None where nothing is shaped): ``(tx, rx, path, gain, n_sources, shaping)``."""
    beams, surfaces = _checked_beams(beams, surfaces, aperture.n_meas)
    tx, rx, path, gain, n_sources = _paths(scene, aperture, err["position_error_m"], direct_gain)
    shaping = _Shaping(scene, tx, rx, path.shape[1], direct_gain, beams, float(np.mean(c)))
    for surf in surfaces:
        path, gain = shaping.add_surface(surf, path, gain)
    return tx, rx, path, gain, n_sources, shaping if shaping.active else None


def _checked_beams(beams, surfaces, n_meas: int) -> tuple[Beams | None, tuple[Surface, ...]]:
    if beams is not None:
        if not isinstance(beams, Beams):
            raise TypeError(f"beams must be clsas.physics.beam.Beams or None, got {type(beams).__name__}")
        if beams.n_meas != n_meas:
            raise ValueError(f"beams must have n_meas={n_meas} boresights, got {beams.n_meas}")
        if beams.is_omni:
            beams = None
    if isinstance(surfaces, Surface):
        surfaces = (surfaces,)
    surfaces = tuple(surfaces)
    for i, surf in enumerate(surfaces):
        if not isinstance(surf, Surface):
            raise TypeError(f"surfaces[{i}] must be a clsas.physics.specular.Surface, got {type(surf).__name__}")
    return beams, surfaces


class _Shaping:
    """The frequency response of each echo beyond a delay and a flat gain: the transducers'
    beams toward where each echo leaves and arrives from, and a facet's ``j f`` and lobe."""

    def __init__(self, scene: Scene, tx: np.ndarray, rx: np.ndarray, n_cols: int, direct_gain, beams, c: float):
        self.tx, self.rx, self.beams, self.c = tx, rx, beams, c
        src, _ = scene.image_sources()
        n = len(tx)
        dep = [np.broadcast_to(src[None], (n, len(src), 3))]
        arr = [dep[0]]
        if scene.wall_echo:
            for wall in scene.walls:
                dep.append(wall.mirror(rx)[:, None, :])
                arr.append(wall.mirror(tx)[:, None, :])
        if direct_gain:
            dep.append(rx[:, None, :])
            arr.append(tx[:, None, :])
        self.dep, self.arr = np.concatenate(dep, axis=1), np.concatenate(arr, axis=1)
        if self.dep.shape[1] != n_cols:
            raise RuntimeError(f"simulate: {self.dep.shape[1]} echo directions for {n_cols} echoes")
        self.facets: list[tuple[int, np.ndarray, np.ndarray]] = []  # (first column, qu, qv)

    @property
    def active(self) -> bool:
        return self.beams is not None or bool(self.facets)

    def add_surface(self, surf: Surface, path: np.ndarray, gain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = surf.geometry(self.tx, self.rx, self.c)
        self.facets.append((path.shape[1], g["qu"], g["qv"]))
        pts = np.broadcast_to(surf.centers_m[None], (len(self.tx), surf.n_facets, 3))
        self.dep = np.concatenate([self.dep, pts], axis=1)
        self.arr = np.concatenate([self.arr, pts], axis=1)
        return np.concatenate([path, g["path"]], axis=1), np.concatenate([gain, g["gain"]], axis=1)

    def __call__(self, sl: slice, f: np.ndarray) -> np.ndarray:
        """(b, k, f) complex multiplier of the measurements ``sl`` at frequencies ``f``, Hz."""
        n_cols = self.dep.shape[1]
        out = np.ones((sl.stop - sl.start, n_cols, len(f)), np.complex128)
        for k0, qu, qv in self.facets:
            k1 = k0 + qu.shape[1]
            out[:, k0:k1] = 1j * f * _sinc(qu[sl, :, None] * f) * _sinc(qv[sl, :, None] * f)
        if self.beams is not None:
            b = self.beams
            out *= _pattern(b.speaker, self.tx[sl], b.tx_boresight[sl], self.dep[sl], f, self.c)
            out *= _pattern(b.microphone, self.rx[sl], b.rx_boresight[sl], self.arr[sl], f, self.c)
        return out


def _pattern(beam, pos: np.ndarray, boresight: np.ndarray, toward: np.ndarray, f: np.ndarray, c: float):
    """(b, k, f) one-way pattern of ``beam`` at ``pos`` (b, 3) pointing ``boresight`` (b, 3)
    toward points ``toward`` (b, k, 3), at frequencies ``f``."""
    d = toward - pos[:, None, :]
    cos_t = (d * boresight[:, None, :]).sum(2) / np.maximum(np.linalg.norm(d, axis=2), 1e-30)
    theta = np.arccos(np.clip(cos_t, -1.0, 1.0))
    return beam.pattern_grid(theta, f, c)


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(pi x) / (pi x), 1 at 0 (numpy.sinc without its copies)."""
    px = np.pi * x
    small = np.abs(px) < 1e-12
    px[small] = 1.0
    out = np.sin(px)
    out /= px
    out[small] = 1.0
    return out
