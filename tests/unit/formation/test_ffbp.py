"""3-D fast factorized backprojection (clsas/formation/ffbp*.py, kernels/ffbp.cl): depth 0 is bp,
point targets on raster, circular and jittered apertures, the error trend with sampling and order,
each kernel against its twin on PoCL, input validation."""

import dataclasses

import numpy as np
import pytest
from conftest import BACKENDS, needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.formation import error_to_signal_db, form
from clsas.formation import ffbp_numpy as twin
from clsas.formation.ffbp import plan_tree
from clsas.formation.ffbp_tree import build_tree, split_sizes

FS = 96e3
TOL_FFBP = 2e-4  # float32 kernels against the float64 twin, relative to the peak


def _chirp():
    return clsas.lfm_chirp(20e3, 30e3, 1e-3, FS, taper=0.1)


@pytest.fixture(scope="module")
def raster_case():
    ds = small_dataset([[0.0, 0.0, 0.5], [0.05, -0.03, 0.55]], nx=16, ny=16, width=0.2, height=0.2)
    prof = clsas.compress(ds, backend="numpy")
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.06), (-0.06, 0.06), (0.46, 0.58), 0.006)
    ref = clsas.backproject(prof, grid, backend="numpy")
    return ds, prof, grid, ref


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_zero_is_exact_backprojection(raster_case, backend):
    _, prof, grid, _ = raster_case
    img = form(prof, grid, "ffbp", backend=backend, depth=0)
    ref = clsas.backproject(prof, grid, backend=backend)
    assert np.array_equal(img.values, ref.values)
    assert img.provenance["formation"] == "ffbp"


def _peak_in_voxel(ds, grid, target, backend, **options):
    img = clsas.reconstruct(ds, grid, backend=backend, formation="ffbp", formation_options=options)
    assert img.provenance["ffbp"]["depth"] == options["depth"]
    assert img.peaks(1)[0].index == grid.index_of(target)
    return img


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_target_lands_in_its_voxel_on_a_raster(backend):
    target = np.array([0.02, -0.015, 0.5])
    ds = small_dataset([target], nx=16, ny=16, width=0.2, height=0.2)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.005)
    img = _peak_in_voxel(ds, grid, target, backend, depth=3)
    assert img.provenance["formation_options"] == {"depth": 3}


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_target_lands_in_its_voxel_on_a_circle(backend):
    target = np.array([0.028, -0.02, 0.0])
    ap = clsas.circular_aperture(128, 0.5, mode="arc", start_deg=-60, stop_deg=60)
    ds = clsas.simulate(clsas.Scene(target[None]), ap, _chirp(), FS)
    grid = clsas.VoxelGrid.plane("z", at_m=0.0, u_m=(-0.06, 0.06), v_m=(-0.06, 0.06), spacing_m=0.004)
    _peak_in_voxel(ds, grid, target, backend, depth=3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_target_lands_in_its_voxel_on_a_jittered_bistatic_track(backend):
    """A hand-held scan: a serpentine with 3 mm of jitter in x, y and z, speaker and microphone
    10 cm apart, and air that warms by 2 K during the scan (a speed of sound per measurement)."""
    rng = np.random.default_rng(5)
    base = clsas.raster_aperture(14, 14, 0.2, 0.2)
    stage = base.stage_positions + rng.normal(0, 0.003, base.stage_positions.shape)
    ap = clsas.Aperture(stage + [-0.05, 0, 0], stage + [0.05, 0, 0], stage)
    target = np.array([-0.015, 0.02, 0.5])
    temps = np.linspace(20.0, 22.0, len(stage))
    ds = clsas.simulate(clsas.Scene(target[None]), ap, _chirp(), FS, temperature_c=temps)
    assert np.ptp(ds.c_mps) > 1.0
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.005)
    img = _peak_in_voxel(ds, grid, target, backend, depth=2)
    ref = clsas.reconstruct(ds, grid, backend=backend)
    assert error_to_signal_db(img, ref) < -25


def test_error_falls_as_sampling_and_order_rise(raster_case):
    """A measured trend on one scene (NumPy twin, depth 3): finer sub-image grids and longer
    stencils each bring the error against bp down."""
    _, prof, grid, ref = raster_case

    def err(**kw):
        return error_to_signal_db(form(prof, grid, "ffbp", backend="numpy", depth=3, **kw), ref)

    by_oversampling = [err(oversample=s, range_oversample=s) for s in (1.25, 2.0, 3.0)]
    by_order = [err(order=o) for o in (1, 3, 5)]
    assert by_oversampling[0] > by_oversampling[1] + 3 > by_oversampling[2] + 6, by_oversampling
    assert by_order[0] > by_order[1] + 6 > by_order[2] + 9, by_order
    assert min(by_order[2], by_oversampling[2]) < -35
    # the least-squares weights beat Lagrange's at the same cost
    assert err(interpolator="lsq") < err(interpolator="lagrange") - 2


@needs_opencl
@pytest.mark.parametrize("taps", [2, 4, 6], ids=lambda t: f"taps{t}")
def test_kernels_equal_their_twins(raster_case, taps):
    from clsas.formation.ffbp_opencl import FfbpLeafPlan, FfbpMergePlan

    _, prof, grid, _ = raster_case
    tree = plan_tree(prof, grid, depth=2, order=taps - 1)
    o = tree.order
    args = (prof.data[o], prof.tau0_s[o], prof.dtau_s, prof.fc_hz, prof.tx_positions[o], prof.rx_positions[o],
            np.full(prof.n_meas, prof.c_mps))
    leaves = tree.levels[-1]
    want = twin.form_leaves(*args, leaves, tree.kref)
    got = FfbpLeafPlan()(*args, leaves, tree.kref)
    assert np.abs(got - want).max() / np.abs(want).max() < TOL_FFBP
    tables = (twin.weight_table(taps, 2.0), twin.weight_table(taps, 2.0, "lagrange"))
    plan = FfbpMergePlan(taps)
    top = twin.merge(want, leaves, tree.levels[0], tree.kref, tables)
    got = plan(want, leaves, tree.levels[0], tree.kref, tables)
    assert np.abs(got - top).max() / np.abs(top).max() < TOL_FFBP
    image = twin.to_grid(top, tree.levels[0], grid.points(), tree.kref, tables)
    got = plan(top, tree.levels[0], None, tree.kref, tables, grid=grid)
    assert np.abs(got - image).max() / np.abs(image).max() < TOL_FFBP


@needs_opencl
def test_kernel_selftests_pass():
    from clsas import cl
    from clsas.formation.ffbp_opencl import FfbpLeafPlan, FfbpMergePlan

    q = cl.get_queue()
    assert FfbpLeafPlan.selftest(q, 4) < TOL_FFBP
    assert FfbpMergePlan.selftest(q, 4) < TOL_FFBP


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_leaf_kernel_equals_its_twin_at_every_width(raster_case, vec):
    # the leaf kernel's samples are vector lanes (a block of 64 shared by VEC of them): every
    # width the device accepts, on a depth-2 tree with padding and samples outside the disc
    from clsas import cl
    from clsas.formation.ffbp_opencl import FfbpLeafPlan

    width_or_skip("ffbp_leaf", vec)
    _, prof, grid, _ = raster_case
    tree = plan_tree(prof, grid, depth=2)
    o = tree.order
    args = (prof.data[o], prof.tau0_s[o], prof.dtau_s, prof.fc_hz, prof.tx_positions[o], prof.rx_positions[o],
            np.full(prof.n_meas, prof.c_mps))
    want = twin.form_leaves(*args, tree.levels[-1], tree.kref)
    got = FfbpLeafPlan(cl.get_queue(), vec)(*args, tree.levels[-1], tree.kref)
    assert np.any(want == 0) and np.abs(got - want).max() / np.abs(want).max() < TOL_FFBP


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("mode", ["weighted", "limited"])
def test_leaf_kernel_with_a_beam_equals_its_twin_at_every_width(vec, mode):
    # -DBEAM: each pair weighted (or gated) by a tilted piston and a cone at the leaf's samples
    from clsas import cl
    from clsas.formation.ffbp_opencl import leaf_beam_selftest

    width_or_skip("ffbp_leaf", vec)
    assert leaf_beam_selftest(cl.get_queue(), vec, mode) < TOL_FFBP


@needs_opencl
def test_opencl_pipeline_equals_the_numpy_path(raster_case):
    _, prof, grid, _ = raster_case
    a = form(prof, grid, "ffbp", backend="numpy", depth=3)
    b = form(prof, grid, "ffbp", backend="opencl", depth=3)
    assert b.backend == "opencl" and "ffbp_merges_kernel" in b.timings_s
    assert np.abs(a.values - b.values).max() / np.abs(a.values).max() < TOL_FFBP


def test_progress_reports_each_level(raster_case):
    _, prof, grid, _ = raster_case
    calls = []
    form(prof, grid, "ffbp", backend="numpy", depth=2, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_tree_splits_rasters_into_quadrants_and_keeps_every_measurement():
    ap = clsas.raster_aperture(8, 8, 0.1, 0.1)
    grid_bounds = np.array([[-0.05, 0.05], [-0.05, 0.05], [0.4, 0.5]])
    tree = build_tree(ap.tx_positions, ap.rx_positions, np.full(64, 343.0), grid_bounds, (20e3, 30e3),
                      depth=2, factor=4, oversample=2, range_oversample=2, taps=4)
    assert sorted(tree.order) == list(range(64))
    assert split_sizes(4) == [2, 2] and split_sizes(6) == [2, 3]
    for lev, size in zip(tree.levels, (16, 4), strict=True):
        counts = lev.ints[:, 5] - lev.ints[:, 4]
        assert np.all(counts == size)
        # a quadrant is square: its centres span as much in x as in y
        first = (ap.tx_positions + ap.rx_positions)[tree.order[lev.ints[0, 4]:lev.ints[0, 5]]] / 2
        assert np.ptp(first[:, 0]) == pytest.approx(np.ptp(first[:, 1]))
    # sub-images of bigger sub-apertures are sampled more finely in angle
    assert tree.levels[0].geom[:, 22].max() < tree.levels[1].geom[:, 22].min()


@pytest.mark.parametrize(
    "options, match",
    [
        ({"depth": -1}, "depth"),
        ({"depth": 9}, "depth"),
        ({"depth": 1.5}, "depth"),
        ({"depth": True}, "depth"),
        ({"factor": 1}, "factor"),
        ({"factor": 2.5}, "factor"),
        ({"oversample": 0.5}, "oversample"),
        ({"oversample": float("nan")}, "oversample"),
        ({"range_oversample": 40}, "range_oversample"),
        ({"order": 2}, "order"),
        ({"interpolator": "sinc"}, "interpolator"),
        ({"band_hz": (30e3, 20e3)}, "band_hz"),
        ({"band_tail": 0.7}, "band_tail"),
        ({"speed": 1}, "speed"),
    ],
    ids=lambda x: str(x) if isinstance(x, str) else "-".join(f"{k}={v}" for k, v in x.items()),
)
def test_bad_options_are_refused(raster_case, options, match):
    _, prof, grid, _ = raster_case
    with pytest.raises((ValueError, TypeError), match=match):
        form(prof, grid, "ffbp", backend="numpy", **options)


def test_bad_inputs_are_refused(raster_case):
    ds, prof, grid, _ = raster_case
    with pytest.raises(TypeError, match="profiles"):
        form(ds, grid, "ffbp")
    with pytest.raises(TypeError, match="grid"):
        form(prof, grid.points(), "ffbp")
    data = prof.data.copy()
    data[3, 5] = np.nan
    bad = dataclasses.replace(prof, data=data)
    with pytest.raises(ValueError, match="NaN"):
        form(bad, grid, "ffbp", backend="numpy")
    # a grid around the aperture (behind some stops) is refused with the alternative named
    around = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (-0.2, 0.2), (-0.1, 0.1), 0.02)
    with pytest.raises(ValueError, match="formation='bp'"):
        form(prof, around, "ffbp", backend="numpy", depth=2)
    with pytest.raises(ValueError, match="depth"):
        clsas.reconstruct(ds, grid, backend="numpy", formation="ffbp", formation_options={"depth": -2})
