"""Beams in the formations and the simulator: the bp kernel's beam hook against its twin,
analytic weights, Oclgrind, directional echoes, specular facets, omega-k's angular weighting, and the
reference case where backprojection without the beam model fails."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import BACKENDS, needs_opencl, width_or_skip

import clsas
from clsas.formation import bp_numpy as twin
from clsas.physics.beam import Beams, Cone, Omni, Piston, beam_weights
from clsas.physics.specular import Surface


@needs_opencl
@pytest.mark.parametrize("mode", ["weighted", "limited"])
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_beam_kernel_equals_its_twin(vec, mode):
    from clsas import cl
    from clsas.formation.bp_opencl import beam_selftest

    width_or_skip("backproject", vec)
    assert beam_selftest(cl.get_queue(), vec, mode) < 2e-4


def _one_pair(backend, beam, points):
    """Profiles of one co-located measurement at the origin facing +z (a flat profile, so every
    voxel in the window gets the same magnitude), imaged on ``points`` (a 1-D grid along x)."""
    fs = 1e6
    prof = clsas.Profiles.from_range_profiles(
        np.ones((1, 400), complex), tau0_s=0.0, dtau_s=1 / fs, tx_positions=np.zeros((1, 3)),
        rx_positions=np.zeros((1, 3)), c_mps=1480.0, fc_hz=1e5, baseband=True)
    beams = Beams(Cone(20.0), Omni(), (0, 0, 1), (0, 0, 1), 1)
    from dataclasses import replace

    prof = replace(prof, beams=beams)
    out = []
    for x in points:
        grid = clsas.VoxelGrid(np.array([x]), np.array([0.0]), np.array([0.1]))
        out.append(abs(clsas.backproject(prof, grid, backend=backend, beam=beam).values[0, 0, 0]))
    return np.array(out)


@pytest.mark.parametrize("backend", BACKENDS)
def test_bp_weights_each_pair_by_the_two_way_pattern(backend):
    """A voxel at angle theta off the boresight gets the cone's 2^-(theta/20 deg)^2 (the microphone is
    omnidirectional); limited keeps it where that is at least -12 dB, the default floor (theta <= 28.3
    deg), none keeps everything."""
    ang = np.radians([0.0, 10.0, 19.0, 21.0, 35.0])
    x = 0.1 * np.tan(ang)
    tol = 2e-4 if backend == "opencl" else 1e-6
    np.testing.assert_allclose(_one_pair(backend, "none", x), 1.0, atol=tol)
    np.testing.assert_allclose(_one_pair(backend, "weighted", x), 2.0 ** -((np.degrees(ang) / 20) ** 2), atol=1e-3)
    got = _one_pair(backend, "limited", x)
    assert got.round(3).tolist() == [1.0, 1.0, 1.0, 1.0, 0.0]


UNKNOWN_BP_OPTION = r"unknown option\(s\) \['beam_width'\] for 'bp'; known: \['beam', 'beam_floor_db', 'max_error_db'\]"


def test_bp_beam_option_is_validated_by_name():
    grid = clsas.VoxelGrid(np.array([0.0]), np.array([0.0]), np.array([0.1]))
    with pytest.raises(ValueError, match="beam"):
        clsas.Backprojector(grid, beam="gated", backend="numpy")
    with pytest.raises(ValueError, match="beam_floor_db"):
        clsas.Backprojector(grid, beam="limited", beam_floor_db=float("nan"), backend="numpy")
    with pytest.raises(ValueError, match=UNKNOWN_BP_OPTION):
        clsas.reconstruct(_dataset_in_water(), grid, formation="bp", formation_options={"beam_width": 3},
                          backend="numpy")
    prof = clsas.compress(_dataset_in_water(), backend="numpy")
    with pytest.raises(ValueError, match=UNKNOWN_BP_OPTION):
        clsas.formation.form(prof, grid, "bp", beam_width=3)


@pytest.mark.oclgrind
def test_beam_kernel_runs_clean_under_oclgrind():
    from conftest import OCLGRIND_DIAGNOSTICS as DIAGNOSTICS
    from conftest import oclgrind_missing as _oclgrind_available

    why = _oclgrind_available()
    if why is not None:
        pytest.skip(why)
    script = Path(__file__).with_name("beam_oclgrind_run.py")
    for checks in ({"OCLGRIND_DATA_RACES": "1"}, {"OCLGRIND_UNINITIALIZED": "1"}):
        for vec in (4, 8):
            env = dict(os.environ, **checks)
            res = subprocess.run([sys.executable, str(script), str(vec)], capture_output=True, text=True, env=env,
                                 timeout=600)
            assert res.returncode == 0 and "oclgrind run ok" in res.stdout, f"{res.stdout}\n{res.stderr[-4000:]}"
            found = [d for d in DIAGNOSTICS if d in res.stderr]
            assert not found, f"Oclgrind reported {found} ({checks}, VEC={vec}):\n{res.stderr[-4000:]}"


def _dataset_in_water():
    fs, wave, ap = _water(2)
    return clsas.simulate(clsas.Scene(np.array([[0, 0, 0.02]])), ap, wave, fs, c_mps=1480.0)


def _water(n=1, pitch=1e-3):
    fs = 12.5e6
    wave = clsas.lfm_chirp(1e6, 4e6, 4e-6, fs, taper=0.2)
    ap = clsas.raster_aperture(n, n, (n - 1) * pitch, (n - 1) * pitch, tx_offset_m=(0, 0, 0), rx_offset_m=(0, 0, 0))
    return fs, wave, ap


def _peak(ds):
    return float(np.abs(clsas.compress(ds, backend="numpy").data).max())


def test_simulated_echo_follows_the_beam_and_the_dataset_keeps_it():
    fs, wave, ap = _water()
    cone = Beams(Cone(10.0), Cone(10.0), (0, 0, 1), (0, 0, 1), 1)
    ratios = []
    for deg in (0.0, 10.0):
        p = 0.03 * np.array([[np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))]])
        scene = clsas.Scene(p)
        omni = _peak(clsas.simulate(scene, ap, wave, fs, c_mps=1480.0))
        ds = clsas.simulate(scene, ap, wave, fs, c_mps=1480.0, beams=cone)
        ratios.append(_peak(ds) / omni)
    assert ratios == pytest.approx([1.0, 0.25], rel=1e-3)  # two-way: 0.5 x 0.5 at the half-angle
    assert ds.beams is cone and ds.c_mps == 1480.0


def test_a_flat_facetted_surface_returns_the_mirror_echo():
    """Kirchhoff: a rigid plane at depth h under a monostatic transducer returns 1 / (2 h), the echo
    of a point of amplitude h / 2 at the same depth (facets of lambda/1.5 over 12 x 12 mm)."""
    fs, wave, ap = _water()
    h = 0.02
    plane = Surface.plane((0, 0, h), (0.012, 0.012), 0.4e-3)
    empty = clsas.Scene(np.array([[0, 0, h]]), np.array([0.0]))  # a scene needs a point: a silent one
    surf = _peak(clsas.simulate(empty, ap, wave, fs, c_mps=1480.0, surfaces=[plane]))
    point = _peak(clsas.simulate(clsas.Scene(np.array([[0, 0, h]]), np.array([h / 2])), ap, wave, fs, c_mps=1480.0))
    assert surf / point == pytest.approx(1.0, abs=0.03)
    # turned by 20 degrees, the mirror sends the sound away (its specular point lies beyond the plate):
    # only the plate's edges return some (Kirchhoff's edge diffraction)
    tilt = Surface.plane((0, 0, h), (0.012, 0.012), 0.4e-3, normal=(np.sin(0.35), 0.0, -np.cos(0.35)))
    away = _peak(clsas.simulate(empty, ap, wave, fs, c_mps=1480.0, surfaces=[tilt]))
    assert away < 0.4 * surf


def test_sphere_cap_faces_the_transducers():
    cap = Surface.sphere_cap((0, 0, 0.02), 0.01, (0.006, 0.006), 1e-3)
    assert np.all(cap.normals[:, 2] < 0) and np.all(cap.centers_m[:, 2] >= 0.02)
    with pytest.raises(ValueError, match="wider than its sphere"):
        Surface.sphere_cap((0, 0, 0.02), 0.002, (0.006, 0.006), 1e-3)


def test_omega_k_refuses_beams_it_cannot_weight():
    fs, wave, ap = _water(4)
    tilted = Beams(Piston(6e-3), Piston(6e-3), (0.3, 0, 1), (0, 0, 1), ap.n_meas)
    ds = clsas.simulate(clsas.Scene(np.array([[0, 0, 0.02]])), ap, wave, fs, c_mps=1480.0, beams=tilted)
    grid = clsas.VoxelGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (0.019, 0.021), 0.5e-3)
    with pytest.raises(ValueError, match="boresight"):
        clsas.reconstruct(ds, grid, formation="omega-k", backend="numpy")
    img = clsas.reconstruct(ds, grid, formation="omega-k", formation_options={"beam": "none"}, backend="numpy")
    assert np.isfinite(img.values).all()
    with pytest.raises(ValueError, match="beam"):
        clsas.reconstruct(ds, grid, formation="omega-k", formation_options={"beam": "on"}, backend="numpy")


def test_twin_without_beam_is_unchanged(rng):
    """beam=None in the twin is the omnidirectional sum, and a weights object of omni beams is None."""
    from clsas.formation.bp_opencl import selftest_scene

    grid, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    a = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points())
    assert beam_weights(Beams(Omni(), Omni(), (0, 0, 1), (0, 0, 1), 3), "weighted", 25e3, 343.0) is None
    b = twin.backproject(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points(), beam=None)
    np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def tilted_water_scan():
    """4 x 4 stops in water, each speaker and microphone tilted its own way (so a boresight
    applied to the wrong measurement changes the image), two points."""
    fs, wave, ap = _water(4)
    rng = np.random.default_rng(3)
    tilt = np.c_[rng.uniform(-0.15, 0.15, (ap.n_meas, 2)), np.ones(ap.n_meas)]
    beams = Beams(Piston(6e-3), Piston(6e-3), tilt, tilt[::-1], ap.n_meas)
    pts = np.array([[0, 0, 0.02], [1.5e-3, -1e-3, 0.021]])
    ds = clsas.simulate(clsas.Scene(pts), ap, wave, fs, c_mps=1480.0, beams=beams)
    grid = clsas.VoxelGrid.from_bounds((-3e-3, 3e-3), (-3e-3, 3e-3), (0.018, 0.023), 0.25e-3)
    return clsas.compress(ds, backend="numpy"), grid


@pytest.mark.parametrize("backend", BACKENDS)
def test_ffbp_applies_the_beams_as_bp_does(tilted_water_scan, backend, caplog):
    """FFBP's leaves weight each pair by its beam at the sub-image's samples, and each mode
    matches bp's image of the same mode; with beams it defaults to "weighted"."""
    prof, grid = tilted_water_scan
    errors, images = {}, {}
    for mode in ("weighted", "limited", "none", None):
        with caplog.at_level("WARNING", logger="clsas.formation.ffbp"):
            img = clsas.formation.form(prof, grid, "ffbp", beam=mode, depth=1, oversample=16.0, backend=backend)
        ref = clsas.formation.form(prof, grid, "bp", beam=mode or "weighted", backend=backend)
        assert img.provenance["ffbp"]["beam"] == (mode or "weighted") and img.backend == backend
        errors[mode], images[mode] = clsas.formation.error_to_signal_db(img, ref), img
    # a gate's edges are not band-limited: "limited" errs most (-10 dB here), "weighted" converges
    assert errors["weighted"] < -30 and errors["none"] < -35 and errors["limited"] < -8, errors
    assert errors[None] == errors["weighted"]
    assert any("omnidirectional" in r.message for r in caplog.records)  # beam="none" with beams warns
    assert not any("angular steps" in r.message for r in caplog.records)
    assert clsas.formation.error_to_signal_db(images["none"], images["limited"]) > -20  # the beams count
    caplog.clear()
    with caplog.at_level("WARNING", logger="clsas.formation.ffbp"):
        coarse = clsas.formation.form(prof, grid, "ffbp", beam="weighted", depth=1, backend=backend)
    assert any("angular steps" in r.message and "oversample=" in r.message for r in caplog.records)
    ref = clsas.formation.form(prof, grid, "bp", beam="weighted", backend=backend)
    assert clsas.formation.error_to_signal_db(coarse, ref) > -20  # what the warning is for


def test_ffbp_beam_options_are_checked_and_keep_the_planned_tree(tilted_water_scan):
    from dataclasses import replace

    from clsas.formation.ffbp import plan_tree
    from clsas.physics.beam import Beams

    prof, grid = tilted_water_scan
    with pytest.raises(ValueError, match="beam"):
        clsas.formation.form(prof, grid, "ffbp", beam="narrow", backend="numpy")
    with pytest.raises(ValueError, match="beam_floor_db"):
        clsas.formation.form(prof, grid, "ffbp", beam_floor_db=float("nan"), backend="numpy")
    short = replace(prof, beams=Beams(Piston(6e-3), Piston(6e-3), (0, 0, 1), (0, 0, 1), prof.n_meas - 1))
    with pytest.raises(ValueError, match="boresights"):
        clsas.formation.form(short, grid, "ffbp", depth=1, backend="numpy")
    tree = plan_tree(prof, grid, depth=1, oversample=4.0, beam="weighted")  # as formation="auto" costs it
    img = clsas.formation.form(prof, grid, "ffbp", beam="weighted", depth=1, oversample=4.0, backend="numpy")
    assert img.plan is tree  # the beam does not change the tree, so it is not planned again
    exact = clsas.formation.form(prof, grid, "ffbp", beam="weighted", depth=0, backend="numpy")
    assert exact.provenance["ffbp"]["beam"] == "weighted" and exact.provenance["bp"]["beam"] == "weighted"
    rec = clsas.formation.form(prof, grid, "bp", backend="numpy").provenance["bp"]
    assert (rec["beam"], rec["beam_floor_db"], rec["variant"]) == ("limited", -12.0, "twin")


@pytest.fixture(scope="module")
def flat_surface_under_a_coarse_line():
    """The directional reference case, small: a line of 24 stops at 1.5 mm (2.5 wavelengths at 2.5
    MHz in water) with 6 mm pistons over a flat rigid surface 20 mm below (and a faint pin)."""
    fs, wave, _ = _water()
    ap = clsas.raster_aperture(24, 1, 23 * 1.5e-3, 0.0, tx_offset_m=(0, 0, 0), rx_offset_m=(0, 0, 0))
    beams = Beams(Piston(6e-3), Piston(6e-3), (0, 0, 1), (0, 0, 1), ap.n_meas)
    surf = Surface.plane((0, 0, 0.02), (0.036, 0.008), 0.75e-3)
    scene = clsas.Scene(np.array([[1e-3, 0, 0.016]]), np.array([0.0005]))
    ds = clsas.simulate(scene, ap, wave, fs, beams=beams, surfaces=[surf], c_mps=1480.0)
    grid = clsas.VoxelGrid.from_bounds((-6e-3, 6e-3), (0, 0), (0.014, 0.024), 0.2e-3)
    return clsas.compress(ds, backend="numpy"), grid


@pytest.mark.parametrize("backend", BACKENDS)
def test_bp_without_the_beam_model_puts_the_surface_above_itself(flat_surface_under_a_coarse_line, backend):
    """Without the beam model, grating lobes of stops whose beams never saw a voxel make the brightest
    voxel of many columns a ghost 1.2 mm above the surface (the failure beams fixed, kept as the
    reference); beam-limited bp finds the surface within one voxel in every column."""
    prof, grid = flat_surface_under_a_coarse_line

    def share_on_surface(mode):
        a = np.abs(clsas.formation.form(prof, grid, "bp", beam=mode, backend=backend).values[:, 0, :])
        return np.mean(np.abs(grid.z_m[a.argmax(axis=1)] - 0.02) <= 0.2e-3 + 1e-9)

    assert share_on_surface("none") < 0.8
    assert share_on_surface("limited") >= 0.95
    assert share_on_surface(None) >= 0.95  # the default for profiles that carry beams


def test_formation_table_has_the_directional_case():
    # bp with and without the beam model, omega-k and FFBP in `python -m bench`'s table
    from bench import formation as bf

    res = bf.run_beams_case(4)
    rows = {r["formation"]: r for r in res["rows"]}
    assert list(rows)[:8] == ["bp", "bp beam=none", "bp beam=weighted", "omega-k", "omega-k beam=weighted",
                              "ffbp beam=none", "ffbp", "ffbp beam=limited"]
    assert rows["bp"]["error_all_db"] is None  # the reference: bp's default with beams ("limited")
    assert all(r.get("time_s", 0) > 0 or "refused" in r for r in res["rows"])
    assert rows["auto"]["chose"] == "bp"  # directional beams take bp
    table = "\n".join(bf.markdown({"cases": [res]}))
    assert "| beams | bp beam=none |" in table and "| beams | auto -> bp |" in table
    assert "beams" in bf.ALL_CASES and "beams" in bf.FULL["cases"] and "beams" not in bf.QUICK["cases"]


def test_omega_k_cone_share_counts_only_angles_inside_the_beams(caplog):
    # stops 2 cm apart alias every steep angle at 30 kHz; 2-degree cones keep only angles the
    # lattice samples unaliased, so the share is the whole grid and nothing is warned
    fs = 96e3
    wave = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    ap = clsas.raster_aperture(12, 12, 0.22, 0.22)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.7, 0.9), 0.02)
    scene = clsas.Scene(np.array([[0.0, 0.0, 0.8]]))
    shares = {}
    for name, beams in (("omni", None), ("cones", Beams(Cone(2.0), Cone(2.0), (0, 0, 1), (0, 0, 1), ap.n_meas))):
        ds = clsas.simulate(scene, ap, wave, fs, beams=beams, temperature_c=20.0)
        caplog.clear()
        img = clsas.reconstruct(ds, grid, formation="omega-k", backend="numpy")
        shares[name] = img.provenance["omega_k"]["cone_fraction"]
        shares[name + "_warned"] = "samples only" in caplog.text
    assert shares["omni"] < 0.5 and shares["omni_warned"]
    assert shares["cones"] == 1.0 and not shares["cones_warned"]
