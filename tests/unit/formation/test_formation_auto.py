"""``formation="auto"`` (clsas/formation/auto/): what it may choose, what it records, its calibration.

No test here asserts a time: the cost model is steered with calibration factors where a test
needs a given formation to be the fastest.
"""

import math

import numpy as np
import pytest

import clsas
from clsas.formation import auto, error_to_signal_db, form
from clsas.formation.auto import predict, timing
from clsas.formation.omega_k import plan_sizes
from clsas.formation.planar import well_sampled_cone

FS = 96e3
CHIRP = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 2e-3}


def _planar(n: int, pitch: float, grid_half: float, spacing: float = 0.006):
    """n x n stops ``pitch`` apart, two reflectors at 0.5 m, a grid of +-grid_half laterally."""
    side = pitch * (n - 1)
    ap = clsas.raster_aperture(n, n, side, side)
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    pts = np.array([[0.01, -0.01, 0.5], [-0.015, 0.01, 0.54]])
    ds = clsas.simulate(clsas.Scene(pts), ap, w, FS, snr_db=40, chirp=CHIRP, seed=1)
    grid = clsas.VoxelGrid.from_bounds((-grid_half, grid_half), (-grid_half, grid_half), (0.46, 0.58), spacing)
    return ds, grid


@pytest.fixture(scope="module")
def dense():
    """A well-sampled planar scan (stops lambda/4 apart at 30 kHz) and its profiles."""
    ds, grid = _planar(24, 0.0028, 0.03)
    return ds, grid, clsas.compress(ds, backend="numpy")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    return tmp_path


def test_max_error_db_is_checked_by_name(dense):
    ds, grid, _ = dense
    with pytest.raises(ValueError, match="max_error_db"):
        clsas.reconstruct(ds, grid, backend="numpy", max_error_db=3.0)
    with pytest.raises(ValueError, match="max_error_db"):
        clsas.reconstruct(ds, grid, backend="numpy", max_error_db=float("nan"))
    with pytest.raises(TypeError, match="max_error_db"):
        clsas.reconstruct(ds, grid, backend="numpy", max_error_db="-30")
    with pytest.raises(ValueError, match="formation_options"):
        clsas.reconstruct(ds, grid, backend="numpy", formation_options={"upsample": 2})
    with pytest.raises(ValueError, match="'auto'"):
        clsas.reconstruct(ds, grid, backend="numpy", formation="fourier")


def test_alias_fraction_zero_at_quarter_wavelength_and_large_when_undersampled(dense):
    _, grid, prof = dense
    assert auto.alias_fraction(plan_sizes(prof, grid)).max() == 0.0
    ds, grid2 = _planar(6, 0.03, 0.1)  # stops 2.6 lambda apart at 30 kHz
    frac = auto.alias_fraction(plan_sizes(clsas.compress(ds, backend="numpy"), grid2))
    # every stop that sees a voxel off its own axis by more than asin(lambda / 4d) is aliased
    assert frac.mean() > 0.5


def test_auto_never_takes_omega_k_where_its_error_is_over_the_target(cache):
    ds, grid = _planar(6, 0.03, 0.1)
    prof = clsas.compress(ds, backend="numpy")
    auto.store_calibration({"omega-k": 1e-6, "ffbp": 1e6})  # omega-k would be by far the fastest
    choice = auto.choose(prof, grid, None)
    ok = next(e for e in choice.estimates if e.formation == "omega-k")
    assert ok.error_db > -30 - auto.MARGIN_DB
    assert choice.formation == "bp"
    assert "omega-k" in choice.reason and "over the target" in choice.reason


def test_auto_refuses_omega_k_on_a_circle_and_says_why(cache):
    ap = clsas.circular_aperture(48, 0.5, mode="arc")
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = clsas.simulate(clsas.Scene(np.array([[0.02, 0.0, 0.0]])), ap, w, FS, chirp=CHIRP)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (-0.01, 0.01), 0.01)
    auto.store_calibration({"bp": 1e3, "omega-k": 1e-6})
    choice = auto.choose(clsas.compress(ds, backend="numpy"), grid, None)
    ok = next(e for e in choice.estimates if e.formation == "omega-k")
    assert not ok.feasible and "planar" in ok.note
    assert choice.formation in ("bp", "ffbp")


def test_auto_takes_omega_k_where_it_is_fastest_and_stays_under_the_target(dense, cache):
    ds, grid, prof = dense
    auto.store_calibration({"bp": 1e3, "ffbp": 1e3})  # bp and FFBP made slow: omega-k must win
    img = clsas.reconstruct(ds, grid, backend="numpy", max_error_db=-30)
    record = img.provenance["formation_auto"]
    assert img.provenance["formation"] == record["formation"] == "omega-k"
    assert "omega-k" in record["reason"] and "calibrated" in record["model"]
    ref = form(prof, grid, "bp", backend="numpy")
    cone = well_sampled_cone(ds.tx_positions, ds.rx_positions, grid, 30e3, float(np.mean(ds.c_mps)))
    assert cone.mean() > 0.9
    assert error_to_signal_db(img, ref) <= -30
    # a target the model cannot promise for omega-k (-42 dB, 3 dB margin): bp, or FFBP oversampled enough
    img = clsas.reconstruct(ds, grid, backend="numpy", max_error_db=-40)
    record = img.provenance["formation_auto"]
    assert record["formation"] != "omega-k"
    if record["formation"] == "ffbp":
        assert error_to_signal_db(img, ref) <= -40


def test_auto_choice_is_kept_in_the_image_file(dense, cache, tmp_path):
    ds, grid, _ = dense
    img = clsas.reconstruct(ds, grid, backend="numpy")
    back = clsas.Image.load(img.save(tmp_path / "img.h5"))
    kept = back.provenance["formation_auto"]
    assert kept["formation"] == img.provenance["formation"]
    assert kept["reason"] and kept["max_error_db"] == -30
    names = {e["formation"] for e in kept["estimates"]}
    assert "bp" in names


def test_calibration_round_trip_and_bad_files(cache):
    assert auto.load_calibration() == {}
    path = auto.store_calibration({"bp": 2.0, "omega-k": 0.5}, detail={"cases": 3})
    assert path.is_file() and path.parent.name == "formation_cost"
    assert auto.load_calibration() == {"bp": 2.0, "omega-k": 0.5}
    path.write_text("{not json")
    assert auto.load_calibration() == {}


def test_ffbp_error_model_grows_with_depth_and_falls_with_oversampling():
    assert predict.FFBP_BASE_DB[2.0] + 20 * math.log10(5) > predict.FFBP_BASE_DB[2.0] + 20 * math.log10(3)
    base = predict.FFBP_BASE_DB
    assert sorted(base.values(), reverse=True) == [base[o] for o in predict.FFBP_CANDIDATES]


def test_plan_sizes_count_what_omega_k_transforms(dense):
    _, grid, prof = dense
    sizes = plan_sizes(prof, grid)
    info = form(prof, grid, "omega-k", backend="numpy").provenance["omega_k"]
    (g,) = sizes["groups"]
    (lat,) = info["lattices"]
    assert (g["mu"], g["mv"]) == tuple(lat["padded"]) and g["up"] == lat["upsample"]
    assert g["columns"] == lat["columns"] and g["n_cells"] == lat["cells"]
    assert abs(sizes["n_f"] - info["n_f"]) <= 0.1 * info["n_f"]  # the band from a subset of the profiles


def test_cli_reconstruct_says_what_auto_chose(dense, tmp_path, capsys):
    from clsas.cli import main

    ds, grid, _ = dense
    ds.save(tmp_path / "scan.h5")
    (x0, x1), (y0, y1), (z0, z1) = grid.bounds()
    args = ["reconstruct", str(tmp_path / "scan.h5"), f"--grid={x0},{x1},{y0},{y1},{z0},{z1}", "--spacing", "0.006",
            "--backend", "numpy", "-q", "--max-error-db", "-35", "--out", str(tmp_path / "img.h5")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "formation: " in out and "auto, error target -35 dB" in out
    back = clsas.Image.load(tmp_path / "img.h5")
    assert back.provenance["formation_auto"]["max_error_db"] == -35
    with pytest.raises(SystemExit):
        main([*args[:-2], "--formation", "fourier"])


def test_alias_fraction_counts_the_share_of_frequencies_above_each_pairs_limit():
    # the per-pair search against a test at every frequency, written out
    import math

    from clsas.formation.omega_k import plan_sizes

    ds, grid = _planar(10, 0.03, 0.03)  # 30 mm stops: aliased at 30 kHz off the normal
    sizes = plan_sizes(clsas.compress(ds, backend="numpy"), grid)
    got = auto.alias_fraction(sizes, n_vox=5, n_stops=25, n_freq=6)
    pu, pv, depth = sizes["axes"]

    def sub(a):
        return a[np.unique(np.linspace(0, len(a) - 1, min(len(a), 5)).astype(int))]

    U, V, W = np.meshgrid(sub(pu), sub(pv), sub(depth), indexing="ij")
    k2 = 4 * np.pi * np.linspace(max(sizes["f_band_hz"][0], 1.0), sizes["f_top_hz"], 6) / sizes["c_mps"]
    g = sizes["aperture"].groups[0]
    (u0, u1), (v0, v1) = g.extent_uv
    su = np.linspace(u0, u1, min(g.shape[0], int(math.sqrt(25)) + 1))
    sv = np.linspace(v0, v1, min(g.shape[1], int(math.sqrt(25)) + 1))
    SU, SV = (a.ravel() for a in np.meshgrid(su, sv, indexing="ij"))
    du, dv = U[..., None] - SU, V[..., None] - SV
    r = np.sqrt(du**2 + dv**2 + W[..., None] ** 2)
    lim_u, lim_v = np.pi / g.spacing_uv[0], np.pi / g.spacing_uv[1]
    bad = (k2 * np.abs(du / r)[..., None] > lim_u) | (k2 * np.abs(dv / r)[..., None] > lim_v)
    want = (bad.mean(axis=-1) / r**2).sum(axis=-1) / (1 / r**2).sum(axis=-1)
    assert 0 < want.max() and np.allclose(got, want, rtol=0, atol=1e-12)


def _fake_selection(kind: str, units: int):
    """A selection whose device is a GPU or a CPU of ``units`` compute units (only what the cost model reads)."""
    from types import SimpleNamespace

    cl = pytest.importorskip("pyopencl")
    dev = SimpleNamespace(type=getattr(cl.device_type, kind), max_compute_units=units)
    return SimpleNamespace(kind="opencl", queue=SimpleNamespace(device=dev))


def test_device_kinds_in_the_cost_model(dense, cache, monkeypatch):
    """omega-k's host work gains little from many cores (16 cores: about 1.5x the 2-core reference,
    not 8x); bp's fixed part on a GPU is 1.5 ms, so a scan a GPU forms in milliseconds is not sized
    for omega-k (sizing alone took longer than bp there)."""
    ds, grid, prof = dense
    sizes = plan_sizes(prof, grid)
    cpu2, gpu = _fake_selection("CPU", 2), _fake_selection("GPU", 132)
    work = timing.work_omega_k(sizes)
    monkeypatch.setattr("os.cpu_count", lambda: 16)
    t16 = timing._seconds("omega-k", work, cpu2, {})
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    t2 = timing._seconds("omega-k", work, cpu2, {})
    fixed = timing.BUILTIN["omega-k"]["fixed"]
    assert (t2 - fixed) / (t16 - fixed) == pytest.approx(8**timing.OMEGA_K_CORE_EXPONENT)
    assert 1.2 < 8**timing.OMEGA_K_CORE_EXPONENT < 2
    assert timing._seconds("bp", {"fixed": 1, "pairs": 0}, gpu, {}) == pytest.approx(timing.GPU_FIXED["bp"])
    assert timing._seconds("bp", {"fixed": 1, "pairs": 0}, cpu2, {}) == pytest.approx(timing.BUILTIN["bp"]["fixed"])
    ds, grid = _planar(12, 0.0028, 0.015)  # a scan PoCL's fixed part would have had sized for omega-k
    prof = clsas.compress(ds, backend="numpy")
    ests = {e.formation: e for e in auto.estimate(prof, grid, gpu)}
    assert ests["bp"].time_s < ests["omega-k"].time_s and "not sized" in ests["omega-k"].note
    monkeypatch.setitem(timing.GPU_FIXED, "bp", 1e-2)  # with a slow enough bp, omega-k is worth sizing
    assert "not sized" not in {e.formation: e for e in auto.estimate(prof, grid, gpu)}["omega-k"].note


def test_omega_k_on_few_stops_a_side_is_predicted_worse_and_left_to_bp():
    """Lattices of fewer than 16 stops a side were never in the fits of omega-k's error; on the formation
    family's fit seeds 8-10 a side measured -27.8 to -40.5 dB. The model counts it, and at 9 a side omega-k
    no longer passes the -30 dB target with its margin, however fast it is."""
    err = {}
    for n in (9, 12, 16, 24):
        ds, grid = _planar(n, 0.0028, 0.01)
        est = predict._omega_k_estimate(clsas.compress(ds, backend="numpy"), grid, None, {})
        err[n] = est.error_db
        assert f"({n} stops on the lattice's shorter side)" in est.note
    assert err[9] > -30 and err[9] > err[12] > err[16]
    assert err[16] == pytest.approx(err[24]) == pytest.approx(predict.OMEGA_K_BASE_DB, abs=0.5)
    ds, grid = _planar(9, 0.0028, 0.01)
    prof = clsas.compress(ds, backend="numpy")  # bp made slow enough that omega-k is sized
    ests = {e.formation: e for e in auto.estimate(prof, grid, None, factors={"bp": 1e3})}
    assert ests["omega-k"].error_db > auto.DEFAULT_MAX_ERROR_DB - auto.MARGIN_DB


def test_alias_fraction_skips_the_sum_where_no_pair_can_alias(dense, monkeypatch):
    """Where even the steepest voxel-stop pair is sampled unaliased at the band's top, the share is
    zero without the sum (a millisecond of auto's choosing on small scans); the sum agrees, here and
    on a coarse lattice where it is not zero."""
    from clsas.formation.omega_k import plan_sizes

    ds, grid, prof = dense
    coarse_ds, coarse_grid = _planar(12, 0.02, 0.04)
    zero = []
    for sizes in (plan_sizes(prof, grid), plan_sizes(clsas.compress(coarse_ds, backend="numpy"), coarse_grid)):
        quick = auto.alias_fraction(sizes)
        zero.append(not quick.any())
        monkeypatch.setattr(predict, "_never_aliased", lambda *a: False)
        full = auto.alias_fraction(sizes)
        monkeypatch.undo()
        assert np.allclose(quick, full)
    assert zero == [True, False]  # the dense lattice (lambda/4) never aliases; the coarse (20 mm) does


def test_auto_weighs_omega_k_with_its_aliased_angles_formed():
    """Where the lattice samples the band's top aliased and plain omega-k misses the target, auto also
    sizes omega-k with upsample="auto" (it forms the aliased angles on a finer lattice), with an error
    of its own; what it chooses runs as chosen and meets the target."""
    ds, grid = _planar(20, 0.012, 0.05, spacing=0.004)
    prof = clsas.compress(ds, backend="numpy")
    ests = auto.estimate(prof, grid, None, factors={"bp": 1e3})
    oks = [e for e in ests if e.formation == "omega-k"]
    assert [e.options for e in oks] == [{}, {"upsample": "auto"}]
    plain, up = oks
    assert plain.error_db > auto.DEFAULT_MAX_ERROR_DB - auto.MARGIN_DB > up.error_db
    assert "lattice 2x as fine" in up.note or "lattice 3x as fine" in up.note
    assert up.time_s > plain.time_s
    img = form(prof, grid, "omega-k", backend="numpy", **up.options)
    ref = form(prof, grid, "bp", backend="numpy")
    assert error_to_signal_db(img.values, ref.values) <= auto.DEFAULT_MAX_ERROR_DB


def test_omega_k_upsampled_is_not_weighed_past_its_steepest_angle(monkeypatch):
    """Past a sine of OMEGA_K_UP_MAX_SINE the upsampled omega-k measured over its predicted error (the
    128 x 128-stop crossover scan: -27 dB predicted -36), so auto does not weigh it there, and says so."""
    ds, grid = _planar(20, 0.012, 0.05, spacing=0.004)
    prof = clsas.compress(ds, backend="numpy")
    monkeypatch.setattr(predict, "OMEGA_K_UP_MAX_SINE", 0.05)
    oks = [e for e in auto.estimate(prof, grid, None, factors={"bp": 1e3}) if e.formation == "omega-k"]
    assert oks[1].options == {"upsample": "auto"} and not oks[1].feasible
    assert "past a sine of 0.05" in oks[1].note
