"""Kernel variants (vector width VEC) verified per device before they are launched in-process.

Why a subprocess: a variant can build "successfully" and still kill the process at its first
launch (PoCL 3.0 on a Zen 4 CPU: ``LLVM ERROR: Do not know how to scalarize ...``, SIGABRT,
for ``float16`` code compiled for a target without AVX-512). No in-process check can catch an
abort, so each (device, driver, kernel source, kernel, width) is first run once in a child
process on a small input and compared with its NumPy twin; the verdict is kept on disk (see
:func:`cache_dir`) so that the probe runs once per machine and source version.

Order of widths: on CPUs, from the device's preferred float vector width (clipped to 4..16)
down to 4 (16 -> 8 -> 4); on other devices, 4. The first width whose verdict is good is used.
A width is rejected when the child crashes or times out, the build fails or holds no such
kernel, the build log warns that a vector type changes the ABI, or the result differs from
the twin. When every width is rejected, :class:`BuildError` carries every reason and log.

The Oclgrind simulator interprets kernels instead of compiling them to machine code, so it is
not probed in a child; the in-process checks still apply.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from .device import _cl, describe
from .program import BuildError, is_simulator, kernel, kernel_source, sources_hash

__all__ = [
    "KERNELS", "KernelSpec", "Verdict", "cache_dir", "candidate_widths", "check", "choose", "clear_cache",
    "kernel_spec", "register_kernel", "runtime_record",
]

log = logging.getLogger("clsas.cl.variants")



@dataclass(frozen=True)
class KernelSpec:
    """A kernel as its plan declares it: the sources it is built from, and the plan class
    (module and qualified name) whose ``selftest(queue, vec)`` the probe runs."""

    name: str
    sources: tuple[str, ...]
    module: str
    qualname: str


# kernel name -> KernelSpec, filled by each Plan subclass that names a KERNEL when its module
# is imported (see clsas.cl.plan.Plan); this layer names none of them itself
KERNELS: dict[str, KernelSpec] = {}


def register_kernel(name: str, sources: tuple[str, ...], module: str, qualname: str) -> KernelSpec:
    """Record that the plan ``module.qualname`` runs kernel ``name`` built from ``sources``.

    Called by :class:`clsas.cl.Plan` for each subclass that sets ``KERNEL``; a second class
    claiming the same kernel is a ``ValueError`` (re-importing the same class is not).
    """
    if not name or not isinstance(name, str):
        raise ValueError(f"kernel name must be a non-empty string, got {name!r}")
    if not sources or not all(isinstance(f, str) and f for f in sources):
        raise ValueError(f"kernel {name!r}: sources must be file names under kernels/, got {sources!r}")
    spec = KernelSpec(name, tuple(sources), module, qualname)
    old = KERNELS.get(name)
    if old is not None and (old.module, old.qualname) != (module, qualname):
        raise ValueError(f"kernel {name!r} is already run by {old.module}.{old.qualname}")
    KERNELS[name] = spec
    return spec


def kernel_spec(name: str) -> KernelSpec:
    """The registered :class:`KernelSpec` of kernel ``name`` (``ValueError`` names the known ones)."""
    try:
        return KERNELS[name]
    except KeyError:
        raise ValueError(f"unknown kernel {name!r}; registered: {sorted(KERNELS)} (a Plan subclass registers "
                         "its KERNEL when its module is imported)") from None


WIDTHS = (16, 8, 4)
PROBE_TIMEOUT_S = 300.0
FORMAT = 1

# set by the probe process itself: it runs the in-process checks only (no nested probes)
_IN_PROBE = False


@dataclass(frozen=True)
class Verdict:
    """Whether a kernel variant may run on a device, and why not."""

    ok: bool
    reason: str = ""
    log: str = ""
    source: str = "probe"  # "probe", "cache", "in-process"


def cache_dir() -> Path:
    """Where verdicts are kept: ``$CLSAS_CACHE_DIR``, else ``$XDG_CACHE_HOME/clsas``, else
    ``~/.cache/clsas``; verdicts are the ``variants/*.json`` files in it."""
    root = os.environ.get("CLSAS_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = str(Path(xdg) / "clsas") if xdg else str(Path.home() / ".cache" / "clsas")
    return Path(root) / "variants"


def clear_cache() -> int:
    """Delete every stored verdict (and forget this process's); returns how many files went."""
    _MEMO.clear()
    d = cache_dir()
    n = 0
    if d.is_dir():
        for f in d.glob("*.json"):
            f.unlink(missing_ok=True)
            n += 1
    return n


def candidate_widths(device: Any) -> list[int]:
    """Widths to try, widest first: CPUs from their preferred float width down to 4, else 4."""
    cl = _cl()
    if device.type & cl.device_type.CPU:
        pref = int(device.preferred_vector_width_float or 4)
        return [w for w in WIDTHS if w <= max(4, pref)]
    return [4]


_IDENTITIES: dict[int, dict] = {}


def device_identity(device: Any) -> dict:
    """What names a device for the stored verdicts and calibrations (its platform, name, versions,
    driver, pyopencl's version); asked of the driver once per device (ten queries, about half a
    millisecond, were a sixth of ``formation="auto"``'s choosing on small scans)."""
    key = getattr(device, "int_ptr", None)
    if key is None or key not in _IDENTITIES:
        p = device.platform
        ident = {
            "platform": p.name.strip(), "platform_version": p.version.strip(), "device": device.name.strip(),
            "device_version": device.version.strip(), "driver": device.driver_version.strip(),
            "pyopencl": _cl().VERSION_TEXT,
        }
        if key is None:
            return ident
        _IDENTITIES[key] = ident
    return dict(_IDENTITIES[key])


@functools.cache
def _plan_code_hash(module: str) -> str:
    """Hash of the plan module (it launches the kernel and holds the probe's selftest)."""
    spec = importlib.util.find_spec(module)
    try:
        return hashlib.sha256(Path(spec.origin).read_bytes()).hexdigest()
    except (AttributeError, TypeError, OSError):
        return "unknown"


def _key(device: Any, name: str, vec: int) -> tuple[str, dict]:
    spec = kernel_spec(name)
    ident = {
        **device_identity(device), "kernel": name, "vec": vec, "sources": sources_hash(spec.sources),
        "plan_code": _plan_code_hash(spec.module), "format": FORMAT,
    }
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:32]
    return digest, ident


_MEMO: dict[str, Verdict] = {}


def _load(digest: str) -> Verdict | None:
    path = cache_dir() / f"{digest}.json"
    try:
        data = json.loads(path.read_text())
        return Verdict(bool(data["ok"]), data.get("reason", ""), data.get("log", ""), "cache")
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _store(digest: str, ident: dict, verdict: Verdict) -> None:
    d = cache_dir()
    try:
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{digest}.{os.getpid()}.tmp"
        tmp.write_text(json.dumps({**ident, **asdict(verdict), "when": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=1))
        os.replace(tmp, d / f"{digest}.json")
    except OSError as exc:
        log.warning("cannot store the kernel-variant verdict in %s (%s): it will be probed again next time", d, exc)


def _probe_command() -> list[str]:
    return [sys.executable, "-m", "clsas.cl.probe"]


def _run_probe(device: Any, name: str, vec: int) -> tuple[Verdict, bool]:
    """Run the variant in a child process; returns the verdict and whether it is definitive."""
    kspec = kernel_spec(name)
    spec = {
        "platform": device.platform.name, "platform_version": device.platform.version, "device": device.name,
        "kernel": name, "vec": vec,
        "module": kspec.module, "qualname": kspec.qualname, "sources": {f: kernel_source(f) for f in kspec.sources},
    }
    env = dict(os.environ)
    pkg_root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = pkg_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("PYOPENCL_CTX", None)
    t0 = time.perf_counter()
    log.info("checking kernel %s at VEC=%d on %s in a child process (once; verdict kept in %s)", name, vec,
             describe(device), cache_dir())
    try:
        res = subprocess.run(
            _probe_command(), input=json.dumps(spec), capture_output=True, text=True, env=env, timeout=PROBE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        return Verdict(False, f"VEC={vec}: the probe did not finish in {PROBE_TIMEOUT_S:.0f} s"), False
    except OSError as exc:
        return Verdict(False, f"VEC={vec}: the probe could not start ({exc})"), False
    log.debug("probe of %s VEC=%d took %.1f s: exit %d", name, vec, time.perf_counter() - t0, res.returncode)
    tail = (res.stderr or "")[-4000:]
    if res.returncode < 0:
        try:
            sig = signal.Signals(-res.returncode).name
        except ValueError:
            sig = f"signal {-res.returncode}"
        return Verdict(False, f"VEC={vec}: the first launch killed the probe process ({sig})", tail), True
    report = None
    for line in reversed((res.stdout or "").splitlines()):
        if line.startswith("{"):
            try:
                report = json.loads(line)
                break
            except ValueError:
                continue
    if report is None:
        # no verdict printed: a crash inside the runtime (abort() via exit codes such as 134) or a
        # broken environment; a runtime crash is definitive, an import failure is not
        definitive = res.returncode >= 128 or "LLVM ERROR" in tail
        return Verdict(False, f"VEC={vec}: the probe exited with status {res.returncode} and no verdict", tail), \
            definitive
    verdict = Verdict(bool(report["ok"]), str(report.get("reason", "")), str(report.get("log", "")) or tail)
    return verdict, bool(report.get("definitive", True))


def check(queue: Any, name: str, vec: int) -> Verdict:
    """Verdict for kernel ``name`` at width ``vec`` on the queue's device (memoised, cached on disk)."""
    spec = kernel_spec(name)
    if vec not in WIDTHS:
        raise ValueError(f"vec must be one of {WIDTHS}, got {vec!r}")
    device = queue.device
    digest, ident = _key(device, name, vec)
    if digest in _MEMO:
        return _MEMO[digest]
    verdict = None
    if not (_IN_PROBE or is_simulator(device)):
        verdict = _load(digest)
        if verdict is None:
            verdict, definitive = _run_probe(device, name, vec)
            if definitive:
                _store(digest, ident, verdict)
    if verdict is None or verdict.ok:
        # the in-process checks: the build holds the kernel, the log has no vector-ABI warning
        try:
            kernel(queue.context, spec.sources, name, {"VEC": vec})
            verdict = verdict or Verdict(True, f"VEC={vec}: built in-process (a simulator: not probed)",
                                         source="in-process")
        except BuildError as exc:
            verdict = Verdict(False, exc.reason, exc.log, "in-process")
    if not verdict.ok:
        log.info("kernel %s at VEC=%d rejected on %s: %s", name, vec, describe(device), verdict.reason)
    _MEMO[digest] = verdict
    return verdict


# (device int_ptr, kernel) -> the width chosen for it in this process
_CHOSEN: dict[tuple[int, str], int] = {}
# (device int_ptr, kernel) -> the label of the work-group shape tuned for it in this process (.shapes)
CHOSEN_SHAPES: dict[tuple[int, str], str] = {}


def runtime_record(queue: Any) -> dict:
    """The OpenCL runtime a result came from, for provenance and benchmarks: platform and its
    version, device, driver, and the vector width and the tuned work-group shape
    (:mod:`.shapes`, as its label) chosen for each kernel run on it so far."""
    device = queue.device
    ident = device_identity(device)
    kernels = {k: w for (ptr, k), w in sorted(_CHOSEN.items(), key=lambda kv: kv[0][1]) if ptr == device.int_ptr}
    shapes = {k: s for (ptr, k), s in sorted(CHOSEN_SHAPES.items(), key=lambda kv: kv[0][1]) if ptr == device.int_ptr}
    return {"platform": ident["platform"], "platform_version": ident["platform_version"], "device": ident["device"],
            "driver": ident["driver"], "kernels_vec": kernels, "kernels_shape": shapes}


def choose(queue: Any, name: str, vec: int | None = None) -> int:
    """The width to build ``name`` with on this queue's device.

    ``vec`` given: that width, if its verdict is good, else :class:`BuildError` (a variant is
    never launched blind). ``vec`` None: the widest good one of :func:`candidate_widths`.
    """
    kernel_spec(name)  # an unknown kernel is a ValueError before anything is probed
    device = queue.device
    widths = [vec] if vec is not None else candidate_widths(device)
    rejected = []
    for w in widths:
        verdict = check(queue, name, w)
        if verdict.ok:
            _CHOSEN[(device.int_ptr, name)] = w
            if rejected:
                log.info("kernel %s on %s: VEC=%d (wider rejected)", name, describe(device), w)
            return w
        rejected.append(verdict)
    files = kernel_spec(name).sources
    if vec is not None:
        raise BuildError(files, describe(device), rejected[0].reason, rejected[0].log)
    reasons = "; ".join(r.reason for r in rejected)
    logs = "\n".join(f"[{r.reason}]\n{r.log.strip()}" for r in rejected if r.log.strip())
    raise BuildError(files, describe(device), f"no usable variant of {name!r} ({reasons})", logs)
