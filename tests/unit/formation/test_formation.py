"""The formation registry behind ``reconstruct(..., formation=...)``; each fast formation has its own tests."""

import numpy as np
import pytest
from conftest import small_dataset

import clsas
from clsas.formation import FORMATIONS, error_to_signal_db, form


def test_bp_formation_equals_backprojection():
    ds = small_dataset([[0.0, 0.0, 0.5]])
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.01)
    ref = clsas.reconstruct(ds, grid, backend="numpy")
    img = clsas.reconstruct(ds, grid, backend="numpy", formation="bp")
    assert np.array_equal(ref.values, img.values)
    prof = clsas.compress(ds, backend="numpy")
    via_form = form(prof, grid, "bp", backend="numpy")
    assert via_form.provenance["formation"] == "bp"
    assert error_to_signal_db(via_form, clsas.backproject(prof, grid, backend="numpy")) < -200


def test_unknown_formation_names_the_known_ones():
    ds = small_dataset([[0.0, 0.0, 0.5]])
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.01)
    with pytest.raises(ValueError, match="formation") as err:
        clsas.reconstruct(ds, grid, backend="numpy", formation="fourier")
    for name in FORMATIONS:
        assert name in str(err.value)
    with pytest.raises(ValueError, match="formation_options"):
        clsas.reconstruct(ds, grid, backend="numpy", formation_options={"depth": 2})


def test_error_to_signal_db_checks_its_inputs():
    a = np.ones((2, 2, 2), complex)
    assert error_to_signal_db(a * 1.1, a) == pytest.approx(-20.0)
    with pytest.raises(ValueError, match="mask"):
        error_to_signal_db(a, a, mask=np.zeros((2, 2, 2), bool))
    with pytest.raises(ValueError, match="reference"):
        error_to_signal_db(a, 0 * a)
    with pytest.raises(ValueError, match="shape"):
        error_to_signal_db(a, np.ones((2, 2)))


@pytest.mark.parametrize("formation", ["bp", "ffbp", "auto"])
def test_the_memory_guard_runs_once_per_reconstruct(monkeypatch, formation):
    """reconstruct checks its grid once, before any work; the formation it calls does not check it
    again (a fallback to another backend kind would)."""
    from clsas.formation import guard

    calls = []
    real = guard._memory_problems
    monkeypatch.setattr(guard, "_memory_problems", lambda *a: (calls.append(a[1]), real(*a)))
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.04, 0.04), (0.45, 0.55), 0.01)
    clsas.reconstruct(ds, grid, backend="numpy", formation=formation)
    assert len(calls) == 1, calls


def test_the_command_line_checks_the_grid_once(monkeypatch, tmp_path):
    from clsas.cli import main
    from clsas.formation import guard

    calls = []
    real = guard._memory_problems
    monkeypatch.setattr(guard, "_memory_problems", lambda *a: (calls.append(a[1]), real(*a)))
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=6, ny=5)
    ds.save(tmp_path / "scan.h5")
    assert main(["reconstruct", str(tmp_path / "scan.h5"), "--grid=-0.05,0.05,-0.04,0.04,0.45,0.55",
                 "--spacing", "0.01", "--backend", "numpy", "-q"]) == 0
    assert len(calls) == 1, calls
