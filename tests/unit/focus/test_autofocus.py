"""Autofocus (clsas/autofocus, kernels/autofocus.cl): the gradient kernel against its twin and
finite differences, simulated errors with their truth, and what autofocus recovers."""

import numpy as np
import pytest
from conftest import BACKENDS, needs_opencl, width_or_skip

import clsas
from clsas.focus import FOCUS_METHODS, autofocus, score
from clsas.focus import gradient_numpy as twin
from clsas.focus.engine import FocusEngine
from clsas.focus.metrics import metric_and_weight
from clsas.physics.scan_errors import HandMotion, hand_motion

FS = 96e3
POINTS = [[0.02, -0.01, 0.6], [-0.05, 0.03, 0.65], [0.06, 0.04, 0.62], [-0.03, -0.05, 0.58]]


def scan(points=POINTS, nx=13, ny=9, width=0.3, height=0.2, **errors):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ap = clsas.raster_aperture(nx, ny, width, height)
    return clsas.simulate(clsas.Scene(np.asarray(points, float)), ap, w, FS, snr_db=30, direct_gain=1.0, **errors)


GRID = clsas.VoxelGrid.from_bounds((-0.09, 0.09), (-0.08, 0.07), (0.55, 0.69), 0.004)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("shape", [(9, 7, 5), (13, 1, 11)], ids=["volume", "plane"])
def test_gradient_kernel_equals_twin(rng, vec, shape):
    from clsas.focus.gradient_opencl import FocusGradientPlan

    width_or_skip("focus_gradient", vec)
    ds = scan(nx=7, ny=5)
    p = clsas.compress(ds, gate_s=(3e-3, 4.5e-3), backend="numpy")
    grid = clsas.VoxelGrid(np.linspace(-0.08, 0.08, shape[0]), np.linspace(-0.05, 0.05, shape[1]),
                           np.linspace(0.56, 0.68, shape[2]))
    weight = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    plan = FocusGradientPlan(grid, p.n_meas, p.n_lags, vec=vec, chunk=6, n_items=3)  # chunks that do not divide
    got = plan(p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, ds.c_mps, weight)
    want = twin.focus_gradient(p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, ds.c_mps,
                               grid.points(), weight)
    # float32 sums over voxels of terms of both signs: relative to the largest |sum| of each column
    err = np.abs(got - want).max(axis=0) / np.abs(want).max(axis=0)
    assert np.all(err < 2e-4), err


@pytest.mark.parametrize("metric", ["sharpness", "entropy"])
def test_metric_weight_is_its_derivative(rng, metric):
    values = rng.normal(size=200) + 1j * rng.normal(size=200)
    m, g = metric_and_weight(values, metric)
    for _ in range(3):
        d = rng.normal(size=200) + 1j * rng.normal(size=200)
        h = 1e-6
        fd = (metric_and_weight(values + h * d, metric)[0] - metric_and_weight(values - h * d, metric)[0]) / (2 * h)
        assert fd == pytest.approx(float(np.sum((np.conj(g) * d).real)), rel=1e-5)
    assert metric_and_weight(3.0 * values, metric)[0] == pytest.approx(m)  # scale-free


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_matches_finite_differences(backend):
    ds = scan(nx=7, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.08, 0.08), (-0.06, 0.06), (0.56, 0.68), 0.006)
    eng = FocusEngine(ds, grid, backend=backend)
    shift = np.random.default_rng(0).normal(0, 3e-6, ds.n_meas)
    c = ds.c_per_meas
    _, sums, _ = eng.evaluate(shift, c)
    tol = 1e-4 if backend == "numpy" else 2e-2  # float32 image and sums on the device
    h = 1e-8
    for k in (0, 17, 30):
        e = np.zeros(ds.n_meas)
        e[k] = h
        fd = (eng.evaluate(shift + e, c, False)[0] - eng.evaluate(shift - e, c, False)[0]) / (2 * h)
        assert -sums[k, 0] == pytest.approx(fd, rel=tol, abs=tol * np.abs(sums[:, 0]).max())
    # c moves every delay: a larger step crosses more interpolation knots, where the slope jumps
    fd_c = (eng.evaluate(shift, c + 0.002, False)[0] - eng.evaluate(shift, c - 0.002, False)[0]) / 0.004
    assert np.sum(-sums[:, 4] / c**2) == pytest.approx(fd_c, rel=max(tol, 1e-2))
    # a shift of the carriage along x: the position columns
    step = 1e-6 if backend == "numpy" else 2e-5  # float32 positions and image on the device
    move = np.zeros((ds.n_meas, 3))
    move[5, 0] = step
    fd_x = (metric_and_weight(eng.image(shift, c, ds.tx_positions + move, ds.rx_positions + move))[0]
            - metric_and_weight(eng.image(shift, c, ds.tx_positions - move, ds.rx_positions - move))[0]) / (2 * step)
    assert sums[5, 1] / c[5] == pytest.approx(fd_x, rel=max(tol, 1e-3), abs=1e-3 * np.abs(sums[:, 1:4]).max() / c[5])


def test_hand_motion_is_band_limited_and_scaled():
    d = hand_motion(400, 0.003, (0.2, 5.0), 0.02, seed=3)
    assert np.sqrt(np.mean(np.sum(d**2, axis=1))) == pytest.approx(0.003)
    spec = np.abs(np.fft.rfft(d, axis=0)) ** 2
    f = np.fft.rfftfreq(400, 0.02)
    assert spec[f > 7].sum() < 0.02 * spec.sum()  # the record's edges leak a little, no more
    per_axis = HandMotion(0.002, per_axis=True, weights=(1, 1, 0)).displacements(100)
    assert np.sqrt(np.mean(per_axis[:, 0] ** 2)) == pytest.approx(0.002) and np.all(per_axis[:, 2] == 0)
    with pytest.raises(ValueError, match="band_hz"):
        HandMotion(0.001, band_hz=(5.0, 1.0))


def test_simulated_errors_keep_the_truth(tmp_path):
    ds = scan(position_error=HandMotion(0.002, seed=1), temperature_error_c=4.0, group_delay_s=15e-6,
              timing_jitter_s=1e-6)
    ap = clsas.raster_aperture(13, 9, 0.3, 0.2)
    assert np.array_equal(ds.tx_positions, ap.tx_positions)  # the dataset states the plan
    assert ds.temperature_c == 20.0 and np.all(ds.t0_s == 0)
    t = clsas.load(ds.save(tmp_path / "s.h5")).truth
    assert np.allclose(t["tx_positions"] - ap.tx_positions, t["position_error_m"])
    assert t["temperature_c"] == 24.0 and t["group_delay_s"] == 15e-6
    assert np.allclose(t["t0_s"], -15e-6 - t["timing_jitter_s"])
    assert t["errors"]["position_error"]["rms_m"] == 0.002
    assert ds.subset(slice(0, 10)).truth["t0_s"].shape == (10,)
    with pytest.raises(ValueError, match="position_error"):
        scan(position_error=np.zeros((5, 3)))


@pytest.mark.slow
def test_error_free_scan_changes_nothing_beyond_tolerance():
    ds = scan(width=0.6, height=0.4)
    out, rep = autofocus(ds, GRID, methods=FOCUS_METHODS, temperature_range_c=2.0, n_basis=8, max_iter=10)
    # stated tolerance: 1 us of delay, 0.75 C (c is loosely determined by so small a scan), 0.05 mm of
    # one-way line of sight, and an image
    # whose complex correlation with the input's is above 0.995
    assert abs(rep.group_delay_s) < 1e-6
    assert abs(rep.temperature_offset_c) < 0.75
    assert np.sqrt(np.mean(rep.los_path_m**2)) / 2 < 5e-5
    assert not rep.parameters["motion"].applied  # noise-fitting motion not used
    a = clsas.reconstruct(ds, GRID, backend="numpy").values.ravel()
    b = clsas.reconstruct(out, GRID, backend="numpy").values.ravel()
    assert abs(np.vdot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b)) > 0.995


def test_never_returns_a_less_sharp_image(monkeypatch):
    from clsas.focus import stage_motion as run_mod

    ds = scan()

    def harmful(engine, base, c, stop, basis, stages, max_iter, history, callback=None):
        return np.random.default_rng(0).normal(0, 0.01, basis.shape[0]), {"stages": [{"metric": 0.0}],
                                                                           "evaluations": 0}

    monkeypatch.setattr(run_mod, "optimise_los", harmful)
    out, rep = autofocus(ds, GRID, methods=("los",))
    assert out is ds and not rep.improved
    assert rep.metric_after == rep.metric_before
    assert not rep.parameters["motion"].applied
    assert any(n.startswith("motion:") and "not applied" in n for n in rep.notes)


def test_stages_run_in_order_and_their_check_decides(monkeypatch):
    from clsas.focus import run as run_mod
    from clsas.focus.stage_delay import DelayStage

    assert [s.name for s in run_mod.STAGES] == ["delay", "motion", "temperature"]
    ds = scan(group_delay_s=20e-6)
    out, rep = autofocus(ds, GRID, methods=("direct",))
    assert rep.improved and rep.parameters["group_delay"].applied
    assert np.median(ds.t0_s - out.t0_s) == pytest.approx(20e-6, abs=1e-6)
    monkeypatch.setattr(DelayStage, "check", lambda self, state, estimate: False)  # the estimate refused
    out, rep = autofocus(ds, GRID, methods=("direct",))
    assert out is ds and not rep.improved and rep.parameters["group_delay"].determined


@pytest.mark.slow
def test_jitter_is_reduced_on_a_partial_scan():
    ds = scan(nx=15, ny=11, width=0.3, height=0.24, position_error=HandMotion(0.0008, seed=2))
    part = ds.subset(slice(0, 120))  # a scan stopped early
    before = clsas.reconstruct(part, GRID, backend="auto")
    out, rep = autofocus(part, GRID, methods=("los",), n_basis=12, max_iter=15)
    s = score(rep, part)
    assert rep.improved and rep.metric_after > rep.metric_before
    assert s["los_residual_rms_m"] < 0.75 * s["los_error_rms_m"]
    after = clsas.reconstruct(out, GRID, backend="auto")
    assert np.abs(after.values).max() > np.abs(before.values).max()


def test_temperature_and_group_delay_are_recovered():
    # a wide aperture for its range: c changes the curvature of the echoes' paths across it
    ds = scan(width=0.6, height=0.4, temperature_error_c=4.0, group_delay_s=20e-6)
    out, rep = autofocus(ds, GRID, methods=("direct", "temperature"), temperature_range_c=6.0)
    s = score(rep, ds)
    assert abs(s["group_delay_error_s"]) < 1e-6
    assert abs(s["temperature_error_c"]) < 0.5
    assert rep.improved and out.temperature_c == pytest.approx(rep.temperature_c)
    assert out.provenance[-1]["step"] == "autofocus"


def test_no_direct_sound_is_said():
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = clsas.simulate(clsas.Scene(np.asarray(POINTS)), clsas.raster_aperture(9, 7, 0.3, 0.2), w, FS, snr_db=30)
    _, rep = autofocus(ds, GRID, methods=("direct",))
    assert any("direct sound not found" in n for n in rep.notes)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"methods": ("focus",)}, ValueError, "methods"),
    ({"methods": "los"}, TypeError, "methods"),
    ({"methods": ()}, ValueError, "methods"),
    ({"metric": "contrast"}, ValueError, "metric"),
    ({"n_basis": 0}, ValueError, "n_basis"),
    ({"n_basis": 2.5}, TypeError, "n_basis"),
    ({"temperature_range_c": float("nan")}, ValueError, "temperature_range_c"),
    ({"max_delay_s": -1e-6}, ValueError, "max_delay_s"),
    ({"motion_bandwidth_hz": 0}, ValueError, "motion_bandwidth_hz"),
    ({"progress": 3}, TypeError, "progress"),
    ({"pga_min_coherence": 1.5}, ValueError, "pga_min_coherence"),
    ({"pga_min_coherence": float("nan")}, ValueError, "pga_min_coherence"),
    ({"pga_max_points": 0}, ValueError, "pga_max_points"),
])
def test_input_validation(kwargs, error, match):
    ds = scan(nx=3, ny=2)
    with pytest.raises(error, match=match):
        autofocus(ds, GRID, **kwargs)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"methods": ("focus",)}, ValueError, "methods"),
    ({"max_iter": 0}, ValueError, "max_iter"),
    ({"check_margin": 1.0}, ValueError, "check_margin"),
    ({"consistency_iter": True}, ValueError, "consistency_iter"),
    ({"phase_region_m": -0.01}, ValueError, "phase_region_m"),
])
def test_options_are_checked_once_where_built(kwargs, error, match):
    from dataclasses import FrozenInstanceError

    from clsas.focus import AutofocusOptions

    with pytest.raises(error, match=match):
        AutofocusOptions(**kwargs)
    o = AutofocusOptions(methods=["direct", "pga"], max_iter=np.int64(3), pga_min_coherence=0.5)
    assert o.methods == ("direct", "pga") and type(o.max_iter) is int and o.motion
    assert o.pga_options == {"max_points": 32, "min_coherence": 0.5}
    with pytest.raises(FrozenInstanceError):
        o.metric = "entropy"


def test_input_validation_of_dataset_and_grid():
    ds = scan(nx=3, ny=2)
    with pytest.raises(TypeError, match="dataset"):
        autofocus(ds.signals, GRID)
    with pytest.raises(TypeError, match="grid"):
        autofocus(ds, (0, 1))
    with pytest.raises(ValueError, match="at least 4"):
        autofocus(ds.subset(slice(0, 3)), GRID)
    with pytest.raises(ValueError, match="no truth"):
        score(autofocus(ds, GRID, methods=("direct",))[1], ds)


def test_cli_autofocus_writes_the_corrected_scan_and_pictures(tmp_path, capsys):
    from clsas.cli import main

    scan(group_delay_s=10e-6).save(tmp_path / "s.h5")
    rc = main(["autofocus", str(tmp_path / "s.h5"), str(tmp_path / "o.h5"), "--grid=-0.09,0.09,-0.08,0.07,0.55,0.69",
               "--spacing", "0.006", "--methods", "direct", "--png", str(tmp_path / "ba.png"), "-q"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "group delay +10.0" in text and "against the stored truth" in text
    assert (tmp_path / "ba.png").stat().st_size > 0
    assert clsas.load(tmp_path / "o.h5").provenance[-1]["step"] == "autofocus"
    assert main(["autofocus", str(tmp_path / "s.h5"), str(tmp_path / "x.h5"), "--methods", "focus", "-q",
                 "--grid=-0.09,0.09,-0.08,0.07,0.55,0.69"]) == 2


def test_conditional_phase_is_the_exact_best(rng):
    from clsas.focus.phases import conditional_best

    rest = rng.normal(size=300) + 1j * rng.normal(size=300)
    a = 0.7 * (rng.normal(size=300) + 1j * rng.normal(size=300))
    table = -np.pi + 2 * np.pi * np.arange(64) / 64
    k, m = conditional_best(rest, a, np.exp(1j * table), np.exp(2j * table))
    brute = [metric_and_weight(rest + np.exp(1j * t) * a)[0] for t in table]
    assert k == int(np.argmax(brute)) and m == pytest.approx(max(brute), rel=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_stop_images_sum_to_the_image(backend):
    ds = scan(nx=5, ny=3)
    grid = clsas.VoxelGrid.from_bounds((-0.08, 0.08), (-0.06, 0.06), (0.56, 0.68), 0.01)
    eng = FocusEngine(ds, grid, backend=backend)
    shift = np.random.default_rng(2).normal(0, 2e-6, ds.n_meas)
    stop = np.arange(ds.n_meas) // 2  # two measurements per "stop": rows are summed
    a = eng.stop_images(shift, ds.c_per_meas, stop)
    whole = eng.image(shift, ds.c_per_meas)
    assert a.shape == (8, grid.size)
    assert np.abs(a.sum(axis=0) - whole).max() < 1e-4 * np.abs(whole).max()
    sub = eng.stop_images(shift, ds.c_per_meas, stop, voxels=np.array([3, 50, 7]))
    assert np.array_equal(sub, a[:, [3, 50, 7]])


def test_phase_step_recovers_jitter_where_the_local_search_fails():
    # 3 mm RMS of hand-like motion, mostly along the line of sight: about 2.5 rad RMS of two-way
    # phase at 25 kHz; the gradient search alone climbs to a wrong optimum
    ds = scan(position_error=HandMotion(0.003, seed=4, weights=(0.3, 0.3, 1.0)))
    out, rep = autofocus(ds, GRID, methods=("phase",))
    s = score(rep, ds)
    assert s["los_error_rms_m"] > 2e-3
    assert rep.improved and s["los_residual_rms_m"] < 0.3e-3
    assert rep.stages[0]["step"] == "phase" and rep.stages[0]["kept"]
    local = score(autofocus(ds, GRID, methods=("los",), n_basis=8, max_iter=8)[1], ds)
    assert local["los_residual_rms_m"] > 3 * s["los_residual_rms_m"]
    # the corrected dataset images sharper than the input, and its peak is higher
    a = np.abs(clsas.reconstruct(ds, GRID, backend="auto").values).max()
    b = np.abs(clsas.reconstruct(out, GRID, backend="auto").values).max()
    assert b > 1.5 * a


def test_3d_step_keeps_the_line_of_sight_on_a_rigid_carriage():
    ds = scan(position_error=HandMotion(0.003, seed=4, weights=(0.3, 0.3, 1.0)))
    out, rep = autofocus(ds, GRID, methods=("phase", "3d"), max_iter=6)
    s = score(rep, ds)
    assert rep.improved and s["los_residual_rms_m"] < 0.3e-3
    assert [st["step"] for st in rep.stages] == ["phase", "3d", "motion"] and rep.parameters["motion"].applied
    move = out.tx_positions - ds.tx_positions
    assert np.allclose(move, out.rx_positions - ds.rx_positions)  # one rigid carriage
    assert np.allclose(move, rep.position_correction_m)


def test_pga_point_samples_are_the_backprojection_terms():
    from clsas.focus.pga import point_samples
    from clsas.formation import bp_numpy as bp_twin

    ds = scan(nx=5, ny=4)
    eng = FocusEngine(ds, GRID, backend="numpy")
    shift = np.random.default_rng(1).normal(0, 2e-6, ds.n_meas)
    pts = np.asarray(POINTS) + 0.001
    a, g = point_samples(eng, shift, ds.c_per_meas, ds.tx_positions, ds.rx_positions, pts)
    data, tau0 = eng._shifted(shift)
    want = bp_twin.backproject(data, tau0, eng.prof.dtau_s, eng.prof.fc_hz, ds.tx_positions, ds.rx_positions,
                               ds.c_per_meas, pts)
    assert np.allclose(a.sum(axis=0), want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    # g is the path's derivative with respect to moving the carriage
    e = np.array([0.0, 0.0, 1e-6])
    path = (np.linalg.norm(pts[1] - ds.tx_positions[3] - e) + np.linalg.norm(pts[1] - ds.rx_positions[3] - e)
            - np.linalg.norm(pts[1] - ds.tx_positions[3]) - np.linalg.norm(pts[1] - ds.rx_positions[3]))
    assert g[3, 1, 2] * 1e-6 == pytest.approx(path, rel=1e-4)


def test_pga_recovers_per_stop_jitter_on_strong_points():
    # jitter up to the stop rate's Nyquist frequency: nearly independent from stop to stop, which
    # no smooth motion basis holds; 0.85 mm RMS of line of sight is about 0.8 rad of two-way phase
    ds = scan(position_error=HandMotion(0.0015, band_hz=(0.2, 25.0), seed=4))
    out, rep = autofocus(ds, GRID, methods=("pga",))
    s = score(rep, ds)
    st = rep.stages[0]
    assert st["step"] == "pga" and st["kept"] and st["points"] >= 4
    assert s["los_error_rms_m"] > 0.7e-3 and s["los_residual_rms_m"] < 0.25e-3  # measured 0.16 mm
    assert rep.improved and rep.metric_after > rep.metric_before + 0.5
    move = out.tx_positions - ds.tx_positions
    assert np.allclose(move, out.rx_positions - ds.rx_positions)  # one rigid carriage


def test_pga_leaves_an_extended_target_alone():
    # 400 scatterers of random sign filling the scene: speckle, no strong isolated point
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-0.07, 0.07, 400), rng.uniform(-0.06, 0.05, 400), rng.uniform(0.57, 0.67, 400)]
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = clsas.simulate(clsas.Scene(pts, rng.normal(size=400)), clsas.raster_aperture(13, 9, 0.3, 0.2), w, FS,
                        snr_db=30, direct_gain=1.0, position_error=HandMotion(0.0006, band_hz=(0.2, 25.0), seed=4))
    out, rep = autofocus(ds, GRID, methods=("pga",))
    st = rep.stages[0]
    assert not st["kept"] and st["points"] < 4 and max(st["coherence_after"]) < 0.5
    assert any("no strong isolated points" in n for n in rep.notes)
    assert out is ds and not rep.improved  # nothing else ran: the input comes back


def test_bench_peak_measures():
    from bench.autofocus import fine_peaks_db, peaks_db, untilted_truth

    ds = scan(nx=7, ny=5, position_error=HandMotion(0.001, seed=3))
    u = untilted_truth(ds)
    d = u.tx_positions - ds.tx_positions
    xy = ds.tx_positions[:, :2]
    nuis = np.c_[np.ones(len(xy)), xy - xy.mean(axis=0)]
    assert np.abs(nuis.T @ d).max() < 1e-12  # no constant, no tilt left
    true_d = ds.truth["tx_positions"] - ds.tx_positions
    coef, *_ = np.linalg.lstsq(nuis, true_d, rcond=None)
    assert np.allclose(d, true_d - nuis @ coef)  # the rest of the true motion, unchanged
    pts = np.asarray(POINTS)
    grid_db = peaks_db(clsas.reconstruct(ds, GRID, backend="numpy"), pts, GRID)
    fine_db = fine_peaks_db(ds, pts, backend="numpy")
    assert np.all(fine_db >= grid_db - 0.05)  # the local peak is the peak, not a voxel near it
    assert np.all(fine_db - grid_db < 3.0)
