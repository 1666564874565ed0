"""Play the chirp and record the microphones and the loopback channel.

Each take plays the chirp on the speaker output and records the microphone inputs and one
loopback input, wired to the speaker drive. The chirp's onset on the loopback channel (its
cross-correlation peak, refined to a fraction of a sample) is the true output-to-input latency
of that take; the stored recording starts at the onset's sample, and ``t0_s`` (the time of
sample 0 after the transmit start) holds the fraction left over and the calibrated acoustic
delay. A take with clipping or a stream over/underflow is retried.

Two sources share :class:`Recorder`: :class:`SoundDeviceIO` (a real sound card through
sounddevice and PortAudio, imported only here) and :class:`SimulatedIO` (what the simulator
says the microphones would hear, for ``clsas acquire --simulate``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.signal

from .. import validate as v
from ..physics.geometry import Aperture, Scene
from ..synthesis.simulation import simulate
from ..validate import install_hint

__all__ = ["AudioError", "Take", "Recorder", "SoundDeviceIO", "SimulatedIO", "find_onset", "import_sounddevice",
           "list_audio_devices"]

log = logging.getLogger(__name__)


class AudioError(RuntimeError):
    """The audio device failed, or a take could not be recorded cleanly."""


def import_sounddevice():
    """Import sounddevice, or say what to install."""
    try:
        import sounddevice
    except ImportError as exc:
        raise ImportError(f"audio acquisition needs sounddevice: {install_hint('rig')}") from exc
    except OSError as exc:  # sounddevice raises OSError when the PortAudio library is missing
        raise ImportError(
            f"sounddevice could not load PortAudio ({exc}): install the system package "
            "(Debian/Ubuntu: sudo apt-get install libportaudio2; Fedora: portaudio; macOS: brew install portaudio)"
        ) from exc
    return sounddevice


def list_audio_devices() -> list[dict]:
    """Audio devices with their channels and which of 96 and 192 kHz they accept."""
    sd = import_sounddevice()
    rows = []
    for i, d in enumerate(sd.query_devices()):
        rates = []
        for fs in (96000, 192000):
            ok = False
            for check, n in ((sd.check_output_settings, d["max_output_channels"]),
                             (sd.check_input_settings, d["max_input_channels"])):
                if n:
                    try:
                        check(device=i, samplerate=fs, channels=1)
                        ok = True
                    except sd.PortAudioError:
                        ok = False
                        break
            if ok:
                rates.append(fs)
        api = sd.query_hostapis(d["hostapi"])["name"]
        rows.append({"index": i, "name": d["name"], "hostapi": api, "inputs": d["max_input_channels"],
                     "outputs": d["max_output_channels"], "default_hz": d["default_samplerate"], "rates_hz": rates})
    return rows


def find_onset(loopback: np.ndarray, waveform: np.ndarray, min_correlation: float = 0.5) -> float:
    """Sample index (fractional) where ``waveform`` starts in ``loopback``.

    The envelope peak of the cross-correlation with the analytic chirp picks the whole sample
    (a carrier-rate ripple cannot fool it); the correlation's phase there gives the fraction
    (phase = 2 pi f_c x offset, f_c the chirp's spectral centroid). A whole-sample delay gives
    phase 0 exactly. Raises :class:`AudioError` when the best match is too weak to be the chirp.
    """
    x = v.array("loopback", loopback, ndim=1)
    w = v.array("waveform", waveform, ndim=1)
    if len(x) < len(w):
        raise AudioError("the loopback recording is shorter than the chirp")
    n = scipy.fft.next_fast_len(2 * len(w))
    spec = scipy.fft.fft(w, n)
    freqs = scipy.fft.fftfreq(n)
    centroid = float(np.sum(np.abs(freqs) * np.abs(spec) ** 2) / np.sum(np.abs(spec) ** 2))  # cycles/sample
    wa = scipy.fft.ifft(spec * (1 + np.sign(freqs)))[: len(w)]  # analytic chirp
    c = scipy.signal.correlate(x, wa, mode="valid", method="fft")  # sum x[k + i] conj(wa[i])
    env = np.abs(c)
    k = int(np.argmax(env))
    seg = x[k:k + len(w)]
    norm = np.linalg.norm(seg) * np.linalg.norm(w)
    rho = env[k] / np.sqrt(2) / norm if norm > 0 else 0.0
    if rho < min_correlation:
        raise AudioError(f"no chirp on the loopback channel (best normalised correlation {rho:.2f}): "
                         "check that the speaker drive is wired back to the loopback input")
    frac = -np.angle(c[k]) / (2 * np.pi * centroid)
    if abs(frac) > 1.0 and 0 < k < len(c) - 1:  # phase wrapped: fall back to the envelope's parabola
        a, b, d = env[k - 1:k + 2]
        frac = 0.5 * (a - d) / (a - 2 * b + d)
    return k + float(frac)


@dataclass
class Take:
    """One stop's recording: (n_mics, n_samples) signals from the onset, the loopback, t0."""

    signals: np.ndarray
    loopback: np.ndarray
    t0_s: float
    onset_samples: float
    attempts: int
    problems: list[str] = field(default_factory=list)


@dataclass
class StopContext:
    index: int
    attempt: int
    tx_m: np.ndarray
    rx_m: np.ndarray  # (n_mics, 3)
    repeat: int = 0


class Recorder:
    """Plays the chirp through ``io`` and turns the raw inputs into a :class:`Take`.

    Parameters
    ----------
    io : SoundDeviceIO or SimulatedIO
        ``io.playrec(drive (n,), context) -> (inputs (n, 1 + n_mics), problems)``: loopback first.
    waveform : (n_wave,) unit-peak chirp; it is played at ``level``.
    fs_hz : sample rate (Hz).
    n_samples : int, optional
        Samples kept per take after the onset; or give ``record_s`` (s) instead.
    level, record_s, repeats, repeat_gap_s, retries, clip_level, max_latency_s, acoustic_delay_s :
        see ``rig.toml``'s ``[recorder]``, whose keys are these arguments.
    """

    def __init__(self, io, waveform: np.ndarray, fs_hz: float, n_samples: int | None = None, *,
                 record_s: float | None = None, level: float = 0.5, repeats: int = 1, repeat_gap_s: float = 0.05,
                 retries: int = 3, clip_level: float = 0.99, max_latency_s: float = 0.1,
                 acoustic_delay_s: float = 0.0) -> None:
        if not callable(getattr(io, "playrec", None)):
            raise TypeError(f"io must have a playrec(out, context) method, got {type(io).__name__}")
        self.io = io
        self.waveform = v.array("waveform", waveform, ndim=1)
        level = v.positive("level", level)
        clip_level = v.positive("clip_level", clip_level)
        if level > 1 or clip_level > 1:
            raise ValueError(f"level and clip_level are fractions of full scale (at most 1), got {level}, {clip_level}")
        self.drive = level * self.waveform
        self.fs_hz = v.positive("fs_hz", fs_hz)
        if (n_samples is None) == (record_s is None):
            raise TypeError("give the take's length as n_samples or as record_s (one of them)")
        if record_s is not None:
            n_samples = int(round(v.positive("record_s", record_s) * self.fs_hz))
        self.n_samples = v.positive_int("n_samples", n_samples)
        self.repeats = v.positive_int("repeats", repeats)
        self.gap = int(round(v.non_negative("repeat_gap_s", repeat_gap_s) * fs_hz))
        self.retries = v.positive_int("retries", retries)
        self.clip_level = clip_level
        max_latency_s = v.positive("max_latency_s", max_latency_s)
        self.n_buffer = self.n_samples + int(np.ceil(max_latency_s * fs_hz))
        self.acoustic_delay_s = v.finite("acoustic_delay_s", acoustic_delay_s)

    def take(self, index: int, tx_m: np.ndarray, rx_m: np.ndarray) -> Take:
        """Record stop ``index``, retrying on clipping and over/underflow."""
        problems: list[str] = []
        for attempt in range(1, self.retries + 1):
            ctx = StopContext(index, attempt, np.asarray(tx_m, float), np.atleast_2d(rx_m))
            got = self._attempt(ctx)
            if isinstance(got, Take):
                got.attempts, got.problems = attempt, problems
                return got
            problems.append(f"attempt {attempt}: {got}")
            log.warning("stop %d, attempt %d of %d: %s", index + 1, attempt, self.retries, got)
        raise AudioError(f"stop {index + 1} failed {self.retries} times: " + "; ".join(problems))

    def _attempt(self, ctx: StopContext) -> Take | str:
        sigs, loops, fracs = [], [], []
        for r in range(self.repeats):
            ctx.repeat = r
            out = np.zeros(self.n_buffer)
            out[:len(self.drive)] = self.drive
            rec, flags = self.io.playrec(out, ctx)
            rec = np.asarray(rec, float)
            if flags:
                return "stream status: " + ", ".join(flags)
            peak = np.abs(rec).max(axis=0)
            if (peak >= self.clip_level).any():
                ch = [i for i, p in enumerate(peak) if p >= self.clip_level]
                names = ["loopback" if i == 0 else f"microphone {i}" for i in ch]
                return f"clipping on {', '.join(names)} (peak {peak.max():.3f}): lower audio.level or the input gain"
            onset = find_onset(rec[:, 0], self.waveform)
            start = int(np.floor(onset + 0.5))
            if start + self.n_samples > len(rec):
                raise AudioError(f"the latency ({onset / self.fs_hz * 1e3:.1f} ms) leaves less than audio.record_s "
                                 "in the buffer: raise audio.max_latency_s")
            sigs.append(rec[start:start + self.n_samples, 1:].T)
            loops.append(rec[start:start + self.n_samples, 0])
            fracs.append(onset - start)
            if self.gap:
                self.io.pause(self.gap / self.fs_hz)
        onset_mean = float(np.mean(fracs))
        return Take(np.mean(sigs, axis=0), np.mean(loops, axis=0),
                    -onset_mean / self.fs_hz - self.acoustic_delay_s, start + onset_mean, 0)


class SoundDeviceIO:
    """A sound card through sounddevice: ``playrec`` on one output and the loopback + microphones."""

    def __init__(self, device: str | int, fs_hz: float, output_channel: int, loopback_channel: int,
                 mic_channels: list[int]) -> None:
        self.sd = import_sounddevice()
        self.fs_hz = fs_hz
        self.output_channel = output_channel
        self.inputs = [loopback_channel, *mic_channels]
        try:
            self.device = None if device == "default" else device
            self.sd.check_output_settings(device=self.device, samplerate=fs_hz, channels=output_channel)
            self.sd.check_input_settings(device=self.device, samplerate=fs_hz, channels=max(self.inputs))
        except (self.sd.PortAudioError, ValueError) as exc:
            raise AudioError(f"audio device {device!r} cannot play channel {output_channel} and record channels "
                             f"{self.inputs} at {fs_hz:g} Hz: {exc} (see `clsas devices`)") from exc

    def playrec(self, out: np.ndarray, ctx: StopContext) -> tuple[np.ndarray, list[str]]:
        sd = self.sd
        try:
            rec = sd.playrec(out.astype(np.float32)[:, None], samplerate=self.fs_hz, device=self.device,
                             input_mapping=self.inputs, output_mapping=[self.output_channel], blocking=True)
            status = sd.get_status()
        except sd.PortAudioError as exc:
            raise AudioError(f"audio device error: {exc}") from exc
        flags = [name.replace("_", " ") for name in ("input_overflow", "input_underflow", "output_underflow",
                                                     "output_overflow") if getattr(status, name)]
        return rec, flags

    def pause(self, seconds: float) -> None:
        import time

        time.sleep(seconds)


class SimulatedIO:
    """What the microphones would hear: the simulator's echoes of ``scene`` at the stop's positions.

    The loopback is the drive delayed by a whole-sample latency that changes from stop to
    stop; the microphones hear the same latency plus the acoustic path, scaled by ``mic_gain``
    (the simulator's amplitudes are per square metre of spreading). Noise is seeded per
    stop and attempt, so a resumed scan records what an uninterrupted one would.

    Faults (stop indices are 0-based): ``clip_at_stop`` and ``xrun_at_stop`` spoil the first
    attempt of that stop (retried), ``error_at_stop`` raises an audio device error.
    ``beams_for`` (speaker and microphone positions (m, 3) -> :class:`clsas.physics.beam.Beams` or None,
    e.g. :meth:`clsas.rig.RigConfig.beams_for`) gives the transducers' directivity, which the
    simulator then applies.
    """

    def __init__(self, scene: Scene, fs_hz: float, *, latency_samples: int = 300, noise_rms: float = 1e-4,
                 mic_gain: float = 0.05, seed: int = 0, clip_at_stop: int | None = None,
                 xrun_at_stop: int | None = None, error_at_stop: int | None = None, beams_for=None) -> None:
        self.scene = scene
        self.beams_for = beams_for
        self.fs_hz = float(fs_hz)
        self.latency = int(latency_samples)
        self.noise_rms = float(noise_rms)
        self.mic_gain = float(mic_gain)
        self.seed = int(seed)
        self.clip_at_stop, self.xrun_at_stop, self.error_at_stop = clip_at_stop, xrun_at_stop, error_at_stop

    def playrec(self, out: np.ndarray, ctx: StopContext) -> tuple[np.ndarray, list[str]]:
        if ctx.index == self.error_at_stop:
            raise AudioError("audio device error: [PaErrorCode -9999] Unanticipated host error (simulated)")
        n = len(out)
        lat = self.latency + (ctx.index * 7) % 11  # latency wanders by whole samples
        nz = np.flatnonzero(out)
        wave = out[: nz[-1] + 1] if len(nz) else out[:1]
        m = len(ctx.rx_m)
        ap = Aperture(np.repeat(ctx.tx_m[None, :], m, 0), ctx.rx_m, np.repeat(ctx.tx_m[None, :], m, 0))
        beams = None if self.beams_for is None else self.beams_for(ap.tx_positions, ap.rx_positions)
        mics = simulate(self.scene, ap, wave, self.fs_hz, n_samples=n, t0_s=-lat / self.fs_hz, beams=beams).signals
        rng = np.random.default_rng([self.seed, ctx.index, ctx.attempt, ctx.repeat])
        rec = np.zeros((n, 1 + m))
        rec[lat:, 0] = out[: n - lat]
        rec[:, 1:] = self.mic_gain * mics.T + rng.normal(0.0, self.noise_rms, (n, m))
        flags: list[str] = []
        if ctx.attempt == 1 and ctx.index == self.clip_at_stop:
            rec[:, 1:] = np.clip(rec[:, 1:] * 1e4, -1.0, 1.0)
        if ctx.attempt == 1 and ctx.index == self.xrun_at_stop:
            flags.append("input overflow")
        return rec, flags

    def pause(self, seconds: float) -> None:
        """No wait: the simulated room has no reverberation to let ring down."""
