"""Guards checked before an image is formed: the grid must fit in memory.

A grid a thousand times too fine (``--spacing 1e-9``) must be refused with the numbers and a
spacing that fits, before anything is allocated, not end in the kernel's OOM killer or a
driver's ``INVALID_BUFFER_SIZE``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

from ..physics.geometry import VoxelGrid

__all__ = ["available_memory_bytes", "check_grid", "bytes_per_voxel", "checked_once", "mark_checked"]

log = logging.getLogger(__name__)

# host bytes per voxel while backprojecting: the NumPy twin holds the voxel centres (24), the
# complex128 image (16) and about ten float64 temporaries per measurement (80), plus the
# Image's copy; the OpenCL path holds float32 re/im on the host (8), the complex64 result (8)
# and the Image (16)
_HOST_BYTES = {"numpy": 136, "opencl": 40}
_DEVICE_BYTES = 8  # float32 re and im of the image on the device


def bytes_per_voxel(kind: str) -> int:
    """Host memory one voxel costs while it is backprojected on ``kind`` ("numpy"/"opencl")."""
    return _HOST_BYTES[kind]


def available_memory_bytes() -> int | None:
    """Memory the system can give without swapping (Linux MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _suggest(grid: VoxelGrid, factor: float) -> float:
    """A spacing that shrinks the voxel count by ``factor`` (over the grid's real dimensions)."""
    dims = max(1, sum(n > 1 for n in grid.shape))
    spacing = max(s for s, n in zip(grid.spacing(), grid.shape, strict=True) if n > 1) if dims else 1.0
    return spacing * factor ** (1.0 / dims) * 1.05


def _gb(n: float) -> str:
    return f"{n / 1e9:.3g} GB"


# (grid, kind) pairs already checked by the call this context belongs to (see checked_once)
_CHECKED: ContextVar[tuple] = ContextVar("clsas_grids_checked", default=())


@contextmanager
def checked_once(grid: VoxelGrid, kind: str) -> Iterator[None]:
    """Within the block, :func:`check_grid` of this grid on this backend kind returns at once: the
    caller (a command, ``reconstruct``) checked it before any work, and the stages it calls do not
    check it again. Another grid, or the same one on another kind (a fallback to NumPy), is
    checked as usual."""
    token = _CHECKED.set((*_CHECKED.get(), (grid, kind)))
    try:
        yield
    finally:
        _CHECKED.reset(token)


def mark_checked(grid: VoxelGrid, kind: str) -> None:
    """Record, for the rest of the current context, that ``grid`` on ``kind`` was checked (the command
    line runs each command in a context of its own, so this ends with the command)."""
    _CHECKED.set((*_CHECKED.get(), (grid, kind)))


def check_grid(grid: VoxelGrid, kind: str, device=None, *, force: bool = False) -> None:
    """Refuse ``grid`` if imaging it on ``kind`` would not fit in memory.

    Raises ``ValueError`` naming the voxel count, the memory needed and available, and a
    spacing that fits; ``force=True`` logs a warning instead. Inside :func:`checked_once` for the
    same grid and kind it does nothing (it was checked).
    """
    if any(g is grid and k == kind for g, k in _CHECKED.get()):
        return
    _memory_problems(grid, kind, device, force)


def _memory_problems(grid: VoxelGrid, kind: str, device, force: bool) -> None:
    """The check itself (see :func:`check_grid`)."""
    need = grid.size * bytes_per_voxel(kind)
    problems = []
    avail = available_memory_bytes()
    if avail is not None and need > 0.8 * avail:
        problems.append((f"about {_gb(need)} of host memory ({bytes_per_voxel(kind)} bytes per voxel on "
                         f"{kind}), {_gb(avail)} available (at most 80% of it is used)", need / (0.8 * avail)))
    if kind == "opencl" and device is not None:
        buf = 4 * grid.size  # one of the re/im buffers
        max_alloc = int(device.max_mem_alloc_size)
        total = int(device.global_mem_size)
        if buf > max_alloc:
            problems.append((f"an image buffer of {_gb(buf)} but the device allocates at most {_gb(max_alloc)} "
                             "at once", buf / max_alloc))
        elif _DEVICE_BYTES * grid.size > 0.8 * total:
            problems.append((f"{_gb(_DEVICE_BYTES * grid.size)} of device memory, {_gb(total)} on the device",
                             _DEVICE_BYTES * grid.size / (0.8 * total)))
    if not problems:
        return
    what, factor = max(problems, key=lambda p: p[1])
    shape = " x ".join(map(str, grid.shape))
    msg = (f"grid: {shape} = {grid.size:.3g} voxels needs {what}; a spacing of {_suggest(grid, factor):.3g} m "
           "or more fits (or force=True, --force on the command line, to try anyway)")
    if force:
        log.warning("%s; going on as forced", msg)
        return
    raise ValueError(msg)
