"""When autofocus applies an estimate (clsas.focus.significance): beyond its uncertainty and large
enough to change the image; an error-free scan keeps its stated values."""

import numpy as np
import pytest

import clsas
from clsas.focus.significance import beyond_uncertainty, delay_floor_s, delay_spread_s, judge
from clsas.synthesis.scene_family import TUNING_2_SEEDS, family_scene


@pytest.fixture(scope="module")
def scene():
    """An odd tuning-2 seed of the family: its scan with errors, its error-free twin (both with
    the direct sound) and its grid."""
    return family_scene(TUNING_2_SEEDS[1])


def test_the_uncertainty_test_uses_students_t_for_the_degrees_of_freedom():
    # one degree of freedom (two halves): the 95 % quantile is 12.7, not 1.96
    assert not beyond_uncertainty(4.0, 1.0, 1) and beyond_uncertainty(13.0, 1.0, 1)
    assert beyond_uncertainty(2.1, 1.0, 1000) and not beyond_uncertainty(1.9, 1.0, 1000)
    assert beyond_uncertainty(1e-9, float("nan"), 5)  # unknown: the effect test decides


def test_judge_names_the_test_that_failed():
    v = judge(0.3, 0.05, 1, effect_s=1e-5, floor_s=2e-6, unit="C")
    assert not v.apply and "within 12.7 x its uncertainty" in v.why
    v = judge(30.0, 0.003, 100, effect_s=1e-7, floor_s=2e-6, unit="us")
    assert not v.apply and "too small to change the image" in v.why
    v = judge(30.0, 0.003, 100, effect_s=3e-5, floor_s=2e-6, unit="us")
    assert v.apply and v.why.startswith("beyond its uncertainty")


def test_the_floor_is_a_sixteenth_of_a_period_at_the_top_of_the_band(scene):
    assert delay_floor_s(scene.clean) == pytest.approx(1 / 16 / 30e3, rel=0.03)


def test_a_common_delay_change_has_no_spread_and_a_speed_change_has_one(scene):
    ds, grid = scene.clean, scene.grid
    assert delay_spread_s(ds, grid, ds.t0_s + 1e-5, ds.c_per_meas) == pytest.approx(0.0, abs=1e-12)
    assert delay_spread_s(ds, grid, ds.t0_s, ds.c_per_meas * 1.01) > 1e-6


def test_the_direct_sound_of_an_error_free_scan_is_not_applied_and_of_a_delayed_one_is(scene):
    """An odd seed of the family has the direct sound. Its error-free scan's arrivals give a delay
    of nanoseconds, within their scatter: nothing applied, the input returned. The recorded scan
    has a 10-50 us group delay: applied, to within its floor."""
    fs = scene
    out, rep = clsas.autofocus(fs.clean, fs.grid)
    assert out is fs.clean and not rep.improved
    assert not any(p.applied for p in rep.parameters.values())
    assert not rep.parameters["group_delay"].determined and not rep.parameters["timing"].determined
    out, rep = clsas.autofocus(fs.dataset, fs.grid)
    gd = rep.parameters["group_delay"]
    assert gd.applied and abs(gd.estimate - fs.params["group_delay_s"]) < delay_floor_s(fs.dataset)
    # the scatter of the arrivals is far under the floor: the median delay, the same for every stop
    assert not rep.parameters["timing"].applied
    assert np.ptp(out.t0_s - fs.dataset.t0_s) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.slow
def test_the_default_applies_nothing_to_the_familys_error_free_scans():
    """The default methods on the error-free scan of each tuning-2 seed (the odd ones carry the
    direct sound): nothing applied in at least 95 %, and the input returned where nothing is."""
    applied = []
    for seed in TUNING_2_SEEDS:
        fs = family_scene(seed, rms_m=0.0)
        out, rep = clsas.autofocus(fs.clean, fs.grid)
        names = [k for k, p in rep.parameters.items() if p.applied]
        assert (out is fs.clean) == (not names)
        applied.append(names)
    assert sum(not a for a in applied) >= 0.95 * len(TUNING_2_SEEDS), applied
