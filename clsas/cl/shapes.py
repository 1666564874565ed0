"""Work-group shapes (local size and build variant) per device: timed once, checked against the twin, kept on disk.

A plan class that declares ``SHAPES = True`` gets its launch shape from :func:`tune`: a
:class:`Shape` is a local size (work-items per group, or None for the runtime's own choice) and
a named build variant of the kernel (``""``: the plain kernel; the class's ``VARIANTS`` maps the
other names to their defines). The first plan of a (device, driver, kernel source, plan code,
width) starts a child process (:mod:`clsas.cl.probe`, as the width verdicts do: a variant that
kills the runtime kills only the child) that, for every candidate shape, runs the plan's
``selftest(queue, vec, shape)`` against the NumPy twin and times the plan's
``time_shapes(queue, vec, shapes)`` on a representative launch, in interleaved rounds. A shape
that differs from the twin by :data:`TOLERANCE` of the peak, or fails to build or launch, is
never chosen; among the others, one that is not the runtime's default is chosen only when its
median time relative to the default's in the same round is below ``1 -`` :data:`MARGIN`
(:func:`pick`), and, on a CPU device, when the host was not busy (load average above its CPU
count: the timings then measure other processes, :func:`busy`; the default is then kept
provisionally, and timed again after :data:`RETIME_S` once the host is quiet). The outcome is kept in
``cache_dir().parent / "shapes"`` (:func:`shapes_dir`).

Inside a probe process and on the Oclgrind simulator (which interprets kernels: its timings
mean nothing) the default shape is used without timing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .device import _cl, describe
from .program import is_simulator, kernel_source
from .variants import CHOSEN_SHAPES, _key, cache_dir, kernel_spec

__all__ = ["MARGIN", "TOLERANCE", "Shape", "Tuning", "candidate_shapes", "clear_shapes", "pick", "shapes_dir",
           "tune"]

log = logging.getLogger("clsas.cl.shapes")

TOLERANCE = 1e-3  # relative to the peak, as the width probe: catches wrong code, not float32 rounding
MARGIN = 0.05  # a shape other than the default must be this much faster (a shared host's timings move)
PROBE_TIMEOUT_S = 300.0
RETIME_S = 3600.0  # a provisional tuning (a busy host) is timed again after this long, on a quiet host
FORMAT = 1


@dataclass(frozen=True)
class Shape:
    """How a kernel is launched: ``local`` work-items per group (None: the runtime's choice) and
    the build ``variant`` (``""``: the plain kernel)."""

    local: int | None = None
    variant: str = ""

    def __post_init__(self) -> None:
        if self.local is not None and (not isinstance(self.local, int) or isinstance(self.local, bool)
                                       or self.local < 1):
            raise ValueError(f"local must be None or a positive int (work-items per group), got {self.local!r}")
        if not isinstance(self.variant, str):
            raise TypeError(f"variant must be a str, got {type(self.variant).__name__}")

    @property
    def label(self) -> str:
        return f"{self.variant or 'plain'}/{'auto' if self.local is None else self.local}"


DEFAULT = Shape()


@dataclass(frozen=True)
class Tuning:
    """The shape chosen for a kernel at a width on a device, and the trials it was chosen from
    (label -> seconds of the timed launch, or why it was refused)."""

    shape: Shape
    reason: str
    seconds: dict[str, float] = field(default_factory=dict)
    refused: dict[str, str] = field(default_factory=dict)
    source: str = "probe"  # "probe", "cache", "default"
    provisional: bool = False  # the default kept because the host was busy: timed again later (RETIME_S)
    when_s: float = 0.0  # when it was timed (time.time())


def shapes_dir() -> Path:
    """Where tunings are kept: the ``shapes`` folder beside the width verdicts (:func:`cache_dir`)."""
    return cache_dir().parent / "shapes"


_MEMO: dict[str, Tuning] = {}


def clear_shapes() -> int:
    """Delete every stored tuning (and forget this process's); returns how many files went."""
    _MEMO.clear()
    n = 0
    if shapes_dir().is_dir():
        for f in shapes_dir().glob("*.json"):
            f.unlink(missing_ok=True)
            n += 1
    return n


def candidate_shapes(device: Any, max_local: int, variants: dict[str, dict], needs_local: set[str]) -> list[Shape]:
    """The shapes to try: the runtime's choice, and local sizes of 16, 64 and 256 work-items (and 32
    and 128 on a GPU) up to ``max_local``, for every variant (those in ``needs_local`` only with a
    local size)."""
    if max_local < 1:
        raise ValueError(f"max_local must be at least 1, got {max_local!r}")
    cl = _cl()
    sizes = {16, 64, 256}
    if device.type & cl.device_type.GPU:
        sizes |= {32, 128}
    out = []
    for name in variants:
        if name not in needs_local:
            out.append(Shape(None, name))
        out += [Shape(n, name) for n in sorted(sizes) if n <= max_local]
    return out


def pick(rounds: dict[Shape, list[float]], margin: float = MARGIN) -> tuple[Shape, str]:
    """The shape to use among those that passed the twin check (shape -> its seconds in each
    interleaved round), with why. Each shape is scored by the median over rounds of its time over
    the default's in the same round (a shared host's load moves between rounds more than within
    one); the best-scored shape is chosen only when it beats the default by ``margin``."""
    if not rounds:
        return DEFAULT, "no shape passed the twin check: the default"
    base = rounds.get(DEFAULT)
    if base is None:
        best = min(rounds, key=lambda s: min(rounds[s]))
        return best, f"{best.label}: the fastest ({min(rounds[best]) * 1e3:.2f} ms; the default was refused)"
    score = {s: float(np.median(np.asarray(t) / np.asarray(base))) for s, t in rounds.items()}
    best = min(score, key=score.get)
    if best == DEFAULT or score[best] > 1 - margin:
        return DEFAULT, f"the default ({min(base) * 1e3:.2f} ms) is within {margin:.0%} of the fastest"
    return best, f"{best.label}: {1 / score[best]:.2f}x the default ({min(rounds[best]) * 1e3:.2f} ms)"


def busy(device: Any) -> float | None:
    """The host's 1-minute load average where it exceeds its CPU count and the device is a CPU
    (its timings then measure the other processes), else None."""
    if not (device.type & _cl().device_type.CPU) or not hasattr(os, "getloadavg"):
        return None
    load = os.getloadavg()[0]
    return load if load > (os.cpu_count() or 1) else None


def _digest(device: Any, name: str, vec: int, candidates: list[Shape]) -> tuple[str, dict]:
    _, ident = _key(device, name, vec)
    ident = {**ident, "what": "shapes", "candidates": [c.label for c in candidates], "shape_format": FORMAT}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:32], ident


def _load(digest: str) -> Tuning | None:
    try:
        data = json.loads((shapes_dir() / f"{digest}.json").read_text())
        shape = Shape(data["local"], data["variant"])
        return Tuning(shape, data["reason"], dict(data["seconds"]), dict(data["refused"]), "cache",
                      bool(data.get("provisional", False)), float(data.get("when_s", 0.0)))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _store(digest: str, ident: dict, tuning: Tuning) -> None:
    d = shapes_dir()
    record = {**ident, "local": tuning.shape.local, "variant": tuning.shape.variant, "reason": tuning.reason,
              "seconds": tuning.seconds, "refused": tuning.refused, "provisional": tuning.provisional,
              "when_s": tuning.when_s, "when": time.strftime("%Y-%m-%dT%H:%M:%S")}
    try:
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{digest}.{os.getpid()}.tmp"
        tmp.write_text(json.dumps(record, indent=1))
        os.replace(tmp, d / f"{digest}.json")
    except OSError as exc:
        log.warning("cannot store the work-group tuning in %s (%s): it will be timed again next time", d, exc)


def _run_child(device: Any, name: str, vec: int, candidates: list[Shape]) -> dict | None:
    """The child's report ``{"seconds": {label: s}, "refused": {label: why}}``, or None (crashed)."""
    kspec = kernel_spec(name)
    spec = {
        "task": "shapes", "platform": device.platform.name, "platform_version": device.platform.version,
        "device": device.name, "kernel": name, "vec": vec, "module": kspec.module, "qualname": kspec.qualname,
        "sources": {f: kernel_source(f) for f in kspec.sources}, "shapes": [asdict(c) for c in candidates],
    }
    env = dict(os.environ)
    pkg_root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = pkg_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("PYOPENCL_CTX", None)
    log.info("timing %d work-group shapes of kernel %s (VEC=%d) on %s in a child process (once; kept in %s)",
             len(candidates), name, vec, describe(device), shapes_dir())
    try:
        res = subprocess.run([sys.executable, "-m", "clsas.cl.probe"], input=json.dumps(spec), capture_output=True,
                             text=True, env=env, timeout=PROBE_TIMEOUT_S)
    except (subprocess.TimeoutExpired, OSError) as exc:
        log.info("work-group tuning of %s did not finish (%s): the default shape", name, exc)
        return None
    for line in reversed((res.stdout or "").splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                continue
    log.info("work-group tuning of %s exited with status %d and no report: the default shape\n%s", name,
             res.returncode, (res.stderr or "")[-2000:])
    return None


def _timed(device: Any, name: str, vec: int, candidates: list[Shape]) -> Tuning:
    """Time the candidates in a child and pick (:func:`pick`); on a busy host, the default, provisionally."""
    report = _run_child(device, name, vec, candidates)
    if report is None:
        return Tuning(DEFAULT, "the timing probe crashed or timed out: the default shape", when_s=time.time())
    by_label = {c.label: c for c in candidates}
    rounds = {by_label[k]: [float(x) for x in v] for k, v in report.get("rounds", {}).items() if k in by_label}
    shape, reason = pick(rounds)
    load = busy(device)
    provisional = load is not None and shape != DEFAULT
    if provisional:
        shape, reason = DEFAULT, (f"the default, for now: the host was busy while timing (load {load:.1f} on "
                                  f"{os.cpu_count()} CPUs; {reason}); timed again on a quiet host after "
                                  f"{RETIME_S / 3600:g} h")
    return Tuning(shape, reason, {c.label: min(t) for c, t in rounds.items()}, dict(report.get("refused", {})),
                  provisional=provisional, when_s=time.time())


def tune(queue: Any, name: str, vec: int, candidates: list[Shape], in_probe: bool = False) -> Tuning:
    """The :class:`Tuning` of kernel ``name`` at width ``vec`` on the queue's device among
    ``candidates`` (memoised, kept on disk; the default shape inside a probe or on a simulator)."""
    if not candidates:
        raise ValueError("candidates must hold at least one Shape")
    device = queue.device
    if in_probe or is_simulator(device):
        return Tuning(DEFAULT, "not timed (a probe process or a simulator)", source="default")
    digest, ident = _digest(device, name, vec, candidates)
    if digest in _MEMO:
        return _MEMO[digest]
    tuning = _load(digest)
    if tuning is not None and tuning.provisional and time.time() - tuning.when_s > RETIME_S and busy(device) is None:
        tuning = None  # kept only because the host was busy; it is quiet now
    if tuning is None:
        tuning = _timed(device, name, vec, candidates)
        _store(digest, ident, tuning)
        log.info("kernel %s (VEC=%d) on %s: work-group shape %s (%s)", name, vec, describe(device),
                 tuning.shape.label, tuning.reason)
    _MEMO[digest] = tuning
    CHOSEN_SHAPES[(device.int_ptr, name)] = tuning.shape.label
    return tuning
