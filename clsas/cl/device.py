"""Device and queue choice, and the backend a public function runs on.

"No OpenCL" is a normal state: :func:`get_queue` raises :class:`OpenCLUnavailable`, and
:func:`select` turns ``backend`` and ``device`` into a :class:`Selection` that either holds a
queue or says "NumPy", with one warning when ``"auto"`` had to fall back.
"""

from __future__ import annotations

import functools
import logging
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from .errors import BuildError, OpenCLUnavailable

log = logging.getLogger("clsas.cl")

BACKENDS = ("auto", "opencl", "numpy")


def _cl():
    """pyopencl, imported after the pip-installed CPU runtimes are registered (:mod:`.runtimes`)."""
    from .runtimes import register

    register()  # once per process; the ICD loader reads its folder at the first platform query
    try:
        import pyopencl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise OpenCLUnavailable(
            "pyopencl is not installed: pip install 'pyopencl[pocl]' for the PoCL CPU device"
        ) from exc
    return pyopencl


def _score(device: Any) -> int:
    """Preference when no device is named: GPUs, then Intel's CPU runtime, then PoCL's CPU, then
    other CPUs; never the Oclgrind simulator. The chosen device must also build kernels
    (:func:`health`)."""
    cl = _cl()
    plat = device.platform.name.strip()
    if "Oclgrind" in plat:
        return -1  # a debugging simulator: only when asked for by name
    if device.type & cl.device_type.GPU:
        return 4
    if plat.startswith("Intel(R) OpenCL") and device.type & cl.device_type.CPU:
        return 3
    if "Portable Computing Language" in plat:
        return 2
    return 1


def _platforms() -> list:
    cl = _cl()
    try:
        return cl.get_platforms()
    except cl.Error as exc:
        raise OpenCLUnavailable(f"no OpenCL platform found ({exc})") from None


def _by_numbers(spec: str, what: str) -> Any:
    """The device ``"P:D"`` (platform and device numbers, as in ``PYOPENCL_CTX``)."""
    platforms = _platforms()
    parts = spec.split(":")
    try:
        p = int(parts[0]) if parts[0] else 0
        d = int(parts[1]) if len(parts) > 1 and parts[1] else 0
    except ValueError:
        raise OpenCLUnavailable(f"{what}={spec!r} is not 'P:D' (platform:device numbers, see clsas devices)") from None
    if not 0 <= p < len(platforms):
        raise OpenCLUnavailable(f"{what}={spec!r}: there are {len(platforms)} OpenCL platform(s)")
    devices = platforms[p].get_devices()
    if not 0 <= d < len(devices):
        raise OpenCLUnavailable(f"{what}={spec!r}: platform {p} has {len(devices)} device(s)")
    return devices[d]


def _default_device() -> Any:
    env = os.environ.get("PYOPENCL_CTX")
    if env:
        return _by_numbers(env, "PYOPENCL_CTX")
    devices = sorted((d for p in _platforms() for d in p.get_devices() if _score(d) >= 0), key=_score, reverse=True)
    if not devices:
        raise OpenCLUnavailable(f"no OpenCL device found; {FIX_CPU}")
    refused = []
    for d in devices:
        if health(d).ok:
            if refused:
                log.info("OpenCL: %s chosen (%s build no kernel)", describe(d), ", ".join(map(describe, refused)))
            return d
        refused.append(d)
    raise OpenCLUnavailable("no OpenCL device builds kernels: " + "; ".join(
        f"{describe(d)}: {health(d).reason}. Fix: {health(d).fix}" for d in refused))


@dataclass(frozen=True)
class Health:
    """Whether a device builds and runs kernels (a small kernel, built and launched once per process).

    ``reason`` gives the compiler's (or runtime's) own words where it fails, ``fix`` what to do.
    """

    ok: bool
    reason: str = ""
    fix: str = ""


CANARY = """__kernel void clsas_canary(__global float *x) {
    size_t i = get_global_id(0);
    x[i] = mad(2.0f, x[i], 1.0f);
}"""

_HEALTH: dict[int, Health] = {}
_ANNOUNCED: set[int] = set()


def health(device: Any) -> Health:
    """Whether ``device`` compiles and runs a small kernel (asked once per device and process).

    A device whose compiler cannot target the machine fails here, before any real kernel is
    tried, with the compiler's words and the fix: the PoCL 3.0 on PyPI (LLVM 14) on CPUs newer
    than its LLVM says ``unknown target CPU 'generic'``.
    """
    key = device.int_ptr
    if key not in _HEALTH:
        _HEALTH[key] = _try_canary(device)
        if not _HEALTH[key].ok:
            log.info("OpenCL: %s builds no kernel: %s", describe(device), _HEALTH[key].reason)
    return _HEALTH[key]


def _try_canary(device: Any) -> Health:
    import numpy as np

    cl = _cl()
    try:
        queue = _queue_for(device.int_ptr)
        prog = cl.Program(queue.context, CANARY)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pyopencl's CompilerWarning
            try:
                prog.build()
            except cl.RuntimeError as exc:
                try:
                    text = prog.get_build_info(device, cl.program_build_info.LOG) or str(exc)
                except cl.Error:
                    text = str(exc)
                return Health(False, f"the compiler failed: {compiler_words(text)}", fix_for(device, text))
        x = np.arange(64, dtype=np.float32)
        buf = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
        prog.clsas_canary(queue, (64,), None, buf)
        out = np.empty_like(x)
        cl.enqueue_copy(queue, out, buf).wait()
    except Exception as exc:  # noqa: BLE001 - any failure of the runtime is the verdict
        text = f"{type(exc).__name__}: {exc}"
        return Health(False, f"the runtime failed: {compiler_words(text)}", fix_for(device, text))
    if not np.array_equal(out, 2 * x + 1):
        return Health(False, "a kernel computing 2x+1 gave wrong numbers", fix_for(device, ""))
    return Health(True)


def compiler_words(log_text: str, lines: int = 2) -> str:
    """The first lines of a build log that say what went wrong (lines naming an error first)."""
    rows = [r.strip() for r in str(log_text).splitlines() if r.strip()]
    errors = [r for r in rows if "error" in r.lower()]
    picked = (errors or rows)[:lines]
    return " | ".join(picked) if picked else "(no build log)"


FIX_CPU = ("install Intel's CPU runtime for OpenCL (pip install intel-opencl-rt intel-cmplr-lib-rt; clsas "
           "registers it itself) or a newer PoCL (Debian/Ubuntu: apt-get install pocl-opencl-icd)")


def fix_for(device: Any, log_text: str) -> str:
    """What to do about a device that builds no kernel."""
    plat = device.platform
    if "unknown target CPU" in log_text:
        return f"the compiler of {plat.name.strip()} ({plat.version.strip()}) does not know this CPU; {FIX_CPU}"
    if device.type & _cl().device_type.CPU:
        return FIX_CPU
    return f"update the OpenCL driver of {plat.name.strip()}, or use a CPU runtime: {FIX_CPU}"


# queue int_ptr -> the context it was made in: the one owner of every context this layer makes.
# Some runtimes' queues do not keep their context alive (Intel's CPU runtime: a queue whose
# context object was collected answers INVALID_CONTEXT), so the context lives as long as its queue.
_CONTEXTS: dict[int, Any] = {}


def make_queue(device: Any, sub_device: bool = False) -> Any:
    """A profiling-enabled queue on ``device`` in a new context that this module keeps alive.

    ``sub_device``: name the device on the queue too (PoCL 3.0 lists a sub-device's parent as its
    context's device, and a queue made without naming the device then runs on every core).
    """
    cl = _cl()
    ctx = cl.Context([device])
    props = cl.command_queue_properties.PROFILING_ENABLE
    queue = cl.CommandQueue(ctx, device=device, properties=props) if sub_device else \
        cl.CommandQueue(ctx, properties=props)
    _CONTEXTS[queue.int_ptr] = ctx
    return queue


# queue.int_ptr -> (queue, its copy queue): the queue is held so that its pointer is not reused
_COPY_QUEUES: dict[int, tuple] = {}


def copy_queue(queue: Any) -> Any:
    """A second profiling-enabled queue on ``queue``'s context and device (one per queue, made on
    first use), for transfers that overlap the kernels of ``queue``: a command on it runs
    beside those of ``queue``, ordered with them only by the events it waits for."""
    held = _COPY_QUEUES.get(queue.int_ptr)
    if held is not None and held[0] is queue:
        return held[1]
    cl = _cl()
    copy = cl.CommandQueue(queue.context, device=queue.device,
                           properties=cl.command_queue_properties.PROFILING_ENABLE)
    _COPY_QUEUES[queue.int_ptr] = (queue, copy)
    return copy


def transfer_queue(queue: Any) -> Any:
    """The queue that reads results back beside ``queue``'s kernels: on a CPU device ``queue``
    itself (a transfer there is a copy by the cores that run the kernels; read without
    blocking, in order between two launches, it lets the host take one result while the next
    kernels run, and a second queue only adds the runtimes' cross-queue waits: Intel's CPU
    runtime ran such a read only after the next kernel had ended), elsewhere
    :func:`copy_queue` (a GPU copies beside its kernels)."""
    return queue if is_cpu(queue.device) else copy_queue(queue)


@functools.cache
def _queue_for(device_ptr: int) -> Any:
    device = next(d for p in _platforms() for d in p.get_devices() if d.int_ptr == device_ptr)
    queue = make_queue(device)
    log.debug("OpenCL queue on %s", describe(device))
    return queue


def get_queue(device: Any = None) -> Any:
    """A profiling-enabled command queue (one per device, created on first use).

    Parameters
    ----------
    device : None, str, pyopencl.Device or pyopencl.CommandQueue
        ``None``: ``PYOPENCL_CTX`` if set, else the preferred device (a GPU, then PoCL's CPU,
        then any CPU; never the Oclgrind simulator). ``"P:D"``: platform and device numbers as
        ``clsas devices`` lists them. A ``Device`` gets its own queue; a ``CommandQueue`` is used
        as it is (it must have profiling enabled for kernel timings).
    """
    cl = _cl()
    if isinstance(device, cl.CommandQueue):
        return device
    if device is None:
        device = _default_device()
        if device.int_ptr not in _ANNOUNCED:
            _ANNOUNCED.add(device.int_ptr)
            log.info("OpenCL device: %s", describe(device))
    elif isinstance(device, str):
        device = _by_numbers(device, "device")
    elif not isinstance(device, cl.Device):
        raise TypeError(
            "device must be None, 'P:D', a pyopencl.Device or a pyopencl.CommandQueue, "
            f"got {type(device).__name__}"
        )
    return _queue_for(device.int_ptr)


def describe(device: Any) -> str:
    """'<device> on <platform>'."""
    return f"{device.name.strip()} on {device.platform.name.strip()}"


def device_info(queue: Any | None = None) -> str:
    """'<device> on <platform>' for the queue's device."""
    return describe((queue or get_queue()).device)


def device_kind(device: Any) -> str:
    """``"GPU"``, ``"CPU"``, ``"ACCELERATOR"``, ``"CUSTOM"`` (joined by ``+``), or ``"OTHER"``."""
    cl = _cl()
    names = [n for n in ("GPU", "CPU", "ACCELERATOR", "CUSTOM") if device.type & getattr(cl.device_type, n, 0)]
    return "+".join(names) or "OTHER"


def is_cpu(device: Any) -> bool:
    """Whether ``device`` (a ``pyopencl.Device``) is a CPU."""
    return bool(device.type & _cl().device_type.CPU)


def default_backend(backend: str | None) -> str:
    """``backend``, or ``CLSAS_BACKEND`` (default ``"auto"``) where it is None; checked."""
    if backend is None:
        backend = os.environ.get("CLSAS_BACKEND", "").strip() or "auto"
        if backend not in BACKENDS:
            raise ValueError(f"CLSAS_BACKEND must be one of {BACKENDS}, got {backend!r}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend


P = TypeVar("P")


@dataclass(frozen=True)
class Selection:
    """Where a call runs, resolved once at the public boundary and passed down.

    ``kind`` is ``"opencl"`` (with ``queue``) or ``"numpy"``; ``requested`` is what the caller
    asked for (``"auto"``, ``"opencl"`` or ``"numpy"``) and travels with it, so that a kernel
    that will not build deep inside a call still falls back (``"auto"``) or raises
    (``"opencl"``) as the caller asked. Every function that takes ``backend`` also takes a
    Selection there (see :func:`select`); :meth:`plan` builds an OpenCL plan or says "run the
    NumPy twin".

    Parameters
    ----------
    kind : {"opencl", "numpy"}
        Where the call runs.
    requested : {"auto", "opencl", "numpy"}
        What the caller asked for.
    queue : pyopencl.CommandQueue, optional
        The device's queue (with ``kind="opencl"``).

    Examples
    --------
    Resolve once, hand the Selection to every call:

    >>> import numpy as np
    >>> import clsas
    >>> from clsas.cl import select
    >>> sel = select("auto")
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, 96e3)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(2, 2, 0.1, 0.1), chirp, 96e3)
    >>> profiles = clsas.compress(data, backend=sel)
    """

    kind: str
    requested: str
    queue: Any = None

    @property
    def opencl(self) -> bool:
        """Whether calls run on the OpenCL device."""
        return self.kind == "opencl"

    @property
    def device(self) -> str:
        """'<device> on <platform>', or ``"NumPy (float64)"``."""
        return device_info(self.queue) if self.opencl else "NumPy (float64)"

    @property
    def cl_device(self) -> Any:
        """The ``pyopencl.Device`` (for its memory limits), or None on NumPy."""
        return self.queue.device if self.opencl else None

    def fall_back(self, exc: Exception) -> Selection:
        """After a failed kernel build (``BuildError``): NumPy with one warning, or raise.

        ``requested="opencl"`` re-raises ``exc`` (its message carries the compiler log);
        otherwise the warning names the device and the first line of the reason, once per
        process and reason.
        """
        if self.requested == "opencl":
            raise exc
        text = _first_line(exc)
        if self.queue is not None and device_info(self.queue) not in text:
            text = f"{device_info(self.queue)}: {text}"
        _warn_once(f"{text}: using the NumPy backend")
        return Selection("numpy", self.requested)

    def plan(self, factory: Callable[[Any], P]) -> tuple[P | None, Selection]:
        """Build an OpenCL plan here, or say that its NumPy twin runs.

        Parameters
        ----------
        factory : callable(queue) -> plan
            Builds the plan on this selection's queue (a :class:`~clsas.cl.Plan` or anything
            whose construction raises :class:`~clsas.cl.BuildError` when a kernel will not build).

        Returns
        -------
        (plan, selection)
            ``(plan, self)`` when it builds; ``(None, self)`` on NumPy; ``(None, NumPy
            selection)`` after a :class:`~clsas.cl.BuildError` with ``requested="auto"`` (one
            warning, see :meth:`fall_back`). With ``requested="opencl"`` the BuildError is raised.
        """
        if not self.opencl:
            return None, self
        try:
            return factory(self.queue), self
        except BuildError as exc:
            return None, self.fall_back(exc)


def select(backend: str | Selection | None = None, device: Any = None) -> Selection:
    """Resolve ``backend`` (None reads ``CLSAS_BACKEND``) and ``device`` into a Selection.

    ``"auto"`` picks OpenCL where a device exists, else NumPy with one warning naming the
    reason; ``"opencl"`` raises :class:`OpenCLUnavailable` where there is none. A Selection
    is returned as it is (its request kept), so a function may be handed either the request
    or what the public boundary resolved; ``device`` must then be None or its own queue.

    Parameters
    ----------
    backend : {"auto", "opencl", "numpy"}, Selection or None
        The request; None reads ``$CLSAS_BACKEND`` (default ``"auto"``).
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
        The OpenCL device (default: ``PYOPENCL_CTX``, else the preferred one).

    Returns
    -------
    Selection

    Examples
    --------
    >>> from clsas.cl import select
    >>> sel = select("numpy")
    >>> sel.kind, sel.requested
    ('numpy', 'numpy')
    >>> select(sel) is sel                       # a Selection is passed down as it is
    True
    """
    if isinstance(backend, Selection):
        if device is not None and device is not backend.queue:
            raise ValueError("device: a resolved clsas.cl.Selection carries its device; give device=None with it")
        return backend
    backend = default_backend(backend)
    if backend == "numpy":
        return Selection("numpy", backend)
    try:
        queue = get_queue(device)
    except OpenCLUnavailable as exc:
        if backend == "opencl":
            raise OpenCLUnavailable(f"backend='opencl' was requested but {exc}") from None
        _warn_once(f"no OpenCL device ({exc}): using the NumPy backend")
        return Selection("numpy", backend)
    return Selection("opencl", backend, queue)


def resolve_backend(backend: str | Selection | None, device: Any = None) -> str:
    """``"opencl"`` or ``"numpy"``: the kind :func:`select` picks."""
    return select(backend, device).kind


def _first_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


@functools.cache
def _warn_once(message: str) -> None:
    log.warning("%s", message)
