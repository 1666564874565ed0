"""The focus metric on the device (kernels/focus_metric.cl): both kernels against their twin at
every width, the twin against the host metric, analytic images, the scale that keeps float's
range, and an autofocus step whose image, metric and weight stay on the device."""

import numpy as np
import pytest
from conftest import needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.focus import metric_numpy as twin
from clsas.focus.engine import FocusEngine
from clsas.focus.metrics import metric_and_weight

METRICS = ("sharpness", "entropy")


@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize("scale", [1.0, 1e-9, 7.5])
def test_twin_is_the_host_metric_split_as_the_device_does(rng, metric, scale):
    values = (rng.normal(size=300) + 1j * rng.normal(size=300)) * 10.0 ** rng.uniform(-2, 2, 300)
    values[7] = 0
    m, a, b = twin.from_moments(twin.focus_moments(values, scale), metric)
    want_m, want_g = metric_and_weight(values, metric)
    assert m == pytest.approx(want_m, rel=1e-12)
    got_g = scale * twin.focus_weight(values, scale, a, b, metric == "entropy")
    np.testing.assert_allclose(got_g, want_g, rtol=1e-10, atol=1e-12 * np.abs(want_g).max())


def test_twin_on_analytic_images():
    one = np.zeros(50, complex)
    one[3] = 2 - 1j  # all the energy in one voxel: the sharpest image; entropy 0
    flat = np.full(50, 0.5 + 0.5j)  # spread evenly over N voxels: sharpness 1/N, entropy log N
    assert twin.from_moments(twin.focus_moments(one, 1.0), "sharpness")[0] == pytest.approx(0.0, abs=1e-15)
    assert twin.from_moments(twin.focus_moments(one, 1.0), "entropy")[0] == pytest.approx(0.0, abs=1e-15)
    assert twin.from_moments(twin.focus_moments(flat, 3.0), "sharpness")[0] == pytest.approx(np.log(1 / 50))
    assert twin.from_moments(twin.focus_moments(flat, 3.0), "entropy")[0] == pytest.approx(-np.log(50))
    assert twin.from_moments(twin.focus_moments(np.zeros(9), 1.0), "sharpness") == (-np.inf, 0.0, 0.0)
    with pytest.raises(ValueError, match="metric"):
        twin.from_moments(twin.focus_moments(flat, 1.0), "contrast")


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_kernels_equal_their_twin(vec):
    from clsas import cl
    from clsas.focus.metric_opencl import FocusMomentsPlan, FocusWeightPlan

    width_or_skip("focus_moments", vec)
    width_or_skip("focus_weight", vec)
    queue = cl.get_queue()
    assert FocusMomentsPlan.selftest(queue, vec) < 1e-5
    assert FocusWeightPlan.selftest(queue, vec) < 1e-5


@needs_opencl
@pytest.mark.parametrize("level", [1e-15, 1.0, 1e15], ids=["faint", "unit", "loud"])
def test_moments_keep_float_range_at_any_level(rng, level):
    """|I|^4 of counts-level images leaves float's range: the plan rescales, and the metric is
    the host's at every level."""
    from clsas.cl import DeviceRows
    from clsas.focus.metric_opencl import FocusMomentsPlan, device_metric

    values = ((rng.normal(size=4000) + 1j * rng.normal(size=4000)) * level).astype(np.complex64)
    plan = FocusMomentsPlan(len(values))
    buf = plan.upload(values.view(np.float32), np.float32)
    rows = DeviceRows(plan, buf, 1, len(values), len(values), values)
    for metric in METRICS:
        got = device_metric(plan, None, rows, metric)
        assert got == pytest.approx(metric_and_weight(values, metric)[0], rel=1e-5)
    assert 1e-6 <= plan.scale * float(np.max(np.abs(values.astype(complex)) ** 2)) <= 1e6


@needs_opencl
@pytest.mark.parametrize("metric", METRICS)
def test_an_autofocus_step_stays_on_the_device(rng, metric):
    """The engine's metric and gradient from the image left on the device equal those computed on
    the host from the image read back (the same image), and the device path was taken."""
    ds = small_dataset([[0.0, 0.0, 0.5], [0.02, 0.01, 0.52]], nx=12, ny=12, width=0.2, height=0.2)
    grid = clsas.VoxelGrid.from_bounds((-0.04, 0.04), (-0.04, 0.04), (0.46, 0.54), 0.006)
    engine = FocusEngine(ds, grid, backend="opencl", metric=metric)
    shift = rng.normal(0, 3e-6, ds.n_meas)
    m, sums, values = engine.evaluate(shift, ds.c_per_meas)
    assert engine.n_device_metrics == 1
    want_m, weight = metric_and_weight(values, metric)
    want_sums = engine.sums(shift, ds.c_per_meas, weight)
    assert m == pytest.approx(want_m, rel=1e-6)
    assert np.abs(sums - want_sums).max() <= 1e-5 * np.abs(want_sums).max()
    m_only, none, _ = engine.evaluate(shift, ds.c_per_meas, gradient=False)
    assert none is None and m_only == pytest.approx(want_m, rel=1e-6) and engine.n_device_metrics == 2
    on_host = FocusEngine(ds, grid, backend="opencl", metric=metric, metric_on_device=False)
    m_host, sums_host, _ = on_host.evaluate(shift, ds.c_per_meas)
    assert on_host.n_device_metrics == 0 and m_host == pytest.approx(m, rel=1e-6)
    assert np.abs(sums_host - sums).max() <= 1e-5 * np.abs(sums).max()


def test_numpy_engine_computes_the_metric_on_the_host(rng):
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=8, ny=8, width=0.2, height=0.2)
    grid = clsas.VoxelGrid.from_bounds((-0.03, 0.03), (-0.03, 0.03), (0.47, 0.53), 0.01)
    engine = FocusEngine(ds, grid, backend="numpy")
    m, _, values = engine.evaluate(np.zeros(ds.n_meas), ds.c_per_meas)
    assert engine.n_device_metrics == 0 and m == metric_and_weight(values, "sharpness")[0]
    with pytest.raises(ValueError, match="weight"):
        engine.sums(np.zeros(ds.n_meas), ds.c_per_meas, None)
    with pytest.raises(TypeError, match="metric_on_device"):
        FocusEngine(ds, grid, backend="numpy", metric_on_device="False")
