"""backproject.cl's -DRANGE_EXPANSION variant (the two distances expanded to second order along z
within runs of a work-item's voxels): its twin against the exact twin and the predicted error
bound (clsas.formation.bp_numpy.range_expansion_error), the kernel against its own twin at every
width, and the plan's choice per call (the plain kernel where the geometry's bound exceeds the
limit)."""

import numpy as np
import pytest
from conftest import TOL, bp_kernel_case, needs_opencl, width_or_skip

import clsas
from clsas import cl
from clsas.formation import bp_numpy as twin

EXPANSION = "range_expansion"


def _db(x: float) -> float:
    return 20 * np.log10(x)


def _geometry(rng, kind: str):
    """(grid, tx, rx): a grid in front of a small aperture, near and wide, or off to the side."""
    if kind == "near":
        grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.05, 0.05, 3), np.linspace(0.3, 0.62, 33))
        tx = np.c_[rng.uniform(-0.3, 0.3, (6, 2)), np.zeros(6)]
    elif kind == "far":
        grid = clsas.VoxelGrid(np.linspace(-0.3, 0.3, 4), np.linspace(-0.3, 0.3, 3), np.linspace(1.0, 1.64, 33))
        tx = np.c_[rng.uniform(-0.5, 0.5, (6, 2)), np.zeros(6)]
    else:  # "side": the grid off the aperture's axis, the transducers below and beside it
        grid = clsas.VoxelGrid(np.linspace(0.4, 0.6, 3), np.linspace(-0.1, 0.1, 3), np.linspace(0.1, 0.42, 17))
        tx = np.c_[rng.uniform(-0.2, 0.0, (6, 2)), rng.uniform(-0.1, 0.1, 6)]
    return grid, tx, tx + [0.03, 0.0, 0.0]


@pytest.mark.parametrize("kind", ["near", "far", "side"])
@pytest.mark.parametrize("run, vec", [(4, 4), (4, 16), (8, 8), (16, 16)], ids=lambda v: str(v))
def test_expanded_paths_stay_within_the_remainder_bound(rng, kind, run, vec):
    """The twin's expanded paths differ from the exact ones by at most the Lagrange bound per
    measurement, and by more than a third of it somewhere (the bound is not loose)."""
    grid, tx, rx = _geometry(rng, kind)
    layout = twin.expansion_layout(grid, run, vec)
    assert layout["along"].any() and not layout["along"].all()  # expanded work-items and exact ones
    bound = twin.expansion_path_error(grid, tx, rx, run)
    for m in range(len(tx)):
        err = np.abs(twin.range_expanded_path(layout, tx[m], rx[m]) - twin.exact_path(layout["points"], tx[m], rx[m]))
        assert err[~layout["along"]].max() == 0  # across a row's end: exact
        assert err.max() <= bound[m] * (1 + 1e-9), (m, err.max(), bound[m])
        assert err.max() > bound[m] / 3, (m, err.max(), bound[m])


def _image_error(data, tau0, dtau, tx, rx, grid, run, vec, fc=25e3, c=343.0):
    want = twin.backproject(data, tau0, dtau, fc, tx, rx, c, grid.points())
    got = twin.backproject_range_expansion(data, tau0, dtau, fc, tx, rx, c, grid, run, vec)
    assert np.all(np.abs(want) > 0)  # every pair inside its profile
    return np.abs(got - want).max() / np.abs(want).max()


def _window(grid, tx, rx, dtau, c=343.0):
    """tau0 and n_lags of profiles that cover every pair of the grid."""
    pts = grid.points()
    path = np.linalg.norm(pts[None] - tx[:, None], axis=2) + np.linalg.norm(pts[None] - rx[:, None], axis=2)
    tau0 = path.min(axis=1) / c - 3 * dtau
    return tau0, int(np.ceil((path.max() / c - tau0.min()) / dtau)) + 4


@pytest.mark.parametrize("kind", ["near", "far", "side"])
@pytest.mark.parametrize("run", [4, 8])
def test_phase_error_of_one_measurement_is_predicted(rng, kind, run):
    """One measurement of a flat profile: the image error is the carrier's phase error alone, within
    6 dB below the predicted bound (``dtau_s`` None; the bound takes the largest over the grid's box,
    which its voxels may miss, for tx and rx each)."""
    grid, tx, rx = _geometry(rng, kind)
    m = rng.integers(len(tx))
    tx, rx = tx[m:m + 1], rx[m:m + 1]
    dtau = 1 / 96e3
    tau0, n_lags = _window(grid, tx, rx, dtau)
    err = _image_error(np.ones((1, n_lags), complex), tau0, dtau, tx, rx, grid, run, 16)
    bound = twin.range_expansion_error(grid, tx, rx, 343.0, 25e3, run)
    assert _db(bound) - 6 < _db(err) <= _db(bound), (_db(err), _db(bound))


@pytest.mark.parametrize("kind", ["near", "far", "side"])
@pytest.mark.parametrize("profile, within_db", [("alternating", 10), ("random", 15)])
def test_image_error_is_bounded(rng, kind, profile, within_db):
    """Run 4 at VEC 16, with the envelope's share of the bound (``dtau_s``): one measurement of a
    profile whose envelope moves by the most per sample (alternating signs), the measured error
    against the exact twin below the bound and within 10 dB of it; six measurements of random
    profiles (an image with no coherent peak, whose pairs' errors do not add up as the bound's
    worst case), below it and within 15 dB."""
    grid, tx, rx = _geometry(rng, kind)
    dtau = 1 / 48e3
    tau0, n_lags = _window(grid, tx, rx, dtau)
    n = 1 if profile == "alternating" else len(tx)
    if profile == "alternating":
        data = np.where(np.arange(n_lags) % 2, 1.0, -1.0)[None].astype(complex)
    else:
        data = rng.normal(size=(n, n_lags)) + 1j * rng.normal(size=(n, n_lags))
    err = _image_error(data, tau0[:n], dtau, tx[:n], rx[:n], grid, 4, 16)
    bound = twin.range_expansion_error(grid, tx[:n], rx[:n], 343.0, 25e3, 4, dtau)
    assert err <= bound and _db(err) > _db(bound) - within_db, (_db(err), _db(bound))


def test_error_bound_checks_its_inputs_and_is_zero_where_nothing_expands():
    grid = clsas.VoxelGrid(np.linspace(0, 0.1, 3), np.array([0.0]), np.linspace(0.5, 0.52, 3))  # 3 z < any run
    tx = np.zeros((2, 3))
    assert twin.range_expansion_error(grid, tx, tx, 343.0, 25e3, 4) == 0.0
    inside = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 3), np.array([0.0]), np.linspace(-0.1, 0.1, 8))
    assert twin.range_expansion_error(inside, tx, tx, 343.0, 25e3, 4) == np.inf  # a transducer in the box
    with pytest.raises(ValueError, match="tx_positions and rx_positions"):
        twin.range_expansion_error(grid, tx, tx[:1], 343.0, 25e3, 4)
    with pytest.raises(ValueError, match="run must be"):
        twin.range_expansion_error(grid, tx, tx, 343.0, 25e3, 0)
    with pytest.raises(ValueError, match="c_mps"):
        twin.range_expansion_error(grid, tx, tx, -1.0, 25e3, 4)
    with pytest.raises(ValueError, match="dtau_s"):
        twin.range_expansion_error(grid, tx, tx, 343.0, 25e3, 4, 0.0)
    with pytest.raises(TypeError, match="grid must be"):
        twin.range_expansion_error("grid", tx, tx, 343.0, 25e3, 4)
    with pytest.raises(ValueError, match="run must divide vec"):
        twin.expansion_layout(grid, 8, 4)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("local", [None, 16], ids=lambda n: f"local{n}")
@pytest.mark.parametrize("nz", [37, 32], ids=["rows-ragged", "rows-aligned"])
def test_range_expansion_equals_its_twin(rng, vec, local, nz):
    """-DRANGE_EXPANSION at every width the device accepts, at each run whose bound is within a loose
    ``max_error`` (the longest run within it; then each shorter one): its own twin's image to the
    plain kernel's tolerance, while that twin differs from the exact one by far more."""
    from clsas.formation.bp_opencl import BackprojectPlan

    width_or_skip("backproject", vec)
    grid, args = bp_kernel_case(rng, nz)
    plan = BackprojectPlan(grid, 12, 40, vec=vec, chunk=5, shape=cl.Shape(local, EXPANSION), max_error=0.9)
    plan.expansion_limit = 0.9  # errors far above the -50 dB a plan admits, to tell the expansion apart
    exact = twin.backproject(*args, grid.points())
    assert np.any(exact == 0) and np.any(exact != 0)
    runs = [r for r in (16, 8, 4) if r <= vec and twin.range_expansion_error(
        grid, args[4], args[5], args[6], args[3], r, args[2] / 2) <= 0.9]  # upsampled 2 x
    assert runs[-1] == 4
    for run in runs:
        plan.expansion_runs = tuple(r for r in runs if r <= run)
        got = plan(*args)
        assert plan.last_variant == EXPANSION and plan.last_expansion_run == run
        want = twin.backproject_range_expansion(*args, grid, run, vec)
        peak = np.abs(want).max()
        assert np.abs(got - want).max() < TOL["backproject"] * peak
        assert np.abs(want - exact).max() > 5 * TOL["backproject"] * peak  # the expansion, not the exact paths
        assert plan.last_error_bound == twin.range_expansion_error(grid, args[4], args[5], args[6], args[3], run,
                                                                   args[2] / 2)  # upsampled 2 x


@needs_opencl
def test_plan_expands_only_where_the_geometrys_bound_is_within_max_error(rng):
    """The plan takes the longest run whose bound is within ``max_error`` (-50 dB where None);
    where none is, it runs the plain kernel (the exact twin's image) and says so."""
    from clsas.formation.bp_opencl import EXPANSION_LIMIT, BackprojectPlan

    grid, args = bp_kernel_case(rng)
    fine = args[2] / 2
    bounds = {r: twin.range_expansion_error(grid, args[4], args[5], args[6], args[3], r, fine) for r in (4, 8, 16)}
    assert bounds[4] > EXPANSION_LIMIT  # this near geometry: not even the shortest run at -50 dB
    exact = twin.backproject(*args, grid.points())
    plan = BackprojectPlan(grid, 12, 40, vec=4, chunk=5, shape=cl.Shape(None, EXPANSION))
    got = plan(*args)
    assert (plan.last_variant, plan.last_expansion_run, plan.last_error_bound) == ("plain", 0, 0.0)
    assert np.abs(got - exact).max() < TOL["backproject"] * np.abs(exact).max()
    limit = (bounds[4] * bounds[8]) ** 0.5  # between the runs' bounds: run 4 is taken, not 8
    plan = BackprojectPlan(grid, 12, 40, vec=8, chunk=5, shape=cl.Shape(None, EXPANSION), max_error=limit)
    plan(*args)
    # an allowance above -50 dB never lets the expansion err more than -50 dB
    assert (plan.last_variant, plan.last_expansion_run) == ("plain", 0)
    plan.expansion_limit = 1.0  # lifted: the longest run within max_error
    got = plan(*args)
    assert (plan.last_variant, plan.last_expansion_run) == (EXPANSION, 4)
    assert np.abs(got - exact).max() < (bounds[4] + TOL["backproject"]) * np.abs(exact).max()
    # a far grid (the bench's kind: 10 mm voxels from 1 m): run 4 within -50 dB
    far = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 3), np.linspace(-0.1, 0.1, 3), np.linspace(1.0, 1.32, 33))
    plan = BackprojectPlan(far, 12, 40, vec=4, chunk=5, shape=cl.Shape(None, EXPANSION))
    plan(*args)
    assert plan.last_variant == EXPANSION and 0 < plan.last_error_bound <= EXPANSION_LIMIT


@needs_opencl
def test_range_expansion_is_a_candidate_only_where_max_error_admits_it():
    from clsas.formation.bp_opencl import EXPANSION_LIMIT, BackprojectPlan

    grid = clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0), (0.5, 0.6), 0.05)
    for max_error, tried in [(None, False), (EXPANSION_LIMIT / 2, False), (EXPANSION_LIMIT, True), (0.01, True)]:
        cands = BackprojectPlan(grid, 3, 10, shape=cl.Shape(), max_error=max_error).candidate_shapes()
        assert any(c.variant == EXPANSION for c in cands) == tried, max_error


@needs_opencl
@pytest.mark.parametrize("complex_image", [False, True], ids=["planes", "complex"])
def test_range_expansion_builds_with_a_beam_and_either_image(complex_image):
    from clsas.formation.bp_opencl import BackprojectPlan, selftest_beam_weights, selftest_scene

    _, prof, tau0, fs, tx, rx, c, rng = selftest_scene()
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 3), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, 37))
    w = selftest_beam_weights(rng, "weighted")
    plan = BackprojectPlan(grid, 3, 40, chunk=2, beam_lut=w.luts.shape[1], complex_image=complex_image,
                           shape=cl.Shape(16, EXPANSION), max_error=0.9)
    plan.expansion_limit = 0.9  # the kernel's arithmetic against its twin, at errors far above -50 dB
    got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c, beam=w)
    assert plan.last_variant == EXPANSION
    want = twin.backproject_range_expansion(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid, plan.last_expansion_run,
                                            plan.vec, beam=w)
    assert np.abs(got - want).max() < TOL["backproject"] * np.abs(want).max()


@needs_opencl
def test_the_variant_selftest_checks_the_expansion():
    """The probe's check of the variant (its selftest against its own twin) passes, and would not
    pass a kernel that computed the exact paths: on the selftest's scene the expanded twin and the
    exact one differ by more than the probe's tolerance."""
    from clsas.cl.shapes import TOLERANCE
    from clsas.formation.bp_opencl import SHORTEST_RUN, BackprojectPlan, selftest_scene

    q = cl.get_queue()
    vec = cl.choose(q, "backproject")
    assert BackprojectPlan.selftest(q, vec, cl.Shape(None, EXPANSION)) < TOL["backproject"]
    _, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 3), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, 37))
    exact = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points())
    expanded = twin.backproject_range_expansion(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid, SHORTEST_RUN, vec)
    assert np.abs(expanded - exact).max() > TOLERANCE * np.abs(expanded).max()
