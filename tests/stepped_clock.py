"""A clock that moves only when told, for the rig tests: shared by :class:`clsas.rig.GrblEmulator`
and :class:`clsas.rig.GrblStage` (their ``clock=``), it makes a move advance exactly as far as the
test moves the clock, and a stage's poll wait (``sleep``) move it by the wait instead of waiting."""

from __future__ import annotations

import threading


class SteppedClock:
    """``monotonic()`` returns the time the clock was stepped to; ``advance(s)`` and ``sleep(s)``
    step it (``sleep`` returns at once); ``sleeps`` records every sleep asked for."""

    def __init__(self, start_s: float = 100.0):
        self._now = float(start_s)
        self._lock = threading.Lock()
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        with self._lock:
            return self._now

    def advance(self, seconds: float) -> None:
        if not seconds >= 0:
            raise ValueError(f"seconds must be >= 0, got {seconds}")
        with self._lock:
            self._now += seconds

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.advance(seconds)
