"""The device layer (clsas.cl): backend and device choice, verified kernel variants, fallback, clean exit."""

import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import TESTS, needs_opencl, small_dataset

import clsas
from clsas import cl
from clsas.cl import variants

BROKEN = "__kernel void backproject(__global float *x) { x[0] = not_declared; }\n"
RENAMED = "__kernel void something_else(__global float *x) { x[0] = 1.0f; }\n"
REAL_PROBE = variants._run_probe

# the tests folder (conftest.py) first, then what the caller had (an install by --target, say)
_TESTS_PATH = os.pathsep.join(p for p in [str(TESTS), os.environ.get("PYTHONPATH", "")] if p)


@pytest.fixture
def scene():
    ds = small_dataset([[0.02, -0.01, 0.6]], nx=7, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.06), (-0.06, 0.06), (0.55, 0.65), 0.02)
    return ds, grid


@pytest.fixture
def fresh_verdicts(tmp_path, monkeypatch):
    """An empty verdict cache on disk and in memory; restored afterwards."""
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    saved = dict(variants._MEMO)
    variants._MEMO.clear()
    cl.device._warn_once.cache_clear()
    yield tmp_path / "variants"
    variants._MEMO.clear()
    variants._MEMO.update(saved)
    cl.device._warn_once.cache_clear()


def _no_device(monkeypatch):
    def none(device=None):
        raise cl.OpenCLUnavailable("no OpenCL device found (test)")

    monkeypatch.setattr(cl.device, "get_queue", none)


# ---- backend choice ------------------------------------------------------------------------


def test_without_a_device_auto_falls_back_and_opencl_raises(monkeypatch, caplog, scene):
    ds, grid = scene
    _no_device(monkeypatch)
    cl.device._warn_once.cache_clear()
    with caplog.at_level(logging.WARNING, logger="clsas.cl"):
        assert clsas.compress(ds, backend="auto").backend == "numpy"
        assert clsas.reconstruct(ds, grid, backend="auto").backend == "numpy"
    assert sum("no OpenCL device (no OpenCL device found (test))" in r.message for r in caplog.records) == 1
    for call in (lambda: clsas.compress(ds, backend="opencl"), lambda: clsas.reconstruct(ds, grid, backend="opencl")):
        with pytest.raises(cl.OpenCLUnavailable, match="backend='opencl' was requested"):
            call()


def test_clsas_backend_sets_the_default_of_every_public_function(monkeypatch, scene):
    ds, grid = scene
    monkeypatch.setenv("CLSAS_BACKEND", "numpy")
    prof = clsas.compress(ds)
    assert prof.backend == "numpy"
    assert clsas.backproject(prof, grid).backend == "numpy"
    assert clsas.Backprojector(grid).backend == "numpy"
    image = clsas.reconstruct(ds, grid)
    assert image.backend == "numpy" and image.device == "NumPy (float64)"
    assert clsas.reconstruct(ds, grid, backend="numpy").plan.kernels == []
    monkeypatch.setenv("CLSAS_BACKEND", "cuda")
    with pytest.raises(ValueError, match="CLSAS_BACKEND must be one of"):
        clsas.compress(ds)
    with pytest.raises(ValueError, match="backend must be one of"):
        clsas.compress(ds, backend="gpu")


def test_clsas_backend_numpy_from_the_shell(tmp_path):
    """The README's recipe: CLSAS_BACKEND=numpy python -c ... runs compress and reconstruct on NumPy."""
    code = textwrap.dedent("""
        import numpy as np, clsas
        from conftest import small_dataset
        ds = small_dataset([[0.0, 0.0, 0.6]], nx=5, ny=3)
        grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (0.0, 0.0), (0.55, 0.65), 0.025)
        print(clsas.compress(ds).backend, clsas.reconstruct(ds, grid).backend)
    """)
    env = dict(os.environ, CLSAS_BACKEND="numpy", PYTHONPATH=_TESTS_PATH)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["numpy", "numpy"]


@needs_opencl
def test_device_argument_picks_the_device(scene):
    import pyopencl

    ds, grid = scene
    row = next(r for r in cl.list_devices() if r.selected)
    q = cl.get_queue()
    assert cl.get_queue(row.index) is q  # "P:D" as clsas devices prints it: the same queue
    assert cl.get_queue(q.device) is q
    own = pyopencl.CommandQueue(q.context, properties=pyopencl.command_queue_properties.PROFILING_ENABLE)
    assert cl.get_queue(own) is own
    a = clsas.reconstruct(ds, grid, device=own, backend="opencl")
    b = clsas.reconstruct(ds, grid, device=row.index, backend="opencl")
    np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-6 * np.abs(b.values).max())
    with pytest.raises(cl.OpenCLUnavailable, match="device='99:0'"):
        clsas.compress(ds, device="99:0", backend="opencl")
    with pytest.raises(cl.OpenCLUnavailable, match="not 'P:D'"):
        cl.get_queue("gpu")
    with pytest.raises(TypeError, match="device must be"):
        clsas.compress(ds, device=3.5, backend="opencl")


@needs_opencl
def test_backprojector_is_built_once_and_called_many_times(scene):
    ds, grid = scene
    bp = clsas.Backprojector(grid, backend="opencl")
    prof = clsas.compress(ds, gate_s=(2e-3, 5e-3), backend="numpy")
    first = bp(prof)
    plan = bp._plan
    half = clsas.Profiles(prof.data * 0.5, prof.tau0_s, prof.dtau_s, prof.fc_hz, "matched", "numpy",
                          prof.tx_positions, prof.rx_positions, prof.c_mps)
    second = bp(half)
    assert bp._plan is plan  # the same compiled plan and buffers
    np.testing.assert_allclose(second.values, 0.5 * first.values, atol=1e-6 * np.abs(first.values).max())
    want = clsas.backproject(prof, grid, backend="numpy").values
    assert np.abs(first.values - want).max() < 2e-4 * np.abs(want).max()


# ---- kernel variants -------------------------------------------------------------------------


def _fake_probe(outcomes):
    """A stand-in for the child process: verdicts by width, and a record of what was probed."""
    calls = []

    def run(device, name, vec):
        calls.append((name, vec))
        if name != "backproject":  # the compression kernels keep their real verdicts
            return REAL_PROBE(device, name, vec)
        ok, reason = outcomes[vec]
        return cl.Verdict(ok, reason, "fake build log" if not ok else ""), True

    return run, calls


@needs_opencl
def test_chooser_steps_down_past_rejected_widths_and_caches_verdicts(monkeypatch, fresh_verdicts):
    run, calls = _fake_probe({16: (False, "killed by SIGABRT"), 8: (False, "vector ABI warning"), 4: (True, "ok")})
    monkeypatch.setattr(variants, "_run_probe", run)
    monkeypatch.setattr(variants, "candidate_widths", lambda device: [16, 8, 4])
    q = cl.get_queue()
    assert cl.choose(q, "backproject") == 4
    assert calls == [("backproject", 16), ("backproject", 8), ("backproject", 4)]
    # a plan takes the chosen width; a width that was rejected is never launched
    from clsas.formation.bp_opencl import BackprojectPlan

    grid = clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0), (0.5, 0.6), 0.05)
    assert BackprojectPlan(grid, 3, 10, queue=q).vec == 4
    with pytest.raises(cl.BuildError, match="SIGABRT") as err:
        BackprojectPlan(grid, 3, 10, queue=q, vec=16)
    assert "fake build log" in err.value.log
    # verdicts are on disk: a new process (here: an emptied memo) reads them, probes nothing
    assert len(list(fresh_verdicts.glob("*.json"))) == 3
    variants._MEMO.clear()
    calls.clear()
    assert cl.choose(q, "backproject") == 4
    assert calls == [] and cl.check(q, "backproject", 16).source == "cache"
    assert cl.clear_cache() == 3 and not list(fresh_verdicts.glob("*.json"))


@needs_opencl
def test_no_usable_width_is_a_build_error_with_every_reason(monkeypatch, fresh_verdicts, scene, caplog):
    run, _ = _fake_probe({16: (False, "a16"), 8: (False, "b8"), 4: (False, "c4")})
    monkeypatch.setattr(variants, "_run_probe", run)
    monkeypatch.setattr(variants, "candidate_widths", lambda device: [16, 8, 4])
    with pytest.raises(cl.BuildError, match="no usable variant of 'backproject' \\(a16; b8; c4\\)"):
        cl.choose(cl.get_queue(), "backproject")
    ds, grid = scene
    with caplog.at_level(logging.WARNING, logger="clsas.cl"):
        image = clsas.reconstruct(ds, grid, backend="auto")
        clsas.reconstruct(ds, grid, backend="auto")
    assert image.backend == "numpy"
    warned = [r.message for r in caplog.records if "using the NumPy backend" in r.message]
    assert len(warned) == 1 and cl.device_info() in warned[0] and "no usable variant" in warned[0]
    with pytest.raises(cl.BuildError):
        clsas.reconstruct(ds, grid, backend="opencl")


@needs_opencl
def test_a_probe_killed_by_a_signal_is_a_rejection(monkeypatch, fresh_verdicts):
    """What PoCL does on a Zen 4 CPU at VEC=16 (LLVM ERROR, abort): the parent lives and says why."""
    monkeypatch.setattr(variants, "_probe_command", lambda: [sys.executable, "-c", "import os; os.abort()"])
    verdict, definitive = variants._run_probe(cl.get_queue().device, "backproject", 8)
    assert not verdict.ok and definitive and "SIGABRT" in verdict.reason
    monkeypatch.setattr(variants, "_probe_command", lambda: [sys.executable, "-c", "import sys; sys.exit(3)"])
    verdict, definitive = variants._run_probe(cl.get_queue().device, "backproject", 8)
    assert not verdict.ok and not definitive  # no verdict printed: probed again next time


@needs_opencl
def test_the_real_probe_accepts_the_width_in_use():
    verdict, definitive = variants._run_probe(cl.get_queue().device, "backproject", 4)
    assert verdict.ok and definitive, verdict
    assert "equal to the twin" in verdict.reason


@needs_opencl
def test_a_vector_abi_warning_in_the_build_log_rejects_the_width(monkeypatch):
    from clsas.cl import program

    warning = ("warning: x.cl:1:2: AVX vector argument of type 'float16' (vector of 16 'float' values) "
               "without 'avx512f' enabled changes the ABI")
    monkeypatch.setattr(program, "_log", lambda prog, device: warning)
    src = cl.kernel_source("backproject.cl") + "\n/* a source of this test only */\n"
    with cl.override_source("backproject.cl", src), pytest.raises(cl.BuildError, match="changes the ABI") as err:
        cl.build(cl.get_queue().context, ("common.cl", "backproject.cl"), {"VEC": 4})
    # rejected for the warning, after a build that succeeded (not for a compiler failure whose log
    # this test replaced)
    assert "the compiler warns that a vector type changes the ABI" in err.value.reason
    assert "avx512f" in err.value.log


@needs_opencl
@pytest.mark.parametrize("source, why", [(BROKEN, "the compiler failed"), (RENAMED, "holds no kernel 'backproject'")],
                         ids=["syntax-error", "kernel-missing"])
def test_a_kernel_that_cannot_be_built_falls_back_or_raises(fresh_verdicts, scene, caplog, source, why):
    """A broken kernel source injected through the layer: the real probe rejects every width."""
    ds, grid = scene
    # bp named: with formation="auto" the NumPy backend's cost model may take another formation
    want = clsas.reconstruct(ds, grid, backend="numpy", formation="bp").values
    with cl.override_source("backproject.cl", source):
        with caplog.at_level(logging.WARNING, logger="clsas.cl"):
            image = clsas.reconstruct(ds, grid, backend="auto", formation="bp")
        assert image.backend == "numpy"  # (compression still ran on OpenCL: float32 profiles)
        assert np.abs(image.values - want).max() < 1e-4 * np.abs(want).max()
        assert any(why in r.message and "using the NumPy backend" in r.message for r in caplog.records)
        with pytest.raises(cl.BuildError, match=why) as err:
            clsas.reconstruct(ds, grid, backend="opencl")
        if source is BROKEN:
            assert "not_declared" in err.value.log
    # the real source builds again once the override is gone
    assert clsas.reconstruct(ds, grid, backend="opencl").backend == "opencl"


@needs_opencl
def test_clean_exit_after_every_build_outcome(tmp_path):
    """No abort or non-zero status at interpreter shutdown after failed, missing and good builds."""
    code = textwrap.dedent(f"""
        import clsas
        from clsas import cl
        from conftest import small_dataset
        ds = small_dataset([[0.0, 0.0, 0.6]], nx=5, ny=3)
        grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (0.0, 0.0), (0.55, 0.65), 0.025)
        for src in ({BROKEN!r}, {RENAMED!r}):
            with cl.override_source("backproject.cl", src):
                assert clsas.reconstruct(ds, grid, backend="auto").backend == "numpy"
                try:
                    cl.build(cl.get_queue().context, ("backproject.cl",), {{"VEC": 4}})
                except cl.BuildError:
                    pass
        assert clsas.reconstruct(ds, grid, backend="auto").backend == "opencl"
        print("done")
    """)
    env = dict(os.environ, CLSAS_CACHE_DIR=str(tmp_path), PYTHONPATH=_TESTS_PATH)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().endswith("done")
    for bad in ("LLVM ERROR", "Aborted", "can't release LLVM context"):
        assert bad not in res.stderr


# ---- the layer's place: below everything, the only importer of pyopencl ------------------------


def _imports(path):
    """(module names imported, relative levels used) of one source file, function bodies included."""
    import ast

    names, levels = [], []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append(node.module or "")
            levels.append(node.level)
    return names, levels


def test_the_device_layer_imports_nothing_above_it():
    from pathlib import Path

    for path in sorted(Path(cl.__file__).parent.glob("*.py")):
        names, levels = _imports(path)
        assert all(level <= 1 for level in levels), f"{path.name} imports from above clsas.cl"
        above = [n for n in names if n.startswith("clsas") and not n.startswith("clsas.cl")]
        assert not above, f"{path.name} imports {above}"


def test_only_the_device_layer_imports_pyopencl():
    from pathlib import Path

    root = Path(clsas.__file__).parent
    importers = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                       if any(n.split(".")[0] == "pyopencl" for n in _imports(p)[0]))
    assert importers and all(p.startswith("cl/") for p in importers), importers


def test_a_plan_declares_its_kernel_and_registers_itself():
    spec = cl.kernel_spec("backproject")
    assert spec.sources == ("common.cl", "beam.cl", "backproject.cl")
    assert (spec.module, spec.qualname) == ("clsas.formation.bp_opencl", "BackprojectPlan")
    try:
        class ToyPlan(cl.Plan):
            KERNEL = "toy_kernel"
            SOURCES = ("common.cl", "toy.cl")

        toy = cl.kernel_spec("toy_kernel")
        assert (toy.module, toy.qualname, toy.sources) == (__name__, ToyPlan.__qualname__, ("common.cl", "toy.cl"))

        before = dict(cl.KERNELS)

        class Base(cl.Plan):  # no kernel of its own: nothing registered
            pass

        assert cl.KERNELS == before
        with pytest.raises(ValueError, match="already run by"):
            class Other(cl.Plan):
                KERNEL = "toy_kernel"
                SOURCES = ("toy.cl",)
        with pytest.raises(TypeError, match="names no KERNEL"):
            Base()
    finally:
        cl.KERNELS.pop("toy_kernel", None)
    with pytest.raises(ValueError, match="unknown kernel 'toy_kernel'"):
        cl.check(None, "toy_kernel", 4)


def test_a_gpu_driver_no_icd_file_registers_is_found_with_its_fix(tmp_path, monkeypatch):
    """A container that mounts NVIDIA's libraries but not /etc/OpenCL/vendors/nvidia.icd (the
    project's first GPU machine): the library is found and the line that registers it is given;
    once registered (by full path or base name), nothing is reported."""
    from clsas.cl import icd

    libs, vendors = tmp_path / "lib", tmp_path / "vendors"
    libs.mkdir()
    vendors.mkdir()
    (libs / "libnvidia-opencl.so.1").write_bytes(b"")
    (vendors / "pocl.icd").write_text("libpocl.so.2\n")
    found = icd.unregistered_drivers(search_dirs=(str(libs),), dirs=[vendors])
    assert [u.vendor for u in found] == ["NVIDIA"]
    assert found[0].library == str(libs / "libnvidia-opencl.so.1")
    assert found[0].fix == f"mkdir -p {vendors} && echo {libs / 'libnvidia-opencl.so.1'} > {vendors / 'nvidia.icd'}"
    monkeypatch.setenv("OCL_ICD_FILENAMES", str(libs / "libnvidia-opencl.so.1"))  # named to the loader directly
    assert icd.unregistered_drivers(search_dirs=(str(libs),), dirs=[vendors]) == []
    monkeypatch.delenv("OCL_ICD_FILENAMES")
    (vendors / "nvidia.icd").write_text(f"{libs / 'libnvidia-opencl.so.1'}\n")
    assert icd.unregistered_drivers(search_dirs=(str(libs),), dirs=[vendors]) == []
    (vendors / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    assert icd.unregistered_drivers(search_dirs=(str(libs),), dirs=[vendors]) == []
    # where the loader looks: $OCL_ICD_VENDORS (a folder or a file in one), else /etc/OpenCL/vendors
    monkeypatch.setenv("OCL_ICD_VENDORS", str(vendors / "nvidia.icd"))
    assert icd.vendor_dirs() == [vendors]
    monkeypatch.setenv("OCL_ICD_VENDORS", str(tmp_path / "not-yet"))  # a folder that does not exist yet
    assert icd.vendor_dirs() == [tmp_path / "not-yet"]
    (vendors / "bad.icd").write_bytes(b"\xff\xfe\x00")  # a malformed file is passed over
    assert icd.registered_libraries([vendors]) >= {"libnvidia-opencl.so.1"}
    monkeypatch.delenv("OCL_ICD_VENDORS")
    assert icd.vendor_dirs() == [Path("/etc/OpenCL/vendors")]


def test_clsas_devices_prints_the_fix_for_an_unregistered_driver(tmp_path, monkeypatch, capsys):
    from clsas.cl import icd
    from clsas.cli import main

    (tmp_path / "libnvidia-opencl.so.1").write_bytes(b"")
    monkeypatch.setattr(icd, "SEARCH_DIRS", (str(tmp_path),))
    monkeypatch.setenv("OCL_ICD_VENDORS", str(tmp_path / "vendors"))  # a folder with no .icd file
    (tmp_path / "vendors").mkdir()
    assert main(["devices", "--opencl-only"]) == 0
    out = capsys.readouterr().out
    assert "NVIDIA's OpenCL driver is installed" in out and "nvidia.icd" in out
