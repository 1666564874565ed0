"""The OpenCL runtimes under the device layer: pip-installed CPU runtimes registered with the ICD
loader, one owner of each context, and a default device chosen by what builds."""

import gc
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import needs_opencl, small_dataset

import clsas
from clsas import cl
from clsas.cl import device as device_mod
from clsas.cl import runtimes

ROOT = Path(__file__).resolve().parents[2]


def _run(code: str, env: dict) -> subprocess.CompletedProcess:
    full = {**os.environ, **env}
    full["PYTHONPATH"] = str(ROOT) + os.pathsep + str(ROOT / "tests")
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, env=full,
                          timeout=300)


def test_registration_keeps_the_loaders_own_drivers(tmp_path):
    """The folder handed to the loader holds every .icd file of the folder it would have read, plus
    the pip-installed runtime; a second process writes the same folder."""
    vendors = tmp_path / "vendors"
    vendors.mkdir()
    (vendors / "somegpu.icd").write_text("libsomegpu-opencl.so.1\n")
    code = """
        import json, os
        from clsas.cl import runtimes
        reg = runtimes.register()
        files = {p.name: p.read_text().strip() for p in __import__('pathlib').Path(reg.folder).glob('*.icd')} \\
            if reg.folder else {}
        print(json.dumps({"folder": reg.folder, "env": os.environ.get("OCL_ICD_VENDORS"), "files": files,
                          "runtimes": [r.library for r in reg.runtimes if not r.problem], "note": reg.note}))
    """
    env = {"OCL_ICD_VENDORS": str(vendors), "CLSAS_CACHE_DIR": str(tmp_path / "cache")}
    first = _run(code, env)
    assert first.returncode == 0, first.stderr
    out = json.loads(first.stdout.strip().splitlines()[-1])
    if not out["runtimes"]:
        pytest.skip(f"no pip-installed OpenCL runtime here ({out['note']})")
    assert out["env"] == out["folder"] and Path(out["folder"]).is_relative_to(tmp_path / "cache")
    assert out["files"]["somegpu.icd"] == "libsomegpu-opencl.so.1"
    assert set(out["runtimes"]) <= set(out["files"].values())
    again = json.loads(_run(code, {**env, "OCL_ICD_VENDORS": out["folder"]}).stdout.strip().splitlines()[-1])
    assert again["folder"] == out["folder"] and again["files"] == out["files"]  # nothing registered twice
    off = json.loads(_run(code, {**env, "CLSAS_PIP_RUNTIMES": "0"}).stdout.strip().splitlines()[-1])
    assert off["folder"] == "" and off["env"] == str(vendors) and off["note"] == "CLSAS_PIP_RUNTIMES=0"


def test_a_pip_runtime_missing_its_libraries_is_named(monkeypatch, tmp_path):
    from importlib import metadata

    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "libintelocl.so").write_bytes(b"")

    class Dist:
        version = "0.0"
        files = [Path("libintelocl.so")]

        def locate_file(self, f):
            return lib / f

    def fake(name):
        if name == "intel-opencl-rt":
            return Dist()
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "distribution", fake)
    (found,) = runtimes.pip_runtimes()
    assert found.library == str(lib / "libintelocl.so")
    assert "libimf.so is missing: pip install intel-cmplr-lib-rt" == found.problem


def test_the_installed_intel_runtime_is_listed():
    """Where intel-opencl-rt is installed (a dependency on x86-64 Linux), pyopencl lists it."""
    found = [r for r in runtimes.registration().runtimes if r.distribution == "intel-opencl-rt"]
    if not found:
        pytest.skip("intel-opencl-rt is not installed here")
    assert not found[0].problem, found[0].problem
    names = [p.name for p in cl._cl().get_platforms()]
    assert any(n.startswith("Intel(R) OpenCL") for n in names), names


@needs_opencl
def test_a_queue_outlives_every_other_reference_to_its_context():
    """One owner of context and queue: on every device here, a queue whose context object nobody
    else holds still runs a plan after a garbage collection (Intel's CPU runtime answered
    INVALID_CONTEXT here when the context was left to the queue)."""
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=4, ny=3)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (0.0, 0.0), (0.45, 0.55), 0.025)
    want = clsas.reconstruct(ds, grid, backend="numpy", formation="bp").values
    ran = 0
    for dev in (d for p in cl._cl().get_platforms() for d in p.get_devices()):
        if "oclgrind" in dev.platform.name.lower():
            continue
        queue = device_mod.make_queue(dev)
        gc.collect()
        assert queue.context.devices[0].int_ptr == dev.int_ptr
        try:
            got = clsas.reconstruct(ds, grid, backend="opencl", device=queue, formation="bp")
        except cl.BuildError:
            continue  # a runtime that cannot target this CPU (its own tests say so)
        gc.collect()
        assert got.backend == "opencl"
        assert np.abs(got.values - want).max() <= 2e-4 * np.abs(want).max()
        ran += 1
    assert ran >= 1


def test_default_device_skips_one_that_builds_nothing(monkeypatch):
    """The preferred device whose compiler fails is passed over for the next one that builds; with
    none left, the error gives the compiler's words and the fix."""
    devices = [d for p in cl._cl().get_platforms() for d in p.get_devices() if device_mod._score(d) >= 0]
    if not devices:
        pytest.skip("no OpenCL device")
    best = max(devices, key=device_mod._score)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    words = "error: unknown target CPU 'generic'"

    def failing(d):
        if d.int_ptr == best.int_ptr or len(devices) == 1:
            return device_mod.Health(False, f"the compiler failed: {words}", device_mod.fix_for(d, words))
        return device_mod.Health(True)

    monkeypatch.setattr(device_mod, "_HEALTH", {})
    monkeypatch.setattr(device_mod, "_try_canary", failing)
    if len(devices) > 1:
        assert device_mod._default_device().int_ptr != best.int_ptr
    monkeypatch.setattr(device_mod, "_HEALTH", {})
    monkeypatch.setattr(device_mod, "_try_canary", lambda d: device_mod.Health(
        False, f"the compiler failed: {words}", device_mod.fix_for(d, words)))
    with pytest.raises(cl.OpenCLUnavailable, match="unknown target CPU 'generic'") as err:
        device_mod._default_device()
    assert "does not know this CPU" in str(err.value) and "intel-opencl-rt" in str(err.value)


@needs_opencl
def test_the_canary_reports_the_compilers_words(monkeypatch):
    """A kernel source the compiler refuses: health() says so with the compiler's own line."""
    dev = cl.get_queue().device
    monkeypatch.setattr(device_mod, "_HEALTH", {})
    monkeypatch.setattr(device_mod, "CANARY", "__kernel void clsas_canary(__global float *x) { x[0] = nope; }")
    h = device_mod.health(dev)
    assert not h.ok and h.reason.startswith("the compiler failed:") and "nope" in h.reason
    assert h.fix


def test_compiler_words_pick_the_error_lines():
    log = "note: something\n<source>:3:5: error: use of undeclared identifier 'nope'\nmore\n1 error generated."
    assert device_mod.compiler_words(log) == ("<source>:3:5: error: use of undeclared identifier 'nope' | "
                                             "1 error generated.")
    assert device_mod.compiler_words("") == "(no build log)"


@needs_opencl
def test_a_build_error_names_the_compilers_words_on_its_first_line():
    src = "__kernel void backproject(__global float *x) { x[0] = not_declared_here; }"
    with cl.override_source("backproject.cl", src), pytest.raises(cl.BuildError) as err:
        cl.build(cl.get_queue().context, ("backproject.cl",), {"VEC": 4})
    first = str(err.value).splitlines()[0]
    assert "the compiler failed:" in first and "not_declared_here" in first


def test_a_ci_run_with_no_device_that_builds_kernels_fails(tmp_path):
    """CI=true and no OpenCL device (the system's ICD folder emptied, the pip runtime not registered,
    PoCL's devices switched off): the test run stops with exit status 3 and one message saying so,
    instead of skipping every kernel test; with CLSAS_BACKEND=numpy it runs and says so in the header."""
    empty = tmp_path / "no-vendors"
    empty.mkdir()
    env = {**os.environ, "CI": "true", "CLSAS_PIP_RUNTIMES": "0", "OCL_ICD_VENDORS": str(empty),
           "POCL_DEVICES": "nonexistent", "CLSAS_CACHE_DIR": str(tmp_path / "cache")}
    env.pop("PYOPENCL_CTX", None)
    env.pop("CLSAS_BACKEND", None)
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(Path(__file__).resolve()),
           "-k", "compiler_words"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert res.returncode == 3, res.stdout[-2000:] + res.stderr[-2000:]
    assert "must test the OpenCL kernels" in res.stdout + res.stderr
    res = subprocess.run([c for c in cmd if c != "-q"], capture_output=True, text=True,
                         env={**env, "CLSAS_BACKEND": "numpy"}, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:]
    assert "clsas kernels: NOT run, NumPy twins only (CLSAS_BACKEND=numpy)" in res.stdout
