"""The scan: move, settle, chirp, record, store, for every stop; stop safely on any fault."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..physics.sound import speed_of_sound
from ..validate import install_hint
from .audio import AudioError, Recorder, SimulatedIO, SoundDeviceIO
from .config import RigConfig
from .emulator import Faults, GrblEmulator
from .grbl import GrblStage, StageError, StageRefused
from .store import ScanFile

__all__ = ["acquire", "stage_for", "audio_for", "recorder_for", "store_for", "run_stops", "ScanResult", "ScanAborted",
           "ScanInterrupted"]

log = logging.getLogger(__name__)


class ScanAborted(RuntimeError):
    """The scan stopped on a fault; the file holds every stop before it. The message says how to resume."""

    def __init__(self, message: str, stops_done: int):
        super().__init__(message)
        self.stops_done = stops_done


class ScanInterrupted(ScanAborted):
    """The scan was stopped by the user (Ctrl-C)."""


@dataclass
class ScanResult:
    path: Path
    n_stops: int
    stops_done: int
    stops_this_run: int
    elapsed_s: float
    retried_stops: int

    @property
    def complete(self) -> bool:
        return self.stops_done == self.n_stops


def _check_config(config) -> None:
    if not isinstance(config, RigConfig):
        raise TypeError(f"config must be a RigConfig (clsas.rig.load_rig_config), got {type(config).__name__}")


def stage_for(config: RigConfig, port: str | None = None, cls: type[GrblStage] = GrblStage, **kwargs) -> GrblStage:
    """The stage ``config`` describes: ``cls(**config.stage)``, on ``port`` if given; ``kwargs``
    override or add constructor arguments."""
    _check_config(config)
    args = {**config.stage, **kwargs}
    if port is not None:
        args["port"] = port
    return cls(**args)


def audio_for(config: RigConfig, simulate: bool, air: tuple[float, float]):
    """The audio source: the sound card ``[audio]`` describes, or (``simulate``) the microphone
    that hears the ``[simulate]`` scene in ``air`` (temperature C, humidity %)."""
    if not simulate:
        return SoundDeviceIO(**config.audio)
    sim = config.simulate
    return SimulatedIO(config.scene(*air), config.fs_hz, latency_samples=int(sim.get("latency_samples", 300)),
                       noise_rms=float(sim.get("noise_rms", 1e-4)), mic_gain=float(sim.get("mic_gain", 0.05)),
                       seed=int(sim.get("seed", 0)), beams_for=config.beams_for)


def recorder_for(config: RigConfig, audio_io) -> Recorder:
    """The takes ``[recorder]`` describes, played and recorded through ``audio_io``."""
    _check_config(config)
    return Recorder(audio_io, config.waveform, config.fs_hz, **config.recorder)


def store_for(config: RigConfig, out: Path, resume: bool, air: tuple[float, float]) -> ScanFile:
    """The scan file: ``out`` reopened at its first missing stop, or created for ``config``."""
    _check_config(config)
    if resume:
        store = ScanFile.resume(out, config.text)
        log.info("resuming %s at stop %d of %d", out, store.stops_done + 1, config.n_stops)
        return store
    return ScanFile.create(out, fs_hz=config.fs_hz, waveform=config.level * config.waveform,
                           n_samples=config.n_samples, n_mics=config.n_mics, n_stops=config.n_stops,
                           temperature_c=air[0], humidity_pct=air[1], c_mps=speed_of_sound(air[0], air[1]),
                           chirp=config.chirp, config_text=config.text,
                           beams=config.beams_for(config.stops_m[:1] + config.tx_offset_m,
                                                  config.stops_m[:1] + config.rx_offsets_m[:1]))


def run_stops(config: RigConfig, stage: GrblStage, recorder: Recorder, store: ScanFile, *, settle_s: float,
              progress: Callable[[int, int], None] | None = None, on_stop: Callable[[int], None] | None = None) -> int:
    """The stop loop on an open stage: home or unlock, then move, settle, record and store every
    stop from the file's first missing one. Returns how many stops needed a retried take."""
    _check_config(config)
    if config.home:
        stage.home()
    else:
        stage.unlock()
    retried = 0
    for i in range(store.stops_done, config.n_stops):
        if on_stop is not None:
            on_stop(i)
        x_mm, y_mm = config.stage_target_mm(i)
        st = stage.move_to(x_mm, y_mm)
        if settle_s:
            time.sleep(settle_s)
        carriage = config.carriage_m(st.position_mm)
        tx = carriage + config.tx_offset_m
        rx = carriage[None, :] + config.rx_offsets_m
        take = recorder.take(i, tx, rx)
        retried += take.attempts > 1
        store.append(i, signals=take.signals, tx_m=tx, rx_m=rx, t0_s=take.t0_s, stage_m=carriage,
                     timestamp=time.time(), loopback=take.loopback,
                     beams=config.beams_for(np.repeat(tx[None, :], len(rx), axis=0), rx))
        if progress is not None:
            progress(i + 1, config.n_stops)
    return retried


def _restart_if_empty(out: Path) -> None:
    """A scan file that stopped before its first stop is started again (nothing in it to keep)."""
    if out.exists() and holds_no_stop(out):
        log.info("%s holds no stop yet: starting it again", out)
        out.unlink()


def acquire(config: RigConfig, out: str | Path, *, resume: bool = False, simulate: bool | str = False,
            faults: Faults | None = None, audio_io=None, stage: GrblStage | None = None,
            progress: Callable[[int, int], None] | None = None, resume_hint: str | None = None) -> ScanResult:
    """Run the scan described by ``config`` and write it to ``out``, one stop at a time.

    The parts are :func:`stage_for`, :func:`audio_for` and :func:`recorder_for`,
    :func:`store_for` and :func:`run_stops`; this function puts them together and makes every
    fault stop the scan safely.

    Parameters
    ----------
    config : RigConfig
        From :func:`clsas.rig.load_rig_config`.
    out : path
        The dataset file. It must not exist unless ``resume``.
    resume : bool
        Continue ``out`` at its first missing stop (the configuration must be the same).
    simulate : bool or {"all", "stage", "audio"}
        ``True`` or ``"all"``: drive a GRBL emulator on a pseudo-terminal instead of
        ``stage.port``, and record what the simulator says the microphones hear for the
        ``[simulate]`` scene. ``"stage"``: the emulator with the real sound card; ``"audio"``:
        the real stage with the simulated microphone.
    faults : Faults, optional
        Faults the emulator injects (``simulate`` only).
    audio_io, stage : optional
        Use these instead of the ones the configuration describes.
    progress : callable(done, total), optional
        Called after each stop.
    resume_hint : str, optional
        How the abort message tells the user to resume (the CLI gives its command line).

    Raises
    ------
    ScanAborted
        On a stage, serial or audio fault, after a feed hold; the file keeps every stop
        recorded so far and the message says how to resume.
    ScanInterrupted
        On Ctrl-C, likewise.
    """
    _check_config(config)
    out = Path(out)
    hint = resume_hint or f"resume with clsas.rig.acquire(config, {str(out)!r}, resume=True)"
    _restart_if_empty(out)
    sim_stage, sim_audio = _checked_request(config, out, resume, simulate, faults, stage)
    recorder, store = _recorder_and_store(config, out, resume and out.exists(), audio_io, sim_audio)
    start_done = store.stops_done
    time_scale = float(config.simulate.get("time_scale", 0.01))
    emulator = None
    t_start = time.monotonic()
    try:
        if start_done >= config.n_stops:
            return _already_complete(config, store, out)
        if stage is None:
            emulator = _started_emulator(config, faults, time_scale) if sim_stage else None
            stage = stage_for(config, emulator.port if emulator else None)
        retried = _run_safely(config, stage, recorder, store, out, hint, progress,
                              settle_s=config.settle_s * (time_scale if sim_stage else 1.0))
    finally:
        if emulator is not None:
            emulator.stop()
        store.close()
    done = config.n_stops
    return ScanResult(out, config.n_stops, done, done - start_done, time.monotonic() - t_start, retried)


def _recorder_and_store(config: RigConfig, out: Path, resuming: bool, audio_io, sim_audio: bool
                        ) -> tuple[Recorder, ScanFile]:
    """The recorder (through ``audio_io``, else the configured or simulated audio) and the scan
    file (``out`` reopened where ``resuming``, else created), both in the air of the stored scan
    when resuming, else the air the configuration reads."""
    air = _stored_air(out) if resuming else config.read_air()
    recorder = recorder_for(config, audio_io if audio_io is not None else audio_for(config, sim_audio, air))
    return recorder, store_for(config, out, resuming, air)


def _already_complete(config: RigConfig, store: ScanFile, out: Path) -> ScanResult:
    """The result of resuming a file that holds every stop: it is marked complete, nothing is recorded."""
    log.info("%s already holds all %d stops", out, config.n_stops)
    done = store.stops_done
    store.close(complete=True)
    return ScanResult(out, config.n_stops, done, 0, 0.0, 0)


def _started_emulator(config: RigConfig, faults: Faults | None, time_scale: float) -> GrblEmulator:
    """A GRBL emulator on a pseudo-terminal, its travel the work area's (and 100 mm in z), injecting ``faults``."""
    travel = (*(max(-lo, hi - lo) for lo, hi in config.work_area_mm), 100.0)
    return GrblEmulator(faults=faults or Faults(), time_scale=time_scale, travel_mm=travel).start()


def _checked_request(config: RigConfig, out: Path, resume: bool, simulate, faults, stage) -> tuple[bool, bool]:
    """:func:`acquire`'s request checked before any file is written: (simulate the stage,
    simulate the audio)."""
    if simulate not in (False, True, "all", "stage", "audio"):
        raise ValueError(f"simulate must be True, False, 'all', 'stage' or 'audio', got {simulate!r}")
    sim_stage = simulate in (True, "all", "stage")
    sim_audio = simulate in (True, "all", "audio")
    if faults is not None and not sim_stage:
        raise ValueError("faults can only be injected into an emulated stage (simulate=True, 'all' or 'stage')")
    if out.exists() and not resume:
        raise FileExistsError(f"{out} exists: resume it (--resume) or choose another file name")
    if not sim_stage and stage is None and not config.port:
        raise ValueError("stage.port is not set in the rig configuration (or run with --simulate)")
    if stage is None:
        from importlib.util import find_spec

        if find_spec("serial") is None:  # before any file is written
            raise ImportError(f"the stage (and its emulator) needs pyserial: {install_hint('rig')}")
    return sim_stage, sim_audio


def _run_safely(config: RigConfig, stage, recorder, store, out: Path, hint: str, progress, settle_s: float) -> int:
    """:func:`run_stops` on the opened stage, the file completed at the end; a fault or Ctrl-C
    sends a feed hold, closes the file with the stops so far and raises ScanAborted or
    ScanInterrupted naming the stop and how to resume. Returns the stops that needed a retry."""
    i = store.stops_done

    def at(stop: int) -> None:
        nonlocal i
        i = stop

    try:
        _open_stage(stage, store, out)
    except BaseException:
        stage.close()
        raise
    try:
        retried = run_stops(config, stage, recorder, store, progress=progress, on_stop=at, settle_s=settle_s)
        store.close(complete=True)
    except StageRefused as exc:  # before any move (homing refused): nothing to hold
        done = store.stops_done
        _drop_if_empty(store, out)
        raise StageRefused(f"{exc}. " + (_NOTHING_MOVED if not done else f"Nothing was moved in this run; the "
                           f"{done} stops saved in {out} are kept: fix it, then {hint}")) from None
    except KeyboardInterrupt:
        stage.feed_hold()
        done = store.stops_done
        store.close()
        raise ScanInterrupted(f"interrupted at stop {i + 1} of {config.n_stops}; {done} stops are saved in "
                              f"{out}; {hint}", done) from None
    except (StageError, AudioError, OSError) as exc:
        held = stage.feed_hold()
        done = store.stops_done
        store.close()
        safe = ("The stage was sent a feed hold" if held else
                "No feed hold could be sent (the port is lost): check that the machine has stopped")
        raise ScanAborted(f"scan stopped at stop {i + 1} of {config.n_stops}: {exc}. {safe}; {done} stops are "
                          f"saved in {out}. Fix the cause, then {hint}", done) from exc
    finally:
        stage.close()
    return retried


_NOTHING_MOVED = "Nothing was moved and no stop recorded; fix it, then run the same command again"


def _open_stage(stage: GrblStage, store: ScanFile, out: Path) -> None:
    """Connect to the stage; a port that cannot be opened, no controller on it, or settings that
    refuse the configuration stop the scan before it starts (nothing moved, the empty file removed)."""
    try:
        stage.open()
    except StageError as exc:
        _drop_if_empty(store, out)
        cls = StageRefused if isinstance(exc, StageRefused) else StageError
        raise cls(f"{exc}. {_NOTHING_MOVED}") from None


def _drop_if_empty(store: ScanFile, out: Path) -> None:
    """Close the scan file, and remove it if it holds no stop (so the same command starts it again)."""
    done = store.stops_done
    store.close()
    if done == 0:
        out.unlink(missing_ok=True)


def holds_no_stop(path: str | Path) -> bool:
    """Whether ``path`` is a scan file ``clsas acquire`` started that holds no stop yet."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return ("n_stops_planned" in f.attrs and not bool(f.attrs.get("complete", False))
                    and "signals" in f and f["signals"].shape[0] == 0)
    except OSError:
        return False


def _stored_air(path: Path) -> tuple[float, float]:
    """The air a partial scan was started with (a resumed scan keeps it)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return float(f.attrs["temperature_c"]), float(f.attrs["humidity_pct"])
    except (OSError, KeyError) as exc:
        raise ValueError(f"cannot resume {path}: {exc}") from None


def stop_indices(path: str | Path) -> np.ndarray:
    """The stop number of every measurement in a scan file (to check each stop is there once)."""
    import h5py

    with h5py.File(path, "r") as f:
        return f["stop_index"][: f["signals"].shape[0]]
