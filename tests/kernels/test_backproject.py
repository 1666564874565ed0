"""Backprojection (kernels/backproject.cl): twin equivalence on PoCL, analytic and physics tests."""

import numpy as np
import pytest
from conftest import BACKENDS, TOL, needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.formation import bp_numpy as twin
from clsas.types.rangegate import path_bounds


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize(
    "shape", [(13, 11, 9), (17, 1, 23), (1, 1, 50)], ids=["volume", "plane", "line"]
)
def test_backproject_opencl_equals_twin(rng, vec, shape):
    from clsas.formation.bp_opencl import BackprojectPlan

    width_or_skip("backproject", vec)
    # dry air, the data this tolerance was set on: on the "line" (2 cm beside the target, so its
    # own peak is low) float32's error relative to that peak moves between 1.6e-4 and 3.2e-4 with
    # the speed of sound (0 to 70 % RH at 20 C); the other shapes stay near 4e-5
    ds = small_dataset([[0.02, -0.01, 0.6]], humidity_pct=0.0)
    p = clsas.compress(ds, gate_s=(2e-3, 6e-3), backend="numpy")
    axes = [np.linspace(-0.1, 0.1, n) if n > 1 else np.zeros(1) for n in shape[:2]]
    grid = clsas.VoxelGrid(axes[0], axes[1], np.linspace(0.5, 0.7, shape[2]))
    plan = BackprojectPlan(grid, p.n_meas, p.n_lags, vec=vec, chunk=17)  # chunks that do not divide n_meas
    got = plan(p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, ds.c_mps)
    want = twin.backproject(p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions,
                            ds.c_mps, grid.points())
    err = np.abs(got - want).max() / np.abs(want).max()
    assert err < TOL["backproject"], err


@pytest.mark.parametrize("cycles", [0.0, 0.26, 0.6, 1.3, 2.7])
def test_carrier_records_reproduce_the_carrier_exactly(rng, cycles):
    """The kernel's split of the carrier (records rotated at each sample, the sub-sample rotation
    in the kernel), evaluated in NumPy, equals lerp(profile) * exp(j 2 pi fc tau) at random
    delays, upsampled profiles (fc dtau > 0.6) included."""
    from clsas.formation.bp_opencl import MAX_CYCLES_PER_SAMPLE, carrier_records

    n_meas, n_lags, dtau = 3, 40, 1 / 96e3
    fc = cycles / dtau
    data = rng.normal(size=(n_meas, n_lags - 5)) + 1j * rng.normal(size=(n_meas, n_lags - 5))
    tau0 = rng.uniform(1e-3, 3e-3, n_meas)
    pairs, dtau_up, phi = carrier_records(data, n_lags, tau0, dtau, fc)
    up = round(dtau / dtau_up)
    assert up == max(1, int(np.ceil(cycles / MAX_CYCLES_PER_SAMPLE - 1e-9)))
    assert phi == pytest.approx(2 * np.pi * fc * dtau_up) and phi / 2 <= 0.6 * np.pi + 1e-12
    assert pairs.shape == (n_meas, (n_lags - 1) * up + 1, 2)
    prof = np.zeros((n_meas, n_lags), complex)
    prof[:, : data.shape[1]] = data
    for m in range(n_meas):
        idx = rng.uniform(0, n_lags - 1, 200)  # in samples of the given profile
        tau = tau0[m] + idx * dtau
        want = np.interp(idx, np.arange(n_lags), prof[m].real) + 1j * np.interp(idx, np.arange(n_lags), prof[m].imag)
        want = want * np.exp(2j * np.pi * fc * tau)
        fine = idx * up
        k = np.minimum(np.floor(fine).astype(int), pairs.shape[1] - 1)
        f = fine - k
        got = ((1 - f) * pairs[m, k, 0] + f * pairs[m, k, 1]) * np.exp(1j * phi * (f - 0.5))
        assert np.abs(got - want).max() < 2e-6 * np.abs(prof).max()


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_backproject_of_coarse_profiles_equals_twin(rng, vec):
    """Profiles of more than 0.6 carrier cycles per sample (upsampled on the host) through the
    kernel: the twin's image, every measurement with its own speed of sound."""
    from clsas.formation.bp_opencl import BackprojectPlan

    width_or_skip("backproject", vec)
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 9), np.linspace(-0.05, 0.05, 5), np.linspace(0.3, 0.7, 17))
    n, n_lags, dtau = 12, 40, 1 / 24e3
    tx = np.c_[rng.uniform(-0.2, 0.2, (n, 2)), np.zeros(n)]
    rx = tx + [0.03, 0, 0]
    c = rng.uniform(340, 346, n)
    prof = rng.normal(size=(n, n_lags)) + 1j * rng.normal(size=(n, n_lags))
    tau0 = 0.8 / 343 - 20 * dtau + rng.uniform(-3, 3, n) * dtau  # voxels in and out of the window
    want = twin.backproject(prof, tau0, dtau, 25e3, tx, rx, c, grid.points())
    got = BackprojectPlan(grid, n, n_lags, vec=vec, chunk=5)(prof, tau0, dtau, 25e3, tx, rx, c)
    assert np.any(want == 0) and np.any(want != 0)
    assert np.abs(got - want).max() < TOL["backproject"] * np.abs(want).max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_target_lands_in_its_voxel(backend):
    target = np.array([0.03, -0.02, 0.55])
    ds = small_dataset([target], nx=15, ny=11)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.45, 0.65), 0.01)
    image = clsas.reconstruct(ds, grid, backend=backend)
    assert image.values.shape == grid.shape
    assert image.peaks(1)[0].index == grid.index_of(target)


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_reflectors_beyond_the_resolution_are_resolved(backend):
    # 4 cm apart in range (resolution 1.7 cm) and 6 cm across (resolution ~1.4 cm here)
    pts = [[0.0, 0.0, 0.50], [0.0, 0.0, 0.54], [0.06, 0.0, 0.50]]
    ds = small_dataset(pts, nx=41, ny=1, width=0.4, height=0.0)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.1), (0.0, 0.0), (0.45, 0.6), 0.005)
    image = clsas.reconstruct(ds, grid, backend=backend)
    found = [p.position_m for p in image.peaks(3, min_separation_m=0.02)]
    for t in pts:
        assert min(np.linalg.norm(f - t) for f in found) < 0.006


@pytest.mark.parametrize("backend", BACKENDS)
def test_around_the_corner_peak_is_at_the_mirror_image(backend):
    wall = clsas.Wall((0.0, 0.0, 0.8), (0.70710678, 0.0, -0.70710678))
    image_pos = np.array([0.0, 0.0, 1.0])
    hidden = wall.mirror(image_pos[None])[0]  # the real target, beside the aperture
    ds = small_dataset([hidden], visible=[False], walls=[wall], nx=15, ny=11)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    image = clsas.reconstruct(ds, grid, backend=backend)
    assert image.peaks(1)[0].index == grid.index_of(image_pos)


def _width_3db(values, axis_m):
    mag = np.abs(values) / np.abs(values).max()
    k = int(np.argmax(mag))
    above = mag >= 1 / np.sqrt(2)
    lo, hi = k, k
    while lo > 0 and above[lo - 1]:
        lo -= 1
    while hi < len(mag) - 1 and above[hi + 1]:
        hi += 1

    def cross(i, j):  # linear interpolation of the -3 dB crossing between samples i and j
        return axis_m[i] + (axis_m[j] - axis_m[i]) * (mag[i] - 1 / np.sqrt(2)) / (mag[i] - mag[j])

    return cross(hi, hi + 1) - cross(lo, lo - 1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_psf_widths_match_the_resolution_limits(backend):
    """A well-sampled line aperture (3 mm < lambda/4 spacing): -3 dB widths within 20 %."""
    R, D = 0.5, 0.3
    ds = small_dataset([[0.0, 0.0, R]], nx=101, ny=1, width=D, height=0.0)
    c = ds.c_mps
    rng_res = c / (2 * 10e3)
    cross_res = (c / 25e3) * R / (2 * D)
    z_line = clsas.VoxelGrid(np.zeros(1), np.zeros(1), np.linspace(R - 0.04, R + 0.04, 161))
    x_line = clsas.VoxelGrid(np.linspace(-0.04, 0.04, 161), np.zeros(1), np.array([R]))
    wz = _width_3db(clsas.reconstruct(ds, z_line, backend=backend).values.ravel(), z_line.z_m)
    wx = _width_3db(clsas.reconstruct(ds, x_line, backend=backend).values.ravel(), x_line.x_m)
    assert wz == pytest.approx(rng_res, rel=0.2), (wz, rng_res)
    assert wx == pytest.approx(cross_res, rel=0.2), (wx, cross_res)


@pytest.mark.parametrize("backend", BACKENDS)
def test_samples_outside_the_window_contribute_nothing(backend):
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=5, ny=3)
    p = clsas.compress(ds, gate_s=(2.5e-3, 3.2e-3), backend="numpy")  # covers ~0.43-0.55 m
    grid = clsas.VoxelGrid(np.zeros(1), np.zeros(1), np.array([0.1, 0.5, 0.9]))
    image = clsas.backproject(p, grid, backend=backend)
    v = image.values.ravel()
    assert v[0] == 0 and v[2] == 0 and abs(v[1]) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_voxel_exactly_at_a_transducer_is_finite(backend):
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=3, ny=1, width=0.1, height=0.0)
    tx = ds.tx_positions[0]
    grid = clsas.VoxelGrid(np.array([tx[0]]), np.array([tx[1]]), np.array([tx[2], 0.5]))
    image = clsas.reconstruct(ds, grid, backend=backend)
    assert np.all(np.isfinite(image.values))


def test_range_gate_is_exact_and_safe(rng):
    """The gate's min/max path equal brute force over a dense grid, and never cut a voxel."""
    tx = rng.uniform(-0.5, 0.5, (20, 3))
    tx[:, 2] = 0
    rx = tx + [0.04, 0, 0]
    tx[0] = [0.0, 0.0, 0.7]  # a transducer inside the box
    lo, hi = np.array([-0.2, -0.3, 0.5]), np.array([0.3, 0.1, 0.9])
    pmin, pmax = path_bounds(lo, hi, tx, rx)
    g = clsas.VoxelGrid.from_bounds(*zip(lo, hi, strict=True), 0.01).points()
    d = np.linalg.norm(g[None] - tx[:, None], axis=2) + np.linalg.norm(g[None] - rx[:, None], axis=2)
    assert np.all(pmin <= d.min(axis=1) + 1e-12)
    assert np.all(pmax >= d.max(axis=1) - 1e-12)
    np.testing.assert_allclose(pmin, d.min(axis=1), atol=0.01)  # grid spacing bounds the gap
    np.testing.assert_allclose(pmax, d.max(axis=1), atol=1e-9)


def test_plan_computes_only_what_the_grid_needs():
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=5, ny=3)
    plane = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (0.0, 0.0), (0.45, 0.55), 0.01)
    image = clsas.reconstruct(ds, plane, backend="numpy")
    plan = image.plan
    assert plan.grid_shape == (21, 1, 11)
    assert plan.lags * plan.lag_step < plan.lags_full / 2
    text = plan.describe()
    assert "2-D" in text and "skipped" in text


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: clsas.VoxelGrid.from_bounds((0.1, -0.1), (0, 0), (0.4, 0.5), 0.01), "inverted"),
        (lambda: clsas.VoxelGrid(np.array([]), np.zeros(1), np.zeros(1)), "empty"),
        (lambda: clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0), (0.4, 0.5), 0.0), "spacing_m"),
        (lambda: clsas.VoxelGrid(np.array([0.0, np.nan]), np.zeros(1), np.zeros(1)), "NaN"),
        (lambda: clsas.raster_aperture(0, 3, 1.0, 1.0), "nx"),
        (lambda: clsas.Scene(np.zeros((2, 2))), "points_m"),
    ],
    ids=["inverted-grid", "empty-grid", "zero-spacing", "nan-axis", "zero-nx", "bad-points-shape"],
)
def test_geometry_rejects_bad_input(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_reconstruct_rejects_bad_input():
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=3, ny=1, width=0.1, height=0.0)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (0, 0), (0.4, 0.5), 0.05)
    with pytest.raises(TypeError, match="dataset"):
        clsas.reconstruct(ds.signals, grid)
    with pytest.raises(ValueError, match="method"):
        clsas.reconstruct(ds, grid, method="magic")
    p = clsas.compress(ds, backend="numpy")
    with pytest.raises(ValueError, match="c_mps"):
        clsas.backproject(p, grid, c_mps=-1.0, backend="numpy")
    with pytest.raises(ValueError, match="tx_positions"):
        clsas.backproject(p, grid, tx_positions=np.zeros((2, 3)), backend="numpy")


@pytest.mark.parametrize("method", ["bpdn", "cbp-polar"])
def test_reconstruct_with_super_resolution_puts_the_reflector_in_its_voxel(method):
    pytest.importorskip("nlopt", reason="sparse methods need the 'sparse' extra")
    ds = small_dataset([[0.02, -0.01, 0.5]], nx=5, ny=4, snr_db=20)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.005)
    img = clsas.reconstruct(ds, grid, method, backend="numpy")
    assert np.linalg.norm(img.peaks(1)[0].position_m - [0.02, -0.01, 0.5]) <= 0.0075
    assert len(img.echoes) == ds.n_meas and all(len(e) >= 1 for e in img.echoes)
    with pytest.raises(ValueError, match="unknown option"):
        clsas.reconstruct(ds, grid, method, backend="numpy", sparse={"lambda": 1})
