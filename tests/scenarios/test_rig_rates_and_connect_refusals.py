"""The rig: moves planned from the rate GRBL really uses, the emulator capping the feed as
the firmware does, connect-time refusals that say what to fix (and leave nothing to delete by hand)."""

import time

import numpy as np
import pytest
from stepped_clock import SteppedClock

from clsas import rig
from clsas.rig import GrblEmulator, GrblStage

pytest.importorskip("serial", reason="the rig tests need pyserial (pip install 'clsas[rig]')")

pytestmark = pytest.mark.hw

STOCK = {110: 500.0, 111: 500.0, 120: 10.0, 121: 10.0}  # GRBL 1.1h's factory rates and accelerations


def _status_line(st: GrblStage) -> str:
    st._write(b"?")
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        line = st._readline()
        if line and line.startswith("<"):
            return line
    raise AssertionError("no status report")


def test_move_time_is_planned_from_the_rate_grbl_uses():
    """A stock board ($110 = $111 = 500 mm/min) moves a F3000 move at 500 mm/min along an axis and
    at 500 sqrt(2) on the diagonal; the timeout must cover that, not the feed's 4 s."""
    st = GrblStage("unused", feed_mm_min=3000)
    st.settings = dict(STOCK)
    v = 500 / 60  # mm/s
    assert st.move_time((0, 0), (-200, 0)) == pytest.approx(200 / v + v / 10)  # cruise + ramps at $120
    vd, ad = v * np.sqrt(2), 10 * np.sqrt(2)
    assert st.move_time((0, 0), (-200, -200)) == pytest.approx(200 * np.sqrt(2) / vd + vd / ad)
    assert st.move_time((0, 0), (-0.5, 0)) == pytest.approx(2 * np.sqrt(0.5 / 10))  # too short to reach the rate
    # the cases: a 200 mm move (about 24 s) and the sample's first move on a 1 m stage (about 120 s)
    for start, target in [((0, 0), (-200, 0)), ((-1, -1), (-1000, -1000)), ((-1000, -1000), (0, -1000))]:
        assert st.move_timeout(start, target) > st.move_time(start, target) + 10
    assert st.move_time((-1, -1), (-1000, -1000)) > 119
    slow = GrblStage("unused", feed_mm_min=300)
    slow.settings = dict(STOCK)
    assert slow.move_time((0, 0), (-200, 0)) == pytest.approx(40 + 5 / 10)  # a feed under $110 is kept
    fixed = GrblStage("unused", move_timeout_s=7)
    assert fixed.move_timeout((0, 0), (-1000, 0)) == 7


def test_feed_above_the_axis_rate_is_logged_on_connect(caplog):
    with GrblEmulator(time_scale=0.01, max_rate_mm_min=500) as emu, GrblStage(emu.port, feed_mm_min=3000) as st:
        assert st.settings[110] == 500
    assert "feed_mm_min = 3000 mm/min is above GRBL's maximum rate $110=500 and $111=500" in caplog.text


def test_emulator_caps_the_feed_at_the_axis_rate_as_grbl_does():
    clock = SteppedClock()  # each status line below is asked for while its move runs: the clock stands still
    with GrblEmulator(time_scale=0.05, max_rate_mm_min=500, clock=clock) as emu, \
            GrblStage(emu.port, clock=clock) as st:
        st.home()
        st.command("G53 G1 X-201 Y-1 F3000")
        line = _status_line(st)
        assert "Run" in line and "FS:500," in line  # not FS:3000
        st.wait_idle(10.0)
        st.command("$110=800")
        st.command("G53 G1 X-1 Y-1 F3000")
        assert "FS:800," in _status_line(st)
        st.wait_idle(10.0)
        st.command("G53 G1 X-201 Y-201 F3000")  # the diagonal: each axis at 800 mm/min at most
        assert f"FS:{500 * np.sqrt(2):.0f}," in _status_line(st)
        assert emu.state == "Run"


def test_home_refused_without_homing_names_the_scan_table():
    with GrblEmulator(time_scale=0.01, homing=False) as emu, GrblStage(emu.port) as st:
        with pytest.raises(rig.StageRefused, match=r"set home = false in the \[scan\] table"):
            st.home()
    rig.parse_rig_config("[scan]\nhome = false\n")  # the key the hint names is accepted there


def _rig_text(port: str, area: str) -> str:
    return f"""
[stage]
port = "{port}"
timeout_s = 1.0
feed_mm_min = 6000
work_area_mm = {area}

[scan]
origin_mm = [-50, -50]
settle_s = 0

[aperture]
nx = 2
ny = 2
width_m = 0.04
height_m = 0.04

[recorder]
record_s = 0.016
repeats = 1
repeat_gap_s = 0

[chirp]
duration_s = 0.002

[simulate]
points = [{{ position_m = [0.0, 0.0, 0.9], amplitude = 1.0 }}]
time_scale = 0.002
"""


def test_connect_time_refusal_says_what_to_fix_and_leaves_nothing_to_delete(tmp_path, capsys):
    """A work area outside GRBL's soft limits: exit 2, the refusal and its fix, no claim of a lost
    port or a feed hold, no resume hint; after the fix, the same command (or the printed one with
    --resume) starts the scan."""
    from clsas.cli import main

    conf, out = tmp_path / "rig.toml", tmp_path / "scan.h5"
    with GrblEmulator(time_scale=0.01, travel_mm=(100, 100, 10), reset_on_open=False) as emu:
        conf.write_text(_rig_text(emu.port, "[[-1000, 0], [-1000, 0]]"))
        assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 2
        err = capsys.readouterr().err
        assert "outside GRBL's soft limits ($20=1, $130=100)" in err and "Nothing was moved" in err
        assert "lost" not in err and "feed hold" not in err and "--resume" not in err
        assert not out.exists()
        conf.write_text(_rig_text(emu.port, "[[-100, 0], [-100, 0]]"))
        assert main(["acquire", str(conf), str(out), "--simulate", "audio", "-q"]) == 0
        assert "4 of 4 stops" in capsys.readouterr().out


def test_a_scan_that_stopped_before_its_first_stop_starts_again(tmp_path):
    """A file that holds no stop (left by an earlier run) is started again, with --resume or
    without, even when the rig file changed meanwhile."""
    out = tmp_path / "scan.h5"
    first = rig.parse_rig_config(_rig_text("unused", "[[-1000, 0], [-1000, 0]]"))
    store = rig.scan.store_for(first, out, False, (20.0, 50.0))
    store.close()
    assert rig.scan.holds_no_stop(out)
    fixed = rig.parse_rig_config(_rig_text("unused", "[[-100, 0], [-100, 0]]"))
    assert rig.acquire(fixed, out, resume=True, simulate=True).complete
    assert not rig.scan.holds_no_stop(out)
    with pytest.raises(FileExistsError):  # a file with stops is never replaced
        rig.acquire(fixed, out, simulate=True)
