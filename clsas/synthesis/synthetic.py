"""Scans that look measured: for tests, examples and benchmarks of the real-data path.

:func:`turntable_scan` imitates a circular in-air SAS scan (the AirSAS kind): the target
turns on a turntable while the speaker and microphone stay put, so in the target's frame the
transducers circle it. On top of the target's echoes it adds what measured recordings have
and simulated ones usually lack: static clutter of the room (the same in every ping, and in a
separate empty-scene scan), the direct speaker-to-microphone sound, a DC offset and mains hum,
air that warms during the scan (each ping its own speed of sound), and a transducer group
delay that the recording does not know about.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .. import validate as v
from ..physics.geometry import Aperture, Scene
from ..physics.signals import lfm_chirp
from ..types.dataset import Dataset
from .simulation import simulate

__all__ = ["TurntableScan", "turntable_scan", "curve_target"]


@dataclass
class TurntableScan:
    """A measured-looking scan, its empty-scene scan and the truth.

    Attributes
    ----------
    dataset : Dataset
        As an importer would give it: ``t0_s`` 0 (the group delay unknown to it), the logged
        per-ping ``temperature_c``, no ``background``.
    background : Dataset
        The empty scene (room clutter and direct sound only) at the same stops, another noise
        draw, the temperature of its own (earlier) scan.
    target_m : (k, 3) target scatterer positions in the target's frame, m.
    clutter_m : (j, 3) clutter positions in the room frame, m.
    group_delay_s : the delay hidden in the recordings, s.
    target_box_m : (3, 2) a box around the target, m (for a target-to-clutter ratio).
    """

    dataset: Dataset
    background: Dataset
    target_m: np.ndarray
    clutter_m: np.ndarray
    group_delay_s: float
    target_box_m: np.ndarray


def curve_target(n: int = 24, radius_m: float = 0.08, center_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """An extended target: ``n`` scatterers along a 270-degree arc plus a short straight
    bar through its centre (a letter-like shape), in the horizontal plane; (n, 3) m."""
    n = v.positive_int("n", n)
    r = v.positive("radius_m", radius_m)
    n_arc = max(1, (3 * n) // 4)
    a = np.linspace(0.25 * np.pi, 1.75 * np.pi, n_arc)
    arc = np.c_[r * np.cos(a), r * np.sin(a), np.zeros(n_arc)]
    bar = np.c_[np.linspace(0, r, n - n_arc), np.zeros(n - n_arc), np.zeros(n - n_arc)]
    return np.vstack([arc, bar]) + v.array("center_m", center_m, shape=(3,))


def _turntable_apertures(n: int, range_m: float):
    """The speaker and microphone in the room frame (fixed, m), and the aperture in the target's
    frame (turning with it) and in the room's, for ``n`` pings over one turn."""
    # transducers in the room frame (fixed): on the -x side, looking at the axis
    tx_room = np.array([-range_m, -0.025, 0.0])
    rx_room = np.array([-range_m, 0.025, 0.0])
    # in the target's frame the transducers turn by -theta about z
    theta = 2 * np.pi * np.arange(n) / n
    c, s = np.cos(-theta), np.sin(-theta)

    def rot(p):
        return np.c_[c * p[0] - s * p[1], s * p[0] + c * p[1], np.full(n, p[2])]

    ap_target = Aperture(rot(tx_room), rot(rx_room), np.zeros((n, 3)))
    ap_room = Aperture(np.tile(tx_room, (n, 1)), np.tile(rx_room, (n, 1)), np.zeros((n, 3)))
    return tx_room, rx_room, ap_target, ap_room


def turntable_scan(
    n_pings: int = 90,
    *,
    range_m: float = 0.8,
    fs_hz: float = 100e3,
    f_start_hz: float = 30e3,
    f_stop_hz: float = 10e3,
    duration_s: float = 1e-3,
    n_samples: int = 1000,
    target_m: np.ndarray | None = None,
    temperature_c: tuple[float, float] = (20.0, 26.0),
    background_temperature_c: float | None = None,
    humidity_pct: float = 50.0,
    clutter_db: float = 12.0,
    direct_db: float = 30.0,
    dc: float = 0.05,
    hum: float = 0.05,
    group_delay_samples: float = 62.33,
    snr_db: float = 25.0,
    seed: int = 0,
) -> TurntableScan:
    """A circular scan of an extended target, with clutter, drift and an unknown delay.

    The speaker and microphone (5 cm apart, at the target's height) look at the turntable's
    axis (the z axis) from ``range_m``; the turntable makes one turn in ``n_pings`` steps.
    Room clutter: three strong scatterers fixed in the room near the turntable (its stand, a
    post), ``clutter_db`` above the target's strongest echo. The air warms linearly from
    ``temperature_c[0]`` to ``temperature_c[1]`` during the scan, at ``humidity_pct`` relative
    humidity (the scan's and the background's, which both datasets state).

    Returns
    -------
    TurntableScan
    """
    n = v.positive_int("n_pings", n_pings)
    rng = np.random.default_rng(seed)
    wave = lfm_chirp(f_start_hz, f_stop_hz, duration_s, fs_hz, taper=0.1)
    chirp = {"f_start_hz": f_start_hz, "f_stop_hz": f_stop_hz, "duration_s": duration_s, "taper": 0.1}
    target = curve_target() if target_m is None else v.array("target_m", target_m, shape=(None, 3))
    tx_room, rx_room, ap_target, ap_room = _turntable_apertures(n, range_m)
    temps = np.linspace(temperature_c[0], temperature_c[1], n)
    t_bg = float(np.mean(temperature_c)) if background_temperature_c is None else background_temperature_c
    gd = group_delay_samples / fs_hz
    # sample 0 is recorded gd before the sound leaves the speaker
    kw = dict(n_samples=n_samples, t0_s=-gd, chirp=chirp, absorption=True)
    # the target: unit scatterers with a little spread
    amps = rng.uniform(0.6, 1.0, len(target))
    echo = simulate(Scene(target, amps, humidity_pct=humidity_pct), ap_target, wave, fs_hz, temperature_c=temps,
                    **kw).signals
    room = _RoomSound(ap_room, 0.5 * (tx_room + rx_room)[None, :], wave, fs_hz, humidity_pct, kw,
                      peak=float(np.abs(echo).max()), clutter_db=clutter_db, direct_db=direct_db, dc=dc, hum=hum,
                      snr_db=snr_db)
    common = dict(fs_hz=fs_hz, waveform=wave, t0_s=np.zeros(n), chirp=chirp, humidity_pct=humidity_pct)
    ds = Dataset(echo + room.signals(temps, seed + 1), ap_target.tx_positions, ap_target.rx_positions,
                 temperature_c=temps, provenance=[{"step": "synthetic", "kind": "turntable_scan", "seed": seed}],
                 **common)
    bg = Dataset(room.signals(np.full(n, t_bg), seed + 2), ap_target.tx_positions, ap_target.rx_positions,
                 temperature_c=t_bg, provenance=[{"step": "synthetic", "kind": "turntable_scan background",
                                                  "seed": seed}], **common)
    pad = 0.03
    box = np.c_[target.min(axis=0) - pad, target.max(axis=0) + pad]
    return TurntableScan(ds, bg, target, _RoomSound.CLUTTER, gd, box)


@dataclass(frozen=True)
class _RoomSound:
    """What the room adds to every recording of a turntable scan: the fixed clutter, the direct
    sound, a DC offset, mains hum and noise, at levels relative to the target's strongest echo."""

    # the turntable's fixed stand and a post beside it: at the target's range, so their echoes
    # fall into the imaged gate (as rings: they do not turn with the target)
    CLUTTER: ClassVar[np.ndarray] = np.array([[0.12, 0.12, -0.03], [-0.15, -0.05, 0.05], [0.02, -0.17, 0.0]])

    aperture: Aperture
    direct_point: np.ndarray  # a scatterer halfway between speaker and microphone, scaled afterwards
    wave: np.ndarray
    fs_hz: float
    humidity_pct: float
    simulate_kw: dict
    peak: float
    clutter_db: float
    direct_db: float
    dc: float
    hum: float
    snr_db: float

    def _echoes(self, points: np.ndarray, temp) -> np.ndarray:
        scene = Scene(points, np.ones(len(points)), humidity_pct=self.humidity_pct)
        return simulate(scene, self.aperture, self.wave, self.fs_hz, temperature_c=temp, **self.simulate_kw).signals

    def signals(self, temp, noise_seed: int) -> np.ndarray:
        """The room's part of each recording at the air temperatures ``temp`` (noise from ``noise_seed``)."""
        clut, dirc = self._echoes(self.CLUTTER, temp), self._echoes(self.direct_point, temp)
        sig = clut * (self.peak * 10 ** (self.clutter_db / 20) / max(np.abs(clut).max(), 1e-300))
        sig += dirc * (self.peak * 10 ** (self.direct_db / 20) / max(np.abs(dirc).max(), 1e-300))
        r = np.random.default_rng(noise_seed)
        tt = np.arange(sig.shape[1]) / self.fs_hz
        sig += self.dc * self.peak + self.hum * self.peak * np.sin(2 * np.pi * 60.0 * tt + r.uniform(0, 2 * np.pi))
        sig += r.normal(0.0, self.peak * 10 ** (-self.snr_db / 20) / np.sqrt(2), sig.shape)
        return sig
