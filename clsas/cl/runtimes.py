"""OpenCL CPU runtimes installed with pip, made visible to the ICD loader before pyopencl starts.

pyopencl's wheels load OpenCL drivers through an ICD loader that reads the ``.icd`` files of one
folder: ``$OCL_ICD_VENDORS`` if set, else ``/etc/OpenCL/vendors`` (and pyopencl's own folder, which
holds the PoCL and Oclgrind it ships). Intel's CPU runtime for OpenCL comes from PyPI as
``intel-opencl-rt`` (with ``intel-cmplr-lib-rt``), a dependency of clsas on x86-64 Linux, but its
wheel's ``.icd`` file names a build-time placeholder path, so no program sees it.

:func:`register` runs once, before pyopencl is imported (:func:`clsas.cl.device._cl` calls it): it
writes a folder under the clsas cache with an ``.icd`` file naming the installed
``libintelocl.so`` by its full path, plus a copy of every ``.icd`` file of the folder the loader
would have read (so no system driver, GPU or PoCL, disappears), and points ``OCL_ICD_VENDORS`` at
it. The runtime's libraries find each other by their own run path; nothing is preloaded.

Why it is needed: the PoCL 3.0 on PyPI is built with LLVM 14, which does not know CPUs newer than
it (AMD Zen 5 among them) and then compiles nothing (``error: unknown target CPU 'generic'``).
Intel's runtime runs on any x86-64 CPU with SSE4.2, AMD's included.

``CLSAS_PIP_RUNTIMES=0`` turns the registration off (the loader then sees what it saw before).
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Registration", "loader_folders", "pip_runtimes", "current", "register", "registration"]

log = logging.getLogger("clsas.cl")

# (distribution, driver library, distribution of the libraries it links, the one file checked of those)
_PIP_RUNTIMES = (("intel-opencl-rt", "libintelocl.so", "intel-cmplr-lib-rt", "libimf.so"),)


@dataclass(frozen=True)
class PipRuntime:
    """An OpenCL driver found in an installed Python distribution."""

    distribution: str
    version: str
    library: str  # full path of the driver library
    problem: str = ""  # why it cannot be loaded ("" when it can)


@dataclass
class Registration:
    """What :func:`register` did: the runtimes it found, the folder it made, why it made none."""

    runtimes: list[PipRuntime] = field(default_factory=list)
    folder: str = ""  # the OCL_ICD_VENDORS folder written ("" when none)
    loader_folders: list[str] = field(default_factory=list)  # where the loader would have looked without it
    note: str = ""  # why nothing was registered, when nothing was

    def lines(self) -> list[str]:
        """One line per runtime found, for ``clsas devices``."""
        out = []
        for r in self.runtimes:
            state = f"not loadable: {r.problem}" if r.problem else (
                f"registered through {self.folder}" if self.folder else f"not registered ({self.note})")
            out.append(f"{r.distribution} {r.version} ({r.library}): {state}")
        return out


_REGISTRATION: Registration | None = None


def _located(dist, name: str) -> Path | None:
    for f in dist.files or ():
        if f.name == name:
            p = Path(os.path.normpath(dist.locate_file(f)))
            if p.is_file():
                return p
    return None


def pip_runtimes() -> list[PipRuntime]:
    """The OpenCL CPU drivers that installed Python distributions carry (empty if none)."""
    from importlib import metadata

    found = []
    for dist_name, lib_name, deps_name, dep_file in _PIP_RUNTIMES:
        try:
            dist = metadata.distribution(dist_name)
        except metadata.PackageNotFoundError:
            continue
        lib = _located(dist, lib_name)
        if lib is None:
            continue
        problem = ""
        if not (lib.parent / dep_file).is_file():
            try:
                deps = metadata.distribution(deps_name)
                dep = _located(deps, dep_file)
            except metadata.PackageNotFoundError:
                dep = None
            if dep is None:
                problem = f"{dep_file} is missing: pip install {deps_name}"
            elif dep.parent != lib.parent:
                problem = f"{dep_file} is in {dep.parent}, not beside {lib.name} in {lib.parent}"
        found.append(PipRuntime(dist_name, dist.version, str(lib), problem))
    return found


def loader_folders() -> list[Path] | None:
    """The folders of ``.icd`` files the loader would read without clsas, or None where
    ``OCL_ICD_VENDORS`` names one file. ``OCL_ICD_VENDORS`` (a folder) replaces the default, which
    is ``$OPENCL_VENDOR_PATH`` or ``/etc/OpenCL/vendors``; the folder of this Python environment
    and of an active conda environment are read too (a conda-built loader looks there)."""
    env = os.environ.get("OCL_ICD_VENDORS", "").strip()
    if env:
        p = Path(env)
        return [p] if p.is_dir() else None
    folders = [Path(os.environ.get("OPENCL_VENDOR_PATH", "").strip() or "/etc/OpenCL/vendors")]
    for prefix in (sys.prefix, os.environ.get("CONDA_PREFIX", "")):
        if prefix:
            folders.append(Path(prefix) / "etc" / "OpenCL" / "vendors")
    return list(dict.fromkeys(folders))


def _cache_root() -> Path:
    root = os.environ.get("CLSAS_CACHE_DIR")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg:
        return Path(xdg) / "clsas"
    try:
        return Path.home() / ".cache" / "clsas"
    except Exception:  # noqa: BLE001 - no home directory (an arbitrary uid in a container)
        import tempfile

        return Path(tempfile.gettempdir()) / f"clsas-{os.getuid() if hasattr(os, 'getuid') else 'user'}"


def _write_folder(entries: dict[str, str]) -> Path:
    """A folder holding exactly ``entries`` (file name -> one line), named by its content."""
    text = "\n".join(f"{k}={v}" for k, v in sorted(entries.items()))
    folder = _cache_root() / "icd" / hashlib.sha256(text.encode()).hexdigest()[:16]
    if not all((folder / k).is_file() and (folder / k).read_text().strip() == v for k, v in entries.items()):
        folder.mkdir(parents=True, exist_ok=True)
        for k, v in entries.items():
            tmp = folder / f".{k}.{os.getpid()}.tmp"
            tmp.write_text(v + "\n")
            os.replace(tmp, folder / k)
    return folder


def register() -> Registration:
    """Make the pip-installed CPU runtimes visible to the ICD loader (once per process).

    Must run before pyopencl first asks for platforms; after that the loader has read its folder
    and the registration is skipped with a note.
    """
    global _REGISTRATION
    if _REGISTRATION is not None:
        return _REGISTRATION
    reg = Registration()
    _REGISTRATION = reg
    if os.environ.get("CLSAS_PIP_RUNTIMES", "").strip() == "0":
        reg.note = "CLSAS_PIP_RUNTIMES=0"
        return reg
    usable = _usable_runtimes(reg)
    if not usable:
        return reg
    sources = loader_folders()
    if sources is None:
        reg.note = f"OCL_ICD_VENDORS names one file ({os.environ['OCL_ICD_VENDORS']}); left as it is"
        return reg
    reg.loader_folders = [str(f) for f in sources]
    entries = _registered_drivers(sources)
    known = {Path(line).name for line in entries.values()}
    for r in usable:
        if Path(r.library).name not in known:  # else the system registers this driver already
            entries[f"clsas-{r.distribution}.icd"] = r.library
    try:
        folder = _write_folder(entries)
    except OSError as exc:
        reg.note = f"cannot write the ICD folder under {_cache_root()} ({exc})"
        log.warning("%s: %s", ", ".join(r.distribution for r in usable), reg.note)
        return reg
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    reg.folder = str(folder)
    log.debug("OpenCL ICD folder %s (%d drivers)", folder, len(entries))
    return reg


def _usable_runtimes(reg: Registration) -> list:
    """The pip-installed runtimes that can be used (kept in ``reg.runtimes``; each one that cannot
    is logged with why); where none, ``reg.note`` says why."""
    try:
        reg.runtimes = pip_runtimes()
    except Exception as exc:  # noqa: BLE001 - a broken metadata entry must not stop OpenCL use
        reg.note = f"the installed distributions could not be read ({exc})"
        return []
    for r in reg.runtimes:
        if r.problem:
            log.warning("%s %s cannot be used: %s", r.distribution, r.version, r.problem)
    usable = [r for r in reg.runtimes if not r.problem]
    if not usable:
        reg.note = reg.note or "none installed"
    return usable


def _registered_drivers(sources: list[Path]) -> dict[str, str]:
    """``file name -> library`` of the drivers the loader's folders already register, each once (a
    library that is not there, such as the Intel wheel's placeholder, left out)."""
    entries: dict[str, str] = {}
    for folder in sources:
        try:
            files = sorted(folder.glob("*.icd")) if folder.is_dir() else []
        except OSError:
            files = []
        for f in files:
            try:
                line = f.read_text().strip()
            except (OSError, UnicodeDecodeError):
                continue
            if not line or line in entries.values() or (Path(line).is_absolute() and not Path(line).is_file()):
                continue
            name = f.name if f.name not in entries else f"{folder.name}-{len(entries)}-{f.name}"
            entries[name] = line
    return entries


def current() -> Registration | None:
    """What :func:`register` did in this process, or None where it has not run."""
    return _REGISTRATION


def registration() -> Registration:
    """What :func:`register` did in this process (running it if it has not run)."""
    return register()
