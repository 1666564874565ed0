"""The rig configuration (``rig.toml``): stage, aperture, audio, chirp, air, grid, simulation.

See the README section "Building and running a rig" for a commented example; every key has a
default except ``stage.port`` (not needed with ``--simulate``).
"""

from __future__ import annotations

import shlex
import subprocess
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import _validate as v
from ..geometry import Scene, Wall, raster_aperture
from ..scenes import _section as _table
from ..signals import lfm_chirp

__all__ = ["RigConfig", "parse_rig_config", "load_rig_config", "SAMPLE_RIG_TOML"]

SAMPLE_RIG_TOML = """\
# clsas rig configuration: one file describes the rig and the scan.
[stage]
port = "/dev/ttyUSB0"          # any pyserial URL: COM3, socket://host:2000, ...
baudrate = 115200
home = true                    # $H before the scan (false: $X unlock only)
feed_mm_min = 3000             # G1 feed rate between stops
work_area_mm = [[0, 1000], [0, 1000]]   # machine travel a move may reach
origin_mm = [500, 500]         # machine position of the scan centre
settle_s = 0.5                 # wait after each move before the chirp (vibration)

[aperture]
nx = 18                        # stops along x
ny = 12                        # stops along y
width_m = 1.0                  # first to last stop along x
height_m = 1.0
pattern = "serpentine"         # or "raster"
tx_offset_m = [-0.02, 0.0, 0.0]      # speaker, relative to the carriage
rx_offset_m = [[0.02, 0.0, 0.0]]     # one offset per microphone

[audio]
device = "default"             # a name (substring) or index from `clsas devices`
fs_hz = 96000                  # 96000 or 192000
output_channel = 1             # speaker drive (1-based)
loopback_channel = 1           # input wired back from the speaker drive
mic_channels = [2]             # one input per microphone, in rx_offset_m's order
level = 0.5                    # peak drive, full scale = 1
record_s = 0.02                # kept per stop after the chirp leaves (0.02 s = 3.4 m of round trip)
max_latency_s = 0.1            # longest output-to-input latency expected
repeats = 4                    # chirps averaged per stop
repeat_gap_s = 0.05            # silence between repeats (let the room ring down)
retries = 3                    # attempts per stop on clipping or an over/underflow
clip_level = 0.99
acoustic_delay_s = 0.0         # speaker + microphone delay beyond the loopback (calibration)

[chirp]
f_start_hz = 20000
f_stop_hz = 30000
duration_s = 0.005
taper = 0.1

[air]
temperature_c = 20.0
humidity_pct = 50.0
# sensor_command = "read-dht22"   # prints "<temperature_c> <humidity_pct>"; read at scan start

[grid]                         # optional: where `clsas reconstruct` images by default
x_m = [-0.5, 0.5]
y_m = [-0.5, 0.5]
z_m = [0.8, 1.6]
spacing_m = 0.01

[simulate]                     # used only by `clsas acquire --simulate`
points = [{ position_m = [0.0, 0.0, 1.2], amplitude = 1.0 }]
noise_rms = 1e-4               # microphone noise, full scale = 1
mic_gain = 0.05                # echo level of a unit reflector at 1 m: 0.05 x level
latency_samples = 300          # output-to-input latency of the emulated sound card
time_scale = 0.01              # emulated moves run 100x faster than real ones
"""


@dataclass
class RigConfig:
    """A parsed ``rig.toml``; ``text`` is stored verbatim in the dataset."""

    text: str
    port: str | None
    baudrate: int
    home: bool
    feed_mm_min: float | None
    work_area_mm: np.ndarray
    origin_mm: np.ndarray
    settle_s: float
    stage_timeout_s: float
    poll_hz: float
    stops_m: np.ndarray  # (n_stops, 3) carriage positions in scan order
    tx_offset_m: np.ndarray  # (3,)
    rx_offsets_m: np.ndarray  # (n_mics, 3)
    device: str | int
    fs_hz: float
    output_channel: int
    loopback_channel: int
    mic_channels: list[int]
    level: float
    record_s: float
    max_latency_s: float
    repeats: int
    repeat_gap_s: float
    retries: int
    clip_level: float
    acoustic_delay_s: float
    chirp: dict
    waveform: np.ndarray  # unit-peak chirp at fs_hz
    temperature_c: float
    humidity_pct: float
    sensor_command: str | None
    simulate: dict = field(default_factory=dict)

    @property
    def n_stops(self) -> int:
        return len(self.stops_m)

    @property
    def n_mics(self) -> int:
        return len(self.rx_offsets_m)

    @property
    def n_samples(self) -> int:
        return int(round(self.record_s * self.fs_hz))

    def stage_target_mm(self, stop: int) -> tuple[float, float]:
        """Machine (x, y) in mm of stop ``stop``."""
        p = self.origin_mm + 1000.0 * self.stops_m[stop, :2]
        return float(p[0]), float(p[1])

    def carriage_m(self, position_mm) -> np.ndarray:
        """Carriage position in the scan frame (m) from a machine position (mm)."""
        xy = (np.asarray(position_mm[:2], float) - self.origin_mm) / 1000.0
        return np.array([xy[0], xy[1], self.stops_m[0, 2]])

    def scene(self, temperature_c: float | None = None, humidity_pct: float | None = None) -> Scene:
        """The scene heard by ``--simulate`` (``[simulate]`` points and walls), in the given air
        (default: the file's)."""
        sim = self.simulate
        points = sim.get("points", [])
        if not points:
            raise ValueError("--simulate needs [simulate] points = [{ position_m = [x, y, z] }, ...] in the rig file")
        walls = tuple(Wall(tuple(w["point_m"]), tuple(w["normal"]), float(w.get("reflectivity", 0.9)))
                      for w in sim.get("walls", []))
        return Scene(np.array([p["position_m"] for p in points], float),
                     np.array([p.get("amplitude", 1.0) for p in points], float),
                     np.array([p.get("visible", True) for p in points], bool), walls,
                     temperature_c=self.temperature_c if temperature_c is None else temperature_c,
                     humidity_pct=self.humidity_pct if humidity_pct is None else humidity_pct)

    def read_air(self) -> tuple[float, float]:
        """Temperature (C) and humidity (%) now: from ``sensor_command`` if set, else the file's."""
        if not self.sensor_command:
            return self.temperature_c, self.humidity_pct
        try:
            out = subprocess.run(shlex.split(self.sensor_command), capture_output=True, text=True, timeout=30,
                                 check=True).stdout.split()
            t, h = float(out[0]), float(out[1])
        except (OSError, subprocess.SubprocessError, IndexError, ValueError) as exc:
            raise ValueError(f"air.sensor_command {self.sensor_command!r} must print '<temperature_c> "
                             f"<humidity_pct>': {exc}") from None
        return v.finite("temperature_c", t), v.non_negative("humidity_pct", h)


_channel = v.positive_int  # a 1-based sound card channel


def parse_rig_config(text: str) -> RigConfig:
    """Parse and check the text of a ``rig.toml``; errors name the key."""
    try:
        cfg = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"rig configuration is not valid TOML: {exc}") from None
    st, ap, au, ch, air = (_table(cfg, k) for k in ("stage", "aperture", "audio", "chirp", "air"))

    fs = v.positive("audio.fs_hz", au.get("fs_hz", 96000))
    if fs not in (96000.0, 192000.0):
        raise ValueError(f"audio.fs_hz must be 96000 or 192000 (a 20-30 kHz chirp needs them), got {fs:g}")
    chirp = {k: float(ch.get(k, d)) for k, d in
             (("f_start_hz", 20e3), ("f_stop_hz", 30e3), ("duration_s", 5e-3), ("taper", 0.1))}
    waveform = lfm_chirp(chirp["f_start_hz"], chirp["f_stop_hz"], chirp["duration_s"], fs, chirp["taper"])

    rx = np.asarray(ap.get("rx_offset_m", [[0.02, 0.0, 0.0]]), float)
    if rx.ndim == 1:
        rx = rx[None, :]
    rx = v.array("aperture.rx_offset_m", rx, shape=(None, 3))
    mics = [_channel("audio.mic_channels", c) for c in au.get("mic_channels", [2])]
    if len(mics) != len(rx):
        raise ValueError(f"audio.mic_channels has {len(mics)} entries but aperture.rx_offset_m has {len(rx)}: "
                         "give one input channel per microphone")
    loop = _channel("audio.loopback_channel", au.get("loopback_channel", 1))
    if loop in mics:
        raise ValueError(f"audio.loopback_channel {loop} is also a microphone channel")
    tx_off = v.array("aperture.tx_offset_m", ap.get("tx_offset_m", (-0.02, 0.0, 0.0)), shape=(3,))
    aperture = raster_aperture(
        ap.get("nx", 18), ap.get("ny", 12), ap.get("width_m", 1.0), ap.get("height_m", 1.0),
        center_m=(0.0, 0.0, 0.0), tx_offset_m=tuple(tx_off), rx_offset_m=tuple(rx[0]),
        pattern=str(ap.get("pattern", "serpentine")),
    )
    area = v.array("stage.work_area_mm", st.get("work_area_mm", [[0, 1000], [0, 1000]]), shape=(2, 2))
    origin = v.array("stage.origin_mm", st.get("origin_mm", [500, 500]), shape=(2,))
    stops = aperture.stage_positions
    targets = origin + 1000.0 * stops[:, :2]
    for axis, name in ((0, "x"), (1, "y")):
        lo, hi = targets[:, axis].min(), targets[:, axis].max()
        if lo < area[axis, 0] or hi > area[axis, 1]:
            raise ValueError(f"the aperture spans {name} = [{lo:g}, {hi:g}] mm on the stage, outside "
                             f"stage.work_area_mm {area[axis].tolist()}: reduce the aperture or move stage.origin_mm")
    feed = st.get("feed_mm_min", 3000.0)
    device = au.get("device", "default")
    if not isinstance(device, str | int) or isinstance(device, bool):
        raise ValueError(f"audio.device must be a device name or index, got {device!r}")
    level = v.positive("audio.level", au.get("level", 0.5))
    if level > 1:
        raise ValueError(f"audio.level must be at most 1 (full scale), got {level}")
    record_s = v.positive("audio.record_s", au.get("record_s", 0.02))
    if record_s * fs < len(waveform):
        raise ValueError(f"audio.record_s = {record_s:g} s is shorter than the chirp ({chirp['duration_s']:g} s)")
    clip = v.positive("audio.clip_level", au.get("clip_level", 0.99))
    sim = _table(cfg, "simulate")
    return RigConfig(
        text=text,
        port=st.get("port"),
        baudrate=v.positive_int("stage.baudrate", st.get("baudrate", 115200)),
        home=bool(st.get("home", True)),
        feed_mm_min=None if feed is None or feed == 0 else v.positive("stage.feed_mm_min", feed),
        work_area_mm=area,
        origin_mm=origin,
        settle_s=v.non_negative("stage.settle_s", st.get("settle_s", 0.5)),
        stage_timeout_s=v.positive("stage.timeout_s", st.get("timeout_s", 5.0)),
        poll_hz=v.positive("stage.poll_hz", st.get("poll_hz", 5.0)),
        stops_m=stops,
        tx_offset_m=tx_off,
        rx_offsets_m=rx,
        device=device,
        fs_hz=fs,
        output_channel=_channel("audio.output_channel", au.get("output_channel", 1)),
        loopback_channel=loop,
        mic_channels=mics,
        level=level,
        record_s=record_s,
        max_latency_s=v.positive("audio.max_latency_s", au.get("max_latency_s", 0.1)),
        repeats=v.positive_int("audio.repeats", au.get("repeats", 1)),
        repeat_gap_s=v.non_negative("audio.repeat_gap_s", au.get("repeat_gap_s", 0.05)),
        retries=v.positive_int("audio.retries", au.get("retries", 3)),
        clip_level=min(clip, 1.0),
        acoustic_delay_s=v.finite("audio.acoustic_delay_s", au.get("acoustic_delay_s", 0.0)),
        chirp=chirp,
        waveform=waveform,
        temperature_c=v.finite("air.temperature_c", air.get("temperature_c", 20.0)),
        humidity_pct=v.non_negative("air.humidity_pct", air.get("humidity_pct", 50.0)),
        sensor_command=air.get("sensor_command"),
        simulate=sim,
    )


def load_rig_config(path: str | Path) -> RigConfig:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no rig configuration at {path} (`clsas acquire --sample-config` prints one)")
    return parse_rig_config(path.read_text())
