"""The request against the data before any work (clsas.types.sanity): a grid in millimetres, a grid
beside the target, positions in the wrong unit."""

import logging

import numpy as np
import pytest
from conftest import small_dataset

import clsas
from clsas.types.sanity import check_grid_against_data, echo_share_in_grid


@pytest.fixture(scope="module")
def scan():
    return small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)


def test_a_grid_on_the_target_holds_its_echoes(scan):
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.6), 0.02)
    check = check_grid_against_data(scan, grid)
    assert check.share > 0.9 and not check.warnings


def test_a_target_within_a_chirps_length_still_counts():
    """A 5 ms chirp is 1.7 m of sound: a target at 0.5 m echoes while the direct sound's sidelobes
    last. The echoes in the grid's delays count, the share is high and nothing warns."""
    fs = 96e3
    wave = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    ds = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), clsas.raster_aperture(4, 3, 0.2, 0.1), wave, fs,
                        snr_db=30, direct_gain=1.0, seed=0)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.01)
    check = check_grid_against_data(ds, grid)
    assert check.share > 0.5 and not check.warnings


def test_a_grid_in_millimetres_is_refused_before_any_work(scan, monkeypatch):
    """The README's grid typed in millimetres: every voxel's delay lies seconds after the recordings
    end; reconstruct refuses it naming grid and the likely unit, before compressing anything."""
    mm = clsas.VoxelGrid.from_bounds((-100, 100), (-80, 80), (400, 600), 20)
    import clsas.pipeline.reconstruction as pipeline

    monkeypatch.setattr(pipeline, "compress", lambda *a, **k: pytest.fail("compressed before the check"))
    with pytest.raises(ValueError, match=r"^grid: .*millimetres"):
        clsas.reconstruct(scan, mm, backend="numpy")


def test_a_grid_beside_the_target_warns_and_says_so_in_the_image(scan, caplog):
    """A grid whose delays overlap the recordings but not the echo: imaged, with one warning naming
    the share, kept in the image's provenance."""
    beside = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.15, 0.25), 0.02)
    with caplog.at_level(logging.WARNING, logger="clsas.types.sanity"):
        image = clsas.reconstruct(scan, beside, backend="numpy", formation="bp")
    record = image.provenance["grid_check"]
    assert record["echo_share"] < 0.2 and len(record["warnings"]) == 1
    assert "% of the echo energy" in record["warnings"][0]
    assert sum("echo energy" in r.getMessage() for r in caplog.records) == 1


def test_positions_in_millimetres_are_named(scan):
    """Positions 1000x too large, grid in metres: the message points at the positions."""
    ds = clsas.Dataset(scan.signals, scan.tx_positions * 1000, scan.rx_positions * 1000, scan.fs_hz, scan.waveform,
                       temperature_c=20.0)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.6), 0.02)
    with pytest.raises(ValueError, match="positions in millimetres"):
        check_grid_against_data(ds, grid)


def test_the_share_is_the_one_inspect_reports(scan):
    from clsas.presenting.inspection import inspect_dataset

    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.45, 0.55), 0.02)
    assert inspect_dataset(scan, grid).in_gate_fraction == pytest.approx(echo_share_in_grid(scan, grid))
    assert np.isfinite(echo_share_in_grid(scan, grid))


def test_the_command_line_refuses_a_grid_in_millimetres(scan, tmp_path, capsys):
    from clsas.cli import main

    scan.save(tmp_path / "scan.h5")
    assert main(["reconstruct", str(tmp_path / "scan.h5"), "--grid=-100,100,-80,80,400,600", "--spacing", "20",
                 "--backend", "numpy", "-q"]) == 2
    err = capsys.readouterr().err
    assert "millimetres" in err and err.count("\n") == 1


def test_inspect_on_a_grid_of_a_billion_voxels_stays_small(scan, tmp_path, capsys):
    """`clsas inspect --grid` in millimetres with the default spacing: 9e8 voxels; the check draws
    a few thousand of them and says what is wrong, within a small memory budget."""
    import resource

    from clsas.cli import main

    scan.save(tmp_path / "scan.h5")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert main(["inspect", str(tmp_path / "scan.h5"), "--grid=-150,150,-150,150,0,0",
                 "--png", str(tmp_path / "i.png")]) in (0, 2)
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mib < 500, grown_mib
    out = capsys.readouterr()
    assert "echo energy" in out.out + out.err or "millimetres" in out.out + out.err


def test_a_missing_solver_names_the_extra_in_the_python_api(monkeypatch, chirp96):
    """superres with CBP-Polar where nlopt is not installed: an ImportError naming nlopt and the
    sparse extra, before any work (not a bare ModuleNotFoundError from inside the solve)."""
    import importlib.util

    import clsas.sparse

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "nlopt" else real(name, *a))
    chirp, fs = chirp96
    x = np.zeros(600)
    x[100:100 + chirp.size] = chirp
    with pytest.raises(ImportError, match=r"nlopt .*sparse extra.*pip install"):
        clsas.sparse.superres(x, chirp, fs, method="cbp-polar")
    assert len(clsas.sparse.superres(x, chirp, fs, method="bpdn").delays_s) >= 1


def test_a_formation_option_typo_lists_the_valid_ones(scan):
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.6), 0.02)
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['oversampel'\] for 'ffbp'; known: .*'oversample'"):
        clsas.reconstruct(scan, grid, backend="numpy", formation="ffbp", formation_options={"oversampel": 1.5})


def test_a_chirp_in_khz_and_ms_and_a_rate_in_khz_are_named(caplog):
    """lfm_chirp(20, 30, 5, fs) (kHz and ms by mistake) and superres(..., 96) (kHz): one warning each
    that names the likely unit and the call that was meant."""
    import clsas.sparse

    with caplog.at_level(logging.WARNING, logger="clsas"):
        clsas.lfm_chirp(20, 30, 5, 96e3)
    assert any("lfm_chirp(20000, 30000, 0.005, fs_hz)" in r.getMessage() for r in caplog.records)
    caplog.clear()
    chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3)
    x = np.zeros(600)
    x[100:100 + chirp.size] = chirp
    with caplog.at_level(logging.WARNING, logger="clsas"):
        clsas.sparse.superres(x, chirp, 96, method="bpdn")
    assert any("fs_hz=96 Hz: a sampling rate in kHz?" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="clsas"):
        clsas.lfm_chirp(20e3, 30e3, 5e-3, 96e3)
    assert not caplog.records


def test_a_plane_or_a_single_voxel_on_the_target_is_not_warned_about(scan):
    """A grid of one plane, or one voxel, through the reflector: its delay gate is thin, but the
    echo's compressed pulse is counted around it, so it holds the echo and nothing is said."""
    plane = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.5, 0.5), 0.01)
    voxel = clsas.VoxelGrid.from_bounds((0.02, 0.02), (-0.01, -0.01), (0.5, 0.5), 0.01)
    for grid in (plane, voxel):
        check = check_grid_against_data(scan, grid)
        assert check.share > 0.5 and not check.warnings, (grid.shape, check)


def test_the_delay_bounds_hold_every_voxel(scan):
    from clsas.types.sanity import grid_delays

    grid = clsas.VoxelGrid.from_bounds((-0.3, 0.2), (-0.08, 0.1), (0.2, 0.9), 0.05)
    bounds = grid_delays(scan, grid)
    pts = grid.points().reshape(-1, 3)
    d = (np.linalg.norm(pts[None] - scan.tx_positions[:, None], axis=2)
         + np.linalg.norm(pts[None] - scan.rx_positions[:, None], axis=2)) / scan.c_per_meas[:, None]
    assert np.all(bounds[:, 0] <= d.min(axis=1) + 1e-12) and np.allclose(bounds[:, 1], d.max(axis=1))


def test_a_long_convex_solve_is_announced_before_it_starts(monkeypatch, caplog):
    """superres with CBP-Taylor on a long recording (the 48 s a newcomer waited without a word): the
    estimate is logged before the solve starts (the solve is stubbed here)."""
    pytest.importorskip("cvxpy")
    import clsas.sparse.registry as registry

    class Started(Exception):
        pass

    def stub(*a, **k):
        raise Started

    monkeypatch.setattr(registry, "sparse_echoes", stub)
    chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, 96e3)
    x = np.zeros(2000)
    x[300:300 + chirp.size] = chirp
    with caplog.at_level(logging.WARNING, logger="clsas.sparse.registry"), pytest.raises(Started):
        clsas.sparse.superres(x, chirp, 96e3, method="cbp-taylor")
    assert any("roughly" in r.getMessage() and "cbp-taylor" in r.getMessage() for r in caplog.records)
