"""GPU OpenCL drivers on the machine that no ICD file registers (so no OpenCL program sees them).

pyopencl's wheels load vendors' drivers through an ICD loader that reads the ``.icd`` files in
``$OCL_ICD_VENDORS`` (a folder or one file) or else ``/etc/OpenCL/vendors``. A GPU driver
installed without its ``.icd`` file is invisible there. This happens in containers that mount
NVIDIA's driver libraries but not ``/etc/OpenCL/vendors/nvidia.icd``, as on the project's first GPU
machine. :func:`unregistered_drivers` finds such libraries, and ``clsas devices`` prints the one
line that registers each.
"""

from __future__ import annotations

import os
import shlex
from dataclasses import dataclass
from pathlib import Path

__all__ = ["DRIVERS", "SEARCH_DIRS", "Unregistered", "registered_libraries", "unregistered_drivers", "vendor_dirs"]

# vendor -> the library file names of its OpenCL driver (what its .icd file names)
DRIVERS = {
    "NVIDIA": ("libnvidia-opencl.so.1", "libnvidia-opencl.so"),
    "AMD": ("libamdocl64.so",),
    "Intel GPU": ("libigdrcl.so",),
}
SEARCH_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
               "/usr/local/nvidia/lib64", "/usr/local/nvidia/lib", "/opt/rocm/lib", "/opt/rocm/opencl/lib",
               "/usr/lib/x86_64-linux-gnu/intel-opencl")


@dataclass(frozen=True)
class Unregistered:
    """A driver library found on disk that no ICD file names."""

    vendor: str
    library: str  # its path
    fix: str  # a shell line that registers it (as root)


def vendor_dirs() -> list[Path]:
    """Where the ICD loader looks: ``$OCL_ICD_VENDORS`` (a folder; for a value naming an ``.icd``
    file, that file's folder), else ``/etc/OpenCL/vendors``."""
    from .runtimes import current

    env = os.environ.get("OCL_ICD_VENDORS", "").strip()
    reg = current()
    if reg is not None and reg.folder and env == reg.folder and reg.loader_folders:
        return [Path(reg.loader_folders[0])]  # where the system registers drivers, not clsas's own folder
    if env:
        p = Path(env)
        return [p.parent if p.suffix == ".icd" else p]
    return [Path("/etc/OpenCL/vendors")]


def registered_libraries(dirs: list[Path] | None = None) -> set[str]:
    """The library names (base names) the ``.icd`` files in ``dirs`` register."""
    # drivers named to the loader directly count as registered
    names = {Path(x).name for x in os.environ.get("OCL_ICD_FILENAMES", "").split(":") if x.strip()}
    for d in dirs if dirs is not None else vendor_dirs():
        try:
            files = sorted(d.glob("*.icd"))
        except OSError:
            continue
        for f in files:
            try:
                line = f.read_text().strip()
            except (OSError, UnicodeDecodeError):
                continue
            if line:
                names.add(Path(line).name)
    return names


def unregistered_drivers(search_dirs=None, dirs: list[Path] | None = None) -> list[Unregistered]:
    """GPU OpenCL driver libraries in ``search_dirs`` (default :data:`SEARCH_DIRS`) that no ICD file
    in ``dirs`` (default: where the loader looks) registers, one per vendor, with the line that
    would register each."""
    search_dirs = SEARCH_DIRS if search_dirs is None else search_dirs
    known = registered_libraries(dirs)
    target = (dirs or vendor_dirs())[0]
    out = []
    for vendor, libs in DRIVERS.items():
        if any(lib in known for lib in libs):
            continue
        found = next((Path(d) / lib for lib in libs for d in search_dirs if (Path(d) / lib).is_file()), None)
        if found is not None:
            icd = target / f"{vendor.split()[0].lower()}.icd"
            q = shlex.quote
            out.append(Unregistered(vendor, str(found), f"mkdir -p {q(str(target))} && echo {q(str(found))} > "
                                                        f"{q(str(icd))}"))
    return out
