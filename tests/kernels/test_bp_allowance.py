"""The error a caller allows bp (``max_error_db``) reaching the kernel's variant choice: the tuning
offered the half-profiles variant only under an allowance of at least its bound, the image within
that bound of the float64 twin, and the variant that ran named in the image's provenance, through
Backprojector, the "bp" and "auto" formations and reconstruct.

The tuning's timings are stood in for (the child that times the shapes reports half profiles as the
fastest, on a host taken as quiet): which variant is the fastest on this host is what the tuning
measures, not what these tests check."""

import numpy as np
import pytest
from conftest import TOL, needs_opencl, small_dataset

import clsas
from clsas import cl
from clsas.cl import shapes
from clsas.formation import bp_numpy as twin
from clsas.formation.bp_opencl import HALF_TOLERANCE

HALF = "half_profiles"


def _has_fp16() -> bool:
    return "cl_khr_fp16" in cl.get_queue().device.extensions.split()


def _needs_fp16() -> None:
    if not _has_fp16():
        pytest.skip(f"{cl.describe(cl.get_queue().device)} does not report cl_khr_fp16")


@pytest.fixture
def half_fastest(tmp_path, monkeypatch):
    """A fresh cache (tunings, calibrations) whose tuning finds any half-profiles shape offered it
    twice as fast as the others. Yields the variant sets the tuning was offered."""
    from clsas.cl import variants

    offered = []

    def child(device, name, vec, candidates):
        offered.append({c.variant for c in candidates})
        return {"rounds": {c.label: [0.5, 0.5] if c.variant == HALF else [1.0, 1.0] for c in candidates},
                "refused": {}}

    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(shapes, "_run_child", child)
    monkeypatch.setattr(shapes, "busy", lambda device: None)
    saved = dict(shapes._MEMO), dict(variants._MEMO)
    shapes._MEMO.clear()
    cl.release_reused()  # no plan tuned before this test is reused
    yield offered
    cl.release_reused()
    shapes._MEMO.clear()
    shapes._MEMO.update(saved[0])
    variants._MEMO.update(saved[1])


def _scene():
    ds = small_dataset([[0.0, 0.0, 0.5], [0.04, -0.03, 0.55]], nx=8, ny=6)
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.06), (-0.06, 0.06), (0.46, 0.6), 0.01)
    return ds, grid


def _twin(prof, grid) -> np.ndarray:
    return twin.backproject(prof.data.astype(np.complex128), prof.tau0_s, prof.dtau_s, prof.fc_hz, prof.tx_positions,
                            prof.rx_positions, prof.c_mps, grid.points()).reshape(grid.shape)


def _error(image, want) -> float:
    return float(np.abs(image.values - want).max() / np.abs(want).max())


@needs_opencl
@pytest.mark.parametrize("resident", [True, False], ids=["resident", "step-by-step"])
def test_backprojector_under_minus_60_db_runs_half_profiles_within_their_bound(half_fastest, resident):
    _needs_fp16()
    ds, grid = _scene()
    prof = clsas.compress(ds, backend="opencl")
    want = _twin(prof, grid)
    image = clsas.Backprojector(grid, backend="opencl", max_error_db=-60, resident=resident)(prof)
    assert HALF in half_fastest[-1]  # -60 dB is 1e-3 of the peak: the half bound, admitted
    rec = image.provenance["bp"]
    assert rec["variant"] == HALF and rec["error_bound"] == HALF_TOLERANCE and rec["max_error_db"] == -60
    assert rec["shape"].startswith(HALF + "/")
    assert rec.get("records") == ("host" if resident else None)  # half records are made on the host
    err = _error(image, want)
    assert TOL["backproject"] / 100 < err < HALF_TOLERANCE, err  # rounded as half records are, within the bound


@needs_opencl
def test_backprojector_without_an_allowance_runs_the_float_kernel(half_fastest):
    ds, grid = _scene()
    prof = clsas.compress(ds, backend="opencl")
    image = clsas.Backprojector(grid, backend="opencl")(prof)
    assert all(HALF not in offered for offered in half_fastest)  # never offered to the tuning
    rec = image.provenance["bp"]
    assert rec["variant"] != HALF and rec["error_bound"] is None and rec["max_error_db"] is None
    assert _error(image, _twin(prof, grid)) < TOL["backproject"]
    tight = clsas.backproject(prof, grid, backend="opencl", max_error_db=-61)  # under the half bound
    assert tight.provenance["bp"]["variant"] != HALF and tight.provenance["bp"]["max_error_db"] == -61


@needs_opencl
def test_plans_are_reused_per_allowance(half_fastest):
    """A Backprojector with another allowance does not take the plan an exact one left (nor the reverse)."""
    _needs_fp16()
    ds, grid = _scene()
    prof = clsas.compress(ds, backend="opencl")
    first = clsas.backproject(prof, grid, backend="opencl")
    half = clsas.backproject(prof, grid, backend="opencl", max_error_db=-40)
    again = clsas.backproject(prof, grid, backend="opencl")
    assert [i.provenance["bp"]["variant"] == HALF for i in (first, half, again)] == [False, True, False]


@needs_opencl
def test_reconstruct_auto_gives_bp_its_target_and_records_the_variant(half_fastest):
    """A target given to reconstruct reaches auto's bp, less the margin; none given: bp exact."""
    ds, grid = _scene()
    sel = cl.select("opencl")
    # the other formations made slow in this fresh cache: auto forms by bp
    clsas.formation.auto.store_calibration({"omega-k": 1e3, "ffbp": 1e3}, sel)
    exact = clsas.reconstruct(ds, grid, backend="opencl")
    assert exact.provenance["formation"] == "bp" and exact.provenance["bp"]["max_error_db"] is None
    assert exact.provenance["bp"]["variant"] != HALF and exact.provenance["bp"]["error_bound"] is None
    image = clsas.reconstruct(ds, grid, backend="opencl", max_error_db=-30)
    choice = image.provenance["formation_auto"]
    assert image.provenance["formation"] == "bp" and choice["max_error_db"] == -30
    assert image.provenance["formation_options"] == {"max_error_db": -30 - clsas.formation.auto.MARGIN_DB}
    rec = image.provenance["bp"]
    assert rec["max_error_db"] == -33
    if _has_fp16():
        assert rec["variant"] == HALF and rec["error_bound"] == HALF_TOLERANCE
    else:  # no half records on this device: the allowance leaves the float kernels
        assert rec["variant"] != HALF and rec["error_bound"] is None
    prof = clsas.compress(ds, gate_s=image.plan.gate_s, backend="opencl")
    assert _error(image, _twin(prof, grid)) < (HALF_TOLERANCE if _has_fp16() else TOL["backproject"])


@needs_opencl
def test_reconstruct_with_bp_named_stays_float_unless_given_a_target(half_fastest):
    ds, grid = _scene()
    exact = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    assert exact.provenance["bp"]["variant"] != HALF and exact.provenance["bp"]["error_bound"] is None
    assert "formation_options" not in exact.provenance
    allowed = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", max_error_db=-50)
    assert allowed.provenance["formation_options"] == {"max_error_db": -50}
    assert (allowed.provenance["bp"]["variant"] == HALF) == _has_fp16()


@needs_opencl
def test_cli_reconstruct_names_the_bp_variant_auto_ran(half_fastest, tmp_path, capsys):
    from clsas.cli import main

    _needs_fp16()
    ds, grid = _scene()
    ds.save(tmp_path / "scan.h5")
    clsas.formation.auto.store_calibration({"omega-k": 1e3, "ffbp": 1e3}, cl.select("opencl"))
    (x0, x1), (y0, y1), (z0, z1) = grid.bounds()
    args = ["reconstruct", str(tmp_path / "scan.h5"), f"--grid={x0},{x1},{y0},{y1},{z0},{z1}", "--spacing", "0.01",
            "--backend", "opencl", "-q", "--out", str(tmp_path / "img.h5")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "formation: bp (auto, error target -30 dB" in out and "bp kernel:" not in out  # no target: exact
    assert main([*args, "--max-error-db", "-30", "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert "formation: bp (auto, error target -30 dB" in out
    assert "bp kernel: half_profiles (half_profiles/" in out and "allowed -33 dB" in out
    assert main([*args, "--formation", "bp", "--overwrite"]) == 0
    assert "bp kernel:" not in capsys.readouterr().out  # bp named: exact float kernels, nothing to say


@pytest.fixture
def expansion_fastest(tmp_path, monkeypatch):
    """As :func:`half_fastest`, for the range-expansion variant."""
    from clsas.cl import variants

    def child(device, name, vec, candidates):
        return {"rounds": {c.label: [0.5, 0.5] if c.variant == "range_expansion" else [1.0, 1.0]
                           for c in candidates}, "refused": {}}

    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(shapes, "_run_child", child)
    monkeypatch.setattr(shapes, "busy", lambda device: None)
    saved = dict(shapes._MEMO), dict(variants._MEMO)
    shapes._MEMO.clear()
    cl.release_reused()
    yield
    cl.release_reused()
    shapes._MEMO.clear()
    shapes._MEMO.update(saved[0])
    variants._MEMO.update(saved[1])


@needs_opencl
def test_provenance_names_the_expansion_that_ran_or_the_plain_kernel_it_fell_back_to(expansion_fastest):
    """Under -40 dB the tuning takes the range expansion; the image's provenance then says which
    kernel each geometry ran: the expansion with its run and its bound for that geometry (within
    -50 dB, the image within it of the float64 twin), or the plain kernel where no run's bound is."""
    from clsas.formation.bp_opencl import EXPANSION_LIMIT

    ds, _ = _scene()
    prof = clsas.compress(ds, backend="opencl")
    xy = np.linspace(-0.05, 0.05, 3)
    fine = clsas.VoxelGrid(xy, xy, 0.45 + 0.005 * np.arange(24))  # run 4 at -64 dB on this scan
    coarse = clsas.VoxelGrid(xy, xy, 0.4 + 0.015 * np.arange(32))  # run 4 near -34 dB: none within -50 dB
    for grid, ran in [(fine, "range_expansion"), (coarse, "plain")]:
        image = clsas.Backprojector(grid, backend="opencl", max_error_db=-40)(prof)
        bp = image.provenance["bp"]
        assert bp["shape"].startswith("range_expansion") and bp["variant"] == ran, bp
        want = _twin(prof, grid)
        if ran == "plain":
            assert bp["error_bound"] is None and "expansion_run" not in bp
            assert _error(image, want) < TOL["backproject"]
        else:
            assert 0 < bp["error_bound"] <= EXPANSION_LIMIT and bp["expansion_run"] >= 4
            assert _error(image, want) <= bp["error_bound"] + TOL["backproject"]
