"""The base of every OpenCL plan: queue, verified kernel variant, device buffers, timings.

A plan is built once for a shape (kernel chosen and compiled, buffers allocated) and called
many times. A subclass declares what it runs as class attributes, ``KERNEL`` (the kernel's
name) and ``SOURCES`` (the files under ``kernels/`` it is built from, in order), and a
``selftest(queue, vec) -> float`` classmethod (its error against the NumPy twin on a small
input, relative to the peak) that the variant probe runs; defining the class registers the
kernel with the device layer (:data:`clsas.cl.KERNELS`). Extra build defines of an instance
come from :meth:`Plan.defines`. It allocates in ``__init__`` after calling
``super().__init__`` and launches through :meth:`Plan.launch` so that kernel time is measured
from profiling events.

A class that sets ``SHAPES = True`` launches with a tuned work-group shape (:mod:`.shapes`): it
names its build variants in ``VARIANTS`` (name -> defines; ``""`` the plain kernel), those that
need a local size in ``NEEDS_LOCAL``, those that need an OpenCL extension in ``NEEDS_EXTENSION``
(tried only where the device reports it), the error bound of those less exact than the plain
kernel in ``ERROR_BOUND`` (tried only for a plan given that ``max_error``), and gives
``selftest(queue, vec, shape)`` and ``time_shapes(queue, vec, shapes) -> seconds per shape``;
:attr:`Plan.shape` is the outcome.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

import numpy as np

from .device import _cl, describe, get_queue
from .program import kernel, sources_hash
from .shapes import DEFAULT, Shape, candidate_shapes, tune
from .variants import choose, kernel_spec, register_kernel

P = TypeVar("P")

__all__ = ["DeviceRows", "Plan", "release_reused", "reused", "reused_plans"]

# (thread, queue, kernel) -> (key, plan): the last plan of each kernel built through :func:`reused`
_REUSED: dict[tuple, tuple] = {}


def reused(queue: Any, kernel: str, key: tuple, factory: Callable[[Any], P]) -> P:
    """The plan ``factory(queue)`` builds for the registered ``kernel``, reused from the last call
    with the same ``key`` (the shapes and tables it is built for) and the same kernel sources on
    this queue in this thread.

    One plan per kernel is kept per queue and thread (a different key replaces it, freeing its
    buffers), so calls with the same shapes skip the allocations and the table uploads; a plan
    is never shared between threads. Its rows left on the device for the previous call
    (:class:`DeviceRows`) become invalid at the next call, as for any plan (those it lent,
    :meth:`Plan.lend`, are read to the host first where still held and unread).
    """
    slot = (threading.get_ident(), id(queue), kernel)
    key = (key, sources_hash(kernel_spec(kernel).sources))  # a source override builds anew
    held = _REUSED.get(slot)
    if held is not None and held[0] == key and held[1].queue is queue:
        return held[1]
    _REUSED.pop(slot, None)  # the old plan's buffers go before the new ones are allocated
    plan = factory(queue)
    _REUSED[slot] = (key, plan)
    return plan


def reused_plans(kernel: str | None = None) -> list:
    """The plans :func:`reused` keeps now (those of ``kernel`` only, where given): what stays on
    the devices between calls."""
    return [plan for (_, _, k), (_, plan) in _REUSED.items() if kernel is None or k == kernel]


def release_reused() -> int:
    """Drop every plan :func:`reused` keeps (their device memory goes with them); returns how many."""
    n = len(_REUSED)
    _REUSED.clear()
    return n


class DeviceRows:
    """Rows a plan left on the device for the next plan on the same queue: ``n_rows`` rows of
    ``n_cols`` complex64 values, ``stride`` values apart, in ``buffer``.

    Their host copy, :attr:`host` ((n_rows, n_cols), read-only), is read from the device the first
    time something asks for it, after the launches that wrote the rows, and then kept: rows that
    only kernels read never cross to the host. A plan that lends its output this way
    (:meth:`Plan.lend`) reads the rows still held and unread before its next call overwrites them
    (:meth:`Plan.begin`), so a host copy asked for later is the one the rows held. Rows made with
    a ``host`` already (an array the caller read itself) keep it.

    The rows are valid while the plan that wrote them has not been called again (:meth:`valid`):
    a plan reuses its buffers from call to call. Holds the buffer, not the plan (whose other
    buffers go when it does). A pickled copy (sent to another process) holds nothing and is never
    valid; whatever holds the rows' data across processes pickles :attr:`host`.
    """

    def __init__(self, plan: Plan, buffer: Any, n_rows: int, n_cols: int, stride: int,
                 host: np.ndarray | None = None):
        self.buffer, self.queue = buffer, plan.queue
        self.n_rows, self.n_cols, self.stride = int(n_rows), int(n_cols), int(stride)
        self._host = host
        self._after = list(plan._events)  # the launches that write the rows: the read waits for them
        self._lock = threading.Lock()  # one read, whichever thread asks first
        self._calls, self._generation = plan._calls, plan._calls[0]

    @property
    def is_read(self) -> bool:
        """Whether the host copy exists (given, or read from the device)."""
        return self._host is not None

    @property
    def host(self) -> np.ndarray | None:
        """The rows on the host, (n_rows, n_cols) complex64, read-only: read from the device on
        first use (:meth:`keep`), the same array afterwards. None for a pickled copy."""
        return self.keep()

    @host.setter
    def host(self, values: np.ndarray) -> None:
        """The host copy, where the caller read the rows itself (the array is kept as it is)."""
        with self._lock:
            self._host = values

    def keep(self) -> np.ndarray | None:
        """Read the rows to the host unless that was done (or the copy was given): the host copy,
        kept from then on (:attr:`host`)."""
        with self._lock:
            if self._host is None and self.buffer is not None:
                self._host = self._read()
            return self._host

    def _read(self) -> np.ndarray:
        """The rows copied back, once the launches that wrote them have ended; only while they
        still hold what those launches wrote."""
        if self._calls[0] != self._generation:
            raise RuntimeError("DeviceRows: the plan that wrote these rows has overwritten them before they were "
                               "read (rows a plan lends are read before its next call: Plan.lend)")
        out = np.empty((self.n_rows, self.stride), np.complex64)
        _cl().enqueue_copy(self.queue, out, self.buffer, wait_for=self._after or None)
        out = out[:, : self.n_cols]
        out.flags.writeable = False
        return out

    def valid(self, queue: Any, host: np.ndarray | None = None) -> bool:
        """Whether a kernel enqueued on ``queue`` (in order after the rows) may read the rows for
        the data it is given: the plan that wrote them has not been called since, and ``host`` is
        the very array read from them (unchanged since: it is read-only) or None (the caller
        holds no host copy and takes the rows as the data: :meth:`clsas.Profiles.device_rows`).
        Never reads the rows."""
        if self.buffer is None or self._calls[0] != self._generation or queue is not self.queue:
            return False
        return host is None or (host is self._host and not host.flags.writeable)

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.buffer = self.queue = self._host = None
        self.n_rows = self.n_cols = self.stride = 0
        self._after, self._lock = [], threading.Lock()
        self._calls, self._generation = [0], -1


class Plan:
    """Queue, kernel variant and buffers of one OpenCL computation.

    Parameters
    ----------
    queue : None, str, pyopencl.Device or pyopencl.CommandQueue
        Where to run (see :func:`clsas.cl.get_queue`).
    vec : int, optional
        Force a vector width (4, 8 or 16); it must pass the variant check, else
        :class:`~clsas.cl.BuildError`. Default: the widest width the device passes.
    shape : "auto" or Shape
        The work-group shape (local size, build variant). ``"auto"``: the tuned one where the
        class is tuned (``SHAPES``), else the runtime's local size and the plain kernel.
    max_error : float, optional
        The error against the twin, relative to the peak, that ``"auto"`` may trade for speed:
        variants whose ``ERROR_BOUND`` exceeds it are not tried. Default None: only variants as
        exact as the plain kernel.
    """

    KERNEL: ClassVar[str] = ""
    SOURCES: ClassVar[tuple[str, ...]] = ()
    SHAPES: ClassVar[bool] = False  # True: the work-group shape is tuned per device (:mod:`.shapes`)
    VARIANTS: ClassVar[dict[str, dict[str, Any]]] = {"": {}}  # build variant name -> its defines
    NEEDS_LOCAL: ClassVar[frozenset[str]] = frozenset()  # variants launched only with a local size
    NEEDS_EXTENSION: ClassVar[dict[str, str]] = {}  # variant -> the OpenCL extension the device must report
    ERROR_BOUND: ClassVar[dict[str, float]] = {}  # variant -> its error bound, where above the plain kernel's

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("KERNEL"):  # a base without a kernel of its own registers nothing
            register_kernel(cls.KERNEL, cls.SOURCES, cls.__module__, cls.__qualname__)

    def __init__(self, queue: Any = None, vec: int | None = None, shape: Shape | str = "auto",
                 max_error: float | None = None):
        if not self.KERNEL:
            raise TypeError(f"{type(self).__name__} names no KERNEL")
        if max_error is not None and not (isinstance(max_error, (int, float)) and 0 < max_error < 1):
            raise ValueError(f"max_error must be None or a fraction of the peak in (0, 1), got {max_error!r}")
        self.max_error = max_error
        self.cl = _cl()
        self.queue = get_queue(queue)
        self.context = self.queue.context
        self.vec = choose(self.queue, self.KERNEL, vec)
        self.tuning = None  # the Tuning behind an "auto" shape of a tuned class (:mod:`.shapes`)
        self.shape = self._shape(shape)
        self.kernel = kernel(self.context, self.SOURCES, self.KERNEL,
                             {**self.VARIANTS[self.shape.variant], **self.defines(), "VEC": self.vec})
        self.last_kernel_s = 0.0
        self._calls = [0]  # calls begun (:meth:`begin`), shared with the DeviceRows this plan made
        self._events: list = []
        self._lent: list[weakref.ref] = []  # the rows :meth:`lend` gave out since :meth:`begin`
        self._written: dict[int, tuple] = {}  # id(buffer) -> (buffer, bytes) of :meth:`write_changed`

    def candidate_shapes(self) -> list[Shape]:
        """The shapes the tuning tries on this plan's device: every variant whose extension the
        device reports (``NEEDS_EXTENSION``) and whose error bound (``ERROR_BOUND``, where it is
        above the plain kernel's) is within ``max_error``, at the local sizes of
        :func:`.shapes.candidate_shapes`."""
        has = set(self.queue.device.extensions.split()) | {""}
        usable = {k: v for k, v in self.VARIANTS.items() if self.NEEDS_EXTENSION.get(k, "") in has
                  and self.ERROR_BOUND.get(k, 0.0) <= (self.max_error or 0.0)}
        return candidate_shapes(self.queue.device, min(256, int(self.queue.device.max_work_group_size)), usable,
                                set(self.NEEDS_LOCAL))

    def _shape(self, shape: Shape | str) -> Shape:
        """The shape asked for, checked; ``"auto"``: tuned (``SHAPES``) or the default."""
        from . import variants

        if isinstance(shape, str) and shape == "auto":
            if not self.SHAPES:
                return DEFAULT
            self.tuning = tune(self.queue, self.KERNEL, self.vec, self.candidate_shapes(), in_probe=variants._IN_PROBE)
            return self.tuning.shape
        if not isinstance(shape, Shape):
            raise TypeError(f"shape must be 'auto' or a clsas.cl.Shape, got {shape!r}")
        if shape.variant not in self.VARIANTS:
            raise ValueError(f"shape: {type(self).__name__} has no variant {shape.variant!r} "
                             f"(it has {sorted(self.VARIANTS)})")
        ext = self.NEEDS_EXTENSION.get(shape.variant)
        if ext and ext not in self.queue.device.extensions.split():
            raise ValueError(f"shape: the variant {shape.variant!r} needs a device with {ext}; "
                             f"{self.queue.device.name.strip()} does not report it")
        if shape.local is None and shape.variant in self.NEEDS_LOCAL:
            raise ValueError(f"shape: the variant {shape.variant!r} needs a local size (got None)")
        limit = int(self.queue.device.max_work_group_size)
        if shape.local is not None and shape.local > limit:
            raise ValueError(f"shape: local={shape.local} exceeds the device's {limit} work-items per group")
        return shape

    def defines(self) -> dict[str, Any]:
        """Build defines of this instance besides ``VEC`` (the variant the probe verifies is
        built without them); set what they depend on before calling ``super().__init__``."""
        return {}

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
        self._written.pop(id(buf), None)
        self.cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(arr, dtype=dtype))

    def write_changed(self, buf: Any, arr: np.ndarray, dtype: Any) -> bool:
        """:meth:`write`, skipped where ``buf`` holds these very bytes from its last write through
        here (a blocking write waits for every command before it on the queue: skipping the
        unchanged ones lets the next launches be enqueued while earlier ones run). Whether it wrote."""
        host = np.ascontiguousarray(arr, dtype=dtype)
        held = self._written.get(id(buf))
        if held is not None and held[0] is buf and held[1] == host.tobytes():
            return False
        self.write(buf, host, dtype)
        self._written[id(buf)] = (buf, host.tobytes())
        return True

    def read(self, buf: Any, shape: tuple[int, ...], dtype: Any, after: Sequence[Any] | None = None) -> np.ndarray:
        """Copy ``buf`` back once the launches it depends on have ended.

        ``after``: those launches' events (of this or another plan on the same queue);
        default every launch of this plan since :meth:`begin`. ``last_kernel_s`` becomes their
        kernel time, s.
        """
        events = list(self._events if after is None else after)
        out = np.empty(shape, dtype)
        self.cl.enqueue_copy(self.queue, out, buf, wait_for=events or None)
        self.last_kernel_s = sum(self.seconds(e) for e in events)
        return out

    def lend(self, buffer: Any, n_rows: int, n_cols: int, stride: int) -> DeviceRows:
        """This call's output in ``buffer`` (``n_rows`` rows of ``n_cols`` complex64 values,
        ``stride`` apart), left on the device for the next plan on the queue, as
        :class:`DeviceRows` whose host copy is read only when asked for. Should they still be held
        and unread when this plan is called again, :meth:`begin` reads them first."""
        rows = DeviceRows(self, buffer, n_rows, n_cols, stride)
        self._lent.append(weakref.ref(rows))
        return rows

    def finish(self) -> float:
        """Wait for the launches since :meth:`begin` to end, reading nothing back;
        ``last_kernel_s`` becomes their kernel time, s (returned)."""
        for evt in self._events:
            evt.wait()
        self.last_kernel_s = sum(self.seconds(e) for e in self._events)
        return self.last_kernel_s

    @staticmethod
    def seconds(event: Any) -> float:
        """Kernel time of a finished launch's event (profiling counters), s."""
        return (event.profile.end - event.profile.start) * 1e-9

    # -- launches ------------------------------------------------------------------------
    def begin(self) -> None:
        """Start a call: the kernel time of the next :meth:`read` covers launches from here, and
        rows an earlier call left on the device (:class:`DeviceRows`) are no longer valid. Rows
        it lent (:meth:`lend`) that are still held and unread are read to the host first (their
        buffer is about to be overwritten)."""
        lent, self._lent = self._lent, []
        for ref in lent:
            rows = ref()
            if rows is not None:
                rows.keep()
        self._events = []
        self._calls[0] += 1

    def launch(self, global_size: tuple[int, ...], *args: Any, local_size: tuple[int, ...] | None = None,
               wait_for: Sequence[Any] | None = None) -> Any:
        """Enqueue the kernel (after the queue's earlier commands, and after ``wait_for``'s events
        of other queues); its event counts in the next :meth:`read`'s kernel time."""
        evt = self.kernel(self.queue, global_size, local_size, *args, wait_for=wait_for or None)
        self._events.append(evt)
        return evt

    @property
    def device(self) -> str:
        return describe(self.queue.device)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.KERNEL}, VEC={self.vec}, shape {self.shape.label}, {self.device})"
