"""The base of every OpenCL plan: queue, verified kernel variant, device buffers, timings.

A plan is built once for a shape (kernel chosen and compiled, buffers allocated) and called
many times. Subclasses name their kernel and sources, allocate in ``__init__`` after calling
``super().__init__``, and launch through :meth:`Plan.launch` so that kernel time is measured
from profiling events.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .device import _cl, describe, get_queue
from .program import kernel
from .variants import KERNELS, choose

__all__ = ["Plan"]


class Plan:
    """Queue, kernel variant and buffers of one OpenCL computation.

    Parameters
    ----------
    queue : None, str, pyopencl.Device or pyopencl.CommandQueue
        Where to run (see :func:`clsas.cl.get_queue`).
    vec : int, optional
        Force a vector width (4, 8 or 16); it must pass the variant check, else
        :class:`~clsas.cl.BuildError`. Default: the widest width the device passes.
    """

    kernel_name: str = ""

    def __init__(self, queue: Any = None, vec: int | None = None):
        self.cl = _cl()
        self.queue = get_queue(queue)
        self.context = self.queue.context
        files = KERNELS[self.kernel_name][0]
        self.vec = choose(self.queue, self.kernel_name, vec)
        self.kernel = kernel(self.context, files, self.kernel_name, {"VEC": self.vec})
        self.last_kernel_s = 0.0
        self._events: list = []

    # -- buffers -------------------------------------------------------------------------
    def alloc(self, nbytes: int, access: str = "rw") -> Any:
        """A device buffer of ``nbytes`` (at least 4); ``access`` is "r", "w" or "rw" for kernels."""
        mf = self.cl.mem_flags
        flags = {"r": mf.READ_ONLY, "w": mf.WRITE_ONLY, "rw": mf.READ_WRITE}[access]
        return self.cl.Buffer(self.context, flags, max(4, int(nbytes)))

    def upload(self, arr: np.ndarray, dtype: Any) -> Any:
        """A read-only device copy of ``arr`` as a contiguous ``dtype`` array."""
        mf = self.cl.mem_flags
        host = np.ascontiguousarray(arr, dtype=dtype)
        if host.nbytes == 0:
            return self.alloc(4, "r")
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=host)

    def write(self, buf: Any, arr: np.ndarray, dtype: Any) -> None:
        self.cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(arr, dtype=dtype))

    def read(self, buf: Any, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        """Copy ``buf`` back after every launch since :meth:`begin` has ended."""
        out = np.empty(shape, dtype)
        self.cl.enqueue_copy(self.queue, out, buf, wait_for=self._events or None)
        self.last_kernel_s = sum((e.profile.end - e.profile.start) * 1e-9 for e in self._events)
        return out

    # -- launches ------------------------------------------------------------------------
    def begin(self) -> None:
        """Start a call: the kernel time of the next :meth:`read` covers launches from here."""
        self._events = []

    def launch(self, global_size: tuple[int, ...], *args: Any, local_size: tuple[int, ...] | None = None) -> Any:
        evt = self.kernel(self.queue, global_size, local_size, *args)
        self._events.append(evt)
        return evt

    @property
    def device(self) -> str:
        return describe(self.queue.device)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.kernel_name}, VEC={self.vec}, {self.device})"
