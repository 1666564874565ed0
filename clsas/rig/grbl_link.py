"""The GRBL 1.1 line protocol over pyserial: connecting, commands, status reports, alarms.

The line protocol keeps one command in flight: a line is sent, and the next is not sent until
GRBL has answered ``ok`` or ``error:N``. GRBL also pushes ``ALARM:N`` and ``[MSG:...]`` lines at
any time, and answers the real-time ``?`` with a status report ``<State|MPos:x,y,z|...>``. A
motion command is acknowledged when it is *planned*, not when it is done, so a move is confirmed
by polling ``?`` (at most 5 Hz) until the state is ``Idle`` at the target.

Any pyserial URL is accepted as the port (``/dev/ttyUSB0``, ``COM3``, ``socket://host:port``,
the path of a pseudo-terminal such as the one :class:`clsas.rig.emulator.GrblEmulator` opens).
The stage operations (homing, moves, limits) are :class:`clsas.rig.grbl.GrblStage`'s.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass

from .. import validate as v
from ..validate import install_hint

__all__ = ["GrblLink", "StageError", "StageRefused", "GrblError", "GrblAlarm", "StageTimeout", "StageDisconnected",
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
#: how long a soft reset's banner may take (a Ctrl-X sent while the board boots waits for the boot)
_RESET_ANSWER_S = 2.0


class StageError(RuntimeError):
    """The stage could not do what was asked; the message says what happened."""


class StageRefused(StageError):
    """GRBL's settings do not fit the rig configuration (found on connecting, or before homing);
    nothing was moved. The message names the setting or key and how to fix it."""


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


class GrblLink:
    """A connection to a GRBL 1.1 controller: one line in flight, pushed lines handled.

    Parameters
    ----------
    port, baudrate, timeout_s, reset_wait_s, reset_on_open :
        As :class:`clsas.rig.GrblStage`'s.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, timeout_s: float = 5.0, reset_wait_s: float = 2.5,
                 reset_on_open: bool | None = None) -> None:
        if not isinstance(port, str) or not port:
            raise ValueError(f"port must be a serial port name or pyserial URL, got {port!r}")
        self.port = port
        self.baudrate = v.positive_int("baudrate", baudrate)
        self.timeout_s = v.positive("timeout_s", timeout_s)
        self.reset_wait_s = v.non_negative("reset_wait_s", reset_wait_s)
        if reset_on_open not in (None, True, False):
            raise TypeError(f"reset_on_open must be True, False or None, got {reset_on_open!r}")
        self.reset_on_open = reset_on_open
        self.version = ""
        self.settings: dict[int, float] = {}
        self._ser = None
        self._buf = b""

    def open(self) -> GrblLink:
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
            banner = self._wait_banner(max(self.reset_wait_s, _RESET_ANSWER_S))
        if banner is None:
            self.close()
            raise StageTimeout(f"no GRBL start-up banner on {self.port!r} at {self.baudrate} baud: is a GRBL 1.1 "
                               "controller connected there?")
        self.version = banner
        log.info("connected to %s on %s", banner, self.port)
        try:
            self.settings = self.read_settings()
            self._check_settings()  # a subclass's
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
        """Refuse settings the caller cannot work with (nothing here)."""

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception as exc:  # noqa: BLE001 - closing a dead port must not mask the real error
                log.debug("closing %s: %s", self.port, exc)
            self._ser = None

    def __enter__(self) -> GrblLink:
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
                wait = max(self.reset_wait_s, _RESET_ANSWER_S)
                banner = self._read_until(lambda line: line.startswith("Grbl "), wait)
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
                if self._read_until(lambda line: line.startswith("Grbl "), max(self.reset_wait_s, _RESET_ANSWER_S)):
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
