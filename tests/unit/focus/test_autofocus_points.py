"""The ``"points"`` motion step: the phases the strong points share,
rank one, unwrapped in time, determined only on isolated points, applied only where disjoint
sub-apertures agree better."""

import numpy as np
import pytest

import clsas
from clsas.focus import autofocus, score
from clsas.focus.points import MIN_COHERENCE, common_phases, pick_points
from clsas.synthesis.scene_family import family_scene


def test_common_phases_read_the_stops_phases_without_a_reference_point():
    # a_sk = alpha_k exp(j phi_s) + noise: the stops' phases come back up to one constant, whatever
    # the points' own phases and amplitudes (no point is the reference)
    rng = np.random.default_rng(0)
    phi = np.cumsum(rng.normal(0, 0.5, 200))  # wraps many times
    alpha = rng.uniform(0.3, 1.0, 6) * np.exp(2j * np.pi * rng.uniform(size=6))
    noise = 0.1 * (rng.normal(size=(200, 6)) + 1j * rng.normal(size=(200, 6)))  # phase noise about 0.06 rad
    z, kept = common_phases(np.exp(1j * phi)[:, None] * alpha[None, :] + noise)
    r = z * np.exp(-1j * phi)
    err = np.angle(r * np.conj(np.mean(r)))  # against the common constant
    assert kept == 6
    assert np.sqrt(np.mean(err**2)) < 0.1


def test_common_phases_drop_a_point_that_does_not_share_them():
    rng = np.random.default_rng(1)
    phi = rng.uniform(-np.pi, np.pi, 150)
    a = np.exp(1j * phi)[:, None] * np.ones((1, 5))
    a[:, 4] = np.exp(2j * np.pi * rng.uniform(size=150))  # speckle: its own phase at every stop
    z, kept = common_phases(a)
    assert kept == 4
    r = z * np.exp(-1j * phi)
    assert np.abs(np.angle(r * np.conj(r[0]))).max() < 1e-6


def test_pick_points_brightest_first_and_apart():
    grid = clsas.VoxelGrid.from_bounds((0, 0.1), (0, 0.1), (0, 0.02), 0.005)
    pts = grid.points()
    values = np.zeros(grid.size)
    for p, amp in (((0.02, 0.02, 0.01), 1.0), ((0.025, 0.02, 0.01), 0.9), ((0.08, 0.07, 0.01), 0.5),
                   ((0.05, 0.09, 0.01), 0.01)):
        values[np.argmin(np.linalg.norm(pts - p, axis=1))] = amp
    got = pick_points(grid, values, min_separation_m=0.02)
    # the second is 5 mm from the first (too close), the last 40 dB down (outside 14 dB)
    assert np.allclose(got, [[0.02, 0.02, 0.01], [0.08, 0.07, 0.01]])
    assert pick_points(grid, np.zeros(grid.size), min_separation_m=0.02).shape == (0, 3)


def test_points_corrects_hand_motion_on_a_point_scene():
    # family seed 6: 12 points at 1.36 m, 17 x 17 stops, 3 mm of hand motion (-7 dB at the peak)
    fs = family_scene(6, rms_m=3e-3)
    out, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "points"))
    s = score(rep, fs.dataset)
    m = rep.parameters["motion"]
    assert rep.improved and m.determined and m.applied
    assert "strong points" in m.how
    assert rep.check["points_passed"]
    assert s["los_residual_rms_m"] < 0.3e-3 < s["los_error_rms_m"]
    clean = np.abs(clsas.reconstruct(fs.clean, fs.grid).values).max()
    after = np.abs(clsas.reconstruct(out, fs.grid).values).max()
    assert 20 * np.log10(after / clean) > -1.0


def test_points_is_not_determined_on_a_surface_and_applies_nothing():  # and say so: see below
    # family seed 4: a sphere cap of 161 scatterers (speckle, no isolated points), no direct sound
    fs = family_scene(4, rms_m=3e-3)
    out, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "points"))
    stage = next(s for s in rep.stages if s["step"] == "points")
    assert not stage["determined"] and stage["coherence"] < MIN_COHERENCE
    assert any(n.startswith("points: not applied") for n in rep.notes)
    assert not rep.improved and out is fs.dataset


def test_points_is_a_method_name_and_others_are_refused():
    from clsas.focus import METHODS

    assert "points" in METHODS
    fs = family_scene(6, rms_m=3e-3)
    with pytest.raises(ValueError, match="methods"):
        autofocus(fs.dataset, fs.grid, methods=("direct", "pointz"))


def test_smooth_unwrapped_follows_time_order_and_skips_dead_stops():
    from clsas.focus.points import smooth_unwrapped
    from clsas.focus.track import smooth_basis

    rng = np.random.default_rng(4)
    n = 240
    t = np.arange(n) * 0.02
    xy = np.c_[np.tile(np.arange(16.0), 15), np.repeat(np.arange(15.0), 16)] * 0.03
    phi = 6 * np.sin(2 * np.pi * 0.7 * t) + 3 * np.cos(2 * np.pi * 2.1 * t)  # wraps many times, smooth
    z = np.exp(1j * phi)
    z[[40, 41, 120]] = 1e-4 * np.exp(2j * np.pi * rng.uniform(size=3))  # dead stops: random phase, no weight
    perm = rng.permutation(n)  # stops not in time order: the time axis decides
    basis = smooth_basis(t[perm], xy[perm], 6.0)
    got = smooth_unwrapped(z[perm], t[perm], basis)
    err = got - phi[perm] - np.mean(got - phi[perm])
    assert np.sqrt(np.mean(err**2)) < 0.05


def test_gauge_free_on_a_line_scan_removes_only_its_one_tilt():
    from clsas.focus.track import gauge_free

    x = np.linspace(0, 0.5, 20)
    xy = np.c_[x, np.zeros(20)]
    p = 1e-3 + 2e-3 * x
    assert np.abs(gauge_free(p, xy)).max() < 1e-12
    bump = np.zeros(20)
    bump[2] = 1e-3  # a single stop's error is not a tilt: mostly kept
    assert gauge_free(bump, xy)[2] > 0.8e-3


def test_points_alone_on_a_surface_says_so_in_the_motion_parameter():
    fs = family_scene(4, rms_m=3e-3)
    _, rep = autofocus(fs.dataset, fs.grid, methods=("direct", "points"))
    m = rep.parameters["motion"]
    assert m.how.startswith("points:") and not m.applied
    assert any("no other motion step named" in n for n in rep.notes)


def test_the_cli_help_names_every_method():
    import argparse

    from clsas.cli.autofocus import add_autofocus_options
    from clsas.focus import METHODS

    ap = argparse.ArgumentParser()
    add_autofocus_options(ap)
    text = next(a.help for a in ap._actions if "--methods" in a.option_strings)
    assert all(m in text for m in METHODS)
