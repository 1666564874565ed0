"""The real GRBL 1.1h firmware (grbl-sim on a pseudo-terminal) for the rig tests.

The firmware is built from the kit in ``../shared/grbl-sim`` (or ``$CLSAS_GRBL_SIM``) with gcc
and make by the ``grbl_exe`` fixture (conftest.py); without them, or without the kit, the tests
that use it skip and say why. :class:`RealGrbl` runs ``grbl_pty.py`` and offers the faults the
kit can really produce: the reset button (SIGUSR1), the port disappearing (the bridge and the
simulator killed), and a restart on the same EEPROM and carriage position.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

KIT = Path(os.environ.get("CLSAS_GRBL_SIM", Path(__file__).resolve().parents[2] / "shared" / "grbl-sim"))
STEP_MM = 1 / 250  # $100/$101 steps per mm: one motor step
# fast but real settings: homing on with soft limits, travel 1000 mm as in the sample rig.toml;
# Z fast too ($112, $122: GRBL homes Z first) and a short debounce ($26), so that $H takes ~4 s
SETUP = ["$22=1", "$20=1", "$21=0", "$130=1000", "$131=1000", "$132=100", "$25=3000", "$24=2000", "$26=10",
         "$27=1", "$110=6000", "$111=6000", "$112=6000", "$120=1000", "$121=1000", "$122=1000"]


def build_grbl(root: Path) -> Path:
    """Build grbl_sim.exe under ``root``, or skip saying what is missing."""
    if sys.platform.startswith("win"):
        pytest.skip("grbl-sim runs on POSIX only")
    if not (KIT / "build.sh").is_file() or not list((KIT / "src").glob("*.tar.gz")):
        pytest.skip(f"the grbl-sim kit is not at {KIT} (set CLSAS_GRBL_SIM)")
    missing = [t for t in ("gcc", "make") if shutil.which(t) is None]
    if missing:
        pytest.skip(f"building the real GRBL firmware needs {' and '.join(missing)}")
    res = subprocess.run(["bash", str(KIT / "build.sh")], env=dict(os.environ, GRBL_REAL_DIR=str(root)),
                         capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        pytest.fail(f"grbl-sim build failed:\n{res.stdout}\n{res.stderr}")
    return root / "build" / "grbl" / "grbl-sim" / "grbl_sim.exe"


def read_until(port, done, timeout_s: float) -> bytes:
    got = b""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done(got):
        got += port.read(4096)
    return got


class RealGrbl:
    """grbl_pty.py running the firmware; ``port`` is the pty's link (``link`` or ``workdir/ttyGRBL``).

    The bridge runs in its own session, so :meth:`pull_cable` can kill it and the simulator
    together; :meth:`start` brings them back on the same link, EEPROM and carriage position.
    """

    def __init__(self, exe: Path, workdir: Path, start_mm: float = 5.0, reset_on_open: bool = False,
                 link: Path | None = None):
        self.exe, self.workdir, self.start_mm, self.reset_on_open = exe, Path(workdir), start_mm, reset_on_open
        self.port = str(link or self.workdir / "ttyGRBL")
        self.log = self.workdir / "transcript.log"
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> RealGrbl:
        import serial  # noqa: F401 - the tests that use this need pyserial anyway

        args = [sys.executable, str(KIT / "grbl_pty.py"), "--link", self.port, "--exe", str(self.exe),
                "--workdir", str(self.workdir), "--start-mm", str(self.start_mm), "--log", str(self.log)]
        if self.reset_on_open:
            args.append("--reset-on-open")
        if os.path.lexists(self.port):
            os.unlink(self.port)
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        deadline = time.monotonic() + 10
        while not os.path.exists(self.port):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                err = self.proc.stderr.read().decode() if self.proc.poll() is not None else "(still running)"
                self.stop()
                pytest.fail(f"grbl_pty.py did not start: {err}")
            time.sleep(0.05)
        return self

    def raw(self, *lines: str) -> str:
        """Send lines with plain pyserial (no clsas checks); each must be answered ``ok``."""
        import serial

        with serial.serial_for_url(self.port, 115200, timeout=0.1) as s:
            if not self.reset_on_open:
                s.write(b"\x18")
            out = read_until(s, lambda got: b"Grbl 1.1" in got, 10.0)
            out += read_until(s, lambda got: False, 0.5)  # the boot's own lines (a fresh EEPROM's error:7)
            for line in lines:
                for attempt in range(2):
                    s.write(line.encode() + b"\n")
                    got = read_until(s, lambda got: b"ok" in got or b"error" in got, 5.0)
                    if attempt == 0 and b"Grbl 1.1" in got and not got.strip().endswith(b"ok"):
                        # a boot that the kit started late (it noticed the last close only after
                        # this open, on a loaded host) swallowed the line: let it finish, send again
                        got += read_until(s, lambda got: False, 0.5)
                        continue
                    break
                assert got.strip().endswith(b"ok"), f"GRBL answered {got!r} to {line!r}"
                out += got
        # the kit notices a close only when it next polls the pty: let it, so that the next open
        # is seen as one (and, with reset_on_open, reboots GRBL)
        closes = self.transcript().count("client closed the port")
        deadline = time.monotonic() + 2.0
        while self.transcript().count("client closed the port") == closes and time.monotonic() < deadline:
            time.sleep(0.01)
        return out.decode(errors="replace")

    def press_reset(self) -> None:
        """The controller's reset button: the kit sends Ctrl-X to GRBL (ALARM:3 when moving)."""
        self.proc.send_signal(signal.SIGUSR1)

    def pull_cable(self) -> None:
        """The port disappears: the bridge (and with it the pty) and the simulator are killed."""
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(5)

    def transcript(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
