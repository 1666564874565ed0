"""The ``"track"`` motion step: phases of neighbouring stops integrated, no free
unwrapping, determined only where the even and odd stops agree, and a check on positions."""

import numpy as np
import pytest

import clsas
from clsas.focus import autofocus, score
from clsas.focus.stage_motion import SAMPLING_COHERENCE, sampling_note
from clsas.focus.track import (
    gauge_free,
    integrate_phases,
    nearest_coherence,
    neighbour_edges,
    pair_phases,
    region_agreement,
    track_phases,
)
from clsas.physics.scan_errors import HandMotion

FS = 96e3
# neighbouring stops see a compact target far away from almost the same direction: their images
# agree up to the phase of their path difference (at 0.6 m over an 18 cm grid they do not)
POINTS = np.array([[0.02, -0.01, 1.2], [-0.03, 0.02, 1.23], [0.03, 0.025, 1.21], [-0.015, -0.03, 1.19]])
GRID = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.045), (1.16, 1.26), 0.005)


def scan(nx=15, ny=11, width=0.3, height=0.2, **kw):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ap = clsas.raster_aperture(nx, ny, width, height)
    return clsas.simulate(clsas.Scene(POINTS), ap, w, FS, snr_db=30, **kw)


def test_integrated_phases_are_not_wrapped():
    # a path that drifts over several wavelengths: per-stop phases wrap many times, their
    # neighbours' differences do not; integrating the differences gives the path back, where
    # unwrapping noisy per-stop phases left whole-wavelength jumps
    rng = np.random.default_rng(0)
    n = 120
    xy = np.c_[np.tile(np.arange(12.0), 10), np.repeat(np.arange(10.0), 12)] * 0.02
    truth = np.cumsum(rng.normal(0.3, 0.5, n))  # rad, a drifting random walk: many turns
    assert np.ptp(truth) > 4 * np.pi
    edges = neighbour_edges(xy, lags=(1, 2), k_spatial=4)
    angle = np.angle(np.exp(1j * (truth[edges[:, 1]] - truth[edges[:, 0]] + rng.normal(0, 0.05, len(edges)))))
    phi = integrate_phases(n, edges, angle, np.full(len(edges), 0.9))
    err = phi - truth
    assert np.std(err) < 0.1  # no 2 pi slips anywhere: a constant apart
    assert np.all(np.abs(err - err.mean()) < np.pi / 2)


def test_pair_phases_read_the_phase_difference():
    rng = np.random.default_rng(1)
    base = rng.normal(size=50) + 1j * rng.normal(size=50)
    a = np.stack([base * np.exp(-1j * p) for p in (0.0, 0.3, -1.0)])
    angle, coh = pair_phases(a, np.array([[0, 1], [1, 2]]))
    # phi_t - phi_s, where a_s carries exp(-j phi_s) (the correction exp(j phi_s) undoes it)
    assert angle == pytest.approx([0.3, -1.3])
    assert coh == pytest.approx([1.0, 1.0])


def test_nearest_coherence_reads_only_the_closest_stops():
    # a 4 x 3 raster, 1 cm along x and 3 cm along y: the x neighbours are the closest pairs
    xy = np.c_[np.tile(np.arange(4.0), 3) * 0.01, np.repeat(np.arange(3.0), 4) * 0.03]
    edges = neighbour_edges(xy, lags=(1,), k_spatial=4)
    length = np.linalg.norm(xy[edges[:, 0]] - xy[edges[:, 1]], axis=1)
    coh = np.where(length < 0.015, 0.9, 0.1)  # alike along x, unlike farther
    assert nearest_coherence(xy, edges, coh) == pytest.approx(0.9)
    assert nearest_coherence(xy, edges, np.where(length < 0.015, 0.3, 0.95)) == pytest.approx(0.3)
    assert np.isnan(nearest_coherence(xy, np.zeros((0, 2), int), np.zeros(0)))
    note = sampling_note({"coherence_nearest": 0.3})
    assert "0.30" in note and "speckle" in note and "not reliably determined" in note
    passed = sampling_note({"coherence_nearest": 0.3}, determined=True)
    assert "passed the tests above" in passed and "not reliably determined" not in passed
    assert sampling_note({"coherence_nearest": 0.95}) == "" and sampling_note({}) == ""


def test_two_sides_of_a_target_give_one_path_where_the_phases_carry_it():
    # a 12 x 10 raster; each stop's image is the same speckle on each side of the target (a
    # different speckle per side, drifting slowly from stop to stop) times the stop's motion
    # phase: both sides, tracked apart with every stop, give the motion back
    rng = np.random.default_rng(4)
    nx, ny, n_vox = 12, 10, 200
    xy = np.c_[np.tile(np.arange(nx) * 0.01, ny), np.repeat(np.arange(ny) * 0.01, nx)]
    t = np.arange(nx * ny) * 0.02
    truth = 1.5 * np.sin(2 * np.pi * 0.7 * t) + 0.8 * np.sin(2 * np.pi * 2.1 * t + 1)
    points = np.c_[rng.uniform(-0.05, 0.05, (n_vox, 2)), np.full(n_vox, 1.0)]
    base = rng.normal(size=n_vox) + 1j * rng.normal(size=n_vox)
    drift = rng.normal(size=n_vox) + 1j * rng.normal(size=n_vox)
    a = (base + 0.05 * (xy[:, :1] + xy[:, 1:]) / 0.01 * drift / 10) * np.exp(-1j * truth)[:, None]
    phi_a, phi_b = region_agreement(a, points, t, xy, cutoff_hz=None)
    for phi in (phi_a, phi_b):
        assert np.sqrt(np.mean(gauge_free(phi - truth, xy) ** 2)) < 0.1
    # the cut is at the intensity-weighted median along the bright region's longest horizontal
    # axis (here y): the y < 0 voxels carry the motion and are the brighter (their stops add up),
    # so the first side holds only y < 0 voxels and tracks it; the second mixes in the voxels
    # whose phase is random at every stop, and does not
    line = np.c_[np.zeros(n_vox), np.linspace(-0.05, 0.05, n_vox), np.ones(n_vox)]
    noise = np.exp(1j * rng.uniform(-np.pi, np.pi, nx * ny))[:, None]
    b = np.where(line[:, 1] < 0, np.exp(-1j * truth)[:, None], noise) * np.ones(n_vox)
    pa, pb = region_agreement(b, line, t, xy, cutoff_hz=None)
    assert np.sqrt(np.mean(gauge_free(pa - truth, xy) ** 2)) < 1e-6
    assert np.sqrt(np.mean(gauge_free(pb - truth, xy) ** 2)) > 0.5


def test_a_side_with_too_few_voxels_gives_no_second_look():
    # one voxel cannot be cut in two: both paths NaN, and the caller's test (<= tolerance) fails
    rng = np.random.default_rng(5)
    xy = np.c_[np.arange(10.0) * 0.01, np.zeros(10)]
    a = np.exp(1j * rng.uniform(-np.pi, np.pi, (10, 1)))
    pa, pb = region_agreement(a, np.array([[0.0, 0.0, 1.0]]), np.arange(10) * 0.02, xy, cutoff_hz=None)
    assert np.all(np.isnan(pa)) and np.all(np.isnan(pb))
    assert not np.sqrt(np.mean((pa - pb) ** 2)) <= 0.5e-3


def test_gauge_is_removed():
    xy = np.random.default_rng(2).uniform(size=(30, 2))
    p = 1e-3 + 2e-3 * xy[:, 0] - 1e-3 * xy[:, 1]
    assert np.abs(gauge_free(p, xy)).max() < 1e-12


def test_track_phases_on_stop_images_of_a_moved_scan():
    ds = scan(position_error=HandMotion(0.003, seed=5, weights=(0.3, 0.3, 1)))
    from clsas.focus.engine import FocusEngine
    from clsas.focus.motion import stops_of

    stop, t, xy = stops_of(ds)
    engine = FocusEngine(ds, GRID, backend="numpy")
    a = engine.stop_images(np.zeros(ds.n_meas), ds.c_per_meas, stop)
    phi, info = track_phases(a, t, xy)
    centre = POINTS.mean(axis=0)
    first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]

    def path(tx, rx):
        return np.linalg.norm(centre - tx, axis=1) + np.linalg.norm(centre - rx, axis=1)

    true = gauge_free((path(ds.truth["tx_positions"], ds.truth["rx_positions"])
                       - path(ds.tx_positions, ds.rx_positions))[first], xy)
    est = gauge_free(phi * float(np.mean(ds.c_per_meas)) / (2 * np.pi * engine.prof.fc_hz), xy)
    assert info["coherence_median"] > 0.5
    # a compact target far away: the closest stops are finer than its speckle (no sampling note)
    assert info["coherence_nearest"] > SAMPLING_COHERENCE and not sampling_note(info)
    assert np.sqrt(np.mean((est - true) ** 2)) < 0.3 * np.sqrt(np.mean(true**2))


@pytest.mark.slow
def test_track_corrects_hand_motion_and_reports_it():
    ds = scan(position_error=HandMotion(0.003, seed=5, weights=(0.3, 0.3, 1)))
    out, rep = autofocus(ds, GRID, methods=("direct", "track"))
    m = rep.parameters["motion"]
    s = score(rep, ds)
    assert m.determined and m.applied and rep.improved
    assert rep.check["where_passed"]
    assert s["los_residual_rms_m"] < 0.5 * s["los_error_rms_m"]
    assert "even and odd stops" in m.how


def test_where_check_rejects_a_correction_that_scatters_the_image():
    # a correction the data do not support (5 mm RMS of random per-stop path): the sub-apertures'
    # brightest points fly apart, and the check on positions says so
    from clsas.focus.engine import FocusEngine
    from clsas.focus.motion import stops_of
    from clsas.focus.split import split_halves
    from clsas.focus.stage_motion_track import where_check

    ds = scan()
    stop, _, xy = stops_of(ds)

    class Fo:  # what where_check reads of the pipeline's state
        pass

    fo = Fo()
    fo.ds, fo.engine, fo.split_names = ds, FocusEngine(ds, GRID, backend="numpy"), ("time", "x")
    fo.splits = [split_halves(ds, GRID, stop, xy, how, backend="numpy") for how in fo.split_names]
    zero = np.zeros(ds.n_meas)
    rng = np.random.default_rng(7)
    bad = np.zeros((ds.n_meas, 3))
    bad[:, 2] = rng.normal(0, 0.005, int(stop.max()) + 1)[stop]
    assert where_check(fo, zero, ds.c_per_meas, np.zeros((ds.n_meas, 3)))["passed"]
    assert not where_check(fo, zero, ds.c_per_meas, bad)["passed"]


@pytest.mark.parametrize("value", [0, -1e-3, float("nan")])
def test_track_tolerance_is_validated_by_name(value):
    with pytest.raises(ValueError, match="track_tolerance_m"):
        autofocus(scan(nx=4, ny=3), GRID, methods=("direct", "track"), track_tolerance_m=value)


@pytest.mark.slow
def test_speckle_at_close_range_is_not_determined_and_the_input_comes_back():
    # 300 scatterers at 0.6 m over an 18 cm box, 3 mm of hand motion: neighbouring stops' images
    # decorrelate, the even and the odd stops track different paths, and nothing is applied
    # (a consistent-looking focus on some scatterer is what the agreement checks passed before)
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-0.07, 0.07, 300), rng.uniform(-0.06, 0.05, 300), rng.uniform(0.57, 0.67, 300)]
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = clsas.simulate(clsas.Scene(pts, rng.normal(size=300)), clsas.raster_aperture(13, 9, 0.3, 0.2), w, FS,
                        snr_db=30, position_error=HandMotion(0.003, seed=2))
    grid = clsas.VoxelGrid.from_bounds((-0.09, 0.09), (-0.08, 0.07), (0.55, 0.69), 0.005)
    out, rep = autofocus(ds, grid, methods=("direct", "track"))
    m = rep.parameters["motion"]
    assert not m.determined and not m.applied
    assert m.uncertainty > 0.5 * 2.5e-3  # half the closer split's difference, over half the tolerance
    assert out is ds and not rep.improved
    assert any("not determined" in n for n in rep.notes) and any("input is returned" in n for n in rep.notes)
    # and it says why: the closest stops' images are too unlike
    assert any("closest stops' images agree" in n for n in rep.notes)


def _peak_db(out, fs):
    clean = np.abs(clsas.reconstruct(fs.clean, fs.grid).values).max()
    return 20 * np.log10(np.abs(clsas.reconstruct(out, fs.grid).values).max() / clean)


def test_a_surface_whose_halves_decorrelate_is_determined_by_its_two_sides():
    # family seed 2002 (tuning-2): a plane at 1.77 m, 17 x 28 stops 30 x 9 mm apart, 3 mm of hand
    # motion. The even and odd stops (60 mm apart along the rows) track different paths; the
    # target's two sides, tracked with every stop, agree
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(2002, rms_m=3e-3)
    out, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "track"))
    stage = next(s for s in rep.stages if s["step"] == "track")
    assert stage["halves_rms_m"] > 2.5e-3 and stage["regions_rms_m"] < 0.5e-3
    m = rep.parameters["motion"]
    assert m.determined and m.applied and rep.improved
    assert m.uncertainty == pytest.approx(0.5 * stage["regions_rms_m"])  # the closer split's half difference
    s = score(rep, fs.dataset)
    assert s["los_residual_rms_m"] < 0.5 * s["los_error_rms_m"]
    assert _peak_db(out, fs) > -1.0


def test_track_replaces_points_on_a_surface_the_points_only_sample():
    # family seed 2001 (tuning-2): a sphere cap; "points" passes its check on speckle peaks and
    # leaves the peak 2.7 dB down; "track" passes its own and the sub-apertures agree better after it
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(2001, rms_m=3e-3)
    out, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "points", "track"))
    assert rep.check["points_passed"] and rep.improved
    assert any(n.startswith("track: applied instead of points") for n in rep.notes)
    assert rep.parameters["motion"].how.startswith("track:")
    assert _peak_db(out, fs) > -1.0


def test_points_stays_on_isolated_points_when_track_runs_too():
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(6, rms_m=3e-3)  # 12 points: "points" is the better of the two
    out, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "points", "track"))
    assert rep.improved and "strong points" in rep.parameters["motion"].how
    assert any(n.startswith("track: run too, not used") for n in rep.notes)
    assert not any(n.startswith("motion: not determined") for n in rep.notes)  # track's own notes are withdrawn
    # its stage stays, marked unused; the motion decision it made and its checks are withdrawn
    assert [st.get("used") for st in rep.stages if st.get("step") == "track"] == [False]
    assert not any(st.get("step") == "motion" for st in rep.stages) and "where_passed" not in rep.check
    s = score(rep, fs.dataset)
    assert s["los_residual_rms_m"] < 0.3e-3
