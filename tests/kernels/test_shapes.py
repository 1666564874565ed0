"""Work-group shapes (clsas.cl.shapes): the pick among timed shapes, the on-disk memory, the real
timing child; backproject.cl's -DLOCAL_PROFILES variant against the twin at every width."""

import json

import numpy as np
import pytest
from conftest import TOL, bp_kernel_case, needs_opencl, width_or_skip

import clsas
from clsas import cl
from clsas.cl import shapes
from clsas.formation import bp_numpy as twin

PLAIN, LOCAL = cl.Shape(), "local_profiles"


@pytest.fixture
def fresh_shapes(tmp_path, monkeypatch):
    """An empty cache (verdicts and tunings) on disk and in memory; restored afterwards."""
    from clsas.cl import variants

    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    saved = dict(shapes._MEMO), dict(variants._MEMO)
    shapes._MEMO.clear()
    yield tmp_path / "shapes"
    shapes._MEMO.clear()
    shapes._MEMO.update(saved[0])
    variants._MEMO.update(saved[1])


def test_pick_keeps_the_default_unless_another_shape_is_clearly_faster():
    a, b = cl.Shape(64), cl.Shape(16, LOCAL)
    assert shapes.pick({PLAIN: [1.0, 1.0], a: [0.97, 0.97], b: [1.2, 1.2]})[0] == PLAIN  # within the 5 % margin
    shape, why = shapes.pick({PLAIN: [1.0, 2.0, 1.0], a: [0.9, 1.8, 0.9], b: [0.5, 1.0, 0.5]})
    assert shape == b and "2.00x the default" in why
    # one round where the default was slowed by another process does not make a winner
    assert shapes.pick({PLAIN: [1.0, 3.0, 1.0], a: [1.0, 1.0, 1.0]})[0] == PLAIN
    assert shapes.pick({a: [0.9], b: [0.5]})[0] == b  # the default refused: the fastest that passed
    assert shapes.pick({})[0] == PLAIN


@pytest.mark.parametrize("bad, match", [(0, "positive int"), (2.0, "positive int"), (True, "positive int")])
def test_shape_rejects_bad_local_sizes(bad, match):
    with pytest.raises(ValueError, match=match):
        cl.Shape(bad)


@needs_opencl
def test_tuning_is_kept_on_disk_and_a_crash_is_the_default(monkeypatch, fresh_shapes):
    q = cl.get_queue()
    cands = [PLAIN, cl.Shape(16), cl.Shape(16, LOCAL)]
    calls = []

    def child(device, name, vec, candidates):
        calls.append(len(candidates))
        return {"rounds": {"plain/auto": [2.0, 2.1], "plain/16": [1.9, 2.0], "local_profiles/16": [1.0, 1.1]},
                "refused": {}}

    monkeypatch.setattr(shapes, "_run_child", child)
    monkeypatch.setattr(shapes, "busy", lambda device: None)
    t = shapes.tune(q, "backproject", 4, cands)
    assert t.shape == cl.Shape(16, LOCAL) and t.source == "probe" and calls == [3]
    stored = json.loads(next(fresh_shapes.glob("*.json")).read_text())
    assert stored["variant"] == LOCAL and stored["local"] == 16 and stored["device"] == q.device.name.strip()
    shapes._MEMO.clear()
    assert shapes.tune(q, "backproject", 4, cands).source == "cache" and calls == [3]  # read, not timed
    assert shapes.tune(q, "backproject", 4, cands[:2]).source == "probe" and calls == [3, 2]  # other candidates
    assert cl.clear_shapes() == 2 and not list(fresh_shapes.glob("*.json"))
    monkeypatch.setattr(shapes, "busy", lambda device: 7.5)  # a busy host keeps the default, for now
    t = shapes.tune(q, "backproject", 4, cands)
    assert t.shape == PLAIN and "busy" in t.reason and t.seconds["local_profiles/16"] == 1.0 and t.provisional
    shapes._MEMO.clear()
    assert shapes.tune(q, "backproject", 4, cands).source == "cache"  # still busy, or not yet an hour old
    monkeypatch.setattr(shapes, "busy", lambda device: None)
    monkeypatch.setattr(shapes.time, "time", lambda: t.when_s + shapes.RETIME_S + 1)
    shapes._MEMO.clear()
    t = shapes.tune(q, "backproject", 4, cands)  # quiet and old: timed again
    assert t.source == "probe" and t.shape == cl.Shape(16, LOCAL) and not t.provisional
    monkeypatch.undo()
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(fresh_shapes.parent))
    shapes._MEMO.clear()
    cl.clear_shapes()
    monkeypatch.setattr(shapes, "_run_child", lambda *a: None)
    t = shapes.tune(q, "backproject", 4, cands)
    assert t.shape == PLAIN and "crashed" in t.reason


@needs_opencl
def test_the_timing_child_checks_and_times_real_shapes(fresh_shapes):
    """The real child on the default device: every candidate checked against the twin and timed
    (or refused with its reason), and the chosen shape is one that passed."""
    q = cl.get_queue()
    vec = cl.choose(q, "backproject")
    cands = [PLAIN, cl.Shape(16, LOCAL)]
    t = shapes.tune(q, "backproject", vec, cands)
    assert t.source == "probe" and set(t.seconds) | set(t.refused) == {c.label for c in cands}, t
    assert all(s > 0 for s in t.seconds.values())
    assert t.shape.label in t.seconds
    assert cl.runtime_record(q)["kernels_shape"]["backproject"] == t.shape.label  # provenance names it


@needs_opencl
def test_plan_checks_the_shape_it_is_given():
    from clsas.formation.bp_opencl import BackprojectPlan

    grid = clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0), (0.5, 0.6), 0.05)
    with pytest.raises(ValueError, match="no variant 'taylor'"):
        BackprojectPlan(grid, 3, 10, shape=cl.Shape(16, "taylor"))
    with pytest.raises(ValueError, match="needs a local size"):
        BackprojectPlan(grid, 3, 10, shape=cl.Shape(None, LOCAL))
    with pytest.raises(ValueError, match="exceeds the device"):
        BackprojectPlan(grid, 3, 10, shape=cl.Shape(1 << 20))
    with pytest.raises(TypeError, match="'auto' or a clsas.cl.Shape"):
        BackprojectPlan(grid, 3, 10, shape=16)


def test_staged_records_cover_every_groups_spread(rng):
    """The run a work-group stages holds every left sample its voxels read: the spread of
    floor(idx) over each group of consecutive voxels, brute force, stays within the bound."""
    from clsas.formation.bp_opencl import staged_records

    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 7), np.linspace(-0.05, 0.05, 5), np.linspace(0.4, 0.7, 11))
    pts = grid.points()
    tx = np.c_[rng.uniform(-0.5, 0.5, (20, 2)), np.zeros(20)]
    rx = tx + [0.03, 0, 0]
    per_m = 96e3 / 343.0
    for per_group in (4, 16, 37, 64, 400):
        bound = staged_records(grid, per_group, per_m)
        path = np.linalg.norm(pts[None] - tx[:, None], axis=2) + np.linalg.norm(pts[None] - rx[:, None], axis=2)
        k = np.floor(path * per_m)
        spread = max((k[:, g:g + per_group].max(axis=1) - k[:, g:g + per_group].min(axis=1)).max()
                     for g in range(0, grid.size, per_group))
        assert spread <= bound - 2, (per_group, spread, bound)
        assert bound <= 2 * np.linalg.norm(grid.bounds()[:, 1] - grid.bounds()[:, 0]) * per_m + 3


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("local", [1, 4, 16], ids=lambda n: f"local{n}")
def test_local_profiles_equal_twin(rng, vec, local):
    """-DLOCAL_PROFILES (records staged per work-group) at every width the device accepts: the
    twin's image to the plain kernel's tolerance, the staged run really used."""
    from clsas.formation.bp_opencl import BackprojectPlan, upsample_factor

    width_or_skip("backproject", vec)
    grid, args = bp_kernel_case(rng, 17)
    plan = BackprojectPlan(grid, 12, 40, vec=vec, chunk=5, shape=cl.Shape(local, LOCAL))
    fine = args[2] / upsample_factor(args[3], args[2])
    assert plan.n_pad % (vec * local) == 0 and len(plan._staging(fine, args[6])[1]) == 3
    got = plan(*args)
    want = twin.backproject(*args, grid.points())
    assert np.any(want == 0) and np.any(want != 0)
    assert np.abs(got - want).max() < TOL["backproject"] * np.abs(want).max()


@needs_opencl
@pytest.mark.parametrize("local", [1, 16], ids=lambda n: f"local{n}")
def test_plain_kernel_with_a_local_size_equals_twin(rng, local):
    from clsas.formation.bp_opencl import BackprojectPlan

    grid, args = bp_kernel_case(rng, 13)
    got = BackprojectPlan(grid, 12, 40, chunk=5, shape=cl.Shape(local))(*args)
    want = twin.backproject(*args, grid.points())
    assert np.abs(got - want).max() < TOL["backproject"] * np.abs(want).max()


@needs_opencl
def test_a_run_too_long_for_local_memory_runs_the_plain_kernel(rng, monkeypatch):
    from clsas.formation import bp_opencl

    grid, args = bp_kernel_case(rng, 13)
    plan = bp_opencl.BackprojectPlan(grid, 12, 40, chunk=5, shape=cl.Shape(4, LOCAL))
    monkeypatch.setattr(bp_opencl, "staged_records", lambda *a: plan.queue.device.local_mem_size // 16)
    kern, extra = plan._staging(args[2] / bp_opencl.upsample_factor(args[3], args[2]), args[6])
    assert extra == () and kern is not plan.kernel
    got = plan(*args)
    want = twin.backproject(*args, grid.points())
    assert np.abs(got - want).max() < TOL["backproject"] * np.abs(want).max()


def _has_fp16() -> bool:
    return "cl_khr_fp16" in cl.get_queue().device.extensions.split()


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("local", [None, 16], ids=lambda n: f"local{n}")
def test_half_profiles_equal_twin(rng, vec, local):
    """-DHALF_PROFILES (records stored as half, scaled into its range) at every width the device
    accepts, on profiles far beyond half's range (1e6): the twin's image to HALF_TOLERANCE."""
    from clsas.formation.bp_opencl import HALF_TOLERANCE, BackprojectPlan

    if not _has_fp16():
        pytest.skip(f"{cl.describe(cl.get_queue().device)} does not report cl_khr_fp16")
    width_or_skip("backproject", vec)
    grid, args = bp_kernel_case(rng, 17)
    args = (args[0] * 1e6, *args[1:])
    plan = BackprojectPlan(grid, 12, 40, vec=vec, chunk=5, shape=cl.Shape(local, "half_profiles"))
    got = plan(*args)
    want = twin.backproject(*args, grid.points())
    err = np.abs(got - want).max() / np.abs(want).max()
    assert TOL["backproject"] / 100 < err < HALF_TOLERANCE, err  # half, not float records: rounded more


@needs_opencl
def test_half_profiles_only_where_the_device_reports_fp16():
    from clsas.formation.bp_opencl import BackprojectPlan

    grid = clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0), (0.5, 0.6), 0.05)
    if _has_fp16():
        assert BackprojectPlan(grid, 3, 10, shape=cl.Shape(None, "half_profiles")).shape.variant == "half_profiles"
    else:
        with pytest.raises(ValueError, match="needs a device with cl_khr_fp16"):
            BackprojectPlan(grid, 3, 10, shape=cl.Shape(None, "half_profiles"))
    cands = BackprojectPlan(grid, 3, 10, shape=PLAIN).candidate_shapes()  # what the tuning tries here
    assert PLAIN in cands and cl.Shape(16, LOCAL) in cands and cl.Shape(None, LOCAL) not in cands
    assert not any(c.variant == "half_profiles" for c in cands)  # less exact: only where max_error admits it
    cands = BackprojectPlan(grid, 3, 10, shape=PLAIN, max_error=1e-3).candidate_shapes()
    assert any(c.variant == "half_profiles" for c in cands) == _has_fp16()
    assert not any(c.variant == "half_profiles"
                   for c in BackprojectPlan(grid, 3, 10, shape=PLAIN, max_error=1e-4).candidate_shapes())
    with pytest.raises(ValueError, match="max_error must be"):
        BackprojectPlan(grid, 3, 10, max_error=0.0)


@needs_opencl
def test_records_made_on_the_device_run_the_plain_kernel_under_half_profiles(rng):
    """The resident path's records are float (records.cl): a half-profiles plan reads them with the
    plain kernel, the twin's image to the plain tolerance."""
    from clsas.formation.bp_opencl import BackprojectPlan, RecordsPlan, selftest_scene, upsample_factor

    if not _has_fp16():
        pytest.skip(f"{cl.describe(cl.get_queue().device)} does not report cl_khr_fp16")
    grid, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    plan = BackprojectPlan(grid, 3, 40, chunk=2, complex_image=True, shape=cl.Shape(None, "half_profiles"))
    d_prof = plan.upload(prof, np.complex64)

    class Rows:
        buffer, n_rows, n_cols, stride = d_prof, 3, 40, 40

    records = RecordsPlan(3, 40, upsample_factor(25e3, 1 / fs), queue=plan.queue)
    got = plan.from_device(Rows, records, tau0, 1 / fs, 25e3, tx, rx, c)
    want = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points())
    assert np.abs(got - want).max() < TOL["backproject"] / 4 * np.abs(want).max()  # float records: no half rounding


@needs_opencl
@pytest.mark.parametrize("shape", [cl.Shape(16), cl.Shape(16, LOCAL), cl.Shape(None, "half_profiles")],
                         ids=lambda s: s.label)
@pytest.mark.parametrize("complex_image", [False, True], ids=["planes", "complex"])
def test_every_variant_builds_with_a_beam_and_either_image(shape, complex_image):
    """The variants with -DBEAM (a tilted piston speaker, a cone microphone) and with the complex
    image: the beam twin's image, to the variant's tolerance."""
    from clsas.formation.bp_opencl import HALF_TOLERANCE, BackprojectPlan, selftest_beam_weights, selftest_scene

    if shape.variant == "half_profiles" and not _has_fp16():
        pytest.skip(f"{cl.describe(cl.get_queue().device)} does not report cl_khr_fp16")
    grid, prof, tau0, fs, tx, rx, c, rng = selftest_scene()
    w = selftest_beam_weights(rng, "weighted")
    plan = BackprojectPlan(grid, 3, 40, chunk=2, beam_lut=w.luts.shape[1], complex_image=complex_image, shape=shape)
    got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c, beam=w)
    want = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points(), beam=w)
    tol = HALF_TOLERANCE if shape.variant == "half_profiles" else TOL["backproject"]
    assert np.abs(got - want).max() < tol * np.abs(want).max()
