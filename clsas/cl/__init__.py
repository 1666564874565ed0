"""OpenCL device choice, program build and cache: the only place that imports pyopencl.

"No OpenCL" is a normal state: :func:`get_queue` raises :class:`OpenCLUnavailable`, and the
dispatchers fall back to the NumPy twins when the backend is ``"auto"``.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

__all__ = [
    "OpenCLUnavailable",
    "BuildError",
    "resolve_backend",
    "get_queue",
    "build",
    "kernel",
    "list_devices",
    "kernel_source",
    "device_info",
]

log = logging.getLogger(__name__)

BACKENDS = ("auto", "opencl", "numpy")


class OpenCLUnavailable(RuntimeError):
    """No usable OpenCL platform or device."""


class BuildError(RuntimeError):
    """An OpenCL program failed to build; ``.log`` holds the compiler's build log."""

    def __init__(self, files: tuple[str, ...], device: str, build_log: str):
        self.log = build_log
        super().__init__(f"building {', '.join(files)} for {device} failed:\n{build_log}")


def _cl():
    try:
        import pyopencl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise OpenCLUnavailable(
            "pyopencl is not installed: pip install 'pyopencl[pocl]' for the PoCL CPU device"
        ) from exc
    return pyopencl


def _score(device: Any) -> int:
    """Preference when PYOPENCL_CTX is not set: GPUs, then PoCL's CPU, then other CPUs."""
    cl = _cl()
    plat = device.platform.name
    if "Oclgrind" in plat:
        return -1  # a debugging simulator: only when asked for by PYOPENCL_CTX
    if device.type & cl.device_type.GPU:
        return 3
    if "Portable Computing Language" in plat:
        return 2
    return 1


@functools.cache
def _context_and_queue() -> tuple[Any, Any]:
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise OpenCLUnavailable(f"no OpenCL platform found ({exc})") from None
    if os.environ.get("PYOPENCL_CTX"):
        try:
            ctx = cl.create_some_context(interactive=False)
        except Exception as exc:  # noqa: BLE001 - pyopencl raises assorted types here
            raise OpenCLUnavailable(
                f"PYOPENCL_CTX={os.environ['PYOPENCL_CTX']!r} selects no device ({exc})"
            ) from None
    else:
        devices = [d for p in platforms for d in p.get_devices()]
        devices = [d for d in devices if _score(d) >= 0]
        if not devices:
            raise OpenCLUnavailable("no OpenCL device found (install pyopencl[pocl])")
        best = max(devices, key=_score)
        ctx = cl.Context([best])
    queue = cl.CommandQueue(ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
    dev = ctx.devices[0]
    log.info("OpenCL device: %s on %s", dev.name.strip(), dev.platform.name.strip())
    return ctx, queue


def get_queue() -> Any:
    """The shared profiling-enabled command queue (created on first use)."""
    return _context_and_queue()[1]


def device_info(queue: Any | None = None) -> str:
    """'<device> on <platform>' for the queue's device."""
    q = queue or get_queue()
    d = q.device
    return f"{d.name.strip()} on {d.platform.name.strip()}"


def resolve_backend(backend: str | None) -> str:
    """Turn ``backend`` into ``"opencl"`` or ``"numpy"``.

    ``None`` reads ``CLSAS_BACKEND`` (default ``"auto"``). ``"auto"`` picks OpenCL where a
    device exists, else NumPy with one log line; ``"opencl"`` raises where there is none.
    """
    if backend is None:
        backend = os.environ.get("CLSAS_BACKEND", "auto") or "auto"
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numpy":
        return "numpy"
    try:
        get_queue()
    except OpenCLUnavailable as exc:
        if backend == "opencl":
            raise OpenCLUnavailable(f"backend='opencl' was requested but {exc}") from None
        _warn_fallback(str(exc))
        return "numpy"
    return "opencl"


@functools.cache
def _warn_fallback(reason: str) -> None:
    log.warning("no OpenCL device (%s): using the NumPy backend", reason)


def _kernel_dir() -> Path:
    installed = resources.files("clsas") / "kernels"
    if installed.is_dir():
        return Path(str(installed))
    source_tree = Path(__file__).resolve().parents[2] / "kernels"
    if source_tree.is_dir():
        return source_tree
    raise FileNotFoundError("OpenCL kernel sources not found (clsas/kernels or ./kernels)")


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>``."""
    return (_kernel_dir() / name).read_text()


@functools.cache
def _build(ctx: Any, files: tuple[str, ...], defines: tuple[tuple[str, Any], ...]) -> Any:
    cl = _cl()
    src = "\n".join(kernel_source(f) for f in files)
    opts = [f"-D{k}={val}" for k, val in defines] + ["-cl-mad-enable"]
    prog = cl.Program(ctx, src)
    try:
        return prog.build(options=opts)
    except cl.RuntimeError as exc:
        dev = ctx.devices[0].name.strip()
        raise BuildError(files, dev, str(exc)) from None


def build(ctx: Any, files: tuple[str, ...], defines: dict[str, Any] | None = None) -> Any:
    """Build (once per context, files and defines) and return the program."""
    return _build(ctx, tuple(files), tuple(sorted((defines or {}).items())))


@functools.cache
def _kernel(ctx: Any, files: tuple[str, ...], defines: tuple, name: str) -> Any:
    return _cl().Kernel(_build(ctx, files, defines), name)


def kernel(ctx: Any, files: tuple[str, ...], name: str, defines: dict[str, Any] | None = None) -> Any:
    """The kernel ``name`` from :func:`build`, retrieved once per context and variant."""
    return _kernel(ctx, tuple(files), tuple(sorted((defines or {}).items())), name)


@dataclass(frozen=True)
class DeviceRow:
    platform: str
    device: str
    kind: str
    compute_units: int
    global_mem_mib: int
    fp64: bool
    selected: bool


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
    for p in platforms:
        for d in p.get_devices():
            rows.append(
                DeviceRow(
                    p.name.strip(),
                    d.name.strip(),
                    cl.device_type.to_string(d.type),
                    d.max_compute_units,
                    d.global_mem_size // 2**20,
                    bool(d.double_fp_config),
                    selected is not None and d.int_ptr == selected.int_ptr,
                )
            )
    return rows
