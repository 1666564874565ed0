"""Kernel sources and program builds: memoised per context, checked before anything launches.

A build counts only if the program holds the kernel that was asked for and its log does not
say that a vector type changes the calling convention (PoCL builds ``float16`` code for a
CPU whose compiler target lacks AVX-512 with such a warning, and that code may abort the
process at its first launch). Both failures raise :class:`BuildError` with the log.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import re
import warnings
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

from .device import _cl, compiler_words, describe
from .errors import BuildError

__all__ = ["BuildError", "kernel_source", "sources_hash", "build", "kernel", "override_source"]

# what a build log says when a vector width does not fit the target's registers
ABI_WARNING = re.compile(r"changes the ABI", re.IGNORECASE)

BUILD_OPTIONS = ("-cl-mad-enable",)


_OVERRIDES: dict[str, str] = {}


@contextlib.contextmanager
def override_source(name: str, text: str) -> Iterator[None]:
    """Replace ``kernels/<name>`` by ``text`` within the block (for tests of build failures).

    Program, kernel and variant caches are keyed by the source text, so nothing built from
    the real file is reused and nothing built from ``text`` outlives the block's key.
    """
    old = _OVERRIDES.get(name)
    _OVERRIDES[name] = text
    try:
        yield
    finally:
        if old is None:
            _OVERRIDES.pop(name, None)
        else:
            _OVERRIDES[name] = old


def _kernel_dir() -> Path:
    installed = resources.files("clsas") / "kernels"
    if installed.is_dir():
        return Path(str(installed))
    source_tree = Path(__file__).resolve().parents[2] / "kernels"
    if source_tree.is_dir():
        return source_tree
    raise FileNotFoundError("OpenCL kernel sources not found (clsas/kernels or ./kernels)")


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` (or of its override)."""
    if name in _OVERRIDES:
        return _OVERRIDES[name]
    return _read(name)


@functools.cache
def _read(name: str) -> str:
    return (_kernel_dir() / name).read_text()


def sources_hash(files: tuple[str, ...]) -> str:
    """SHA-256 of the concatenated sources and the build options (a cache key)."""
    return _sources_hash(tuple(files), tuple(_OVERRIDES.get(f) for f in files))


@functools.lru_cache(maxsize=256)
def _sources_hash(files: tuple[str, ...], overrides: tuple) -> str:
    """:func:`sources_hash` of ``files`` with these overrides in place (memoised: plans reused per
    call ask for it on every call)."""
    h = hashlib.sha256()
    for f in files:
        h.update(f.encode() + b"\0" + kernel_source(f).encode() + b"\0")
    h.update(" ".join(BUILD_OPTIONS).encode())
    return h.hexdigest()


def _variant(defines: tuple[tuple[str, Any], ...]) -> str:
    return " ".join(f"-D{k}={val}" for k, val in defines) or "no defines"


def _options(defines: tuple[tuple[str, Any], ...], device: Any = None) -> list[str]:
    return [f"-D{k}={val}" for k, val in defines] + list(BUILD_OPTIONS) + device_options(device)


def is_simulator(device: Any) -> bool:
    """Whether ``device`` is the Oclgrind simulator (it interprets kernels, it does not compile them)."""
    return "oclgrind" in device.platform.name.lower()


def device_options(device: Any) -> list[str]:
    """Build options a device needs besides the variant's: Oclgrind's interpreter has no
    ``llvm.sqrt`` intrinsic, so its kernels take the OpenCL ``sqrt`` builtin instead of the
    inlined one (``vsqrt`` in kernels/common.cl; the same square root)."""
    return ["-DCLSAS_OPENCL_SQRT=1"] if device is not None and is_simulator(device) else []


@functools.cache
def _build(ctx: Any, files: tuple[str, ...], defines: tuple[tuple[str, Any], ...], src_hash: str) -> Any:
    cl = _cl()
    src = "\n".join(kernel_source(f) for f in files)
    device = ctx.devices[0]
    prog = cl.Program(ctx, src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyopencl's CompilerWarning: the log is read below
        try:
            prog.build(options=_options(defines, device))
        except cl.RuntimeError as exc:
            text = _log(prog, device) or str(exc)
            raise BuildError(
                files, describe(device), f"{_variant(defines)}: the compiler failed: {compiler_words(text)}", text
            ) from None
    build_log = _log(prog, device)
    if ABI_WARNING.search(build_log):
        raise BuildError(
            files, describe(device),
            f"{_variant(defines)}: the compiler warns that a vector type changes the ABI "
            "(the target lacks registers of that width)", build_log,
        )
    return prog


def _log(prog: Any, device: Any) -> str:
    cl = _cl()
    try:
        return prog.get_build_info(device, cl.program_build_info.LOG) or ""
    except cl.Error:
        return ""


def build(ctx: Any, files: tuple[str, ...], defines: dict[str, Any] | None = None) -> Any:
    """Build (once per context, sources and defines) and return the program.

    Raises :class:`BuildError` if the compiler fails or warns about the vector ABI.
    """
    files = tuple(files)
    return _build(ctx, files, tuple(sorted((defines or {}).items())), sources_hash(files))


@functools.cache
def _kernel(ctx: Any, files: tuple[str, ...], defines: tuple, name: str, src_hash: str) -> Any:
    cl = _cl()
    prog = _build(ctx, files, defines, src_hash)
    names = [n for n in prog.get_info(cl.program_info.KERNEL_NAMES).split(";") if n]
    if name not in names:
        raise BuildError(
            files, describe(ctx.devices[0]),
            f"{_variant(defines)}: the program holds no kernel {name!r} (it holds {names or 'none'})",
            _log(prog, ctx.devices[0]),
        )
    try:
        return cl.Kernel(prog, name)
    except cl.Error as exc:
        raise BuildError(files, describe(ctx.devices[0]), f"{_variant(defines)}: kernel {name!r}: {exc}") from None


def kernel(ctx: Any, files: tuple[str, ...], name: str, defines: dict[str, Any] | None = None) -> Any:
    """The kernel ``name`` of :func:`build`'s program; :class:`BuildError` if it is absent."""
    files = tuple(files)
    return _kernel(ctx, files, tuple(sorted((defines or {}).items())), name, sources_hash(files))
