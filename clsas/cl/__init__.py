"""The device layer: device and queue choice, verified kernel variants, builds, plans, fallback.

The only place that imports pyopencl, and it imports nothing of clsas above it. "No OpenCL" is
a normal state: :func:`select` resolves a public function's ``backend`` and ``device`` once
into a :class:`Selection`, NumPy (one warning) where ``backend="auto"`` finds no device; the
Selection is passed down (every function that takes ``backend`` takes one), and
:meth:`Selection.plan` builds an OpenCL plan or, when a kernel cannot be built
(:class:`BuildError`) and ``"auto"`` was asked for, says "run the NumPy twin" with one warning.

- :mod:`.errors`: :class:`OpenCLUnavailable` and :class:`BuildError` (which carries the build log).
- :mod:`.runtimes`: the CPU runtimes installed with pip (Intel's), made visible to the ICD loader
  before pyopencl starts.
- :mod:`.device`: which device (one that builds kernels: :func:`health`), one owner of each
  context and queue, the Selection a call runs on.
- :mod:`.program`: kernel sources, memoised builds that must hold the kernel and carry no
  vector-ABI warning.
- :mod:`.variants`: the vector width per device, verified once in a child process and cached
  on disk (:func:`cache_dir`, :func:`clear_cache`).
- :mod:`.shapes`: the work-group shape (local size, build variant) per device, timed once in a
  child process among candidates that equal the twin, kept on disk (:func:`shapes_dir`).
- :mod:`.fission`: a sub-device of some compute units (Dask workers), a device's copy time.
- :mod:`.plan`: the :class:`Plan` base class; each plan declares its ``KERNEL`` and ``SOURCES``
  and registers them in :data:`KERNELS` when its module is imported.
- :mod:`.trace`: :class:`Tracer`, the kernel and copy times of a call from their profiling events.
"""

from __future__ import annotations

from dataclasses import dataclass

from .device import (
    BACKENDS,
    Health,
    OpenCLUnavailable,
    Selection,
    _cl,
    copy_queue,
    default_backend,
    describe,
    device_info,
    device_kind,
    get_queue,
    health,
    is_cpu,
    resolve_backend,
    select,
    transfer_queue,
)
from .fission import copy_seconds, sub_device_queue
from .plan import DeviceRows, Plan, release_reused, reused, reused_plans
from .program import BuildError, build, kernel, kernel_source, override_source
from .shapes import Shape, Tuning, clear_shapes, shapes_dir
from .trace import Tracer
from .variants import (
    KERNELS,
    KernelSpec,
    Verdict,
    cache_dir,
    candidate_widths,
    check,
    choose,
    clear_cache,
    kernel_spec,
    register_kernel,
    runtime_record,
)

__all__ = [
    "BACKENDS", "BuildError", "DeviceRow", "DeviceRows", "KERNELS", "KernelSpec", "OpenCLUnavailable", "Plan",
    "Selection",
    "Verdict", "build", "cache_dir", "candidate_widths", "check", "choose", "clear_cache", "default_backend",
    "describe", "device_info", "Health", "health", "device_kind", "get_queue", "is_cpu", "kernel", "kernel_source",
    "kernel_spec",
    "copy_queue", "copy_seconds", "list_devices", "override_source", "register_kernel", "release_reused",
    "resolve_backend", "reused", "reused_plans", "runtime_record", "select",
    "Shape", "Tuning", "clear_shapes", "shapes_dir", "sub_device_queue", "transfer_queue", "Tracer",
]


@dataclass(frozen=True)
class DeviceRow:
    index: str  # "P:D", as PYOPENCL_CTX and device= take it
    platform: str
    device: str
    kind: str
    compute_units: int
    global_mem_mib: int
    fp64: bool
    selected: bool
    driver: str = ""
    preferred_vec: int = 0
    platform_version: str = ""
    builds: bool = True  # whether a small kernel builds and runs there (:func:`health`)
    reason: str = ""  # the compiler's or runtime's words where it does not
    fix: str = ""  # what to do then


def list_devices() -> list[DeviceRow]:
    """Every OpenCL device visible to pyopencl (empty if none)."""
    try:
        cl = _cl()
        platforms = cl.get_platforms()
    except Exception:  # noqa: BLE001 - an ICD loader with no platform raises cl.Error
        return []
    try:
        selected = get_queue().device
    except OpenCLUnavailable:
        selected = None
    rows = []
    for i, p in enumerate(platforms):
        for j, d in enumerate(p.get_devices()):
            h = health(d)
            rows.append(
                DeviceRow(
                    f"{i}:{j}", p.name.strip(), d.name.strip(), device_kind(d), d.max_compute_units,
                    d.global_mem_size // 2**20, bool(d.double_fp_config),
                    selected is not None and d.int_ptr == selected.int_ptr,
                    d.driver_version.strip(), int(d.preferred_vector_width_float), p.version.strip(),
                    h.ok, h.reason, h.fix,
                )
            )
    return rows
