"""Autofocus estimates only what the scan determines: the failures of sharpness alone
on scenes nobody tuned it on, each on a small scene, and the seeded scene family."""

import numpy as np
import pytest

import clsas
from clsas.focus import DEFAULT_METHODS, FOCUS_METHODS, autofocus
from clsas.focus.split import agreement, magnitude_correlation
from clsas.physics.scan_errors import HandMotion
from clsas.synthesis.scene_family import HELD_OUT_SEEDS, KINDS, SEED_SETS, TUNING_SEEDS, family_scene

FS = 96e3
POINTS = np.array([[0.02, -0.01, 0.6], [-0.05, 0.03, 0.65], [0.06, 0.04, 0.62], [-0.03, -0.05, 0.58]])
GRID = clsas.VoxelGrid.from_bounds((-0.09, 0.09), (-0.08, 0.07), (0.55, 0.69), 0.005)


def scan(points=POINTS, nx=13, ny=9, width=0.3, height=0.2, amplitudes=None, **kw):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ap = clsas.raster_aperture(nx, ny, width, height)
    return clsas.simulate(clsas.Scene(np.asarray(points, float), amplitudes), ap, w, FS, snr_db=30, **kw)


def test_a_delay_without_direct_sound_stays_at_zero():
    # no direct sound, and no delay: a delay from sharpness mostly shifts the image in range
    ds = scan(position_error=HandMotion(0.0, seed=1))
    out, rep = autofocus(ds, GRID, methods=("direct", "delay"), max_delay_s=3e-4)
    gd = rep.parameters["group_delay"]
    # either the halves disagree (not determined: exactly 0) or they agree, and then near the truth (0)
    assert (not gd.determined and rep.group_delay_s == 0.0) or abs(rep.group_delay_s) <= 2e-6
    assert np.array_equal(out.t0_s, ds.t0_s) or abs(rep.group_delay_s) <= 2e-6
    assert "delay" not in DEFAULT_METHODS and "delay" not in FOCUS_METHODS
    _, rep = autofocus(ds, GRID, methods=("direct", "phase", "3d"), max_iter=4)  # no delay search
    assert rep.group_delay_s == 0.0 and not rep.parameters["group_delay"].determined
    assert "no direct sound" in rep.parameters["group_delay"].how


def test_an_undetermined_temperature_is_left_alone():
    # an aperture 4 cm wide at 0.6 m: c scales the range, which changes no focus metric
    ds = scan(nx=4, ny=3, width=0.04, height=0.03, temperature_error_c=3.0, direct_gain=1.0)
    out, rep = autofocus(ds, GRID, methods=("direct", "temperature"), temperature_range_c=5.0)
    t = rep.parameters["temperature"]
    assert not t.determined and not t.applied
    assert rep.temperature_offset_c == 0.0 and rep.temperature_c == pytest.approx(20.0)
    assert out.temperature_c == ds.temperature_c  # unchanged, not pushed to a search bound
    assert "not determined" in t.how
    # the direct sound still measures the delay: none was added, so its estimate (the temperature
    # error's sub-microsecond change of the direct path's time) is too small to apply
    gd = rep.parameters["group_delay"]
    assert abs(gd.estimate) < 2e-6 and not gd.determined and not gd.applied
    assert "too small to change the image" in gd.how and np.array_equal(out.t0_s, ds.t0_s)


def test_sharpness_over_fit_returns_the_input_with_a_note():
    # speckle from 300 scatterers, no motion at all: a line-of-sight motion in 30 smooth functions
    # makes the image sharper, and disjoint sub-apertures' images do not agree better
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-0.07, 0.07, 300), rng.uniform(-0.06, 0.05, 300), rng.uniform(0.57, 0.67, 300)]
    ds = scan(pts, amplitudes=rng.normal(size=300), position_error=HandMotion(0.0, seed=2))
    out, rep = autofocus(ds, GRID, methods=("los",), n_basis=30, max_iter=10)
    assert next(st for st in rep.stages if st["step"] == "los")["metric"] > rep.metric_before + 0.05  # over-fit
    assert out is ds and not rep.improved
    assert not rep.parameters["motion"].applied and not rep.parameters["motion"].determined
    assert any("over-fits" in n for n in rep.notes) and any("input is returned" in n for n in rep.notes)


@pytest.mark.slow
def test_hand_motion_is_corrected_and_checked():
    ds = scan(nx=19, ny=13, width=0.4, height=0.3, position_error=HandMotion(0.003, seed=4, weights=(0.3, 0.3, 1)))
    out, rep = autofocus(ds, GRID, methods=FOCUS_METHODS, max_iter=15)
    s = clsas.focus.score(rep, ds)
    assert rep.improved and rep.parameters["motion"].applied
    assert rep.check["motion_passed"] and rep.check["passed"]
    assert rep.check["motion_time_after"] > rep.check["motion_time_before"]
    assert s["los_residual_rms_m"] < s["los_error_rms_m"]


@pytest.mark.parametrize("kwargs, match", [
    ({"temperature_tolerance_c": 0}, "temperature_tolerance_c"),
    ({"delay_tolerance_s": -1e-6}, "delay_tolerance_s"),
    ({"check_margin": 1.0}, "check_margin"),
    ({"check_margin": float("nan")}, "check_margin"),
    ({"heldout_gain": 0}, "heldout_gain"),
    ({"phase_region_m": -0.01}, "phase_region_m"),
])
def test_new_options_are_validated_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        autofocus(scan(nx=3, ny=2), GRID, **kwargs)


def test_report_per_parameter():
    ds = scan(nx=4, ny=3, width=0.04, height=0.03, group_delay_s=2e-5, direct_gain=1.0)
    out, rep = autofocus(ds, GRID, methods=("direct",))
    gd = rep.parameters["group_delay"]
    assert gd.determined and gd.applied and rep.improved
    assert gd.estimate == pytest.approx(2e-5, abs=1e-6) and gd.uncertainty < 1e-6
    d = rep.as_dict()
    assert d["parameters"]["group_delay"]["applied"] and "passed" in d["check"]
    assert "group_delay:" in rep.summary()


def test_split_helpers():
    rng = np.random.default_rng(0)
    img = rng.normal(size=500) + 1j * rng.normal(size=500)
    assert magnitude_correlation(img, 2 * img * np.exp(1j * rng.uniform(0, 6, 500))) == pytest.approx(1.0)
    assert abs(magnitude_correlation(img, rng.normal(size=500) + 1j * rng.normal(size=500))) < 0.2
    assert agreement(0.1, 0.2, -5, 5, 0.25)["determined"]
    assert not agreement(4.9, 4.8, -5, 5, 0.25)["determined"]  # at the edge
    assert not agreement(-1.0, 1.0, -5, 5, 0.25)["determined"]


def test_scene_family_is_seeded_and_disjoint():
    assert not set(TUNING_SEEDS) & set(HELD_OUT_SEEDS) and len(HELD_OUT_SEEDS) >= 30
    sets = [set(v) for v in SEED_SETS.values()]
    assert sum(map(len, sets)) == len(set().union(*sets))  # every set disjoint from the others
    assert len(SEED_SETS["held-out-2"]) >= 30 and set(SEED_SETS) == {"tuning", "tuning-2", "held-out", "held-out-2"}
    a, b = family_scene(5, rms_m=0.001), family_scene(5, rms_m=0.001)
    assert np.array_equal(a.dataset.signals, b.dataset.signals) and a.params == b.params
    p = a.params
    assert 13 <= p["nx"] <= 28 and 13 <= p["ny"] <= 28 and 0.24 <= p["width_m"] <= 1.0
    assert 0.5 <= p["range_m"] <= 1.8 and 15 <= p["snr_db"] <= 35 and a.kind in KINDS
    assert p["direct"] and 10e-6 <= p["group_delay_s"] <= 50e-6 and 0.5 <= abs(p["temperature_error_c"]) <= 3
    assert a.dataset.truth["group_delay_s"] == p["group_delay_s"] and "position_error_m" in a.dataset.truth
    assert a.grid.size <= 30_000 * 1.1
    with pytest.raises(ValueError, match="seed"):
        family_scene(-1)
    with pytest.raises(ValueError, match="kind"):
        family_scene(2, kind="cube")


def test_family_summary_markdown_and_plot(tmp_path):
    from bench.autofocus_family import family_markdown, plot_family, summarise

    def row(seed, before, after, los_b, los_a, direct):
        return {"seed": seed, "kind": "points", "nx": 13, "ny": 13, "range_m": 1.0, "peak_before_db": before,
                "peak_after_db": after, "peak_oracle_db": -0.1, "los_error_rms_m": los_b,
                "los_residual_rms_m": los_a, "improved": True,
                "time_s": 10.0 + seed, "direct": direct, "group_delay_error_s": 1e-6 if direct else 0.0,
                "temperature_error_c": 0.2, "parameters": {"temperature": {"determined": seed == 1}}}

    rows = [row(0, -8.0, -0.5, 2e-3, 1e-4, False), row(1, -6.0, -7.0, 2e-3, 3e-3, True),
            {"seed": 2, "rms_m": 0.003, "error": "ValueError: x"}]
    s = summarise(rows)
    assert s["n"] == 2 and s["failed"] == 1
    assert s["within_1db"] == 0.5 and s["worse_than_none"] == 0.5 and s["worse_than_none_by_0_5db"] == 0.5
    assert s["worst_peak_db"] == -7.0 and s["los_reduced"] == 0.5
    assert s["group_delay_error_max_us"] == pytest.approx(1.0) and s["temperature_determined"] == 1
    md = family_markdown({"tuning 3 mm": {"summary": s, "rows": rows}})
    assert s["within_1db_oracle"] == 1.0
    assert "| tuning 3 mm | 2 | 50% (0%; 100%)" in md and "error: ValueError" in md and "(-0.10)" in md
    plot_family({"tuning 3 mm": {"summary": s, "rows": rows}}, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 0


def test_bench_autofocus_set_is_checked():
    from bench.__main__ import build_parser, main
    from bench.autofocus_family import run_and_write

    with pytest.raises(ValueError, match="seed_set"):
        run_and_write("all")
    with pytest.raises(SystemExit):
        main(["--autofocus", "all"])
    # the command line offers every seed set the library names, and no other
    offered = next(a for a in build_parser()._actions if "--autofocus" in a.option_strings).choices
    assert set(offered) == set(SEED_SETS)


def test_the_per_stop_ceiling_undoes_the_hand_motion_of_a_family_scene():
    # the truth applied as one delay per stop (towards the grid's centre) brings the brightest
    # voxel's local peak back to the error-free one: the per-stop model holds on this scene
    from bench.autofocus_family import local_peak_db, oracle_per_stop
    from clsas.synthesis.scene_family import family_scene

    fs = family_scene(6)
    clean = clsas.reconstruct(fs.clean, fs.grid)
    point = fs.grid.points()[int(np.argmax(np.abs(clean.values).ravel()))]
    ref = local_peak_db(fs.clean, point)
    assert local_peak_db(fs.dataset, point) - ref < -3
    assert abs(local_peak_db(oracle_per_stop(fs), point) - ref) < 0.3
