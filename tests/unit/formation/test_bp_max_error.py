"""bp's ``max_error_db`` (the error its kernel may trade for speed): checked by name wherever it is
taken, turned into the plan's fraction of the peak, recorded with the image, given by auto (its target
less the margin) and by reconstruct only where the caller gave one. The kernels themselves:
tests/kernels/test_bp_allowance.py."""

import math

import numpy as np
import pytest
from conftest import small_dataset

import clsas
from clsas.formation import auto, form
from clsas.formation.bp import allowed_error


@pytest.fixture(scope="module")
def scan():
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.04, 0.04), (-0.04, 0.04), (0.47, 0.53), 0.01)
    return ds, grid, clsas.compress(ds, backend="numpy")


BAD = [(float("nan"), ValueError), (float("inf"), ValueError), (-float("inf"), ValueError), (0.0, ValueError),
       (6.0, ValueError), ("-60", TypeError), (True, TypeError), ([-60], TypeError)]


@pytest.mark.parametrize("bad, kind", BAD, ids=lambda x: repr(x) if not isinstance(x, type) else x.__name__)
def test_max_error_db_is_checked_by_name_everywhere_bp_takes_it(scan, bad, kind):
    ds, grid, prof = scan
    with pytest.raises(kind, match="max_error_db"):
        clsas.Backprojector(grid, backend="numpy", max_error_db=bad)
    with pytest.raises(kind, match="max_error_db"):
        clsas.backproject(prof, grid, backend="numpy", max_error_db=bad)
    with pytest.raises(kind, match="max_error_db"):
        form(prof, grid, "bp", backend="numpy", max_error_db=bad)
    with pytest.raises(kind, match="max_error_db"):
        list(clsas.formation.bp.form_tiles(prof, [grid], backend="numpy", max_error_db=bad))
    with pytest.raises(kind, match="max_error_db"):
        clsas.reconstruct(ds, grid, backend="numpy", formation="bp", max_error_db=bad)


def test_the_allowance_is_the_plans_fraction_of_the_peak():
    assert allowed_error(None) is None
    assert allowed_error(-60) == pytest.approx(1e-3) and allowed_error(-60) <= 1e-3  # the half bound, admitted
    assert allowed_error(np.float32(-20)) == pytest.approx(0.1)
    assert 0 < allowed_error(-1e6) < 1e-300 and allowed_error(-1e-30) < 1  # inside the plan's (0, 1)


def test_the_twin_is_recorded_as_such(scan):
    _, grid, prof = scan
    rec = clsas.backproject(prof, grid, backend="numpy", max_error_db=-40).provenance["bp"]
    assert rec == {"variant": "twin", "shape": None, "error_bound": None, "max_error_db": -40.0}


def test_auto_gives_bp_its_target_less_the_margin(scan):
    _, grid, prof = scan
    est = next(e for e in auto.estimate(prof, grid, None, max_error_db=-40) if e.formation == "bp")
    assert est.options == {"max_error_db": -40 - auto.MARGIN_DB} and est.error_db == -math.inf
    rule = auto.by_rule(prof, -30.0, tiled=True)
    assert rule.formation == "bp" and rule.options == {"max_error_db": -33.0}
    assert auto.bp_options(-30.0) == {"max_error_db": -33.0}
    # no target given: auto aims at its default, and bp stays exact
    assert auto.bp_options(None) == {}
    default = auto.by_rule(prof, None, tiled=True)
    assert default.options == {} and default.max_error_db == auto.DEFAULT_MAX_ERROR_DB
    est = next(e for e in auto.estimate(prof, grid, None) if e.formation == "bp")
    assert est.options == {}


def test_reconstruct_gives_bp_a_target_only_where_the_caller_gave_one(scan, tmp_path, monkeypatch):
    ds, grid, _ = scan
    named = clsas.reconstruct(ds, grid, backend="numpy", formation="bp")
    assert "formation_options" not in named.provenance and named.provenance["bp"]["max_error_db"] is None
    given = clsas.reconstruct(ds, grid, backend="numpy", formation="bp", max_error_db=-45)
    assert given.provenance["formation_options"] == {"max_error_db": -45}
    assert given.provenance["bp"]["max_error_db"] == -45
    with pytest.raises(ValueError, match="max_error_db is reconstruct's own parameter"):
        clsas.reconstruct(ds, grid, backend="numpy", formation="bp", formation_options={"max_error_db": -45})
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    auto.store_calibration({"omega-k": 1e3, "ffbp": 1e3})  # auto forms by bp
    image = clsas.reconstruct(ds, grid, backend="numpy")
    assert image.provenance["formation"] == "bp" and image.provenance["formation_auto"]["max_error_db"] == -30
    assert image.provenance["bp"]["max_error_db"] is None and "formation_options" not in image.provenance
    image = clsas.reconstruct(ds, grid, backend="numpy", max_error_db=-30)
    assert image.provenance["bp"]["max_error_db"] == -33
    assert "exact, or a kernel variant stated within -33 dB" in image.provenance["formation_auto"]["reason"]


def test_cli_names_a_bp_variant_less_exact_than_the_float_kernel():
    from clsas.cli.reconstruct import bp_variant_line

    exact = {"variant": "plain", "shape": "plain/auto", "error_bound": None, "max_error_db": -33.0}
    assert bp_variant_line(exact) == ""
    assert bp_variant_line(None) == ""
    line = bp_variant_line({"variant": "half_profiles", "shape": "half_profiles/64", "error_bound": 1e-3,
                            "max_error_db": -33.0})
    assert line.startswith("bp kernel: half_profiles (half_profiles/64)") and "(-60 dB), allowed -33 dB" in line
