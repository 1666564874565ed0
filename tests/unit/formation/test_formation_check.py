"""``formation="auto"`` measures a fast formation's error where its prediction is not enough
(clsas/formation/auto/measure.py): exact bp on a sub-lattice of the grid, and the steps auto takes in turn.

No test here asserts a time: which steps are measured is steered through the estimates given.
"""

import logging
import math

import numpy as np
import pytest

import clsas
from clsas.formation import error_to_signal_db, form
from clsas.formation.auto import choice, predict, rules, trust
from clsas.formation.auto import measure as check

FS = 96e3


@pytest.fixture(scope="module")
def scan():
    """A small planar scan, its profiles and a grid of 20 x 20 x 24 voxels (stride 1 at the default
    CHECK_VOXELS; the tests that need a sparser sub-lattice lower it)."""
    ap = clsas.raster_aperture(10, 10, 0.05, 0.05)
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    pts = np.array([[0.005, -0.004, 0.5], [-0.01, 0.006, 0.53]])
    ds = clsas.simulate(clsas.Scene(pts), ap, w, FS, snr_db=40, seed=3,
                        chirp={"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 2e-3})
    grid = clsas.VoxelGrid.from_bounds((-0.03, 0.03), (-0.03, 0.03), (0.46, 0.58), 0.005)
    prof = clsas.compress(ds, backend="numpy")
    ref = np.asarray(form(prof, grid, "bp", backend="numpy").values)
    return ds, grid, prof, ref


def test_sublattice_is_regular_and_reproducible(monkeypatch):
    monkeypatch.setattr(check, "CHECK_VOXELS", 64)
    grid = clsas.VoxelGrid(np.arange(40) * 0.01, np.arange(30) * 0.01, 1 + np.arange(20) * 0.01)
    sub, sl, s = check.sublattice(grid)
    assert s == check.stride_for(grid.shape) == 7  # floor((24000 / 64) ** (1 / 3))
    np.testing.assert_array_equal(sub.x_m, grid.x_m[sl[0]])
    np.testing.assert_array_equal(sub.z_m, grid.z_m[sl[2]])
    assert check.sublattice(grid)[1] == sl  # the same request, the same voxels
    monkeypatch.setattr(check, "CHECK_VOXELS", 10**9)
    assert check.stride_for(grid.shape) == 1
    monkeypatch.setattr(check, "CHECK_VOXELS", 1)
    assert check.stride_for(grid.shape) == check.MAX_STRIDE


def test_measured_error_of_uniform_noise_is_exact(scan, monkeypatch):
    """Analytic: an error of the same size on every voxel is measured exactly from any sub-lattice
    (the sub-lattice's error energy scaled by the share of the grid it covers, over the image's)."""
    _, grid, prof, ref = scan
    monkeypatch.setattr(check, "CHECK_VOXELS", 500)
    rng = np.random.default_rng(0)
    delta = 0.03 * np.abs(ref).max()
    values = ref + delta * np.exp(2j * np.pi * rng.random(ref.shape))
    want = 10 * math.log10(ref.size * delta**2 / np.sum(np.abs(values) ** 2))
    got = check.measure_error(prof, grid, values, backend="numpy")
    assert got.stride > 1 and got.voxels < grid.size
    assert got.error_db == pytest.approx(want, abs=1e-6)
    assert got.upper_db >= got.error_db - 1e-9
    exact = check.measure_error(prof, grid, ref, backend="numpy")
    assert exact.error_db < -250  # bp against itself: nothing


def test_measured_error_follows_the_whole_grids(scan):
    """At stride 1 (this grid) the measurement is the whole grid's error, against the profiles'
    bp (float64 twin): a formation's image is measured as error_to_signal_db measures it, but over
    the formed image's energy (within 0.3 dB at -30 dB)."""
    _, grid, prof, ref = scan
    img = np.asarray(form(prof, grid, "ffbp", backend="numpy", oversample=1.5, range_oversample=1.5).values)
    got = check.measure_error(prof, grid, img, backend="numpy")
    assert got.stride == 1
    assert got.error_db == pytest.approx(error_to_signal_db(img, ref), abs=0.3)


def test_measure_error_checks_its_inputs(scan):
    _, grid, prof, ref = scan
    with pytest.raises(ValueError, match="values"):
        check.measure_error(prof, grid, ref[:, :, :-1], backend="numpy")
    bad = ref.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="values"):
        check.measure_error(prof, grid, bad, backend="numpy")
    with pytest.raises(TypeError, match="profiles"):
        check.measure_error(ref, grid, ref, backend="numpy")
    with pytest.raises(TypeError, match="grid"):
        check.sublattice((1, 2, 3))


def _choice(steps, target):
    ests = tuple(e for e, _ in steps)
    return rules.Choice(steps[0][0].formation, dict(steps[0][0].options), "test", target, "test", ests, tuple(steps))


def test_a_step_that_misses_the_target_gives_way(scan, caplog):
    """FFBP at a coarse sampling, measured, misses a -200 dB target: auto forms bp instead, says so
    at WARNING, and records the measurement; at -1 dB it keeps FFBP."""
    _, grid, prof, ref = scan
    opts = {"oversample": 1.5, "range_oversample": 1.5}
    steps = [(trust.Estimate("ffbp", 1.0, -40.0, opts), True), (trust.Estimate("bp", 2.0, -math.inf), False)]
    with caplog.at_level(logging.WARNING, logger="clsas.formation.auto.measure"):
        img, rec = check.form_choice(prof, grid, _choice(steps, -200.0), backend="numpy")
    assert rec["formation"] == "bp" and np.allclose(img.values, ref)
    assert [c["kept"] for c in rec["checks"]] == [False] and rec["checks"][0]["formation"] == "ffbp"
    assert "forming bp instead" in caplog.text
    img, rec = check.form_choice(prof, grid, _choice(steps, -1.0), backend="numpy")
    assert rec["formation"] == "ffbp" and rec["options"] == opts and rec["checks"][0]["kept"]
    assert rec["checks"][0]["upper_db"] <= -1.0


def test_steps_measure_a_near_prediction_only_where_it_pays():
    """A formation predicted just over the target's margin is tried first (measured) only where it
    and its check take under CHECK_IF_UNDER of the best safe one; a safe fast formation is measured
    where its check costs at most CHECK_SHARE of it; the steps end at the first unmeasured one."""
    bp = trust.Estimate("bp", 10.0, -math.inf)
    near = trust.Estimate("omega-k", 1.0, -31.0)
    safe = trust.Estimate("omega-k", 6.0, -39.0, {"upsample": "auto"})
    far = trust.Estimate("ffbp", 0.5, -20.0)
    steps = trust._steps([bp, near, safe, far], -30.0, check_s=0.5)
    assert [(e.formation, e.options, m) for e, m in steps] == [
        ("omega-k", {}, True), ("omega-k", {"upsample": "auto"}, True), ("bp", {}, False)]
    steps = trust._steps([bp, near, safe, far], -30.0, check_s=2.5)  # 1 + 2.5 > 0.5 x 6; 2.5 > 0.1 x 6
    assert [(e.formation, m) for e, m in steps] == [("omega-k", False)]
    steps = trust._steps([bp, far], -30.0, check_s=0.1)
    assert [(e.formation, m) for e, m in steps] == [("bp", False)]


def test_reconstruct_records_what_was_measured(scan, monkeypatch):
    """Through clsas.reconstruct: auto's record in the image's provenance lists its steps and
    checks; where the first step is measured and kept, that formation is the image's."""
    ds, grid, prof, _ = scan
    real = trust._steps

    def measure_first(ests, target, check_s):  # whatever the model says, measure a fast formation first
        fast = next(e for e in ests if e.formation != "bp" and e.feasible)
        return ((fast, True),) + real(ests, target, check_s)

    monkeypatch.setattr(choice, "_steps", measure_first)
    img = clsas.reconstruct(ds, grid, backend="numpy", max_error_db=-1.0)
    rec = img.provenance["formation_auto"]
    assert rec["steps"][0]["measured"] and rec["checks"] and rec["checks"][0]["kept"]
    assert img.provenance["formation"] == rec["formation"] == rec["checks"][0]["formation"]


def test_command_line_prints_the_measurement(tmp_path, capsys, monkeypatch):
    """`clsas reconstruct` prints each step auto measured, and the image file keeps the record."""
    from clsas.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text('[chirp]\nf_start_hz = 20000.0\nf_stop_hz = 30000.0\nduration_s = 0.002\nfs_hz = 96000.0\n'
                     '[aperture]\nnx = 10\nny = 10\nwidth_m = 0.05\nheight_m = 0.05\n'
                     '[[points]]\nposition_m = [0.005, -0.004, 0.5]\n'
                     '[grid]\nx_m = [-0.03, 0.03]\ny_m = [-0.03, 0.03]\nz_m = [0.46, 0.58]\nspacing_m = 0.005\n')
    data = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(data), "-q", "--backend", "numpy"]) == 0
    real = trust._steps

    def measure_first(ests, target, check_s):
        fast = next(e for e in ests if e.formation != "bp" and e.feasible)
        return ((fast, True),) + real(ests, target, check_s)

    monkeypatch.setattr(choice, "_steps", measure_first)
    assert main(["reconstruct", str(data), "-q", "--backend", "numpy", "--max-error-db", "-1"]) == 0
    out = capsys.readouterr().out
    assert f"voxels (a stride of 1): {rec_db(tmp_path)}" in out and ": kept" in out
    rec = clsas.Image.load(tmp_path / "scan-image.h5").provenance["formation_auto"]
    assert rec["checks"][0]["kept"] and rec["steps"][0]["measured"]


def rec_db(folder) -> str:
    """The first check's error as `clsas reconstruct` prints it, from the image file's record."""
    rec = clsas.Image.load(folder / "scan-image.h5").provenance["formation_auto"]
    return f"{rec['checks'][0]['error_db']:.1f} dB"


def test_a_flat_grid_is_thinned_along_its_two_axes(monkeypatch):
    """A plane (one voxel deep) is thinned along x and y only: about CHECK_VOXELS voxels, not
    CHECK_VOXELS ** (2/3)."""
    monkeypatch.setattr(check, "CHECK_VOXELS", 4096)
    assert check.stride_for((201, 201, 1)) == 3  # floor(sqrt(40401 / 4096))
    assert check.stride_for((1, 1, 50000)) == 12  # a line: floor(50000 / 4096)
    grid = clsas.VoxelGrid(np.arange(201) * 0.01, np.arange(201) * 0.01, np.array([1.0]))
    sub, _, _ = check.sublattice(grid)
    assert 4096 <= sub.size <= 4624


def test_a_step_with_nan_gives_way(scan, monkeypatch):
    """A measured formation whose image comes out with NaN misses any target: auto forms the next
    step and records why, rather than failing."""
    import clsas.formation as formation

    _, grid, prof, ref = scan
    real = formation.form

    def broken(profiles, grid, name, **kw):
        img = real(profiles, grid, name, **kw)
        if name != "ffbp":
            return img
        values = np.array(img.values)
        values[0, 0, 0] = np.nan
        return img.__class__(**{**img.__dict__, "values": values})

    monkeypatch.setattr(formation, "form", broken)
    steps = [(trust.Estimate("ffbp", 1.0, -40.0, {"oversample": 1.5, "range_oversample": 1.5}), True),
             (trust.Estimate("bp", 2.0, -math.inf), False)]
    img, rec = check.form_choice(prof, grid, _choice(steps, -1.0), backend="numpy")
    assert rec["formation"] == "bp" and np.allclose(img.values, ref)
    assert rec["checks"][0]["error_db"] == "inf" and not rec["checks"][0]["kept"]


def test_an_unpredicted_formation_is_taken_only_measured():
    """Plain ω-k with aliased voxel-stop pairs is not taken on its prediction where its check costs
    at most as much as it (CHECK_UNPREDICTED_SHARE): it is formed and measured first where that pays,
    else the safe formation is taken; where the check would cost more, the prediction is trusted."""
    bp = trust.Estimate("bp", 10.0, -math.inf)
    wk = trust.Estimate("omega-k", 1.0, -42.0, unpredicted=True)
    steps = trust._steps([bp, wk], -30.0, check_s=0.5)
    assert [(e.formation, m) for e, m in steps] == [("omega-k", True), ("bp", False)]
    wk4 = trust.Estimate("omega-k", 4.0, -42.0, unpredicted=True)
    steps = trust._steps([bp, wk4], -30.0, check_s=3.0)  # 4 + 3 > 0.5 x 10: not worth measuring
    assert [(e.formation, m) for e, m in steps] == [("bp", False)]
    steps = trust._steps([bp, wk], -30.0, check_s=6.0)  # the check costs 6x ω-k: its prediction is trusted
    assert [(e.formation, m) for e, m in steps] == [("omega-k", False)]
    over = trust.Estimate("omega-k", 1.0, -20.0, unpredicted=True)  # predicted over the target: not tried
    assert [(e.formation, m) for e, m in trust._steps([bp, over], -30.0, check_s=0.5)] == [("bp", False)]


def test_omega_k_on_an_aliased_lattice_is_unpredicted():
    """The estimate marks plain ω-k unpredicted exactly where some voxel-stop pair aliases."""
    from clsas.formation.omega_k import plan_sizes

    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    chirp = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 2e-3}
    pts = np.array([[0.0, 0.0, 0.5]])
    grid = clsas.VoxelGrid.from_bounds((-0.03, 0.03), (-0.03, 0.03), (0.46, 0.54), 0.006)
    for pitch, aliased in ((0.0028, False), (0.012, True)):  # lambda/4 and 1 wavelength at 30 kHz
        ap = clsas.raster_aperture(16, 16, 15 * pitch, 15 * pitch)
        ds = clsas.simulate(clsas.Scene(pts), ap, w, FS, snr_db=40, chirp=chirp, seed=1)
        prof = clsas.compress(ds, backend="numpy")
        est = predict._omega_k_estimate(prof, grid, None, {})
        assert est.unpredicted is aliased is predict.lattice_aliases(plan_sizes(prof, grid))
