"""Child process of :mod:`clsas.cl.variants`: build one kernel variant, launch it, check it.

Reads a JSON spec on stdin (platform and device names, kernel, width, the plan class's module
and qualified name, source texts), runs the plan class's ``selftest`` (a small input against
the NumPy twin) on that device and prints one JSON line ``{"ok": ..., "reason": ..., "log":
...}``. With ``"task": "shapes"`` and a list of shapes (:mod:`clsas.cl.shapes`) it checks each
shape against the twin and times those that pass, printing ``{"rounds": {label: [s per round]},
"refused": {label: why}}``. A crash of the OpenCL runtime kills only this process; the parent reads that from the
exit status.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import sys

from . import variants
from .device import _cl, make_queue
from .program import BuildError, override_source
from .shapes import TOLERANCE as shapes_tolerance
from .shapes import Shape

TOLERANCE = 1e-3  # relative to the peak: catches wrong code, not float32 rounding


def _device(platform: str, name: str, version: str | None = None):
    """The device named so on the platform named so (and of that platform version, where given: two
    PoCLs, PyPI's and the system's, carry the same platform name)."""
    for p in _cl().get_platforms():
        if p.name == platform and (version is None or p.version == version):
            for d in p.get_devices():
                if d.name == name:
                    return d
    raise LookupError(f"device {name!r} on {platform!r} ({version or 'any version'}) not found")


def _plan_class(module: str, qualname: str):
    """The plan class the parent named (its module imported here: this layer names none)."""
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def run(spec: dict) -> dict:
    variants._IN_PROBE = True
    vec = int(spec["vec"])
    device = _device(spec["platform"], spec["device"], spec.get("platform_version"))
    queue = make_queue(device)
    with contextlib.ExitStack() as stack:
        for f, text in spec.get("sources", {}).items():
            stack.enter_context(override_source(f, text))
        plan_cls = _plan_class(spec["module"], spec["qualname"])
        if spec.get("task") == "shapes":
            return time_shapes(plan_cls, queue, vec, [Shape(**s) for s in spec["shapes"]])
        try:
            err = plan_cls.selftest(queue, vec)
        except BuildError as exc:
            return {"ok": False, "reason": exc.reason, "log": exc.log}
    if not err < TOLERANCE:
        return {"ok": False, "reason": f"VEC={vec}: result differs from the NumPy twin by {err:.3g} of the peak"}
    return {"ok": True, "reason": f"VEC={vec}: equal to the twin to {err:.2g} of the peak"}


def time_shapes(plan_cls, queue, vec: int, shapes: list[Shape]) -> dict:
    """Each shape checked against the twin (``plan_cls.selftest(queue, vec, shape)``), those that
    pass timed together (``plan_cls.time_shapes``); label -> seconds per round, label -> why refused."""
    refused, passed = {}, []
    for shape in shapes:
        try:
            err = plan_cls.selftest(queue, vec, shape)
        except Exception as exc:  # noqa: BLE001 - any failure of a shape refuses it
            refused[shape.label] = f"{type(exc).__name__}: {exc}"[:500]
            continue
        if err < shapes_tolerance:
            passed.append(shape)
        else:
            refused[shape.label] = f"differs from the NumPy twin by {err:.3g} of the peak"
    rounds = plan_cls.time_shapes(queue, vec, passed) if passed else []
    return {"rounds": {s.label: t for s, t in zip(passed, rounds, strict=True)}, "refused": refused}


def main() -> int:
    spec = json.loads(sys.stdin.read())
    try:
        report = run(spec)
    except ImportError as exc:  # a broken installation, not a verdict on the variant
        report = {"ok": False, "definitive": False, "reason": f"the probe cannot import what it needs ({exc})"}
    except Exception as exc:  # noqa: BLE001 - any failure of the variant is a verdict, reported to the parent
        report = {"ok": False, "reason": f"VEC={spec.get('vec')}: {type(exc).__name__}: {exc}"}
    # the verdict is this child's output to its parent (a protocol line, not a message to a user)
    sys.stdout.write(json.dumps(report) + "\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
