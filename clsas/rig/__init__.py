"""Scripted rig acquisition: a GRBL x-y stage, a sound card, resumable scans.

``clsas acquire rig.toml out.h5`` (or :func:`acquire`) moves the carriage to each stop, plays
the chirp, records the microphones and the loopback channel, and appends the stop to the
dataset file before the next move. ``--simulate`` runs the same scan against
:class:`GrblEmulator` and a simulated microphone. The parts of a scan (:mod:`clsas.rig.scan`:
``stage_for``, ``audio_for``, ``recorder_for``, ``store_for``, ``run_stops``) are built from the
rig file's ``[stage]``, ``[audio]``, ``[recorder]`` and ``[scan]`` tables.

pyserial and sounddevice (PortAudio) are imported only when a stage or sound card is used.
"""

from .audio import AudioError, Recorder, SimulatedIO, SoundDeviceIO, Take, find_onset, list_audio_devices
from .config import SAMPLE_RIG_TOML, RigConfig, load_rig_config, parse_rig_config
from .emulator import Faults, GrblEmulator
from .grbl import (
    GrblAlarm,
    GrblError,
    GrblStage,
    StageDisconnected,
    StageError,
    StageRefused,
    StageTimeout,
    Status,
)
from .grbl_link import GrblLink
from .scan import ScanAborted, ScanInterrupted, ScanResult, acquire, stop_indices
from .store import ScanFile

__all__ = [
    "AudioError", "Faults", "GrblAlarm", "GrblEmulator", "GrblError", "GrblLink", "GrblStage", "Recorder", "RigConfig",
    "SAMPLE_RIG_TOML", "ScanAborted", "ScanFile", "ScanInterrupted", "ScanResult", "SimulatedIO",
    "SoundDeviceIO", "StageDisconnected", "StageError", "StageRefused", "StageTimeout", "Status", "Take", "acquire",
    "find_onset", "list_audio_devices", "load_rig_config", "parse_rig_config", "stop_indices",
]
