"""The rig configuration (``rig.toml``): stage, scan, aperture, audio, recorder, chirp, air, grid,
simulation.

``[stage]``, ``[audio]`` and ``[recorder]`` hold the constructor arguments of :class:`GrblStage`,
:class:`SoundDeviceIO` and :class:`Recorder`; ``[scan]`` the stop loop's (homing, origin,
settling). See the guide page docs/guide/rig.md for a commented example; every
key has a default except ``stage.port`` (not needed with ``--simulate``). Files in the older flat
layout are read with a warning that names where each key moved.
"""

from __future__ import annotations

import shlex
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import validate as v
from ..io import config as c
from ..physics.geometry import Scene, VoxelGrid, raster_aperture

__all__ = ["RigConfig", "parse_rig_config", "load_rig_config", "SAMPLE_RIG_TOML"]

SAMPLE_RIG_TOML = """\
# clsas rig configuration: one file describes the rig and the scan.
[stage]                        # the GRBL stage: clsas.rig.GrblStage(**[stage])
port = "/dev/ttyUSB0"          # any pyserial URL: COM3, socket://host:2000, ...
baudrate = 115200
feed_mm_min = 3000             # G1 feed rate between stops; GRBL caps each axis at $110/$111
                               # (500 mm/min on a stock board), and clsas plans each move at that rate
work_area_mm = [[-1000, -10], [-1000, -10]]   # machine coordinates a move may reach: after $H, GRBL's
                               # machine space is [-travel, 0] ($130/$131) with soft limits on; the
                               # upper ends 10 mm off machine 0, where the home switches are
reset_on_open = true           # an Arduino Uno/Nano reboots when its port opens (false: a board without
                               # auto-reset, which gets a soft reset instead)
# timeout_s = 5                # for the answer ('ok') to one line
# home_timeout_s = 300         # default: from GRBL's $25 seek rate and $130-$132 travel
# move_timeout_s = 60          # default: 3 x the move's time at the rate GRBL uses ($110/$111,
                               # $120/$121 acceleration), plus 10 s
# reset_wait_s = 2.5           # for the start-up banner after opening the port
# poll_hz = 5                  # '?' status reports while a move runs (at most 5)
# position_tol_mm = 0.02       # how close to the target a move must end

[scan]                         # the stop loop
home = true                    # $H before the scan (false: $X unlock only); needs $22=1
origin_mm = [-500, -500]       # machine position of the scan centre
settle_s = 0.5                 # wait after each move before the chirp (vibration)

[aperture]
nx = 18                        # stops along x
ny = 12                        # stops along y
width_m = 0.96                 # first to last stop along x (20 mm inside the
                               # 1 m travel at each end: a stop on machine 0 would press a
                               # limit switch with hard limits on)
height_m = 0.96
pattern = "serpentine"         # or "raster"
tx_offset_m = [-0.02, 0.0, 0.0]      # speaker, relative to the carriage
rx_offset_m = [[0.02, 0.0, 0.0]]     # one offset per microphone

[audio]                        # the sound card: clsas.rig.SoundDeviceIO(**[audio])
device = "default"             # a name (substring) or index from `clsas devices`
fs_hz = 96000                  # 96000 or 192000
output_channel = 1             # speaker drive (1-based)
loopback_channel = 1           # input wired back from the speaker drive
mic_channels = [2]             # one input per microphone, in rx_offset_m's order

[recorder]                     # the takes: clsas.rig.Recorder(io, chirp, fs_hz, **[recorder])
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
    """A parsed ``rig.toml``; ``text`` is stored verbatim in the dataset.

    ``stage``, ``audio`` and ``recorder`` are the keyword arguments of :class:`GrblStage`,
    :class:`SoundDeviceIO` and :class:`Recorder` (``[stage]``, ``[audio]``, ``[recorder]``, with
    every default filled in); ``home``, ``origin_mm`` and ``settle_s`` drive the stop loop
    (``[scan]``).
    """

    text: str
    stage: dict  # GrblStage(**stage); stage["port"] may be None (--simulate)
    home: bool
    origin_mm: np.ndarray
    settle_s: float
    audio: dict  # SoundDeviceIO(**audio)
    recorder: dict  # Recorder(io, waveform, audio["fs_hz"], **recorder)
    stops_m: np.ndarray  # (n_stops, 3) carriage positions in scan order
    tx_offset_m: np.ndarray  # (3,)
    rx_offsets_m: np.ndarray  # (n_mics, 3)
    chirp: dict
    waveform: np.ndarray  # unit-peak chirp at fs_hz
    temperature_c: float
    humidity_pct: float
    sensor_command: str | None
    simulate: dict = field(default_factory=dict)  # [simulate], checked: points, walls, numbers
    preprocess: dict = field(default_factory=dict)  # [preprocess], checked by clsas.preprocess.from_table
    grid: VoxelGrid | None = None  # [grid], where `clsas reconstruct` images by default
    beams: dict | None = None  # [beams] as written (checked on the planned stops); None: omnidirectional

    @property
    def port(self) -> str | None:
        return self.stage["port"]

    @property
    def work_area_mm(self) -> np.ndarray:
        return np.asarray(self.stage["work_area_mm"], float)

    @property
    def fs_hz(self) -> float:
        return self.audio["fs_hz"]

    @property
    def level(self) -> float:
        return self.recorder["level"]

    @property
    def repeats(self) -> int:
        return self.recorder["repeats"]

    @property
    def n_stops(self) -> int:
        return len(self.stops_m)

    @property
    def n_mics(self) -> int:
        return len(self.rx_offsets_m)

    @property
    def n_samples(self) -> int:
        return int(round(self.recorder["record_s"] * self.fs_hz))

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
        points = self.simulate.get("points", [])
        if not points:
            raise ValueError("--simulate needs [simulate] points = [{ position_m = [x, y, z] }, ...] in the rig file")
        return c.build_scene(points, self.simulate.get("walls", []),
                             self.temperature_c if temperature_c is None else temperature_c,
                             self.humidity_pct if humidity_pct is None else humidity_pct)

    def beams_for(self, tx_m: np.ndarray, rx_m: np.ndarray):
        """The transducers' beams (:class:`clsas.physics.beam.Beams`) of measurements at these positions
        ((n, 3) speaker and microphone, m), boresights by the ``[beams]`` rule; None without
        ``[beams]`` (omnidirectional)."""
        if self.beams is None:
            return None
        return c.beams_table({"beams": self.beams}, "rig configuration", tx_m, rx_m)

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


#: [stage]: GrblStage's arguments; [scan]: the stop loop; [audio]: SoundDeviceIO's; [recorder]: Recorder's
STAGE_KEYS = ("port", "baudrate", "work_area_mm", "feed_mm_min", "timeout_s", "home_timeout_s", "move_timeout_s",
              "poll_hz", "reset_wait_s", "reset_on_open", "position_tol_mm")
SCAN_KEYS = ("home", "origin_mm", "settle_s")
APERTURE_KEYS = ("nx", "ny", "width_m", "height_m", "pattern", "tx_offset_m", "rx_offset_m")
AUDIO_KEYS = ("device", "fs_hz", "output_channel", "loopback_channel", "mic_channels")
RECORDER_KEYS = ("level", "record_s", "max_latency_s", "repeats", "repeat_gap_s", "retries", "clip_level",
                 "acoustic_delay_s")
AIR_KEYS = ("temperature_c", "humidity_pct", "sensor_command")
SIMULATE_KEYS = ("points", "walls", "noise_rms", "mic_gain", "latency_samples", "time_scale", "seed")
#: keys of the flat layout (before [scan] and [recorder]): (table, key) -> (new table, new key)
MOVED = {("stage", "home"): ("scan", "home"), ("stage", "origin_mm"): ("scan", "origin_mm"),
         ("stage", "settle_s"): ("scan", "settle_s"), ("stage", "homing_timeout_s"): ("stage", "home_timeout_s"),
         **{("audio", k): ("recorder", k) for k in RECORDER_KEYS}}


def _optional_seconds(st: c.Table, key: str) -> float | None:
    return float(st.number(key, above=0)) if key in st else None


def _simulate_table(cfg: dict, source: str) -> dict:
    """The ``[simulate]`` table, checked: points and walls parsed, numbers in range."""
    sim = c.Table(cfg.get("simulate", {}), source, "[simulate]", SIMULATE_KEYS)
    out: dict = {}
    if "points" in sim:
        out["points"] = c.points_table(sim.raw("points"), source, "[simulate] points")
    if "walls" in sim:
        out["walls"] = c.walls_table(sim.raw("walls"), source, "[simulate] walls")
    for key, check in (("noise_rms", {"low": 0}), ("mic_gain", {"low": 0}), ("time_scale", {"above": 0})):
        if key in sim:
            out[key] = sim.number(key, **check)
    for key in ("latency_samples", "seed"):
        if key in sim:
            out[key] = sim.integer(key, low=0)
    return out


def _move_old_keys(cfg: dict, source: str) -> None:
    """Read the flat layout's keys at their new places, with one warning that says where each moved."""
    import warnings

    moved = []
    for (old_table, key), (table, new_key) in MOVED.items():
        old = cfg.get(old_table)
        if not isinstance(old, dict) or key not in old:
            continue
        new = cfg.setdefault(table, {})
        if not isinstance(new, dict):
            continue  # the table check says what is wrong with it
        if new_key in new:
            raise c.ConfigError(f"{source}: [{old_table}] {key} and [{table}] {new_key} are the same setting; "
                                f"keep [{table}] {new_key} only")
        new[new_key] = old.pop(key)
        moved.append(f"[{old_table}] {key} has moved to [{table}] {new_key}")
    if moved:
        warnings.warn(f"{source} uses keys of the older flat layout: {'; '.join(moved)}. They are read from the "
                      "old places for now, but a later clsas will refuse them there (clsas acquire "
                      "--sample-config prints the new layout)", FutureWarning, stacklevel=3)


def parse_rig_config(text: str, source: str = "rig configuration") -> RigConfig:
    """Parse and check the text of a ``rig.toml``.

    Parameters
    ----------
    text : str
        The rig file's text.
    source : str
        What to call the text in error messages (the file name).

    Raises
    ------
    clsas.config.ConfigError
        (a ``ValueError``) naming the file, the table and the key: invalid TOML, a scene file,
        an unknown table or key, a value of the wrong type or out of range, or keys that
        disagree (one input channel per microphone, the aperture inside the work area, ...).

    Warns
    -----
    FutureWarning
        For a key of the older flat layout (``[stage] home, origin_mm, settle_s``,
        ``homing_timeout_s``; ``[audio] level, record_s, repeats, ...``), naming where it moved
        (``[scan]``, ``[stage] home_timeout_s``, ``[recorder]``); its value is used.
    """
    cfg = c.read_toml(text, source, "rig", {"stage": STAGE_KEYS, "scan": SCAN_KEYS, "aperture": APERTURE_KEYS,
                                             "audio": AUDIO_KEYS, "recorder": RECORDER_KEYS, "chirp": c.CHIRP_KEYS,
                                             "air": AIR_KEYS, "grid": c.GRID_KEYS, "simulate": SIMULATE_KEYS})
    _move_old_keys(cfg, source)
    st, sc, ap, au, rec, ch, air = _tables(cfg, source)

    def fail(message: str) -> c.ConfigError:
        return c.ConfigError(f"{source}: {message}")

    fs = float(au.number("fs_hz", 96000.0, above=0))
    if fs not in (96000.0, 192000.0):
        raise fail(f"audio.fs_hz must be 96000 or 192000 (a 20-30 kHz chirp needs them), got {fs:g}")
    chirp, waveform = c.chirp_table(ch, fs)
    rx, mics, loop = _channels(ap, au, fail)
    tx_off, area, origin, stops = _aperture_on_stage(ap, st, sc, rx, fail)
    feed, device, level, record_s, poll_hz, reset_on_open = _checked_settings(st, au, rec, fs, chirp, waveform, fail)
    stage = _stage_settings(st, area, feed, poll_hz, reset_on_open)
    recorder = _recorder_settings(rec, level, record_s)
    audio = {"device": device, "fs_hz": fs, "output_channel": au.integer("output_channel", 1, low=1),
             "loopback_channel": loop, "mic_channels": mics}
    beams = _beams_table(cfg, source, stops, tx_off, rx)
    return RigConfig(
        text=text, stage=stage, home=sc.boolean("home", True), origin_mm=origin,
        settle_s=float(sc.number("settle_s", 0.5, low=0)), audio=audio, recorder=recorder, stops_m=stops,
        tx_offset_m=tx_off, rx_offsets_m=rx, chirp=chirp, waveform=waveform,
        temperature_c=float(air.number("temperature_c", 20.0, low=-273.15)),
        humidity_pct=float(air.number("humidity_pct", 50.0, low=0, high=100)),
        sensor_command=air.string("sensor_command", None), simulate=_simulate_table(cfg, source),
        preprocess=c.preprocess_table(cfg, source), grid=c.grid_table(cfg, source), beams=beams,
    )


def _beams_table(cfg: dict, source: str, stops: np.ndarray, tx_off: np.ndarray, rx: np.ndarray) -> dict | None:
    """``[beams]`` (the scene file's table: speaker, microphone, boresight rule), checked by
    building the beams of every planned measurement; each stop's are built again from its
    measured position when it is stored (:meth:`RigConfig.beams_for`)."""
    if "beams" not in cfg:
        return None
    m = len(rx)
    tx = np.repeat(stops + tx_off, m, axis=0)
    rxs = (stops[:, None, :] + rx[None, :, :]).reshape(-1, 3)
    c.beams_table(cfg, source, tx, rxs)
    return dict(cfg["beams"])


def _tables(cfg: dict, source: str) -> tuple:
    """The rig file's tables, each checked for unknown keys (with hints where a key belongs elsewhere):
    ``[stage]``, ``[scan]``, ``[aperture]``, ``[audio]``, ``[recorder]``, ``[chirp]``, ``[air]``."""
    st = c.Table(cfg.get("stage", {}), source, "[stage]", STAGE_KEYS,
                 hints={k: f"it belongs in [scan] {k}" for k in SCAN_KEYS})
    sc = c.Table(cfg.get("scan", {}), source, "[scan]", SCAN_KEYS,
                 hints={k: f"it belongs in [stage] {k} (GrblStage's arguments)" for k in STAGE_KEYS})
    ap = c.Table(cfg.get("aperture", {}), source, "[aperture]", APERTURE_KEYS)
    au = c.Table(cfg.get("audio", {}), source, "[audio]", AUDIO_KEYS,
                 hints={"snr_db": "the emulated microphone's noise is [simulate] noise_rms"})
    rec = c.Table(cfg.get("recorder", {}), source, "[recorder]", RECORDER_KEYS,
                  hints={k: f"it belongs in [audio] {k} (the sound card's)" for k in AUDIO_KEYS})
    ch = c.Table(cfg.get("chirp", {}), source, "[chirp]", c.CHIRP_KEYS,
                 hints={"fs_hz": "a rig's sample rate is [audio] fs_hz"})
    air = c.Table(cfg.get("air", {}), source, "[air]", AIR_KEYS)
    return st, sc, ap, au, rec, ch, air


def _channels(ap, au, fail) -> tuple:
    """The microphones' offsets (k, 3) m, their input channels (one each) and the loopback channel."""
    rx = ap.raw("rx_offset_m", [[0.02, 0.0, 0.0]])
    if isinstance(rx, list) and rx and not isinstance(rx[0], list):
        ap.data["rx_offset_m"] = rx = [rx]
    rx = ap.vector("rx_offset_m", np.asarray(rx, float), shape=(None, 3))
    mics = au.raw("mic_channels", [2])
    if (not isinstance(mics, list) or not mics
            or any(isinstance(m, bool) or not isinstance(m, int) or m < 1 for m in mics)):
        raise fail(f"audio.mic_channels must be a list of input channels (integers, 1-based), got {mics!r}")
    if len(mics) != len(rx):
        raise fail(f"audio.mic_channels has {len(mics)} entries but aperture.rx_offset_m has {len(rx)}: "
                   "give one input channel per microphone")
    loop = au.integer("loopback_channel", 1, low=1)
    if loop in mics:
        raise fail(f"audio.loopback_channel {loop} is also a microphone channel")
    return rx, mics, loop


def _aperture_on_stage(ap, st, sc, rx, fail) -> tuple:
    """The speaker's offset (m), the stage's work area (mm), the scan's origin on it (mm) and the
    stops (m), checked to lie inside the work area."""
    tx_off = ap.vector("tx_offset_m", (-0.02, 0.0, 0.0))
    aperture = ap.build(
        raster_aperture, ap.integer("nx", 18, low=1), ap.integer("ny", 12, low=1),
        float(ap.number("width_m", 1.0, low=0)), float(ap.number("height_m", 1.0, low=0)),
        center_m=(0.0, 0.0, 0.0), tx_offset_m=tuple(tx_off), rx_offset_m=tuple(rx[0]),
        pattern=ap.string("pattern", "serpentine", choices=("serpentine", "raster")),
    )
    area = st.vector("work_area_mm", [[-1000, 0], [-1000, 0]], shape=(2, 2))
    origin = sc.vector("origin_mm", [-500, -500], shape=(2,))
    stops = aperture.stage_positions
    targets = origin + 1000.0 * stops[:, :2]
    for axis, name in ((0, "x"), (1, "y")):
        lo, hi = targets[:, axis].min(), targets[:, axis].max()
        if lo < area[axis, 0] or hi > area[axis, 1]:
            raise fail(f"the aperture spans {name} = [{lo:g}, {hi:g}] mm on the stage, outside stage.work_area_mm "
                       f"{area[axis].tolist()}: reduce the aperture or move scan.origin_mm")
    return tx_off, area, origin, stops


def _checked_settings(st, au, rec, fs, chirp, waveform, fail) -> tuple:
    """The settings checked against each other: the feed, the audio device, the output level,
    the recording's length (at least the chirp's), the status polling rate (GRBL's limit), and
    whether to reset the controller on opening."""
    feed = st.number("feed_mm_min", 3000.0, low=0)
    device = au.raw("device", "default")
    if not isinstance(device, str | int) or isinstance(device, bool):
        raise fail(f"audio.device must be a device name or index, got {device!r}")
    level = float(rec.number("level", 0.5, above=0))
    if level > 1:
        raise fail(f"recorder.level must be at most 1 (full scale), got {level:g}")
    record_s = float(rec.number("record_s", 0.02, above=0))
    if record_s * fs < len(waveform):
        raise fail(f"recorder.record_s = {record_s:g} s is shorter than the chirp ({chirp['duration_s']:g} s)")
    poll_hz = float(st.number("poll_hz", 5.0, above=0))
    if poll_hz > 5:
        raise fail(f"stage.poll_hz must be at most 5 (GRBL's advice for '?' polling), got {poll_hz:g}")
    reset_on_open = st.raw("reset_on_open", None)
    if reset_on_open is not None:
        reset_on_open = st.boolean("reset_on_open")
    return feed, device, level, record_s, poll_hz, reset_on_open


def _stage_settings(st, area, feed, poll_hz, reset_on_open) -> dict:
    """``RigConfig.stage``: GrblStage's keyword arguments."""
    return {
        "port": st.string("port", None),
        "baudrate": st.integer("baudrate", 115200, low=1),
        "work_area_mm": tuple(map(tuple, area.tolist())),
        "feed_mm_min": None if feed == 0 else float(feed),
        "timeout_s": float(st.number("timeout_s", 5.0, above=0)),
        "home_timeout_s": _optional_seconds(st, "home_timeout_s"),
        "move_timeout_s": _optional_seconds(st, "move_timeout_s"),
        "poll_hz": poll_hz,
        "reset_wait_s": float(st.number("reset_wait_s", 2.5, low=0)),
        "reset_on_open": reset_on_open,
        "position_tol_mm": float(st.number("position_tol_mm", 0.02, above=0)),
    }


def _recorder_settings(rec, level, record_s) -> dict:
    """``RigConfig.recorder``: the Recorder's keyword arguments."""
    return {
        "level": level,
        "record_s": record_s,
        "max_latency_s": float(rec.number("max_latency_s", 0.1, above=0)),
        "repeats": rec.integer("repeats", 1, low=1),
        "repeat_gap_s": float(rec.number("repeat_gap_s", 0.05, low=0)),
        "retries": rec.integer("retries", 3, low=1),
        "clip_level": min(float(rec.number("clip_level", 0.99, above=0)), 1.0),
        "acoustic_delay_s": float(rec.number("acoustic_delay_s", 0.0)),
    }


def load_rig_config(path: str | Path) -> RigConfig:
    """Read and check a ``rig.toml``; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no rig configuration at {path} (`clsas acquire --sample-config` prints one)")
    return parse_rig_config(c.read_text(path, "rig"), str(path))
