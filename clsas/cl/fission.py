"""Device fission and a device's copy bandwidth: the two device questions the scaling and
roofline code ask, kept here because only the device layer imports pyopencl."""

from __future__ import annotations

import functools
import logging
from typing import Any

from .device import _cl, describe, make_queue

log = logging.getLogger("clsas.cl")


@functools.cache
def sub_device_queue(device_ptr: int, units: int) -> Any:
    """A profiling queue on a sub-device of ``units`` compute units of the device whose ``int_ptr``
    is ``device_ptr`` (memoised per process); None where the device cannot be split so."""
    pcl = _cl()
    device = next(d for p in pcl.get_platforms() for d in p.get_devices() if d.int_ptr == device_ptr)
    prop = pcl.device_partition_property
    try:
        sub = device.create_sub_devices([prop.BY_COUNTS, units, prop.BY_COUNTS_LIST_END])[0]
    except (pcl.Error, AttributeError) as exc:  # a driver without fission: the whole device
        log.info("%s: no sub-device of %d compute units (%s); using the whole device", describe(device), units, exc)
        return None
    log.info("%s: a sub-device of %d of %d compute units", describe(device), units, device.max_compute_units)
    # the queue names the sub-device: PoCL 3.0 lists the parent as the context's device, and a queue
    # made without naming the device then runs kernels on every core (measured: per-thread CPU ticks)
    return make_queue(sub, sub_device=True)


def copy_seconds(queue: Any, nbytes: int, repeats: int = 3) -> float | None:
    """The fastest of ``repeats`` buffer-to-buffer copies of ``nbytes`` on ``queue``'s device, s,
    timed by profiling events (after one warm-up); None on a queue without profiling."""
    pcl = _cl()
    a = pcl.Buffer(queue.context, pcl.mem_flags.READ_WRITE, nbytes)
    b = pcl.Buffer(queue.context, pcl.mem_flags.READ_WRITE, nbytes)
    best = float("inf")
    for _ in range(repeats + 1):
        evt = pcl.enqueue_copy(queue, b, a)
        evt.wait()
        try:
            best = min(best, (evt.profile.end - evt.profile.start) * 1e-9)
        except pcl.RuntimeError:  # a queue without profiling
            return None
    return best
