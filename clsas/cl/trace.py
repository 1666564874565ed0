"""Where a call's device time goes: the kernels and copies it enqueues, from their profiling events.

:class:`Tracer` is a context manager. While it is entered, every kernel launch
(``pyopencl``'s ``enqueue_nd_range_kernel``, which every ``Kernel.__call__`` and
:meth:`~clsas.cl.Plan.launch` goes through) and every copy between host and device
(``pyopencl.enqueue_copy``, which :meth:`~clsas.cl.Plan.read` and :meth:`~clsas.cl.Plan.write`
use) has its event recorded, and every :meth:`~clsas.cl.Plan.upload` (a buffer made from host
data, which has no event) its host time. Nothing in the traced code changes: the functions are
wrapped on entry and put back on exit, also when the call raises. The wrapping is process-wide
(module attributes), so a trace counts what every thread enqueues meanwhile; trace one call at a
time.

:meth:`Tracer.seconds` sums the events' start-to-end times once they have ended. A queue made
without profiling gives no times: then it returns ``(None, None)``.
"""

from __future__ import annotations

import time
from typing import Any

from .device import _cl
from .plan import Plan

__all__ = ["Tracer", "event_seconds"]


def event_seconds(event: Any) -> float:
    """Start-to-end time of an enqueued command's event, s (waits for it to end first)."""
    event.wait()
    return Plan.seconds(event)


class Tracer:
    """Record the events of the kernel launches and host-device copies enqueued while entered.

    Attributes (filled while entered): ``kernels`` (the launches' events), ``copies`` (the copies'
    events), ``upload_s`` (host seconds spent in :meth:`clsas.cl.Plan.upload`).
    """

    def __init__(self) -> None:
        self.kernels: list[Any] = []
        self.copies: list[Any] = []
        self.upload_s = 0.0
        self._saved: tuple | None = None

    def __enter__(self) -> Tracer:
        if self._saved is not None:
            raise RuntimeError("Tracer: already entered; a tracer traces one block at a time")
        cl = _cl()
        low = cl._cl
        self.kernels, self.copies, self.upload_s = [], [], 0.0
        self._saved = (cl.enqueue_copy, low.enqueue_nd_range_kernel, Plan.__dict__["upload"])
        copy, launch, upload = self._saved
        cl.enqueue_copy = self._recording(copy, self.copies)
        low.enqueue_nd_range_kernel = self._recording(launch, self.kernels)
        Plan.upload = self._timed(upload)
        return self

    def __exit__(self, *exc: object) -> None:
        cl = _cl()
        cl.enqueue_copy, cl._cl.enqueue_nd_range_kernel, Plan.upload = self._saved
        self._saved = None

    @staticmethod
    def _recording(fn: Any, into: list) -> Any:
        def recorded(*args: Any, **kwargs: Any) -> Any:
            evt = fn(*args, **kwargs)
            if evt is not None:  # a copy into host memory without an event (is_blocking) gives none
                into.append(evt)
            return evt

        return recorded

    def _timed(self, upload: Any) -> Any:
        def timed(plan: Plan, *args: Any, **kwargs: Any) -> Any:
            t = time.perf_counter()
            try:
                return upload(plan, *args, **kwargs)
            finally:
                self.upload_s += time.perf_counter() - t

        return timed

    def seconds(self) -> tuple[float | None, float | None]:
        """(kernel seconds, transfer seconds) of what was recorded: the launches' events summed, and
        the copies' events summed plus the uploads' host time; ``(None, None)`` where a queue gives
        no profiling times (pyopencl's ``PROFILING_INFO_NOT_AVAILABLE``)."""
        cl = _cl()
        try:
            kernel = sum(event_seconds(e) for e in self.kernels)
            transfer = sum(event_seconds(e) for e in self.copies) + self.upload_s
        except cl.Error as exc:
            if "PROFILING" not in str(exc).upper():
                raise
            return None, None
        return kernel, transfer
