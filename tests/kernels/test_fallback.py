"""Every kernel that will not build, through the public call that uses it.

A broken source is injected for each kernel (``clsas.cl.override_source``). With
``backend="auto"`` (the string, or the :class:`clsas.cl.Selection` the public boundary resolves
it into and passes down) the call falls back to the NumPy twin with exactly one warning naming
the device, and returns what ``backend="numpy"`` returns; with ``backend="opencl"`` it raises
:class:`clsas.cl.BuildError` whose message holds the compiler's log.
"""

import logging

import numpy as np
import pytest
from conftest import needs_opencl, small_dataset

import clsas
import clsas.formation.ffbp  # noqa: F401 - a plan registers its kernel when its module is imported
import clsas.formation.omega_k  # noqa: F401
from clsas import cl
from clsas.focus import gradient_numpy as focus_twin
from clsas.focus.engine import FocusEngine
from clsas.focus.metrics import metric_and_weight
from clsas.formation import FORMATIONS, form
from clsas.inverse import project_opencl  # noqa: F401 (its plan registers the project kernel)

pytestmark = [pytest.mark.opencl, needs_opencl]

MARK = "clsas_fallback_test_undeclared"  # the identifier the compiler's log must name
ALL_KERNELS = ("matched_filter", "fmcw_dechirp", "matched_fft", "backproject", "focus_gradient", "stolt_spread",
               "stolt_depths", "ffbp_leaf", "ffbp_merge", "project", "carrier_records", "focus_moments",
               "focus_weight")
SELF_CHECKED = ("focus_gradient", "focus_moments", "focus_weight")  # cases that compare with the twin themselves


def broken_source(kernel: str, only_with: str | None = None) -> tuple[str, str]:
    """(file, text): the kernel's own source with an undeclared identifier in its body.

    ``only_with``: the error is compiled only where that macro is defined (``"TAPS"``: only the
    FFBP merge plans built for 2 or 6 taps, not the leaf kernel built from the same file).
    """
    name = cl.kernel_spec(kernel).sources[-1]
    src = cl.kernel_source(name)
    start = src.index(f"__kernel void {kernel}(")
    body = src.index("{", start) + 1
    line = f"\n    {MARK}_{kernel} = 1;\n"
    if only_with:
        line = f"\n#ifdef {only_with}{line}#endif\n"
    return name, src[:body] + line + src[body:]


@pytest.fixture(autouse=True)
def _fresh_warnings():
    """The fallback warning is logged once per process and reason: forget earlier ones."""
    cl.device._warn_once.cache_clear()
    yield
    cl.device._warn_once.cache_clear()


@pytest.fixture(scope="module")
def scene():
    """A 16 x 16 raster (planar and uniform, for omega-k), one point, a small grid in front."""
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=16, ny=16, width=0.2, height=0.2)
    grid = clsas.VoxelGrid.from_bounds((-0.04, 0.04), (-0.04, 0.04), (0.46, 0.54), 0.008)
    gate = clsas.types.rangegate.plan_reconstruction(ds, grid, []).gate_s
    prof = clsas.compress(ds, gate_s=gate, backend="numpy")
    return ds, grid, prof


def _auto_requests():
    return [pytest.param(lambda: "auto", id="auto"), pytest.param(lambda: cl.select("auto"), id="selection")]


def _opencl_requests():
    return [pytest.param(lambda: "opencl", id="opencl"), pytest.param(lambda: cl.select("opencl"), id="selection")]


# kernel -> the public call that runs it: f(scene, backend) -> array, and whether it ran on NumPy
def _compress(**kw):
    def call(scene, backend):
        ds, grid, _ = scene
        prof = clsas.compress(ds, backend=backend, **kw)
        return prof.data, prof.backend

    return call


def _backproject(scene, backend):
    _, grid, prof = scene
    image = clsas.backproject(prof, grid, backend=backend)
    return image.values, image.backend


def _resident(scene, backend):
    """bp of profiles that the OpenCL compression left on the device: the carrier records are made
    there (kernels/records.cl). The profiles come from OpenCL whatever ``backend`` is, so that the
    twin's image is of the same (float32) profiles."""
    ds, grid, _ = scene
    gate = clsas.types.rangegate.plan_reconstruction(ds, grid, []).gate_s
    prof = clsas.compress(ds, gate_s=gate, backend="opencl")
    assert prof.on_device is not None
    image = clsas.backproject(prof, grid, backend=backend)
    return image.values, image.backend


def _formation(name, **options):
    def call(scene, backend):
        _, grid, prof = scene
        image = form(prof, grid, name, backend=backend, **options)
        return image.values, image.backend

    return call


def _gradient(scene, backend):
    ds, grid, _ = scene
    eng = FocusEngine(ds, grid, backend=backend)
    p = eng.prof
    shift = np.random.default_rng(0).normal(0, 3e-6, ds.n_meas)
    weight = np.random.default_rng(1).normal(size=grid.size) + 0j
    got = eng.sums(shift, ds.c_per_meas, weight)
    # the twin on the engine's own profiles (compressed on OpenCL under "auto")
    data, tau0 = eng._shifted(shift)
    want = focus_twin.focus_gradient(data, tau0, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, ds.c_per_meas,
                                     grid.points(), weight)
    assert np.array_equal(got, want)
    return got, eng.backend


def _metric(scene, backend):
    """An autofocus step's metric: on the device from the image bp left there, or (the fallback)
    on the host from the image read back; either way the host's metric of that image."""
    ds, grid, _ = scene
    eng = FocusEngine(ds, grid, backend=backend)
    m, _, values = eng.evaluate(np.zeros(ds.n_meas), ds.c_per_meas)
    assert m == pytest.approx(metric_and_weight(values, "sharpness")[0], rel=1e-6)
    return m, "opencl" if eng.n_device_metrics else "numpy"


def _project(scene, backend):
    """The model-based methods' forward projector (clsas.inverse.ImagingOperator.matvec)."""
    from clsas.inverse import ImagingOperator

    _, grid, prof = scene
    op = ImagingOperator(prof, grid, backend=backend)
    x = np.random.default_rng(2).normal(size=grid.size) + 0j
    return op.matvec(x), op.backend


CASES = {
    "matched_filter": (None, _compress(algorithm="direct")),
    "fmcw_dechirp": (None, _compress(method="fmcw")),
    "matched_fft": (None, _compress(algorithm="fft")),
    "backproject": (None, _backproject),
    "focus_gradient": (None, _gradient),
    "stolt_spread": (None, _formation("omega-k", depths="spread")),
    "stolt_depths": (None, _formation("omega-k", depths="direct")),
    "ffbp_leaf": (None, _formation("ffbp", depth=1)),
    "ffbp_merge": ("TAPS", _formation("ffbp", depth=1, order=1)),  # the leaf kernel still builds
    "project": (None, _project),
    "carrier_records": (None, _resident),
    "focus_moments": (None, _metric),
    "focus_weight": (None, _metric),
}


def test_every_kernel_has_a_case():
    assert set(CASES) == set(ALL_KERNELS) == set(cl.KERNELS)
    assert {"omega-k", "ffbp"} <= set(FORMATIONS)


def _fallback_warnings(caplog):
    return [r.getMessage() for r in caplog.records if "using the NumPy backend" in r.getMessage()]


@pytest.mark.parametrize("request_", _auto_requests())
@pytest.mark.parametrize("kernel", ALL_KERNELS)
def test_auto_falls_back_with_one_warning_and_the_twins_result(scene, caplog, kernel, request_):
    only_with, call = CASES[kernel]
    # the real kernel builds here: the fallback below is the injected source's doing, not the device's
    assert cl.choose(cl.get_queue(), kernel) in cl.candidate_widths(cl.get_queue().device)
    if kernel not in SELF_CHECKED:
        want, kind = call(scene, "numpy")
        assert kind == "numpy"
    name, text = broken_source(kernel, only_with)
    with cl.override_source(name, text), caplog.at_level(logging.WARNING, logger="clsas"):
        got, kind = call(scene, request_())
    assert kind == "numpy"
    if kernel not in SELF_CHECKED:
        assert np.array_equal(got, want)
    warned = _fallback_warnings(caplog)
    assert len(warned) == 1, warned
    assert cl.device_info() in warned[0]


@pytest.mark.parametrize("request_", _opencl_requests())
@pytest.mark.parametrize("kernel", ALL_KERNELS)
def test_opencl_raises_with_the_compiler_log(scene, caplog, kernel, request_):
    only_with, call = CASES[kernel]
    name, text = broken_source(kernel, only_with)
    with cl.override_source(name, text), caplog.at_level(logging.WARNING, logger="clsas"):
        with pytest.raises(cl.BuildError) as err:
            call(scene, request_())
    assert f"{MARK}_{kernel}" in err.value.log
    assert "--- build log ---" in str(err.value) and f"{MARK}_{kernel}" in str(err.value)
    assert not _fallback_warnings(caplog)


def test_the_real_sources_build_again(scene):
    """Nothing built from an injected source outlives its block."""
    for kernel in ("stolt_spread", "stolt_depths", "ffbp_merge"):
        _, call = CASES[kernel]
        assert call(scene, "opencl")[1] == "opencl"


# ---- the resolved request: what the public boundary passes down -------------------------------


def test_a_selection_is_passed_through_and_keeps_its_request():
    sel = cl.select("auto")
    assert cl.select(sel) is sel and cl.select(sel, sel.queue) is sel
    assert sel.requested == "auto" and sel.opencl and sel.cl_device is sel.queue.device
    with pytest.raises(ValueError, match="device"):
        cl.select(sel, "0:0")
    numpy = cl.select("numpy")
    assert numpy.plan(lambda q: pytest.fail("no plan is built on NumPy")) == (None, numpy)
    assert numpy.cl_device is None and numpy.device == "NumPy (float64)"


def test_plan_falls_back_once_per_request(caplog):
    error = cl.BuildError(("x.cl",), cl.device_info(), "the compiler failed", "x.cl:1: error: MARK")

    def factory(queue):
        raise error

    auto = cl.select("auto")
    with caplog.at_level(logging.WARNING, logger="clsas"):
        plan, after = auto.plan(factory)
    assert plan is None and after.kind == "numpy" and after.requested == "auto"
    assert len(_fallback_warnings(caplog)) == 1
    assert after.plan(factory) == (None, after)  # NumPy from then on: nothing is built again
    with pytest.raises(cl.BuildError, match="MARK"):
        cl.select("opencl").plan(factory)
    built, same = auto.plan(lambda q: ("a plan on", q))
    assert built == ("a plan on", auto.queue) and same is auto


# every registered formation, with each kernel it builds
FORMATION_KERNELS = [("bp", "backproject"), ("omega-k", "stolt_spread"), ("omega-k", "stolt_depths"),
                     ("ffbp", "ffbp_leaf"), ("ffbp", "ffbp_merge")]


def test_every_registered_formation_is_covered():
    # auto builds no kernel of its own: it forms by one of the others
    assert {f for f, _ in FORMATION_KERNELS} == set(FORMATIONS) - {"auto"}


@pytest.mark.parametrize("formation, kernel", FORMATION_KERNELS)
def test_reconstruct_falls_back_for_every_formation(scene, caplog, formation, kernel):
    """reconstruct resolves the request once and hands the Selection down: "auto" falls back to the
    twin with one warning (the image equals backend="numpy"'s), "opencl" raises with the log."""
    ds, grid, _ = scene
    name, text = broken_source(kernel, "TAPS" if kernel == "ffbp_merge" else None)
    with cl.override_source(name, text), caplog.at_level(logging.WARNING, logger="clsas"):
        image = clsas.reconstruct(ds, grid, backend="auto", formation=formation)
    assert image.backend == "numpy" and len(_fallback_warnings(caplog)) == 1
    ref = clsas.reconstruct(ds, grid, backend="numpy", formation=formation)
    peak = np.abs(ref.values).max()
    # compression still ran on OpenCL (float32 profiles), so the two agree to float32 rounding
    assert np.abs(image.values - ref.values).max() < 1e-3 * peak
    cl.device._warn_once.cache_clear()
    with cl.override_source(name, text), pytest.raises(cl.BuildError, match=f"{MARK}_{kernel}"):
        clsas.reconstruct(ds, grid, backend="opencl", formation=formation)
