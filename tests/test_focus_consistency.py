"""The data-consistency test (issue 26, thirteenth session): a least-squares target in the grid
explains a static scan to the noise, and leaves a scan with motion largely unexplained."""

import numpy as np
import pytest

import clsas
from clsas.focus.consistency import Consistency, data_consistency
from clsas.scan_errors import HandMotion

FS = 96e3
POINTS = np.array([[0.02, -0.01, 0.6], [-0.03, 0.02, 0.62], [0.01, 0.025, 0.61]])
GRID = clsas.VoxelGrid.from_bounds((-0.05, 0.04), (-0.03, 0.045), (0.585, 0.635), 0.005)


def scan(motion_m=0.0, snr_db=30.0):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ap = clsas.raster_aperture(8, 7, 0.24, 0.2)
    return clsas.simulate(clsas.Scene(POINTS), ap, w, FS, snr_db=snr_db, seed=3,
                          position_error=HandMotion(motion_m, seed=5))


@pytest.fixture(scope="module")
def fits():
    static, moved = scan(), scan(3e-3)
    c_static = data_consistency(static, GRID, max_iter=25, backend="numpy")
    c_moved = data_consistency(moved, GRID, max_iter=25, backend="numpy")
    tr = moved.truth
    at_truth = moved.replace(tx_positions=tr["tx_positions"], rx_positions=tr["rx_positions"])
    c_truth = data_consistency(at_truth, GRID, max_iter=25, floor_of=c_moved, backend="numpy")
    return c_static, c_moved, c_truth


def test_static_scan_is_explained_to_the_noise(fits):
    c, _, _ = fits
    assert isinstance(c, Consistency)
    assert c.iterations == 25 and len(c.history) == len(c.floor_history) == 26
    assert c.history[0] == pytest.approx(1.0)  # before the fit nothing is explained
    assert np.all(np.diff(c.history) <= 1e-12)  # CGLS never raises the residual
    assert c.residual < 0.1
    assert c.floor > 0 and c.noise_sigma > 0
    assert c.excess == pytest.approx(np.sqrt(max(c.residual ** 2 - c.floor ** 2, 0.0)))


def test_motion_leaves_the_data_unexplained_and_the_truth_explains_them(fits):
    static, moved, truth = fits
    # 3 mm of hand motion is about 1.4 rad of phase per stop at 25 kHz: no single target fits it
    assert moved.residual > 3 * static.residual
    assert moved.excess > 0.2
    # the same recordings at their true positions are explained as well as the static scan
    assert truth.residual < 1.5 * static.residual + 0.01
    assert truth.excess < 0.2 * moved.excess


def test_floor_of_reuses_the_noise_fit(fits):
    _, moved, truth = fits
    assert truth.noise_sigma == moved.noise_sigma
    assert truth.floor == pytest.approx(moved.floor * moved.scale / truth.scale)


def test_progress_names_each_fit():
    calls = []
    data_consistency(scan(), GRID, max_iter=2, backend="numpy", progress=lambda *a: calls.append(a))
    assert [c[0] for c in calls] == ["fit", "fit", "noise", "noise"]
    assert calls[-1][1:] == (2, 2)


@pytest.mark.parametrize("kwargs, match", [
    ({"max_iter": 0}, "max_iter"), ({"max_iter": 10_001}, "max_iter"), ({"max_iter": 2.5}, "max_iter"),
    ({"seed": -1}, "seed"), ({"seed": True}, "seed"), ({"floor_of": 3.0}, "floor_of"),
    ({"progress": 3}, "progress"),
])
def test_options_are_checked_by_name(kwargs, match):
    with pytest.raises((TypeError, ValueError), match=match):
        data_consistency(scan(), GRID, **kwargs)


def test_floor_of_must_match_the_iterations():
    c = Consistency(0.1, 0.01, 0.09, [1.0, 0.1], [0.02, 0.01], 1.0, 1.0, 1)
    with pytest.raises(ValueError, match="floor_of"):
        data_consistency(scan(), GRID, max_iter=2, floor_of=c)


def test_dataset_and_grid_types_are_checked():
    with pytest.raises(TypeError, match="dataset"):
        data_consistency(np.zeros((3, 3)), GRID)
    with pytest.raises(TypeError, match="grid"):
        data_consistency(scan(), "grid")


def test_cli_autofocus_prints_the_consistency_before_and_after(tmp_path, capsys):
    from clsas.cli import main

    scan(3e-3).save(tmp_path / "s.h5")
    args = ["autofocus", str(tmp_path / "s.h5"), str(tmp_path / "o.h5"), "--grid=-0.05,0.04,-0.03,0.045,0.585,0.635",
            "--spacing", "0.005", "--methods", "direct,points", "-q", "--backend", "numpy"]
    assert main([*args, "--consistency", "5"]) == 0
    text = capsys.readouterr().out
    assert "before: data consistency:" in text and "after 5 iterations" in text
    # a negative count is refused before any focusing
    assert main([*args, "--consistency", "-1"]) == 2
    assert "--consistency" in capsys.readouterr().err
