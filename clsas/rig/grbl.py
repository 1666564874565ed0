"""An x-y stage driven by a GRBL 1.1 controller over pyserial.

The line protocol keeps one command in flight: a line is sent, and the next is not sent until
GRBL has answered ``ok`` or ``error:N``. GRBL also pushes ``ALARM:N`` and ``[MSG:...]`` lines at
any time, and answers the real-time ``?`` with a status report ``<State|MPos:x,y,z|...>``. A
motion command is acknowledged when it is *planned*, not when it is done, so a move is confirmed
by polling ``?`` (at most 5 Hz) until the state is ``Idle`` at the target.

Any pyserial URL is accepted as the port (``/dev/ttyUSB0``, ``COM3``, ``socket://host:port``,
the path of a pseudo-terminal such as the one :class:`clsas.rig.emulator.GrblEmulator` opens).
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass

import numpy as np

from .. import _validate as v
from .._validate import install_hint

__all__ = ["GrblStage", "StageError", "GrblError", "GrblAlarm", "StageTimeout", "StageDisconnected",
           "Status", "ERRORS", "ALARMS"]

log = logging.getLogger(__name__)

# GRBL 1.1 error and alarm codes (grbl/doc/csv/error_codes_en_US.csv, alarm_codes_en_US.csv)
ERRORS = {
    1: "G-code words consist of a letter and a value; letter was not found",
    2: "numeric value format is not valid or missing an expected value",
    3: "Grbl '$' system command was not recognized or supported",
    4: "negative value received for an expected positive value",
    5: "homing cycle is not enabled via settings ($22)",
    8: "Grbl '$' command cannot be used unless Grbl is IDLE",
    9: "G-code locked out during alarm or jog state",
    10: "soft limits cannot be enabled without homing also enabled",
    11: "max characters per line exceeded",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid g-code command found in block",
    22: "feed rate has not yet been set or is undefined",
    33: "motion command target is invalid",
}
ALARMS = {
    1: "hard limit triggered; machine position is likely lost, re-homing is recommended",
    2: "soft limit: the target exceeds machine travel; position kept",
    3: "reset while in motion; position is likely lost, re-homing is recommended",
    4: "probe fail",
    5: "probe fail",
    6: "homing fail: reset during the homing cycle",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: pull-off did not clear the limit switch",
    9: "homing fail: limit switch not found within the search distance",
    10: "homing fail: second switch not found (dual axis)",
}

_STATUS = re.compile(r"<([A-Za-z]+)(?::\d)?\|(MPos|WPos):([-\d.]+),([-\d.]+),([-\d.]+)")
_SETTING = re.compile(r"^\$(\d+)=([-\d.]+)")
#: alarms after which GRBL answers nothing but Ctrl-X ("[MSG:Reset to continue]")
_RESET_ALARMS = (1, 2)
#: alarms raised by a reset (ALARM:3, the reset button or Ctrl-X mid-move) or a failed homing
#: cycle, after which GRBL prints its banner without being asked
_SELF_RESET_ALARMS = (3, 6, 7, 8, 9, 10)


class StageError(RuntimeError):
    """The stage could not do what was asked; the message says what happened."""


class GrblError(StageError):
    def __init__(self, code: int, line: str):
        self.code = code
        super().__init__(f"GRBL answered error:{code} ({ERRORS.get(code, 'unknown error')}) to {line!r}")


class GrblAlarm(StageError):
    def __init__(self, code: int, advice: str = ""):
        self.code = code
        text = f"GRBL raised ALARM:{code} ({ALARMS.get(code, 'unknown alarm')})"
        super().__init__(f"{text}; {advice}" if advice else text)


class StageTimeout(StageError):
    pass


class StageDisconnected(StageError):
    pass


@dataclass(frozen=True)
class Status:
    """One ``?`` report: the machine state and its machine position in mm."""

    state: str
    position_mm: tuple[float, float, float]


class GrblStage:
    """A GRBL 1.1 x-y stage.

    Parameters
    ----------
    port : str
        A pyserial port name or URL.
    baudrate : int
        115200 for GRBL 1.1.
    work_area_mm : ((x_min, x_max), (y_min, y_max))
        Machine coordinates a move may reach; a target outside is refused before it is sent.
        After ``$H`` GRBL's machine space is ``[-travel, 0]`` on each axis (``$130``, ``$131``);
        with soft limits on (``$20=1``) an area outside it is refused on connect.
    feed_mm_min : float
        Feed rate of ``G1`` moves; ``None`` moves with ``G0`` (the machine's rapid rate).
    timeout_s : float
        How long to wait for the answer to one line.
    home_timeout_s : float, optional
        How long ``$H`` may take; by default twice the search (1.5 x the longest ``$13x``
        travel) at the ``$25`` seek rate plus 30 s, or 300 s where GRBL does not report them.
    move_timeout_s : float, optional
        How long one move may take to reach ``Idle``; by default three times the work area's
        diagonal at the feed rate (``$110``/``$111`` for ``G0``) plus 10 s.
    poll_hz : float
        Rate of ``?`` status polling while a move runs (GRBL recommends at most 5 Hz).
    reset_wait_s : float
        How long to wait for GRBL's start-up banner: an Arduino Uno resets when its port is
        opened and boots for about 1.5 s (and bytes sent meanwhile are lost).
    reset_on_open : bool, optional
        Whether opening the port reboots the controller. True (an Uno, a Nano): wait for the
        boot banner without sending anything, then soft-reset (Ctrl-X) only if none came.
        False (boards without auto-reset, 32-bit boards): soft-reset at once. None: wait for a
        banner, then soft-reset. In every case the lines of a second banner that follows (a
        reset crossing the boot) are read and dropped, not taken for an answer.
    position_tol_mm : float
        How close the reported position must come to the target.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        work_area_mm: tuple[tuple[float, float], tuple[float, float]] = ((-1000.0, 0.0), (-1000.0, 0.0)),
        feed_mm_min: float | None = 3000.0,
        timeout_s: float = 5.0,
        home_timeout_s: float | None = None,
        move_timeout_s: float | None = None,
        poll_hz: float = 5.0,
        reset_wait_s: float = 2.5,
        reset_on_open: bool | None = None,
        position_tol_mm: float = 0.02,
    ) -> None:
        if not isinstance(port, str) or not port:
            raise ValueError(f"port must be a serial port name or pyserial URL, got {port!r}")
        self.port = port
        self.baudrate = v.positive_int("baudrate", baudrate)
        area = v.array("work_area_mm", work_area_mm, shape=(2, 2))
        if not (area[:, 0] < area[:, 1]).all():
            raise ValueError("work_area_mm must be ((x_min, x_max), (y_min, y_max)) with min < max, "
                             f"got {area.tolist()}")
        self.work_area_mm = area
        self.feed_mm_min = None if feed_mm_min is None else v.positive("feed_mm_min", feed_mm_min)
        self.timeout_s = v.positive("timeout_s", timeout_s)
        self.home_timeout_s = None if home_timeout_s is None else v.positive("home_timeout_s", home_timeout_s)
        self.move_timeout_s = None if move_timeout_s is None else v.positive("move_timeout_s", move_timeout_s)
        poll_hz = v.positive("poll_hz", poll_hz)
        if poll_hz > 5.0:
            raise ValueError(f"poll_hz must be at most 5 (GRBL's advice for '?' polling), got {poll_hz}")
        self.poll_s = 1.0 / poll_hz
        self.reset_wait_s = v.non_negative("reset_wait_s", reset_wait_s)
        if reset_on_open not in (None, True, False):
            raise TypeError(f"reset_on_open must be True, False or None, got {reset_on_open!r}")
        self.reset_on_open = reset_on_open
        self.position_tol_mm = v.positive("position_tol_mm", position_tol_mm)
        self.version = ""
        self.settings: dict[int, float] = {}
        self._ser = None
        self._buf = b""

    # -- connection ---------------------------------------------------------------------

    def open(self) -> GrblStage:
        """Open the port, wait for GRBL's banner (soft-resetting once if none comes)."""
        try:
            import serial
        except ImportError as exc:
            raise ImportError(f"the stage needs pyserial: {install_hint('rig')}") from exc
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.05,
                                              write_timeout=self.timeout_s)
        except (serial.SerialException, ValueError) as exc:
            raise StageDisconnected(f"cannot open the stage port {self.port!r}: {exc}") from exc
        banner = None if self.reset_on_open is False else self._wait_banner(self.reset_wait_s)
        if banner is None:
            if self.reset_on_open:
                log.warning("no boot banner from %s within %.1f s of opening it although stage.reset_on_open is "
                            "true; sending a soft reset", self.port, self.reset_wait_s)
            self._write(b"\x18")
            banner = self._wait_banner(self.reset_wait_s)
        if banner is None:
            self.close()
            raise StageTimeout(f"no GRBL start-up banner on {self.port!r} at {self.baudrate} baud within "
                               f"{self.reset_wait_s:g} s: is a GRBL 1.1 controller connected there (and booted)?")
        self.version = banner
        log.info("connected to %s on %s", banner, self.port)
        try:
            self.settings = self.read_settings()
            self._check_settings()
        except StageError:
            self.close()
            raise
        return self

    def read_settings(self) -> dict[int, float]:
        """GRBL's ``$$`` settings as ``{number: value}``."""
        out: dict[int, float] = {}
        for line in self.command("$$"):
            m = _SETTING.match(line)
            if m:
                out[int(m.group(1))] = float(m.group(2))
        return out

    def _check_settings(self) -> None:
        """Refuse settings the scan cannot work with, naming the setting."""
        st = self.settings
        if 10 in st and not int(st[10]) & 1:
            raise StageError(f"GRBL's $10={st[10]:g} makes status reports carry the work position (WPos), "
                             "but clsas checks and records the machine position: send '$10=1' once "
                             "(it is kept in EEPROM)")
        if st.get(20, 0) and 130 in st and 131 in st:
            for axis, (lo, hi) in zip("xy", self.work_area_mm, strict=True):
                travel = st[130 + "xy".index(axis)]
                if lo < -travel - 1e-6 or hi > 1e-6:
                    raise StageError(
                        f"work_area_mm {axis} = [{lo:g}, {hi:g}] mm is outside GRBL's soft limits ($20=1, "
                        f"${130 + 'xy'.index(axis)}={travel:g}): after homing ($H) GRBL's machine "
                        f"coordinates run from -{travel:g} to 0 mm, so set work_area_mm within "
                        f"[-{travel:g}, 0] and origin_mm inside it")

    def home_timeout(self) -> float:
        """Seconds ``$H`` may take (``home_timeout_s``, or from ``$25`` and ``$130``-``$132``)."""
        if self.home_timeout_s is not None:
            return self.home_timeout_s
        st = self.settings
        travel = max((st[k] for k in (130, 131, 132) if k in st), default=0.0)
        if st.get(25, 0) > 0 and travel > 0:
            return 2.0 * 1.5 * travel / st[25] * 60.0 + 30.0
        return 300.0

    def move_timeout(self, distance_mm: float) -> float:
        """Seconds a move of ``distance_mm`` may take (``move_timeout_s``, or from the feed rate)."""
        if self.move_timeout_s is not None:
            return self.move_timeout_s
        rate = self.feed_mm_min or min((self.settings.get(k, 0.0) for k in (110, 111)), default=0.0)
        if not rate:
            return 120.0
        return 3.0 * distance_mm / rate * 60.0 + 10.0

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception as exc:  # noqa: BLE001 - closing a dead port must not mask the real error
                log.debug("closing %s: %s", self.port, exc)
            self._ser = None

    def __enter__(self) -> GrblStage:
        return self.open() if self._ser is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    def _wait_banner(self, wait_s: float, quiet_s: float = 0.25) -> str | None:
        """The first banner within ``wait_s``; then lines are read until ``quiet_s`` passes without
        one: the banner's ``[MSG:...]`` lines, and a second banner (a Ctrl-X that crossed the
        boot, a reset button pressed just before), which is dropped rather than taken later
        for an unexpected reset or an answer."""
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            line = self._readline()
            if line is None or not line.startswith("Grbl "):
                continue  # boot-loader noise, a stale 'ok' or status report from before
            quiet = time.monotonic() + quiet_s
            while time.monotonic() < quiet:
                more = self._readline()
                if more is None:
                    continue
                if more.startswith("Grbl "):
                    log.info("a second GRBL banner on %s (dropped): %s", self.port, more)
                    quiet = time.monotonic() + quiet_s
                elif more.startswith(("[", "ALARM:")):
                    self._push(more)
                else:
                    log.debug("dropped after the banner: %r", more)
            return line.split("[")[0].strip()
        return None

    # -- low level ------------------------------------------------------------------------

    @staticmethod
    def _port_errors() -> tuple[type[BaseException], ...]:
        """What a lost port raises: pyserial's errors, OSError, and on POSIX termios.error
        (``flush()`` calls tcdrain, whose EIO is neither of the others)."""
        import serial

        errors: tuple[type[BaseException], ...] = (serial.SerialException, OSError)
        try:
            import termios
        except ImportError:  # Windows
            return errors
        return (*errors, termios.error)

    def _write(self, data: bytes) -> None:

        if self._ser is None:
            raise StageDisconnected("the stage port is not open")
        try:
            self._ser.write(data)
            self._ser.flush()
        except self._port_errors() as exc:
            raise StageDisconnected(f"stage port {self.port!r} lost while writing: {exc}") from exc

    def _readline(self) -> str | None:
        """One line without its end, or None if none arrived within the port timeout."""
        if self._ser is None:
            raise StageDisconnected("the stage port is not open")
        while b"\n" not in self._buf:
            try:
                chunk = self._ser.read(self._ser.in_waiting or 1)
            except self._port_errors() as exc:
                raise StageDisconnected(f"stage port {self.port!r} lost while reading: {exc}") from exc
            if not chunk:
                return None
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\n", 1)
        line = raw.decode("ascii", "replace").strip().strip("\ufffd\x00")
        return line or None

    def _push(self, line: str) -> str | None:
        """Handle a line GRBL may send at any time; return it if it is something else."""
        if line.startswith("ALARM:"):
            code = _code(line)
            if code in _RESET_ALARMS:
                raise GrblAlarm(code, self._reset_after_alarm(code))
            if code in _SELF_RESET_ALARMS:  # GRBL resets itself: its banner follows
                banner = self._read_until(lambda line: line.startswith("Grbl "), max(self.reset_wait_s, 2.0))
                raise GrblAlarm(code, "GRBL reset itself" + ("" if banner else " (no banner came)")
                                + ": its position is lost; home again ($H) before moving")
            raise GrblAlarm(code)
        if line.startswith("[MSG:") or line.startswith("[GC:") or line.startswith("[echo:"):
            log.info("GRBL: %s", line)
            return None
        if line.startswith("Grbl "):
            raise StageError(f"the controller on {self.port!r} reset unexpectedly ({line}); "
                             "its position is lost and it must be homed again")
        return line

    def _reset_after_alarm(self, code: int) -> str:
        """After ALARM:1/2 GRBL answers only Ctrl-X: soft-reset, wait for the banner and discard
        the late ``ok`` of the refused line. Returns what the user should do next."""
        log.info("ALARM:%d: sending a soft reset (Ctrl-X), as GRBL asks", code)
        try:
            # GRBL discards a reset that comes before its "[MSG:Reset to continue]": wait for it
            self._read_until(lambda line: "Reset to continue" in line, 2.0)
            for _ in range(2):
                self._write(b"\x18")
                if self._read_until(lambda line: line.startswith("Grbl "), max(self.reset_wait_s, 2.0)):
                    break
            # the [MSG:...] lines after the banner and a late 'ok' of the refused line
            self._read_until(lambda line: False, 0.3)
        except StageError as exc:
            return f"the soft reset (Ctrl-X) failed ({exc}): reset the controller by hand"
        if code == 1:
            return ("clsas sent a soft reset (Ctrl-X); the position is lost: move the carriage off the "
                    "limit switch with hard limits off ('$21=0', then '$X' and a jog, then '$21=1'), "
                    "and home again ($H) before scanning")
        return ("clsas sent a soft reset (Ctrl-X); the position is kept but GRBL is locked: check "
                "stage.work_area_mm against the soft limits, then home ($H) or unlock ($X)")

    def _read_until(self, done, wait_s: float) -> bool:
        """Read and discard lines until ``done(line)`` (True) or ``wait_s`` passes (False)."""
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            line = self._readline()
            if line is not None:
                log.debug("< %s (while recovering from an alarm)", line)
                if done(line):
                    return True
        return False

    def command(self, line: str, timeout_s: float | None = None) -> list[str]:
        """Send one line and wait for ``ok``; return the lines GRBL sent before it.

        Raises :class:`GrblError` on ``error:N``, :class:`GrblAlarm` on ``ALARM:N``,
        :class:`StageTimeout` when no answer comes within ``timeout_s``.
        """
        line = line.strip()
        if "\n" in line or not line:
            raise ValueError(f"line must be one non-empty line, got {line!r}")
        wait = self.timeout_s if timeout_s is None else timeout_s
        log.debug("> %s", line)
        self._write(line.encode("ascii") + b"\n")
        got: list[str] = []
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            reply = self._readline()
            if reply is None:
                continue
            log.debug("< %s", reply)
            reply = self._push(reply)
            if reply is None or reply.startswith("<"):
                continue
            if reply == "ok":
                return got
            if reply.startswith("error:"):
                raise GrblError(_code(reply), line)
            got.append(reply)
        raise StageTimeout(f"GRBL did not answer {line!r} within {wait:g} s (a lost 'ok' or a stalled controller)")

    def status(self) -> Status:
        """Ask for a status report (real-time ``?``)."""
        self._write(b"?")
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            reply = self._readline()
            if reply is None:
                continue
            reply = self._push(reply)
            if reply is None:
                continue
            m = _STATUS.match(reply)
            if m:
                if m.group(2) == "WPos":
                    raise StageError("GRBL reports the work position (WPos, $10=0); clsas needs the machine "
                                     "position: send '$10=1' once")
                return Status(m.group(1), (float(m.group(3)), float(m.group(4)), float(m.group(5))))
            log.debug("ignored while waiting for a status report: %r", reply)
        raise StageTimeout(f"no status report from GRBL within {self.timeout_s:g} s")

    # -- operations --------------------------------------------------------------------------

    def home(self) -> Status:
        """Run the homing cycle (``$H``) and set millimetres, absolute (``G21 G90``)."""
        if self.settings.get(22, 1) == 0:
            raise StageError("stage.home = true but homing is disabled in GRBL ($22=0): enable it with "
                             "'$22=1' (with limit switches fitted), or set stage.home = false")
        t0 = time.monotonic()
        self.command("$H", timeout_s=self.home_timeout())
        log.info("homed in %.1f s", time.monotonic() - t0)
        self.command("G21 G90")
        return self.wait_idle(self.home_timeout())

    def unlock(self) -> Status:
        """Clear an alarm lock without homing (``$X``) and set ``G21 G90``."""
        if self.settings.get(20, 0):
            raise StageError("stage.home = false but GRBL's soft limits are on ($20=1): they check targets "
                             "against the position homing sets, so set stage.home = true or turn them off "
                             "with '$20=0'")
        self.command("$X")
        self.command("G21 G90")
        return self.status()

    def move_off_limit(self, dx_mm: float, dy_mm: float) -> Status:
        """Move the carriage off a limit switch after ``ALARM:1`` (and the reset).

        With hard limits on (``$21=1``) the switch re-trips the alarm as soon as the carriage
        moves, so ``$21=0`` is sent first and ``$21=1`` restored after the relative move
        (``G91``) by (``dx_mm``, ``dy_mm``). The position is not trusted afterwards: home again.
        """
        dx_mm, dy_mm = v.finite("dx_mm", dx_mm), v.finite("dy_mm", dy_mm)
        hard = int(self.settings.get(21, 0)) == 1
        if hard:
            self.command("$21=0")
        try:
            self.command("$X")
            feed = self.feed_mm_min or 500.0
            self.command(f"G91 G1 X{dx_mm:.3f} Y{dy_mm:.3f} F{feed:.0f}")
            st = self.wait_idle(self.move_timeout(float(np.hypot(dx_mm, dy_mm))))
            self.command("G90")
        finally:
            if hard:
                self.command("$21=1")
        return st

    def check_target(self, x_mm: float, y_mm: float) -> None:
        """Refuse a target outside the work area (before anything is sent)."""
        for name, val, (lo, hi) in (("x_mm", x_mm, self.work_area_mm[0]), ("y_mm", y_mm, self.work_area_mm[1])):
            val = v.finite(name, val)
            if not lo <= val <= hi:
                raise ValueError(f"{name} = {val:.3f} is outside the stage's work area [{lo:g}, {hi:g}] mm")

    def move_to(self, x_mm: float, y_mm: float) -> Status:
        """Move to machine position (x, y) in mm and wait until GRBL reports ``Idle`` there.

        The move is sent in machine coordinates (``G53``), so a work offset stored in the
        controller (``G54``-``G59``, ``G92``) cannot shift it.
        """
        self.check_target(x_mm, y_mm)
        word = "G0" if self.feed_mm_min is None else "G1"
        feed = "" if self.feed_mm_min is None else f" F{self.feed_mm_min:.0f}"
        dist = float(np.hypot(*np.ptp(self.work_area_mm, axis=1)))  # the longest move the area allows
        self.command(f"G53 {word} X{x_mm:.3f} Y{y_mm:.3f}{feed}")
        st = self.wait_idle(self.move_timeout(dist))
        err = max(abs(st.position_mm[0] - x_mm), abs(st.position_mm[1] - y_mm))
        if err > self.position_tol_mm:
            raise StageError(f"the stage reports Idle at ({st.position_mm[0]:.3f}, {st.position_mm[1]:.3f}) mm, "
                             f"{err:.3f} mm from the target ({x_mm:.3f}, {y_mm:.3f})")
        return st

    def wait_idle(self, timeout_s: float) -> Status:
        """Poll ``?`` at ``poll_hz`` until the state is ``Idle``."""
        deadline = time.monotonic() + timeout_s
        while True:
            t = time.monotonic()
            st = self.status()
            if st.state == "Idle":
                return st
            if st.state == "Alarm":
                raise StageError("GRBL is in the Alarm state (an earlier alarm was not cleared)")
            if t > deadline:
                raise StageTimeout(f"the stage did not reach Idle within {timeout_s:g} s (state {st.state})")
            time.sleep(max(0.0, self.poll_s - (time.monotonic() - t)))

    def feed_hold(self) -> bool:
        """Real-time feed hold (``!``): decelerate and stop. Returns False if the port was lost."""
        try:
            self._write(b"!")
        except StageError as exc:
            log.warning("could not send a feed hold: %s", exc)
            return False
        log.info("feed hold sent to %s", self.port)
        return True


    def cycle_start(self) -> None:
        """Real-time cycle start (``~``): resume the motion a feed hold stopped."""
        self._write(b"~")


def _code(line: str) -> int:
    try:
        return int(line.split(":", 1)[1])
    except (IndexError, ValueError):
        return -1
