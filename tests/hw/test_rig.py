"""Rig acquisition against real protocol peers: a GRBL emulator on a pseudo-terminal (opened by
pyserial as a serial port) and, where a JACK server runs, real PortAudio through sounddevice."""

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from stepped_clock import SteppedClock

import clsas
from clsas import rig
from clsas.rig import Faults, GrblEmulator, GrblStage, ScanAborted, ScanInterrupted, stop_indices

pytest.importorskip("serial", reason="the rig tests need pyserial (pip install 'clsas[rig]')")

pytestmark = pytest.mark.hw


def rig_toml(nx=4, ny=3, mics=1, repeats=1, timeout_s=1.0, extra=""):
    rx = "[[0.02, 0.0, 0.0]]" if mics == 1 else "[[0.02, 0.0, 0.0], [0.0, 0.03, 0.0]]"
    ch = "[2]" if mics == 1 else "[2, 3]"
    return f"""
[stage]
port = "unused"
timeout_s = {timeout_s}
feed_mm_min = 6000

[scan]
origin_mm = [-300, -300]
settle_s = 0

[aperture]
nx = {nx}
ny = {ny}
width_m = 0.24
height_m = 0.16
rx_offset_m = {rx}

[audio]
mic_channels = {ch}

[recorder]
record_s = 0.016
repeats = {repeats}
repeat_gap_s = 0

[chirp]
duration_s = 0.002

[grid]
x_m = [-0.15, 0.15]
y_m = [-0.15, 0.15]
z_m = [0.8, 1.0]
spacing_m = 0.01

[simulate]
points = [{{ position_m = [0.05, -0.03, 0.9], amplitude = 1.0 }}]
noise_rms = 1e-4
latency_samples = 250
time_scale = 0.002
{extra}
"""


@pytest.fixture
def emulator():
    with GrblEmulator(time_scale=0.01) as emu:
        yield emu


@pytest.fixture
def stage(emulator):
    st = GrblStage(emulator.port, timeout_s=1.0, reset_wait_s=1.0, work_area_mm=((-900, 0), (-900, 0)))
    with st:
        yield st


def arrays(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f if k != "timestamps"}, {k: f.attrs[k] for k in f.attrs if k != "complete"}


# -- GRBL protocol ------------------------------------------------------------------------------

def test_banner_after_boot_noise_and_alarm_lock(emulator, stage):
    assert stage.version == "Grbl 1.1h"
    assert stage.status().state == "Alarm"  # homing enabled: locked until $H or $X
    with pytest.raises(rig.GrblError, match="error:9 .*alarm"):
        stage.command("G0 X10")
    stage.home()
    assert stage.status() == rig.Status("Idle", (-1.0, -1.0, -1.0))  # GRBL 1.1: -pulloff after $H
    assert emulator.received[:3] == ["$$", "G0 X10", "$H"]  # settings read on connect


def test_move_runs_then_idles_at_target_and_polls_at_most_5hz():
    clock = SteppedClock()  # the machine moves only as the test, or the stage's poll waits, step the clock
    with GrblEmulator(homing=False, banner_delay_s=0.05, clock=clock) as emu, \
            GrblStage(emu.port, feed_mm_min=3000, clock=clock) as st:
        st.unlock()
        st.command("G1 X-20 Y0 F3000")  # 20 mm at 50 mm/s: 0.4 s
        clock.advance(0.15)
        assert st.status() == rig.Status("Run", (-7.5, 0.0, 0.0))  # the position advances with the clock
        emu.status_times.clear()
        end = st.move_to(-40.0, -10.0)  # queued behind the first: Idle at 0.4 + 22.4 mm / 50 mm/s
        assert end.state == "Idle" and end.position_mm[:2] == (-40.0, -10.0)
        gaps = np.diff(emu.status_times)
        assert len(gaps) >= 3 and gaps.min() >= st.poll_s - 1e-9  # '?' no faster than 5 Hz
        assert emu.status_times[-1] - emu.status_times[0] >= 0.4 + np.hypot(20, 10) / 50 - 0.15 - 1e-9
        assert "G21 G90" in emu.received and "G53 G1 X-40.000 Y-10.000 F3000" in emu.received


def test_error_reply_names_code_and_meaning(stage):
    stage.home()
    with pytest.raises(rig.GrblError, match=r"error:20 \(unsupported or invalid g-code") as exc:
        stage.command("G99")
    assert exc.value.code == 20


def test_target_outside_work_area_is_refused_before_sending(emulator, stage):
    stage.home()
    with pytest.raises(ValueError, match="x_mm = -950.000 is outside the stage's work area"):
        stage.move_to(-950, -10)
    assert not any(line.startswith("G1") for line in emulator.received)


def test_soft_limit_alarm_resets_and_drops_the_late_ok():
    with GrblEmulator(time_scale=0.01, travel_mm=(100, 100, 10)) as emu:
        with GrblStage(emu.port, work_area_mm=((-100, 0), (-100, 0))) as st:
            st.home()
            with pytest.raises(rig.GrblAlarm, match=r"ALARM:2 .soft limit.*soft reset \(Ctrl-X\)") as exc:
                st.command("G53 G1 X-200 F3000")
            assert exc.value.code == 2
            assert st.status().state == "Alarm"  # reset done: GRBL answers again, locked until $H/$X
            # the refused line's late 'ok' came after the banner: it must not answer the next command
            assert any(line.startswith("$130=") for line in st.command("$$"))
            st.home()
            assert st.move_to(-50, -50).position_mm[:2] == (-50.0, -50.0)


def test_work_area_outside_soft_limits_is_refused_on_connect():
    with GrblEmulator(time_scale=0.01, travel_mm=(100, 100, 10)) as emu:
        with pytest.raises(rig.StageError, match=r"outside GRBL's soft limits \(\$20=1, \$130=100\).*\[-100, 0\]"):
            GrblStage(emu.port, work_area_mm=((0, 500), (0, 500))).open()


def test_wpos_reports_are_refused_naming_10():
    with GrblEmulator(time_scale=0.01, report_mpos=False) as emu:
        with pytest.raises(rig.StageError, match=r"\$10=0.*'\$10=1'"):
            GrblStage(emu.port).open()


def test_stored_work_offset_does_not_shift_moves():
    with GrblEmulator(time_scale=0.01, work_offset_mm=(5.0, 0.0, 0.0)) as emu, GrblStage(emu.port) as st:
        st.home()
        assert st.move_to(-100, -20).position_mm[:2] == (-100.0, -20.0)
        assert emu.position_mm[0] == pytest.approx(-100.0)


def test_timeouts_default_from_grbl_settings():
    with GrblEmulator(time_scale=0.01) as emu, GrblStage(emu.port, feed_mm_min=6000) as st:
        # $25=500 mm/min seek over 1.5 x 1000 mm, twice, plus 30 s
        assert st.home_timeout() == pytest.approx(2 * 1.5 * 1000 / 500 * 60 + 30)
        assert st.move_timeout((0, 0), (-1000, 0)) == pytest.approx(3 * st.move_time((0, 0), (-1000, 0)) + 10)
    assert GrblStage("unused", home_timeout_s=7, move_timeout_s=3).home_timeout() == 7


@pytest.mark.parametrize("fault,error", [
    (Faults(alarm_at_move=1), rig.GrblAlarm),
    (Faults(drop_ok_at_move=1), rig.StageTimeout),
    (Faults(disconnect_at_move=1), rig.StageDisconnected),
    (Faults(error_at_move=1), rig.GrblError),
], ids=["alarm", "dropped-ok", "disconnect", "error"])
def test_injected_faults_raise(fault, error):
    with GrblEmulator(time_scale=0.01, faults=fault) as emu, GrblStage(emu.port, timeout_s=0.5) as st:
        st.home()
        with pytest.raises(error):
            st.move_to(-100, -100)


def test_alarm_stops_the_machine_part_way():
    with GrblEmulator(time_scale=0.05, faults=Faults(alarm_at_move=1)) as emu, GrblStage(emu.port) as st:
        st.home()
        with pytest.raises(rig.GrblAlarm, match="hard limit"):
            st.move_to(-201, -1)
        assert emu.state == "Alarm"
        assert emu.position_mm[0] == pytest.approx(-101.0)


def test_feed_hold_stops_motion():
    clock = SteppedClock()
    with GrblEmulator(homing=False, banner_delay_s=0.05, clock=clock) as emu, GrblStage(emu.port, clock=clock) as st:
        st.unlock()
        st.command("G1 X-50 F3000")  # 50 mm at 50 mm/s: 1 s
        clock.advance(0.2)
        assert st.feed_hold()
        held = st.status()  # the '?' follows the '!' on the line: the hold is in force
        assert held == rig.Status("Hold", (-10.0, 0.0, 0.0))
        clock.advance(0.5)
        assert st.status() == held  # held: the clock moves, the carriage does not
        st.cycle_start()  # the rest of the move runs from where it was held
        assert st.wait_idle(5.0).position_mm == (-50.0, 0.0, 0.0)
        assert emu.state == "Idle"


def test_no_controller_on_the_port_says_so():
    master, slave = os.openpty()
    try:
        st = GrblStage(os.ttyname(slave), reset_wait_s=0.2)
        with pytest.raises(rig.StageTimeout, match="no GRBL start-up banner"):
            st.open()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("kwargs,match", [
    ({"poll_hz": 10}, "poll_hz must be at most 5"),
    ({"work_area_mm": ((10, 0), (0, 10))}, "min < max"),
    ({"feed_mm_min": -1}, "feed_mm_min"),
    ({"timeout_s": float("nan")}, "timeout_s"),
])
def test_stage_arguments_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GrblStage("/dev/null", **kwargs)


# -- audio takes (no sound card) ----------------------------------------------------------------

@pytest.mark.parametrize("delay", [0.0, 123.0, 123.3, 401.75])
def test_onset_found_to_a_fraction_of_a_sample(chirp96, delay):
    w, fs = chirp96
    n = 2048
    x = np.fft.irfft(np.fft.rfft(w, n) * np.exp(-2j * np.pi * np.fft.rfftfreq(n) * delay), n)
    assert rig.find_onset(x, w) == pytest.approx(delay, abs=0.05)
    if delay == int(delay):
        assert rig.find_onset(x, w) == pytest.approx(delay, abs=1e-6)  # whole samples exactly


def test_onset_refuses_a_loopback_without_chirp(chirp96, rng):
    w, _ = chirp96
    with pytest.raises(rig.AudioError, match="no chirp on the loopback channel"):
        rig.find_onset(rng.normal(size=3000), w)


def _recorder(io, retries=3):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    return rig.Recorder(io, w, 96e3, 1500, level=0.5, retries=retries, max_latency_s=0.01)


def test_take_aligns_on_the_loopback_and_sets_t0():
    scene = clsas.Scene(np.array([[0.0, 0.0, 0.5]]))
    io = rig.SimulatedIO(scene, 96e3, latency_samples=333, noise_rms=0.0)
    take = _recorder(io).take(0, np.zeros(3), np.zeros((1, 3)))
    assert take.onset_samples == pytest.approx(333, abs=1e-6) and take.t0_s == pytest.approx(0.0, abs=1e-9)
    echo = rig.find_onset(take.signals[0], _recorder(io).waveform)
    assert echo == pytest.approx(1.0 / clsas.speed_of_sound(20.0, 50.0) * 96e3, abs=0.05)  # the echo at its acoustic
    # delay (the scene's air: 20 C, 50 % RH), latency removed


@pytest.mark.parametrize("fault", ["clip_at_stop", "xrun_at_stop"])
def test_spoiled_take_is_retried(fault):
    scene = clsas.Scene(np.array([[0.0, 0.0, 0.5]]))
    io = rig.SimulatedIO(scene, 96e3, **{fault: 2})
    take = _recorder(io).take(2, np.zeros(3), np.zeros((1, 3)))
    assert take.attempts == 2
    assert ("clipping on microphone 1" if fault == "clip_at_stop" else "input overflow") in take.problems[0]


def test_device_error_is_reported():
    io = rig.SimulatedIO(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), 96e3, error_at_stop=0)
    with pytest.raises(rig.AudioError, match="audio device error"):
        _recorder(io).take(0, np.zeros(3), np.zeros((1, 3)))


def test_persistent_clipping_fails_after_the_retries():
    class Clipping(rig.SimulatedIO):
        def playrec(self, out, ctx):
            rec, flags = super().playrec(out, ctx)
            rec[:, 0] = np.clip(4 * rec[:, 0], -1, 1)
            return rec, flags

    io = Clipping(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), 96e3)
    with pytest.raises(rig.AudioError, match="failed 2 times: attempt 1: clipping on loopback"):
        _recorder(io, retries=2).take(0, np.zeros(3), np.zeros((1, 3)))


def test_missing_portaudio_says_which_package(monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "sounddevice":
            raise OSError("PortAudio library not found")
        return real(name, *a, **k)

    monkeypatch.delitem(sys.modules, "sounddevice", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(ImportError, match="libportaudio2"):
        rig.audio.import_sounddevice()


def test_import_clsas_stays_light():
    code = "import clsas, clsas.rig, sys; print(sorted(m for m in ('serial', 'sounddevice') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# -- configuration ------------------------------------------------------------------------------

@pytest.mark.parametrize("old,new,match", [
    ("mic_channels = [2]", "mic_channels = [2]\nfs_hz = 44100", "audio.fs_hz must be 96000 or 192000"),
    ("mic_channels = [2]", "mic_channels = [2, 3]", "one input channel per microphone"),
    ("mic_channels = [2]", "mic_channels = [1]", "loopback_channel 1 is also a microphone"),
    ("origin_mm = [-300, -300]", "origin_mm = [-50, -300]", "outside stage.work_area_mm"),
    ("repeats = 1", "repeats = 0", "recorder.repeats"),
    ("record_s = 0.016", "record_s = 0.016\ndevice = 1",
     r"\[recorder\] unknown key 'device': it belongs in \[audio\] device"),
    ("record_s = 0.016", "record_s = 0.001", "shorter than the chirp"),
    ("[stage]", "[stage\n", "not valid TOML"),
])
def test_rig_config_errors_name_the_key(old, new, match):
    with pytest.raises(ValueError, match=match):
        rig.parse_rig_config(rig_toml().replace(old, new))


def test_sample_config_parses():
    cfg = rig.parse_rig_config(rig.SAMPLE_RIG_TOML)
    assert cfg.n_stops == 18 * 12 and cfg.n_mics == 1 and cfg.fs_hz == 96000
    # 20 mm inside the 1 m travel at each end: no stop on machine 0, where the home switches are
    assert cfg.stage_target_mm(0) == pytest.approx((-980.0, -980.0))
    assert cfg.stage_target_mm(17) == pytest.approx((-20.0, -980.0))
    assert cfg.stage["reset_on_open"] is True and cfg.home and cfg.settle_s == 0.5


def _parameters(func, skip=()):
    import inspect

    return {name for name in inspect.signature(func).parameters if name not in ("self", *skip)}


def test_config_sections_are_the_constructors_arguments():
    cfg = rig.parse_rig_config(rig.SAMPLE_RIG_TOML)
    assert set(cfg.stage) == _parameters(GrblStage.__init__, skip=("clock",))  # a time base, not a rig setting
    assert set(cfg.audio) == _parameters(rig.SoundDeviceIO.__init__)
    assert set(cfg.recorder) == _parameters(rig.Recorder.__init__, skip=("io", "waveform", "fs_hz", "n_samples"))
    st = rig.scan.stage_for(cfg)
    assert st.port == "/dev/ttyUSB0" and st.reset_on_open is True and st.work_area_mm.tolist() == [[-1000, -10]] * 2
    rec = rig.scan.recorder_for(cfg, rig.SimulatedIO(cfg.scene(), cfg.fs_hz))
    assert rec.n_samples == cfg.n_samples == 1920 and rec.repeats == 4


FLAT = """
[stage]
port = "/dev/ttyACM0"
home = false
origin_mm = [-200, -200]
settle_s = 0.25
homing_timeout_s = 90
feed_mm_min = 2000

[aperture]
nx = 2
ny = 2
width_m = 0.1
height_m = 0.1

[audio]
device = 3
record_s = 0.01
repeats = 2
level = 0.3
"""


def test_old_flat_keys_are_read_with_a_warning_naming_where_they_moved():
    with pytest.warns(FutureWarning) as record:
        old = rig.parse_rig_config(FLAT, "old.toml")
    assert len(record) == 1 and str(record[0].message).startswith("old.toml uses keys of the older flat layout: ")
    for moved in ("[stage] settle_s has moved to [scan] settle_s", "[stage] home has moved to [scan] home",
                  "[stage] homing_timeout_s has moved to [stage] home_timeout_s",
                  "[audio] record_s has moved to [recorder] record_s", "[audio] level has moved to [recorder] level"):
        assert moved in str(record[0].message), moved
    new = rig.parse_rig_config(FLAT.replace("home = false\norigin_mm = [-200, -200]\nsettle_s = 0.25\n", "")
                               .replace("homing_timeout_s", "home_timeout_s")
                               .replace("record_s = 0.01\nrepeats = 2\nlevel = 0.3\n", "")
                               + "\n[scan]\nhome = false\norigin_mm = [-200, -200]\nsettle_s = 0.25\n"
                               + "\n[recorder]\nrecord_s = 0.01\nrepeats = 2\nlevel = 0.3\n")
    assert old.stage == new.stage and old.audio == new.audio and old.recorder == new.recorder
    assert (old.home, old.settle_s, old.origin_mm.tolist()) == (False, 0.25, [-200, -200]) == \
        (new.home, new.settle_s, new.origin_mm.tolist())
    assert old.stage["home_timeout_s"] == 90 and old.recorder["repeats"] == 2
    with pytest.raises(ValueError, match=r"\[stage\] settle_s and \[scan\] settle_s are the same setting; keep"):
        rig.parse_rig_config(FLAT + "\n[scan]\nsettle_s = 1\n")


# -- scans: faults, resume, equality ------------------------------------------------------------

@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted emulated scan of 12 stops."""
    path = tmp_path_factory.mktemp("ref") / "ref.h5"
    res = rig.acquire(rig.parse_rig_config(rig_toml()), path, simulate=True)
    assert res.complete and res.stops_this_run == 12
    return path


def _assert_equal_files(a, b):
    (arr_a, att_a), (arr_b, att_b) = arrays(a), arrays(b)
    assert sorted(arr_a) == sorted(arr_b)
    for k in arr_a:
        np.testing.assert_array_equal(arr_a[k], arr_b[k], err_msg=k)
    assert att_a.keys() == att_b.keys()
    for k in att_a:
        assert att_a[k] == att_b[k] or k == "clsas_version", k


# alarms, resets, disconnects, audio errors and Ctrl-C: tests/hw/test_rig_faults.py (emulator and real firmware)
FAULTS = [(kind, n) for kind in ("error", "drop-ok") for n in (1, 7, 12)]


@pytest.mark.parametrize("kind,n", FAULTS, ids=[f"{k}@{n}" for k, n in FAULTS])
def test_fault_at_any_stop_keeps_the_stops_before_and_resume_completes(tmp_path, reference, kind, n):
    cfg = rig.parse_rig_config(rig_toml())
    path = tmp_path / "scan.h5"
    with pytest.raises(ScanAborted, match=f"at stop {n} of 12.*{n - 1} stops are saved.*resume=True") as exc:
        rig.acquire(cfg, path, simulate=True, faults=Faults.parse(f"{kind}@{n}"))
    assert exc.value.stops_done == n - 1
    np.testing.assert_array_equal(stop_indices(path), np.arange(n - 1))
    if n > 1:
        partial = clsas.load(path)  # readable as a dataset as it is
        assert partial.n_meas == n - 1
    res = rig.acquire(cfg, path, resume=True, simulate=True)
    assert res.complete and res.stops_this_run == 12 - (n - 1)
    np.testing.assert_array_equal(stop_indices(path), np.arange(12))
    _assert_equal_files(reference, path)


def test_audio_fault_stops_the_scan_and_resume_completes(tmp_path, reference):
    cfg = rig.parse_rig_config(rig_toml())
    sim = cfg.simulate
    io = rig.SimulatedIO(cfg.scene(), cfg.fs_hz, latency_samples=sim["latency_samples"],
                         noise_rms=sim["noise_rms"], error_at_stop=4)
    path = tmp_path / "scan.h5"
    with pytest.raises(ScanAborted, match="at stop 5 of 12: audio device error"):
        rig.acquire(cfg, path, simulate=True, audio_io=io)
    np.testing.assert_array_equal(stop_indices(path), np.arange(4))
    rig.acquire(cfg, path, resume=True, simulate=True)
    _assert_equal_files(reference, path)


def test_ctrl_c_stops_cleanly_and_resumes(tmp_path, reference):
    cfg = rig.parse_rig_config(rig_toml())
    path = tmp_path / "scan.h5"

    def interrupt(done, total):
        if done == 5:
            raise KeyboardInterrupt

    with pytest.raises(ScanInterrupted, match="interrupted at stop 5 of 12; 5 stops are saved"):
        rig.acquire(cfg, path, simulate=True, progress=interrupt)
    rig.acquire(cfg, path, resume=True, simulate=True)
    _assert_equal_files(reference, path)


def test_resume_trims_a_stop_caught_in_flight(tmp_path, reference):
    """A crash between writing a stop's positions and its signals leaves arrays running ahead."""
    cfg = rig.parse_rig_config(rig_toml())
    path = tmp_path / "scan.h5"
    with pytest.raises(ScanAborted):
        rig.acquire(cfg, path, simulate=True, faults=Faults(alarm_at_move=4))
    with h5py.File(path, "r+") as f:
        for name in ("tx_positions", "t0_s", "stop_index"):
            f[name].resize(f[name].shape[0] + 1, axis=0)
    assert clsas.load(path).n_meas == 3  # readers trim to 'signals'
    rig.acquire(cfg, path, resume=True, simulate=True)
    _assert_equal_files(reference, path)


def test_resume_refuses_a_different_configuration(tmp_path, reference):
    path = tmp_path / "scan.h5"
    path.write_bytes(reference.read_bytes())
    with pytest.raises(ValueError, match="different rig configuration"):
        rig.acquire(rig.parse_rig_config(rig_toml(nx=5)), path, resume=True, simulate=True)
    with pytest.raises(FileExistsError, match="--resume"):
        rig.acquire(rig.parse_rig_config(rig_toml()), path, simulate=True)
    res = rig.acquire(rig.parse_rig_config(rig_toml()), path, resume=True, simulate=True)
    assert res.complete and res.stops_this_run == 0


def test_scan_images_the_reflector_where_it_is(reference):
    ds = clsas.load(reference)
    assert ds.n_meas == 12 and ds.loopback.shape == (12, ds.n_samples)
    assert np.all(np.abs(ds.t0_s) < 1 / ds.fs_hz)
    grid = clsas.VoxelGrid.from_bounds((-0.15, 0.15), (-0.15, 0.15), (0.8, 1.0), 0.01)
    peak = clsas.reconstruct(ds, grid, backend="numpy").peaks(1)[0].position_m
    assert np.linalg.norm(peak - [0.05, -0.03, 0.9]) <= 0.011


def test_two_microphones_make_two_measurements_per_stop(tmp_path):
    cfg = rig.parse_rig_config(rig_toml(nx=3, ny=2, mics=2, repeats=2))
    path = tmp_path / "two.h5"
    rig.acquire(cfg, path, simulate=True)
    ds = clsas.load(path)
    assert ds.n_meas == 12
    np.testing.assert_array_equal(stop_indices(path), np.repeat(np.arange(6), 2))
    np.testing.assert_allclose(ds.rx_positions[1] - ds.rx_positions[0], [-0.02, 0.03, 0.0], atol=1e-9)
    grid = clsas.VoxelGrid.from_bounds((-0.15, 0.15), (-0.15, 0.15), (0.8, 1.0), 0.01)
    peak = clsas.reconstruct(ds, grid, backend="numpy").peaks(1)[0].position_m
    assert np.linalg.norm(peak - [0.05, -0.03, 0.9]) <= 0.015


def test_cli_acquire_fault_resume_reconstruct(tmp_path, capsys):
    from clsas.cli import main

    conf = tmp_path / "rig.toml"
    conf.write_text(rig_toml())
    out = tmp_path / "scan.h5"
    assert main(["acquire", str(conf), str(out), "--simulate", "--fault", "disconnect@6", "-q"]) == 3
    err = capsys.readouterr().err
    assert "5 stops are saved" in err and f"clsas acquire {conf} {out} --resume --simulate" in err
    assert main(["acquire", str(conf), str(out), "--simulate", "--resume", "-q"]) == 0
    assert "12 of 12 stops (7 this run" in capsys.readouterr().out
    assert main(["reconstruct", str(out), "--backend", "numpy", "-q", "--peaks", "1"]) == 0
    assert "peak (+0.050, -0.030, 0.900) m" in capsys.readouterr().out
    assert main(["acquire", "--sample-config"]) == 0
    assert "[stage]" in capsys.readouterr().out
    assert main(["acquire", str(conf), str(out), "--fault", "alarm@1"]) == 2


# -- real PortAudio through a JACK server ------------------------------------------------------

def _jack_loopback_reason():
    try:
        sd = rig.audio.import_sounddevice()
    except ImportError as exc:
        return str(exc)
    apis = [a["name"] for a in sd.query_hostapis()]
    if not any("JACK" in a for a in apis):
        return "no JACK server is running (.ci/run starts one: jackd -L 2 -d dummy -r 96000)"
    names = [d["name"] for d in sd.query_devices()]
    if "loopback" not in names:
        return "the JACK server has no loopback ports (start jackd with -L 2)"
    return None


JACK = _jack_loopback_reason()
needs_jack = pytest.mark.skipif(JACK is not None, reason=f"real audio tests: {JACK}")


@pytest.fixture
def jack_io():
    return rig.SoundDeviceIO("loopback", 96000, output_channel=1, loopback_channel=1, mic_channels=[2])


def _ctx():
    return rig.audio.StopContext(0, 1, np.zeros(3), np.zeros((1, 3)))


@needs_jack
def test_jack_loopback_latency_found_to_the_sample(jack_io):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    onsets = {}
    for extra in (0, 37, 100):  # a known extra delay in the output buffer, in samples
        out = np.zeros(6000)
        out[extra:extra + len(w)] = 0.5 * w
        for _ in range(5):  # a take with an xrun is retried, as a scan would
            rec, flags = jack_io.playrec(out, _ctx())
            if not flags:
                break
        assert not flags, flags
        onsets[extra] = rig.find_onset(rec[:, 0], w)
        k = int(round(onsets[extra]))
        assert abs(onsets[extra] - k) < 1e-3  # a digital loopback delays by whole samples
        np.testing.assert_allclose(rec[k:k + len(w), 0], 0.5 * w, atol=1e-6)  # the drive, bit for bit
    assert onsets[37] - onsets[0] == pytest.approx(37, abs=1e-3)
    assert onsets[100] - onsets[0] == pytest.approx(100, abs=1e-3)


@needs_jack
def test_jack_take_and_clipping(jack_io):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    take = rig.Recorder(jack_io, w, 96e3, 1000, level=0.5, retries=5, max_latency_s=0.05).take(
        0, np.zeros(3), np.zeros((1, 3)))
    np.testing.assert_allclose(take.loopback[:len(w)], 0.5 * w, atol=1e-6)
    assert abs(take.t0_s) < 1e-8
    loud = rig.Recorder(jack_io, w, 96e3, 1000, level=1.0, retries=5, clip_level=0.99, max_latency_s=0.05)
    with pytest.raises(rig.AudioError, match="clipping on loopback"):
        loud.take(0, np.zeros(3), np.zeros((1, 3)))


@needs_jack
def test_jack_unknown_device_is_refused():
    with pytest.raises(rig.AudioError, match="cannot play channel 1"):
        rig.SoundDeviceIO("no such card", 96000, 1, 1, [2])


@needs_jack
def test_jack_scan_with_emulated_stage(tmp_path, jack_io):
    """The scan script end to end with real audio: the stops' t0 come from the JACK loopback."""
    text = rig_toml(nx=3, ny=1).replace("record_s = 0.016", "record_s = 0.01\nretries = 5")
    cfg = rig.parse_rig_config(text.replace("mic_channels = [2]", "mic_channels = [2]\ndevice = \"loopback\""))
    path = tmp_path / "jack.h5"
    res = rig.acquire(cfg, path, simulate=True, audio_io=jack_io)
    assert res.complete
    ds = clsas.load(path)
    assert ds.n_meas == 3 and np.all(np.abs(ds.t0_s) < 1e-8)
    np.testing.assert_allclose(ds.loopback[:, :192], np.tile(cfg.level * cfg.waveform[:192], (3, 1)), atol=1e-6)


def test_air_sensor_command_sets_the_speed_of_sound(tmp_path):
    cfg = rig.parse_rig_config(rig_toml(nx=2, ny=1) + '\n[air]\nsensor_command = "echo 30.0 40"\n')
    assert cfg.read_air() == (30.0, 40.0)
    rig.acquire(cfg, tmp_path / "warm.h5", simulate=True)
    ds = clsas.load(tmp_path / "warm.h5")
    assert ds.temperature_c == 30.0 and ds.humidity_pct == 40.0
    assert ds.c_mps == pytest.approx(clsas.speed_of_sound(30.0, 40.0))
    p = np.array([0.05, -0.03, 0.9])  # the [simulate] reflector
    path = np.linalg.norm(p - ds.tx_positions[0]) + np.linalg.norm(p - ds.rx_positions[0])
    heard = rig.find_onset(ds.signals[0], cfg.waveform) / ds.fs_hz + ds.t0_s[0]
    assert heard == pytest.approx(path / clsas.speed_of_sound(30.0, 40.0), abs=0.2 / ds.fs_hz)  # the room's air too
    bad = rig.parse_rig_config(rig_toml(nx=2, ny=1) + '\n[air]\nsensor_command = "echo warm"\n')
    with pytest.raises(ValueError, match="air.sensor_command 'echo warm' must print"):
        bad.read_air()


def test_only_a_finished_scan_is_marked_complete(tmp_path, reference):
    with h5py.File(reference, "r") as f:
        assert bool(f.attrs["complete"]) and int(f.attrs["n_stops_planned"]) == 12
    path = tmp_path / "part.h5"
    with pytest.raises(ScanAborted):
        rig.acquire(rig.parse_rig_config(rig_toml()), path, simulate=True, faults=Faults(error_at_move=3))
    with h5py.File(path, "r") as f:
        assert not bool(f.attrs["complete"])


@pytest.mark.parametrize("kwargs,match", [
    ({"level": 1.5}, "at most 1"), ({"fs_hz": 0}, "fs_hz"), ({"repeats": 0}, "repeats"),
    ({"max_latency_s": float("inf")}, "max_latency_s"),
])
def test_recorder_arguments_are_checked(kwargs, match):
    io = rig.SimulatedIO(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), 96e3)
    args = {"fs_hz": 96e3, "n_samples": 100, **kwargs}
    with pytest.raises(ValueError, match=match):
        rig.Recorder(io, np.ones(10), args.pop("fs_hz"), args.pop("n_samples"), **args)
    with pytest.raises(ValueError, match="loopback"):
        rig.find_onset(np.full(50, np.nan), np.ones(10))


@pytest.mark.skipif(sys.platform == "win32", reason="termios is POSIX")
def test_a_port_lost_in_tcdrain_is_a_disconnect_not_a_crash():
    # pyserial's flush() calls termios.tcdrain: a pulled cable raises termios.error, which is
    # neither SerialException nor OSError
    import termios

    from clsas.rig.grbl import StageDisconnected

    class DeadPort:
        def write(self, data):
            return len(data)

        def flush(self):
            raise termios.error(5, "Input/output error")

    stage = GrblStage("/dev/null")
    stage._ser = DeadPort()
    with pytest.raises(StageDisconnected, match="lost while writing"):
        stage._write(b"?")


def test_unlock_with_soft_limits_and_home_without_homing_name_the_setting():
    with GrblEmulator(time_scale=0.01) as emu, GrblStage(emu.port) as st:
        with pytest.raises(rig.StageError, match=r"soft limits are on \(\$20=1\)"):
            st.unlock()
    with GrblEmulator(time_scale=0.01, homing=False) as emu, GrblStage(emu.port) as st:
        with pytest.raises(rig.StageError, match=r"homing is disabled in GRBL \(\$22=0\)"):
            st.home()


def test_import_clsas_rig_needs_no_posix_terminal_modules():
    code = ("import sys; import clsas.rig; "
            "print(sorted(m for m in ('tty', 'termios', 'pty') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"  # Windows has none of them


def test_moving_off_a_limit_switch_turns_hard_limits_off_then_on():
    with GrblEmulator(time_scale=0.01, faults=Faults(alarm_at_move=1)) as emu, GrblStage(emu.port) as st:
        emu.hard_limits = True  # $21=1
        st.settings = st.read_settings()
        st.home()
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 .*'\$21=0'"):
            st.move_to(-201, -1)
        st.move_off_limit(5.0, 0.0)
        sent = emu.received
        i = sent.index("$21=0")
        assert sent[i + 1] == "$X" and sent[i + 2].startswith("G91 G1 X5.000") and sent[-1] == "$21=1"
        assert emu.written[21] == 1.0 and emu.state == "Idle"


def test_hard_limit_then_jogging_off_retrips_as_on_the_real_firmware():
    """As tests/hw/test_grbl_real.py checks on GRBL 1.1h: the switch trips on the way onto it and off it."""
    with GrblEmulator(time_scale=0.01, soft_limits=False, hard_limits=True) as emu, GrblStage(emu.port) as st:
        st.home()
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 \(hard limit.*'\$21=0'"):
            st.command("G53 G1 X5 F3000")
            st.wait_idle(5.0)
        assert emu.position_mm[0] == pytest.approx(0.0)  # stopped on the switch
        st.command("$X")
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 "):
            st.command("G91 G1 X-5 F1000")
            st.wait_idle(5.0)
        assert st.move_off_limit(-5.0, 0.0).state == "Idle" and st.read_settings()[21] == 1
        assert st.home().position_mm[:2] == (-1.0, -1.0)


@pytest.mark.parametrize("board,client,wait_s,banners,ctrl_x", [
    (True, True, 2.0, 1, 0),     # an Uno: the boot banner is waited for, nothing is sent before it
    (True, True, 0.2, 2, 1),     # the wait is shorter than the boot: the Ctrl-X's banner follows, dropped
    (True, False, 2.0, 1, 0),    # a Ctrl-X sent at once is lost in the boot: the boot banner answers
    (False, True, 0.3, 1, 1),    # no reset on open: no banner, so a soft reset after the wait
    (False, None, 0.3, 1, 1),
], ids=["uno", "uno-reset-crosses-boot", "uno-client-resets", "no-auto-reset", "no-auto-reset-auto"])
def test_reset_on_open_banner_is_waited_for_and_a_second_one_dropped(board, client, wait_s, banners, ctrl_x):
    """As tests/hw/test_grbl_real.py checks on GRBL 1.1h behind the kit's --reset-on-open port."""
    with GrblEmulator(time_scale=1.0, banner_delay_s=0.6, homing_s=0.1, reset_on_open=board) as emu:
        with GrblStage(emu.port, reset_on_open=client, reset_wait_s=wait_s) as st:
            assert st.version == "Grbl 1.1h" and st.settings[130] == 1000
            assert any(line.startswith("$130=") for line in st.command("$$"))  # not a banner's leftovers
            assert st.home().state == "Idle"
        assert (emu.banners, emu.ctrl_x) == (banners, ctrl_x)


def test_recorder_takes_its_length_as_samples_or_seconds():
    io = rig.SimulatedIO(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), 96e3)
    assert rig.Recorder(io, np.ones(10), 96e3, record_s=0.01).n_samples == 960
    for args in ({}, {"n_samples": 960, "record_s": 0.01}):
        with pytest.raises(TypeError, match="n_samples or as record_s"):
            rig.Recorder(io, np.ones(10), 96e3, **args)
    with pytest.raises(ValueError, match="record_s"):
        rig.Recorder(io, np.ones(10), 96e3, record_s=-1.0)
