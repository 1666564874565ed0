"""The rig client against the real GRBL 1.1h firmware (grbl-sim on a pseudo-terminal).

The firmware is built from the kit in ``../shared/grbl-sim`` (or ``$CLSAS_GRBL_SIM``) with gcc
and make (tests/grbl_kit.py, the ``grbl_exe`` fixture); without them, or without the kit, these
tests skip and say why. The fault matrix on it is in tests/hw/test_rig_faults.py.
"""

from __future__ import annotations

import time

import h5py
import numpy as np
import pytest
from grbl_kit import SETUP, STEP_MM, RealGrbl

import clsas
from clsas import rig
from clsas.rig import GrblStage

serial = pytest.importorskip("serial", reason="the rig tests need pyserial (pip install 'clsas[rig]')")

pytestmark = pytest.mark.hw


@pytest.fixture
def grbl(grbl_exe, tmp_path):
    g = RealGrbl(grbl_exe, tmp_path)
    g.raw(*SETUP)
    yield g
    g.stop()


def test_homing_ends_in_negative_space_and_moves_land_within_a_step(grbl):
    with GrblStage(grbl.port, feed_mm_min=6000) as st:
        assert st.settings[22] == 1 and st.settings[130] == 1000
        t0 = time.monotonic()
        home = st.home()
        print(f"homing took {time.monotonic() - t0:.1f} s")
        assert home.position_mm[:2] == pytest.approx((-1.0, -1.0), abs=STEP_MM)  # the pull-off
        end = st.move_to(-40.0, -25.5)
        assert end.position_mm[:2] == pytest.approx((-40.0, -25.5), abs=STEP_MM)


def test_stored_work_offset_does_not_shift_moves(grbl):
    with GrblStage(grbl.port, feed_mm_min=6000) as st:
        st.home()
        st.command("G10 L2 P1 X5")  # as other CNC software leaves it in EEPROM
        end = st.move_to(-30.0, -10.0)
        assert end.position_mm[:2] == pytest.approx((-30.0, -10.0), abs=STEP_MM)


def test_wpos_reports_are_refused_naming_10(grbl):
    grbl.raw("$10=0")
    with pytest.raises(rig.StageError, match=r"\$10=0"):
        GrblStage(grbl.port).open()


def test_positive_work_area_is_refused_naming_the_soft_limits(grbl):
    with pytest.raises(rig.StageError, match=r"\$20=1, \$130=1000.*\[-1000, 0\]"):
        GrblStage(grbl.port, work_area_mm=((0, 1000), (0, 1000))).open()


def test_soft_limit_alarm_resets_and_the_late_ok_is_not_taken_for_the_next_answer(grbl):
    with GrblStage(grbl.port, feed_mm_min=6000) as st:
        st.home()
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:2 .*soft reset \(Ctrl-X\)") as exc:
            st.command("G53 G1 X-1200 F3000")
        assert exc.value.code == 2
        assert any(line.startswith("$130=") for line in st.command("$$"))  # a real answer, not a stale ok
        st.home()
        assert st.move_to(-20.0, -20.0).position_mm[:2] == pytest.approx((-20.0, -20.0), abs=STEP_MM)


def test_sample_config_scans_on_the_real_firmware_with_simulated_audio(uno, tmp_path, capsys):
    """The acceptance run: `clsas acquire --sample-config`, pointed at the firmware's pty (an Uno,
    as the sample's reset_on_open = true says), with --simulate audio."""
    from clsas.cli import main

    assert main(["acquire", "--sample-config"]) == 0
    text = capsys.readouterr().out.replace('port = "/dev/ttyUSB0"', f'port = "{uno.port}"')
    # a small, fast grid near the sample's origin (positions, not speed, are what is checked)
    small = (text.replace("nx = 18", "nx = 3").replace("ny = 12", "ny = 2").replace("width_m = 0.96", "width_m = 0.06")
             .replace("height_m = 0.96", "height_m = 0.04").replace("settle_s = 0.5", "settle_s = 0")
             .replace("repeats = 4", "repeats = 1").replace("feed_mm_min = 3000", "feed_mm_min = 6000"))
    assert small.count("\n") == text.count("\n") and small != text
    conf, out = tmp_path / "rig.toml", tmp_path / "scan.h5"
    conf.write_text(small)
    assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 0
    assert "6 of 6 stops (6 this run" in capsys.readouterr().out
    cfg = rig.load_rig_config(conf)
    with h5py.File(out, "r") as f:
        assert f.attrs["complete"]
        stops = f["stop_index"][()]
        stage_m = f["stage_positions"][()]
    np.testing.assert_array_equal(stops, np.arange(cfg.n_stops))  # every stop written once, in order
    targets = np.array([cfg.carriage_m(cfg.stage_target_mm(i)) for i in range(cfg.n_stops)])
    np.testing.assert_allclose(stage_m[:, :2], targets[:, :2], atol=STEP_MM / 1000)  # within a motor step
    assert "\\x18" not in uno.transcript().split("reset on open (DTR)")[-1]  # the boot banner was waited for


def test_rig_beams_are_stored_per_stop_on_the_real_firmware(uno, tmp_path, capsys):
    """A rig file with [beams] on the real firmware: every stop's boresights follow the
    axis rule from the position the firmware reports, stored with the stop."""
    from clsas.cli import main

    assert main(["acquire", "--sample-config"]) == 0
    text = capsys.readouterr().out.replace('port = "/dev/ttyUSB0"', f'port = "{uno.port}"')
    small = (text.replace("nx = 18", "nx = 2").replace("ny = 12", "ny = 2").replace("width_m = 0.96", "width_m = 0.04")
             .replace("height_m = 0.96", "height_m = 0.04").replace("settle_s = 0.5", "settle_s = 0")
             .replace("repeats = 4", "repeats = 1").replace("feed_mm_min = 3000", "feed_mm_min = 6000"))
    small += ('\n[beams]\nspeaker = { model = "cone", half_angle_deg = 30 }\nmicrophone = { model = "omni" }\n'
              'boresight = "axis"\naxis_point_m = [0.5, 0.5, 0]\naxis_dir = [0, 0, 1]\n')
    conf, out = tmp_path / "rig.toml", tmp_path / "scan.h5"
    conf.write_text(small)
    assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 0
    ds = clsas.load(out)
    assert ds.beams is not None and ds.beams.n_meas == ds.n_meas == 4
    want = clsas.physics.beam.axis_boresights(ds.tx_positions, (0.5, 0.5, 0.0), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(ds.beams.tx_boresight, want, atol=1e-12)


@pytest.fixture
def uno(grbl_exe, tmp_path):
    """The firmware behind a port that reboots it when opened, as an Arduino Uno's does."""
    g = RealGrbl(grbl_exe, tmp_path, reset_on_open=True)
    g.raw(*SETUP)
    yield g
    g.stop()


@pytest.mark.parametrize("reset_wait_s,banners", [(3.0, 1), (0.3, 2)], ids=["waits-for-boot", "reset-crosses-boot"])
def test_uno_reset_on_open_banner_is_waited_for_and_not_taken_for_an_answer(uno, reset_wait_s, banners):
    """``reset_on_open``: the boot banner is waited for; when the wait is shorter than the boot,
    the Ctrl-X sent meanwhile makes GRBL print a second banner, which must be dropped (not taken
    for an answer to ``$$`` or for an unexpected reset)."""
    start = len(uno.transcript())
    with GrblStage(uno.port, feed_mm_min=6000, reset_on_open=True, reset_wait_s=reset_wait_s) as st:
        assert st.version == "Grbl 1.1h" and st.settings[130] == 1000  # $$ answered by its own lines
        assert any(line.startswith("$130=") for line in st.command("$$"))
        st.home()
        assert st.move_to(-30.0, -20.0).position_mm[:2] == pytest.approx((-30.0, -20.0), abs=STEP_MM)
    log = uno.transcript()[start:]
    assert "reset on open (DTR): restarting the simulator" in log  # the kit rebooted GRBL as the port opened
    assert log.count("Grbl 1.1h") == banners
    assert ("\\x18" in log) == (banners == 2)  # Ctrl-X only when the boot outlasted the wait


def test_hard_limit_alarm_then_jogging_off_retrips_unless_hard_limits_are_off(grbl):
    """``$21=1``: driving onto a home switch raises ALARM:1 (clsas resets); a jog off the switch
    after ``$X`` trips it again (GRBL reacts to any change of the pin), ``move_off_limit`` turns
    hard limits off for the jog, and ``$H`` homes from the pressed switch."""
    grbl.raw("$20=0", "$21=1")
    with GrblStage(grbl.port, feed_mm_min=6000, reset_on_open=False) as st:
        st.home()
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 \(hard limit.*'\$21=0'"):
            st.command("G53 G1 X5 F3000")
            st.wait_idle(10.0)
        st.command("$X")
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 "):
            st.command("G91 G1 X-5 F1000")
            st.wait_idle(10.0)
        off = st.move_off_limit(-5.0, 0.0)
        assert off.state == "Idle" and st.read_settings()[21] == 1  # hard limits on again
        assert st.home().position_mm[:2] == pytest.approx((-1.0, -1.0), abs=STEP_MM)
        st.command("G53 G1 X5 F3000")  # onto the switch again, and home from there
        with pytest.raises(rig.GrblAlarm, match=r"ALARM:1 "):
            st.wait_idle(10.0)
        assert st.home().position_mm[:2] == pytest.approx((-1.0, -1.0), abs=STEP_MM)


# GRBL 1.1h's factory settings ($110 = $111 = 500 mm/min, $120 = $121 = 10 mm/s^2, $25 = 500 mm/min,
# homing and limits off, 200 mm travel) with the edits the README's "GRBL settings" table asks for
README_EDITS = ["$22=1", "$20=1", "$21=1", "$130=1000", "$131=1000"]  # $20 after $22 (else error:10)


@pytest.mark.slow
def test_sample_config_scans_a_stock_board_after_the_readme_edits(grbl_exe, tmp_path, capsys):
    """The sample's feed_mm_min = 3000 on a stock board, which moves at $110 = 500 mm/min.
    The moves below take about 108 s and 96 s; a timeout from the feed alone (95 s) stopped the
    scan at its first stop, and every resume the same way. About 4 minutes."""
    from clsas.cli import main

    g = RealGrbl(grbl_exe, tmp_path, reset_on_open=True)
    try:
        settings = g.raw("$$")
        assert "$110=500.000" in settings and "$120=10.000" in settings and "$22=0" in settings  # factory
        g.raw(*README_EDITS)
        assert main(["acquire", "--sample-config"]) == 0
        text = capsys.readouterr().out.replace('port = "/dev/ttyUSB0"', f'port = "{g.port}"')
        # two stops 960 mm apart, the sample's own x extremes (20 mm inside the travel, off the switches);
        # feed_mm_min, the work area and the origin are the sample's
        small = (text.replace("nx = 18", "nx = 2").replace("ny = 12", "ny = 1")
                 .replace("settle_s = 0.5", "settle_s = 0").replace("repeats = 4", "repeats = 1"))
        assert "feed_mm_min = 3000" in small and small != text
        conf, out = tmp_path / "rig.toml", tmp_path / "scan.h5"
        conf.write_text(small)
        assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 0
        assert "2 of 2 stops (2 this run" in capsys.readouterr().out
        cfg = rig.load_rig_config(conf)
        with h5py.File(out, "r") as f:
            stage_m = f["stage_positions"][()]
        targets = np.array([cfg.carriage_m(cfg.stage_target_mm(i)) for i in range(cfg.n_stops)])
        np.testing.assert_allclose(stage_m[:, :2], targets[:, :2], atol=STEP_MM / 1000)
    finally:
        g.stop()
