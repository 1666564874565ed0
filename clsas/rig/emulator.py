"""A GRBL 1.1 emulator on a pseudo-terminal, with fault injection.

pyserial opens :attr:`GrblEmulator.port` as a real serial port; the emulator answers on the
other end like a GRBL 1.1 controller: a start-up banner (after an optional boot delay and
boot-loader noise, as an Arduino that resets when its port is opened), ``ok`` and ``error:N``,
``ALARM:N`` pushes, ``$H`` homing, ``$X``, ``$$``, ``G0``/``G1`` moves that take time (the
machine position advances while the state is ``Run``), ``G4`` dwells, and the real-time
``?`` (status report), ``!`` (feed hold), ``~`` (cycle start) and Ctrl-X (soft reset).

Faults (:class:`Faults`) are injected at the N-th motion command; :meth:`GrblEmulator.press_reset`
and :meth:`GrblEmulator.disconnect` press the reset button or pull the cable at any time. Used by
the tests and by ``clsas acquire --simulate``.
"""

from __future__ import annotations

import logging
import os
import re
import select
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["GrblEmulator", "Faults"]

log = logging.getLogger(__name__)

_WORD = re.compile(r"([A-Z])\s*([-+]?\d*\.?\d+)")


@dataclass
class Faults:
    """Faults to inject, each at the N-th motion command (1-based); None for none.

    alarm_at_move : ALARM:1 (hard limit) half way through that move; the machine stops.
    reset_at_move : the reset button half way through that move (``ALARM:3``, then the banner).
    error_at_move : answer ``error:<error_code>`` to that move instead of running it.
    drop_ok_at_move : run that move but never send its ``ok``.
    disconnect_at_move : close the port when that move arrives.
    """

    alarm_at_move: int | None = None
    reset_at_move: int | None = None
    error_at_move: int | None = None
    error_code: int = 33
    drop_ok_at_move: int | None = None
    disconnect_at_move: int | None = None

    @classmethod
    def parse(cls, text: str) -> Faults:
        """From ``"alarm@5"``, ``"reset@2"``, ``"error@3"``, ``"drop-ok@2"``, ``"disconnect@4"``
        (comma-separated)."""
        f = cls()
        names = {"alarm": "alarm_at_move", "reset": "reset_at_move", "error": "error_at_move",
                 "drop-ok": "drop_ok_at_move", "disconnect": "disconnect_at_move"}
        for part in filter(None, (p.strip() for p in text.split(","))):
            kind, _, n = part.partition("@")
            if kind not in names or not n.isdigit() or int(n) < 1:
                raise ValueError(f"fault must be one of {', '.join(k + '@N' for k in names)} with N >= 1, "
                                 f"got {part!r}")
            setattr(f, names[kind], int(n))
        return f


@dataclass
class _Move:
    start: np.ndarray
    end: np.ndarray
    duration_s: float
    alarm_at: float | None = None  # fraction of the move where ALARM:1 (hard limit) trips
    reset_at: float | None = None  # fraction of the move where the reset button is pressed
    t_start: float | None = None
    rate: float = 0.0  # mm/min, as GRBL moves it (the status report's FS)


@dataclass
class GrblEmulator:
    """A GRBL 1.1 controller behind a pseudo-terminal.

    Parameters
    ----------
    faults : Faults
    time_scale : float
        Multiplies every duration (moves, homing, boot); 0.01 makes a 1 s move take 10 ms.
    travel_mm : machine travel per axis (``$130``-``$132``). As on GRBL 1.1, homing ends at
        ``-pulloff_mm`` on each axis and soft limits allow ``[-travel, 0]``.
    pulloff_mm : homing pull-off (``$27``).
    report_mpos : ``$10=1`` (status reports carry ``MPos``); False reports ``WPos``.
    work_offset_mm : a G54 work offset stored in EEPROM; ``G0``/``G1`` without ``G53`` are shifted
        by it, as on the real controller.
    max_rate_mm_min : each axis's maximum rate (``$110``-``$112``; a ``$11x=`` write changes that
        axis's). As on GRBL, ``G0`` moves at it and ``G1`` at the feed lowered until no axis
        exceeds it; status reports give that rate (``FS:``).
    homing : starts locked in Alarm until ``$H`` or ``$X`` (``$22=1``).
    soft_limits : a target outside the travel raises ALARM:2 (``$20=1``).
    hard_limits : limit switches at the home end of each axis, at machine coordinate 0 (where
        ``$H`` finds them, before the pull-off), trip ALARM:1 when the carriage reaches one, or
        moves off the one it stopped on (``$21=1``). ``$20=`` and ``$21=`` writes switch both.
    banner_delay_s : boot time after the port opens, before the banner (an Arduino's boot loader
        takes ~1.5 s); scaled by ``time_scale`` but never under 50 ms.
    reset_on_open : like an Arduino Uno, the controller reboots whenever its port is opened
        (position lost, banner after ``banner_delay_s``); False: it runs on across opens and
        says nothing until spoken to, like a board without auto-reset.
    clock : the time base of motion, homing and dwells: an object with ``monotonic()`` and
        ``sleep(seconds)``, the :mod:`time` module by default. A clock that moves only when told
        (shared with :class:`clsas.rig.GrblStage`) makes the machine step on command: a move
        advances exactly as far as the clock is moved. The serial line's own waits (the boot,
        a client that does not read) stay on real time.
    """

    faults: Faults = field(default_factory=Faults)
    time_scale: float = 1.0
    travel_mm: tuple[float, float, float] = (1000.0, 1000.0, 100.0)
    max_rate_mm_min: float = 6000.0
    homing: bool = True
    homing_s: float = 3.0
    soft_limits: bool = True
    hard_limits: bool = False
    banner_delay_s: float = 1.5
    pulloff_mm: float = 1.0
    report_mpos: bool = True
    work_offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seek_rate_mm_min: float = 500.0
    reset_on_open: bool = True
    clock: Any = time

    def __post_init__(self) -> None:
        self.received: list[str] = []  # every line received, for the tests
        self.written: dict[int, float] = {}  # settings written with $N=value
        self.status_times: list[float] = []  # when each '?' arrived (s, on the clock)
        self.banners = 0  # start-up banners sent (boots and soft resets)
        self.ctrl_x = 0  # soft resets (Ctrl-X) received
        self.moves = 0
        self._pos = np.zeros(3)
        self._queue: list[_Move] = []
        self._state = "Alarm" if self.homing else "Idle"
        self._feed = 0.0
        self._relative = False
        self._line = b""
        self._locked_until_reset = False  # after ALARM:1/2 only Ctrl-X is answered
        self._on_switch = False  # a hard limit left the carriage on a switch
        self._late_ok = False  # the refused line's ok, sent after the reset
        self._stop = threading.Event()
        self._lock = threading.Lock()
        import tty  # POSIX only: imported here so that `import clsas.rig` works on Windows

        self._master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        os.close(slave)  # clients open it by name; the master keeps the pair alive
        os.set_blocking(self._master, False)
        self._thread = threading.Thread(target=self._run, name="grbl-emulator", daemon=True)
        self._closed = False

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> GrblEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self._close_master()

    def __enter__(self) -> GrblEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _close_master(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                os.close(self._master)
            except OSError:
                pass

    @property
    def position_mm(self) -> np.ndarray:
        with self._lock:
            self._advance(self.clock.monotonic())
            return self._pos.copy()

    @property
    def state(self) -> str:
        with self._lock:
            self._advance(self.clock.monotonic())
            return self._state

    # -- I/O -----------------------------------------------------------------------------------

    def _send(self, text: str) -> None:
        self._write(text.encode("ascii") + b"\r\n")

    def _write(self, data: bytes) -> None:
        deadline = time.monotonic() + 2.0
        while data and not self._closed:
            try:
                data = data[os.write(self._master, data):]
            except BlockingIOError:  # the client is not reading: wait a little, as a UART would
                if time.monotonic() > deadline:
                    return
                time.sleep(0.001)
            except OSError:
                return  # no client on the port: the line is lost, as on a real serial line

    def _banner(self) -> None:
        self.banners += 1
        self._send("")
        self._send("Grbl 1.1h ['$' for help]")
        if self._state == "Alarm":
            self._send("[MSG:'$H'|'$X' to unlock]")

    def _run(self) -> None:
        # Until a client opens the pseudo-terminal, reading the master fails (EIO); the first quiet
        # select after that means a client is there (and, reset_on_open, the banner follows the boot).
        connected = False
        while not self._stop.is_set() and not self._closed:
            try:
                ready, _, _ = select.select([self._master], [], [], 0.005)
            except (OSError, ValueError):
                break
            with self._lock:
                self._advance(self.clock.monotonic())
            if not connected:
                data = b""
                if ready:
                    try:
                        data = os.read(self._master, 1024)
                    except BlockingIOError:
                        pass  # a client opened the port between select and read
                    except OSError:
                        time.sleep(0.005)  # no client: the slave side is closed
                        continue
                    if self.reset_on_open:
                        continue  # bytes that arrive while the board boots are lost
                connected = True
                log.debug("emulator: a client opened %s", self.port)
                if self.reset_on_open:
                    self._reset_on_open()
                for byte in data:  # a board that runs on answers at once
                    self._byte(byte)
                continue
            if not ready:
                continue
            try:
                data = os.read(self._master, 1024)
            except BlockingIOError:
                continue
            except OSError:
                log.debug("emulator: the client closed %s", self.port)
                connected = False  # the client closed the port
                continue
            for byte in data:
                self._byte(byte)

    def _reset_on_open(self) -> None:
        with self._lock:
            self._queue.clear()
            self._pos = np.zeros(3) if self.homing else self._pos
            self._state = "Alarm" if self.homing else "Idle"
        # boot time (at least 50 ms: pyserial flushes the input buffer as it opens the port)
        time.sleep(max(0.05, self.banner_delay_s * self.time_scale))
        self._write(b"\x00\xf0\xfe")  # boot-loader noise before the banner
        self._banner()

    def _byte(self, byte: int) -> None:
        ch = bytes([byte])
        if ch == b"?":
            self.status_times.append(self.clock.monotonic())
            with self._lock:
                self._advance(self.clock.monotonic())
                x, y, z = self._pos if self.report_mpos else self._pos - np.asarray(self.work_offset_mm)
                state = "Hold:0" if self._state == "Hold" else self._state
                feed = self._queue[0].rate if self._state == "Run" and self._queue else 0
            kind = "MPos" if self.report_mpos else "WPos"
            self._send(f"<{state}|{kind}:{x:.3f},{y:.3f},{z:.3f}|FS:{feed:.0f},0>")
        elif ch == b"!":
            with self._lock:
                self._advance(self.clock.monotonic())
                if self._state == "Run":
                    self._hold_now()
        elif ch == b"~":
            with self._lock:
                if self._state == "Hold":
                    self._state = "Run" if self._queue else "Idle"
                    if self._queue:
                        self._queue[0].t_start = self.clock.monotonic()
        elif ch == b"\x18":
            self.ctrl_x += 1
            with self._lock:
                self._soft_reset()
        elif ch in (b"\n", b"\r"):
            line, self._line = self._line.decode("ascii", "replace").strip(), b""
            if line and self._locked_until_reset:
                self.received.append(line)  # GRBL reads it but answers nothing until Ctrl-X
            elif line:
                self.received.append(line)
                self._command(line)
        else:
            self._line += ch

    # -- motion ----------------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Bring the position up to ``now`` (called with the lock held)."""
        while self._queue and self._state == "Run":
            mv = self._queue[0]
            if mv.t_start is None:
                mv.t_start = now
            frac = (now - mv.t_start) / mv.duration_s if mv.duration_s > 0 else 1.0
            if mv.alarm_at is not None and frac >= mv.alarm_at:
                self._pos = mv.start + mv.alarm_at * (mv.end - mv.start)
                self._queue.clear()
                self._state = "Alarm"
                self._send("ALARM:1")
                self._on_switch = True
                self._send("[MSG:Reset to continue]")
                self._locked_until_reset = True
                return
            if mv.reset_at is not None and frac >= mv.reset_at:
                self._pos = mv.start + mv.reset_at * (mv.end - mv.start)
                self._soft_reset()
                return
            if frac < 1.0:
                self._pos = mv.start + frac * (mv.end - mv.start)
                return
            self._pos = mv.end.copy()
            self._queue.pop(0)
            self._on_switch = False  # it moved off (hard limits were off, or it would have tripped)
            if self._queue:
                self._queue[0].t_start = mv.t_start + mv.duration_s
                self._queue[0].start = self._pos.copy()
        if not self._queue and self._state == "Run":
            self._state = "Idle"

    def _soft_reset(self) -> None:
        """Ctrl-X or the reset button (called with the lock held): stop, ALARM:3 if moving, banner."""
        moving = self._state in ("Run", "Hold", "Home")
        self._queue.clear()
        self._state = "Alarm" if (self.homing or moving or self._locked_until_reset) else "Idle"
        self._locked_until_reset = False
        late, self._late_ok = self._late_ok, False
        if moving:
            self._send("ALARM:3")
        self._banner()
        if late:
            self._send("ok")

    def press_reset(self) -> None:
        """The controller's reset button: a soft reset as if Ctrl-X had come from the port."""
        with self._lock:
            self._advance(self.clock.monotonic())
            self._soft_reset()

    def disconnect(self) -> None:
        """The port disappears (a pulled USB cable): the client's next read or write fails."""
        log.info("emulator: disconnected")
        self._close_master()

    def _hold_now(self) -> None:
        mv = self._queue[0]
        full = float(np.linalg.norm(mv.end - mv.start)) or 1.0
        mv.start = self._pos.copy()  # the rest of the move runs from here after '~'
        mv.duration_s *= float(np.linalg.norm(mv.end - mv.start)) / full
        mv.t_start = None
        self._state = "Hold"

    # -- commands --------------------------------------------------------------------------------

    def _command(self, line: str) -> None:
        up = line.upper().replace(" ", "")
        if len(line) > 80:
            return self._send("error:11")
        if up.startswith("$"):
            return self._system(up)
        if self._state == "Alarm":
            return self._send("error:9")
        words = _WORD.findall(up)
        if not words or _WORD.sub("", up):
            return self._send("error:1")  # not a sequence of letter-number words
        vals: dict[str, float] = {}
        motion = None
        machine = False
        for letter, num in words:
            if letter == "G":
                g = float(num)
                if g in (0, 1):
                    motion = int(g)
                elif g == 21:
                    pass
                elif g == 53:
                    machine = True
                elif g == 90:
                    self._relative = False
                elif g == 91:
                    self._relative = True
                elif g == 4:
                    motion = 4
                else:
                    return self._send("error:20")
            elif letter in "XYZFP":
                vals[letter] = float(num)
            else:
                return self._send("error:20")
        if "F" in vals:
            if vals["F"] <= 0:
                return self._send("error:4")
            self._feed = vals["F"]
        if motion == 4:
            with self._lock:
                self._advance(self.clock.monotonic())
                busy = bool(self._queue)
            while busy and not self._closed:  # a dwell waits for the planner to empty
                self.clock.sleep(0.005)
                with self._lock:
                    self._advance(self.clock.monotonic())
                    busy = bool(self._queue) and self._state != "Alarm"
            self.clock.sleep(vals.get("P", 0.0) * self.time_scale)
            return self._send("ok")
        if motion is None:
            return self._send("ok")
        return self._move(motion, vals, machine)

    def _move(self, motion: int, vals: dict[str, float], machine: bool = False) -> None:
        self.moves += 1
        n, f = self.moves, self.faults
        if f.disconnect_at_move == n:
            log.info("emulator: disconnect at move %d", n)
            return self._close_master()
        if f.error_at_move == n:
            return self._send(f"error:{f.error_code}")
        with self._lock:
            last = self._queue[-1].end if self._queue else self._pos
            target = last.copy()
            offset = np.zeros(3) if machine else np.asarray(self.work_offset_mm, float)
            for i, axis in enumerate("XYZ"):
                if axis in vals:
                    target[i] = (last[i] + vals[axis]) if self._relative else vals[axis] + offset[i]
            outside = np.any(target > 1e-9) or np.any(target < -np.asarray(self.travel_mm) - 1e-9)
            if self.soft_limits and self.homing and outside:
                self._queue.clear()
                self._state = "Alarm"
                self._send("ALARM:2")
                self._send("[MSG:Reset to continue]")
                self._locked_until_reset = True
                self._late_ok = True
                return
            if motion != 0 and self._feed <= 0:
                self._send("error:22")
                return
            dist = float(np.linalg.norm(target - last))
            rate = self._capped_rate(target - last, np.inf if motion == 0 else self._feed)
            alarm_at = 0.5 if f.alarm_at_move == n else None
            if self.hard_limits and self._on_switch:
                alarm_at = 0.0  # GRBL trips on any change of a switch's pin: moving off it too
            if self.hard_limits and np.any(target > 0):  # the carriage reaches a home switch at 0
                hit = [(0.0 - last[i]) / (target[i] - last[i]) for i in range(3) if target[i] > 0 >= last[i]]
                alarm_at = min([*hit, *([] if alarm_at is None else [alarm_at])], default=0.0)
            # a move queued behind none starts now; the next ones where the one before ends (_advance)
            self._queue.append(_Move(last.copy(), target, dist / rate * 60.0 * self.time_scale if dist else 0.0,
                                     alarm_at=alarm_at, reset_at=0.5 if f.reset_at_move == n else None, rate=rate,
                                     t_start=None if self._queue else self.clock.monotonic()))
            if self._state == "Idle":
                self._state = "Run"
        if f.drop_ok_at_move == n:
            log.info("emulator: dropping the ok of move %d", n)
            return None
        return self._send("ok")

    def _capped_rate(self, delta_mm: np.ndarray, feed_mm_min: float) -> float:
        """The rate GRBL moves at (mm/min): the feed, lowered until no axis runs faster than its
        ``$110``-``$112`` (``G0``: ``feed_mm_min`` inf, the axes' rates alone)."""
        dist = float(np.linalg.norm(delta_mm))
        if dist == 0.0:
            return float(min(feed_mm_min, self.max_rate_mm_min))
        caps = [self.written.get(110 + i, self.max_rate_mm_min) * dist / abs(d)
                for i, d in enumerate(delta_mm) if abs(d) > 1e-12]
        return float(min([feed_mm_min, *caps]))

    def _system(self, up: str) -> None:
        if up == "$H":
            if not self.homing:
                return self._send("error:5")
            with self._lock:
                self._state = "Home"
            self.clock.sleep(self.homing_s * self.time_scale)
            with self._lock:
                self._pos = -self.pulloff_mm * np.ones(3)
                self._on_switch = False
                self._queue.clear()
                self._state = "Idle"
            return self._send("ok")
        if up == "$X":
            with self._lock:
                if self._state == "Alarm":
                    self._state = "Idle"
                    self._send("[MSG:Caution: Unlocked]")
            return self._send("ok")
        m = re.fullmatch(r"\$(\d+)=([-+]?\d*\.?\d+)", up)
        if m:  # a setting write, kept for `$$` ($20 and $21 switch the soft and hard limits)
            key, val = int(m.group(1)), float(m.group(2))
            self.written[key] = val
            if key == 20:
                self.soft_limits = bool(val)
            elif key == 21:
                self.hard_limits = bool(val)
            return self._send("ok")
        if up == "$$":
            settings = {10: int(self.report_mpos), 20: int(self.soft_limits and self.homing), 21: int(self.hard_limits),
                        22: int(self.homing), 25: self.seek_rate_mm_min, 27: self.pulloff_mm,
                        110: self.max_rate_mm_min, 111: self.max_rate_mm_min,
                        **{130 + i: travel for i, travel in enumerate(self.travel_mm)}}
            settings.update({k: val for k, val in self.written.items() if k not in (20, 21)})
            for k, val in settings.items():
                self._send(f"${k}={val:g}")
            return self._send("ok")
        answers = {"$I": ["[VER:1.1h.20190825:clsas-emulator]", "[OPT:V,15,128]"],
                   "$": ["[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"]}
        if up in answers:
            for line in answers[up]:
                self._send(line)
            return self._send("ok")
        return self._send("error:3")
