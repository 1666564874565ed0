"""Every fault kind at the first, a middle and the last stop, on the real GRBL firmware and on the
emulator: the file keeps the stops before, and a resumed scan completes it to a file equal to an
uninterrupted one (every stop once, same positions and signals; only the timestamps differ).

The faults are the ones the real firmware and its pseudo-terminal can really produce: a soft-limit
alarm (a target beyond the travel), a hard-limit alarm (the carriage driven onto a home switch with
``$21=1``), the reset button mid-move (the kit's SIGUSR1: ``ALARM:3``), the port disappearing (the
firmware and its pty killed), an audio device error, and Ctrl-C mid-move. The real-firmware cases
need the kit (tests/grbl_kit.py) and skip without it; one case per kind runs by default, the rest
of the matrix is marked slow.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from grbl_kit import SETUP, RealGrbl

from clsas import rig
from clsas.rig import GrblEmulator, GrblStage, ScanAborted, ScanInterrupted, stop_indices

pytest.importorskip("serial", reason="the rig tests need pyserial (pip install 'clsas[rig]')")

pytestmark = pytest.mark.hw

# four stops (2 x 2, serpentine) 40 mm apart: stops 1, 3 and 4 are the first, a middle and the last
RIG = """
[stage]
port = "set by the test"
work_area_mm = [[-1000, 0], [-1000, 0]]
feed_mm_min = 6000

[scan]
origin_mm = [-60, -60]
settle_s = 0

[aperture]
nx = 2
ny = 2
width_m = 0.04
height_m = 0.04

[recorder]
record_s = 0.012
repeat_gap_s = 0

[chirp]
duration_s = 0.002

[simulate]
points = [{ position_m = [0.01, -0.02, 0.8], amplitude = 1.0 }]
noise_rms = 1e-4
latency_samples = 250
"""
N_STOPS = 4
KINDS = ("soft-limit", "hard-limit", "reset", "disconnect", "audio", "ctrl-c")
AT = (1, 3, 4)
# one case per kind in the default run on the real firmware, the stops spread over the kinds
DEFAULT = {("soft-limit", 3), ("hard-limit", 1), ("reset", 4), ("disconnect", 3), ("audio", 4), ("ctrl-c", 1)}
WHAT = {"soft-limit": "ALARM:2", "hard-limit": "ALARM:1", "reset": "ALARM:3", "disconnect": "lost while",
        "audio": "audio device error", "ctrl-c": "interrupted"}


class EmulatedRig:
    """The emulator, with the same fault controls as :class:`RealRig`."""

    def __init__(self):
        self.emu = None
        self.start()

    def start(self):
        if self.emu is not None:
            self.emu.stop()
        # like the kit's port (no --reset-on-open): GRBL runs on across opens
        self.emu = GrblEmulator(time_scale=0.01, homing_s=20.0, reset_on_open=False).start()

    @property
    def port(self):
        return self.emu.port

    def prepare(self, kind):
        self.emu.soft_limits, self.emu.hard_limits = kind != "hard-limit", kind == "hard-limit"
        if kind == "reset":
            # the button half way through the at-th move of this scan (the emulator counts them all)
            self.emu.faults = rig.Faults(reset_at_move=self.emu.moves + self.at)

    def during_move(self, kind):
        if kind == "disconnect":
            self.emu.disconnect()

    def recover(self, kind):
        if kind == "disconnect":  # plugged in again: a new port
            self.start()
        self.emu.faults = rig.Faults()

    def stop(self):
        self.emu.stop()


class RealRig:
    """GRBL 1.1h on grbl-sim behind a pty; its link's path does not change across restarts."""

    def __init__(self, exe, workdir):
        self.grbl = RealGrbl(exe, workdir)
        self.grbl.raw(*SETUP)

    @property
    def port(self):
        return self.grbl.port

    def prepare(self, kind):
        if self.grbl.proc.poll() is not None:
            self.grbl.start()
        self.grbl.raw(*(("$20=0", "$21=1") if kind == "hard-limit" else ("$20=1", "$21=0")))

    def during_move(self, kind):
        if kind == "reset":
            self.grbl.press_reset()
        elif kind == "disconnect":
            self.grbl.pull_cable()

    def recover(self, kind):
        if kind == "disconnect":
            self.grbl.start()  # the same EEPROM and carriage position

    def stop(self):
        self.grbl.stop()


class FaultyStage(GrblStage):
    """A GrblStage whose ``at``-th move is the fault ``kind`` (the rest are plain moves)."""

    def __init__(self, port, *, rig_, kind, at, **kwargs):
        super().__init__(port, **kwargs)
        self.rig_, self.kind, self.at, self.moves = rig_, kind, at, 0

    def move_to(self, x_mm, y_mm):
        self.moves += 1
        if self.moves != self.at or self.kind == "audio":
            return super().move_to(x_mm, y_mm)
        if self.kind == "soft-limit":  # beyond the 1000 mm travel: GRBL refuses it with ALARM:2
            self.command(f"G53 G1 X{x_mm:.3f} Y-1100 F6000")
        elif self.kind == "hard-limit":  # onto the X home switch at machine 0 (soft limits off)
            self.command(f"G53 G1 X5 Y{y_mm:.3f} F6000")
        else:
            self.command(f"G53 G1 X{x_mm:.3f} Y{y_mm:.3f} F6000")
            if self.kind == "ctrl-c":
                raise KeyboardInterrupt  # while the carriage moves
            self.rig_.during_move(self.kind)
        self.wait_idle(10.0)
        raise AssertionError(f"the {self.kind} fault did not stop the scan")


def _stage(cfg, port, **kwargs):
    return rig.scan.stage_for(cfg, port, reset_on_open=False, **kwargs)  # neither resets on open


def _audio(cfg, error_at_stop=None):
    sim = cfg.simulate
    return rig.SimulatedIO(cfg.scene(), cfg.fs_hz, latency_samples=sim["latency_samples"],
                           noise_rms=sim["noise_rms"], error_at_stop=error_at_stop)


def _scan(cfg, rig_, path, **kwargs):
    return rig.acquire(cfg, path, simulate="audio", audio_io=kwargs.pop("audio_io", None) or _audio(cfg),
                       stage=kwargs.pop("stage", None) or _stage(cfg, rig_.port), **kwargs)


def _arrays(path):
    with h5py.File(path, "r") as f:
        arrays = {k: f[k][()] for k in f if k != "timestamps"}
        attrs = {k: f.attrs[k] for k in f.attrs}
    return arrays, attrs


def _reference(rig_, tmp_path_factory):
    """The config and an uninterrupted scan on ``rig_``."""
    cfg = rig.parse_rig_config(RIG)
    ref = tmp_path_factory.mktemp("ref") / "ref.h5"
    res = _scan(cfg, rig_, ref)
    assert res.complete and res.stops_this_run == N_STOPS
    return cfg, ref


@pytest.fixture(scope="module")
def emulated(tmp_path_factory):
    rig_ = EmulatedRig()
    try:
        yield (rig_, *_reference(rig_, tmp_path_factory))
    finally:
        rig_.stop()


@pytest.fixture(scope="module")
def real(grbl_exe, tmp_path_factory):
    rig_ = RealRig(grbl_exe, tmp_path_factory.mktemp("grbl_faults"))
    try:
        yield (rig_, *_reference(rig_, tmp_path_factory))
    finally:
        rig_.stop()


CASES = [pytest.param(kind, at, id=f"{kind}@{at}") for kind in KINDS for at in AT]
REAL_CASES = [pytest.param(kind, at, id=f"{kind}@{at}", marks=[] if (kind, at) in DEFAULT else [pytest.mark.slow])
              for kind in KINDS for at in AT]


@pytest.mark.parametrize("kind,at", CASES)
def test_fault_on_the_emulator_keeps_the_stops_before_and_resume_completes_the_scan(emulated, kind, at, tmp_path):
    _fault_then_resume(emulated, kind, at, tmp_path)


@pytest.mark.parametrize("kind,at", REAL_CASES)
def test_fault_on_the_real_firmware_keeps_the_stops_before_and_resume_completes_the_scan(real, kind, at, tmp_path):
    _fault_then_resume(real, kind, at, tmp_path)


def _fault_then_resume(backend, kind, at, tmp_path):
    rig_, cfg, ref = backend
    path = tmp_path / "scan.h5"
    rig_.at = at
    rig_.prepare(kind)
    stage = _stage(cfg, rig_.port, cls=FaultyStage, rig_=rig_, kind=kind, at=at)
    audio = _audio(cfg, error_at_stop=at - 1 if kind == "audio" else None)
    with pytest.raises(ScanInterrupted if kind == "ctrl-c" else ScanAborted,
                       match=f"at stop {at} of {N_STOPS}.*{at - 1} stops are saved") as exc:
        _scan(cfg, rig_, path, stage=stage, audio_io=audio)
    assert WHAT[kind] in str(exc.value)
    assert exc.value.stops_done == at - 1
    np.testing.assert_array_equal(stop_indices(path), np.arange(at - 1))  # the stops before, once each

    rig_.recover(kind)
    res = _scan(cfg, rig_, path, resume=True)
    assert res.complete and res.stops_this_run == N_STOPS - (at - 1)
    np.testing.assert_array_equal(stop_indices(path), np.arange(N_STOPS))  # every stop exactly once
    (got, got_attrs), (want, want_attrs) = _arrays(path), _arrays(ref)
    assert sorted(got) == sorted(want)
    for key in want:  # positions, signals, loopback, t0: equal to the uninterrupted scan
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    assert {k: v for k, v in got_attrs.items() if k != "clsas_version"} == \
        {k: v for k, v in want_attrs.items() if k != "clsas_version"}


def test_cli_resume_after_the_reset_button_on_the_real_firmware(real, tmp_path, capsys):
    """The same through `clsas acquire ... --simulate audio` and `--resume`, the port taken from
    the rig file: the reset button pressed while the carriage moves to stop 3."""
    import threading
    import time

    from clsas.cli import main

    rig_, _, ref = real
    rig_.prepare("reset")
    conf, out = tmp_path / "rig.toml", tmp_path / "scan.h5"
    conf.write_text(RIG.replace('port = "set by the test"', f'port = "{rig_.port}"\nreset_on_open = false'))
    log, start = rig_.grbl.transcript, len(rig_.grbl.transcript())

    def press_during_the_third_move():
        for _ in range(3000):
            if log()[start:].count("> b'G53 G1 ") >= 3:
                return rig_.grbl.press_reset()
            time.sleep(0.01)

    presser = threading.Thread(target=press_during_the_third_move)
    presser.start()
    try:
        assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 3
    finally:
        presser.join()
    err = capsys.readouterr().err
    assert "at stop 3 of 4: GRBL raised ALARM:3" in err and "2 stops are saved" in err
    assert f"clsas acquire {conf} {out} --resume --simulate audio" in err
    assert main(["acquire", str(conf), str(out), "--resume", "--simulate", "audio", "-q"]) == 0
    assert "4 of 4 stops (2 this run" in capsys.readouterr().out
    (got, got_attrs), (want, want_attrs) = _arrays(out), _arrays(ref)
    assert sorted(got) == sorted(want)
    for key in want:  # the same scan as the matrix's reference, stop for stop
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    skip = ("clsas_version", "config_toml")  # the rig file names the port
    for key in set(got_attrs) | set(want_attrs):
        assert key in skip or got_attrs.get(key) == want_attrs.get(key), key
