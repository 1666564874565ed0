"""An x-y stage driven by a GRBL 1.1 controller over pyserial.

The stage homes (``$H``) or unlocks (``$X``), moves in machine coordinates (``G53``) and confirms
each move by polling ``?`` until GRBL reports ``Idle`` at the target; on connecting it reads
``$$`` and refuses settings a scan cannot work with. The line protocol, the banner and the
alarms are :class:`clsas.rig.grbl_link.GrblLink`'s.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from .. import validate as v
from .grbl_link import (
    ALARMS,
    ERRORS,
    GrblAlarm,
    GrblError,
    GrblLink,
    StageDisconnected,
    StageError,
    StageRefused,
    StageTimeout,
    Status,
)

__all__ = ["GrblStage", "StageError", "StageRefused", "GrblError", "GrblAlarm", "StageTimeout", "StageDisconnected",
           "Status", "ERRORS", "ALARMS"]

log = logging.getLogger(__name__)


class GrblStage(GrblLink):
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
        How long one move may take to reach ``Idle``; by default three times the time GRBL
        needs for it (:meth:`move_time`: the feed rate capped per axis by ``$110``/``$111``,
        accelerating at ``$120``/``$121``) plus 10 s.
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
    clock : object with ``monotonic()`` and ``sleep(seconds)``
        The time base of homing and of a move's polling and deadline: the :mod:`time` module by
        default; a clock shared with :class:`clsas.rig.GrblEmulator` that moves only when told
        makes a move's polls land at known times. Waits for a line on the port stay on real time.
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
        clock: Any = time,
    ) -> None:
        super().__init__(port, baudrate=baudrate, timeout_s=timeout_s, reset_wait_s=reset_wait_s,
                         reset_on_open=reset_on_open)
        area = v.array("work_area_mm", work_area_mm, shape=(2, 2))
        if not (area[:, 0] < area[:, 1]).all():
            raise ValueError("work_area_mm must be ((x_min, x_max), (y_min, y_max)) with min < max, "
                             f"got {area.tolist()}")
        self.work_area_mm = area
        self.feed_mm_min = None if feed_mm_min is None else v.positive("feed_mm_min", feed_mm_min)
        self.home_timeout_s = None if home_timeout_s is None else v.positive("home_timeout_s", home_timeout_s)
        self.move_timeout_s = None if move_timeout_s is None else v.positive("move_timeout_s", move_timeout_s)
        poll_hz = v.positive("poll_hz", poll_hz)
        if poll_hz > 5.0:
            raise ValueError(f"poll_hz must be at most 5 (GRBL's advice for '?' polling), got {poll_hz}")
        self.poll_s = 1.0 / poll_hz
        self.position_tol_mm = v.positive("position_tol_mm", position_tol_mm)
        if not (callable(getattr(clock, "monotonic", None)) and callable(getattr(clock, "sleep", None))):
            raise TypeError(f"clock must have monotonic() and sleep(seconds), as the time module has, got {clock!r}")
        self.clock = clock

    def _check_settings(self) -> None:
        """Refuse settings the scan cannot work with, naming the setting."""
        st = self.settings
        if 10 in st and not int(st[10]) & 1:
            raise StageRefused(f"GRBL's $10={st[10]:g} makes status reports carry the work position (WPos), "
                             "but clsas checks and records the machine position: send '$10=1' once "
                             "(it is kept in EEPROM)")
        if st.get(20, 0) and 130 in st and 131 in st:
            for axis, (lo, hi) in zip("xy", self.work_area_mm, strict=True):
                travel = st[130 + "xy".index(axis)]
                if lo < -travel - 1e-6 or hi > 1e-6:
                    raise StageRefused(
                        f"stage.work_area_mm {axis} = [{lo:g}, {hi:g}] mm is outside GRBL's soft limits ($20=1, "
                        f"${130 + 'xy'.index(axis)}={travel:g}): after homing ($H) GRBL's machine "
                        f"coordinates run from -{travel:g} to 0 mm, so set [stage] work_area_mm within "
                        f"[-{travel:g}, 0] and [scan] origin_mm inside it (or set ${130 + 'xy'.index(axis)} "
                        "to the stage's real travel)")
        pulloff = st.get(27, 1.0)
        if int(st.get(21, 0)) == 1 and (self.work_area_mm[:, 1] > -pulloff).any():
            log.warning("GRBL's hard limits are on ($21=1) and stage.work_area_mm reaches machine 0, where homing "
                        "found the switches: a stop there presses a switch and raises ALARM:1; keep work_area_mm's "
                        "upper ends at most -%g mm (the pull-off, $27)", pulloff)
        capped = [k for k in (110, 111) if self.feed_mm_min is not None and 0 < st.get(k, np.inf) < self.feed_mm_min]
        if capped:
            log.warning("stage.feed_mm_min = %g mm/min is above GRBL's maximum rate %s: GRBL moves at most at that "
                        "rate, and clsas plans each move's time from it (raise %s, or lower feed_mm_min)",
                        self.feed_mm_min, " and ".join(f"${k}={st[k]:g}" for k in capped),
                        " and ".join(f"${k}" for k in capped))

    def home_timeout(self) -> float:
        """Seconds ``$H`` may take (``home_timeout_s``, or from ``$25`` and ``$130``-``$132``)."""
        if self.home_timeout_s is not None:
            return self.home_timeout_s
        st = self.settings
        travel = max((st[k] for k in (130, 131, 132) if k in st), default=0.0)
        if st.get(25, 0) > 0 and travel > 0:
            return 2.0 * 1.5 * travel / st[25] * 60.0 + 30.0
        return 300.0

    def move_time(self, start_mm, target_mm) -> float | None:
        """Seconds GRBL takes for the straight x-y move from ``start_mm`` to ``target_mm``.

        The rate is what GRBL uses: ``feed_mm_min`` (``G1``; ``G0`` has none), lowered until no
        axis runs faster than its ``$110``/``$111`` (mm/min); the acceleration likewise from
        ``$120``/``$121`` (mm/s^2), with a trapezoidal (or triangular) speed profile. None where
        GRBL did not report a rate for a ``G0`` move.
        """
        d = np.abs(np.asarray(target_mm, float)[:2] - np.asarray(start_mm, float)[:2])
        dist = float(np.hypot(*d))
        if dist == 0.0:
            return 0.0
        st = self.settings
        caps = [st[k] * dist / d[i] for i, k in enumerate((110, 111)) if d[i] > 0 and st.get(k, 0) > 0]
        rate = min([self.feed_mm_min or np.inf, *caps])
        if not np.isfinite(rate):
            return None
        v_mm_s = rate / 60.0
        accs = [st[k] * dist / d[i] for i, k in enumerate((120, 121)) if d[i] > 0 and st.get(k, 0) > 0]
        if not accs:
            return dist / v_mm_s
        acc = min(accs)
        if dist >= v_mm_s**2 / acc:  # reaches the rate: accelerate, cruise, decelerate
            return dist / v_mm_s + v_mm_s / acc
        return 2.0 * float(np.sqrt(dist / acc))

    def move_timeout(self, start_mm, target_mm) -> float:
        """Seconds the move from ``start_mm`` to ``target_mm`` may take: ``move_timeout_s``, or
        three times :meth:`move_time` plus 10 s (120 s where GRBL reports no rate)."""
        if self.move_timeout_s is not None:
            return self.move_timeout_s
        t = self.move_time(start_mm, target_mm)
        return 120.0 if t is None else 3.0 * t + 10.0

    def _farthest_corner(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """The work-area corner farthest from (x, y): where a move may start when the position is unknown."""
        (x0, x1), (y0, y1) = self.work_area_mm
        return (x0 if abs(x_mm - x0) > abs(x_mm - x1) else x1, y0 if abs(y_mm - y0) > abs(y_mm - y1) else y1)

    def home(self) -> Status:
        """Run the homing cycle (``$H``) and set millimetres, absolute (``G21 G90``)."""
        if self.settings.get(22, 1) == 0:
            raise StageRefused("[scan] home = true but homing is disabled in GRBL ($22=0): enable it with "
                               "'$22=1' (with limit switches fitted), or set home = false in the [scan] table")
        t0 = self.clock.monotonic()
        self.command("$H", timeout_s=self.home_timeout())
        log.info("homed in %.1f s", self.clock.monotonic() - t0)
        self.command("G21 G90")
        return self.wait_idle(self.home_timeout())

    def unlock(self) -> Status:
        """Clear an alarm lock without homing (``$X``) and set ``G21 G90``."""
        if self.settings.get(20, 0):
            raise StageRefused("[scan] home = false but GRBL's soft limits are on ($20=1): they check targets "
                               "against the position homing sets, so set home = true in the [scan] table or turn "
                               "them off with '$20=0'")
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
            st = self.wait_idle(self.move_timeout((0.0, 0.0), (dx_mm, dy_mm)))
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
        now = self.status()  # where the move starts (idle between moves), else the worst case
        self._polled_at = self.clock.monotonic()
        start = now.position_mm[:2] if now.state == "Idle" else self._farthest_corner(x_mm, y_mm)
        timeout = self.move_timeout(start, (x_mm, y_mm))
        log.debug("move to (%.3f, %.3f) mm: %s s planned, timeout %.1f s", x_mm, y_mm,
                  self.move_time(start, (x_mm, y_mm)), timeout)
        self.command(f"G53 {word} X{x_mm:.3f} Y{y_mm:.3f}{feed}")
        st = self.wait_idle(timeout)
        err = max(abs(st.position_mm[0] - x_mm), abs(st.position_mm[1] - y_mm))
        if err > self.position_tol_mm:
            raise StageError(f"the stage reports Idle at ({st.position_mm[0]:.3f}, {st.position_mm[1]:.3f}) mm, "
                             f"{err:.3f} mm from the target ({x_mm:.3f}, {y_mm:.3f})")
        return st

    def wait_idle(self, timeout_s: float) -> Status:
        """Poll ``?`` at ``poll_hz`` until the state is ``Idle``."""
        clock = self.clock
        deadline = clock.monotonic() + timeout_s
        clock.sleep(max(0.0, self.poll_s - (clock.monotonic() - getattr(self, "_polled_at", -np.inf))))
        while True:
            t = clock.monotonic()
            st = self.status()
            if st.state == "Idle":
                return st
            if st.state == "Alarm":
                raise StageError("GRBL is in the Alarm state (an earlier alarm was not cleared)")
            if t > deadline:
                raise StageTimeout(f"the stage did not reach Idle within {timeout_s:g} s (state {st.state})")
            clock.sleep(max(0.0, self.poll_s - (clock.monotonic() - t)))
