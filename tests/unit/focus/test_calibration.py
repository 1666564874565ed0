"""Geometry calibration by focus (clsas.focus.calibrate) on simulated turntable scans."""

import numpy as np
import pytest

import clsas
from clsas.focus.calibrate import PARAMETERS, apply_calibration, calibrate, perturb


def _scan(radius_m=0.6, n=72, seed=0):
    """A turntable scan of five points (a letter-like asymmetric shape), 30 -> 10 kHz."""
    ap = clsas.circular_aperture(n, radius_m, height_m=0.1)
    pts = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.0, 0.05, 0.0], [-0.03, -0.03, 0.0], [0.05, 0.06, 0.0]])
    wave = clsas.lfm_chirp(30e3, 10e3, 1e-3, 100e3, taper=0.1)
    ds = clsas.simulate(clsas.Scene(pts, np.ones(len(pts))), ap, wave, 100e3, n_samples=900, snr_db=30, seed=seed,
                        chirp={"f_start_hz": 30e3, "f_stop_hz": 10e3, "duration_s": 1e-3, "taper": 0.1})
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.08), (-0.06, 0.09), (0, 0), 0.002)
    return ds, grid


def test_perturb_moves_radius_height_and_delay():
    ds, _ = _scan(n=8)
    r0 = np.hypot(ds.tx_positions[:, 0], ds.tx_positions[:, 1])
    tx, rx, t0 = perturb(ds, "radius", 0.005)
    assert np.allclose(np.hypot(tx[:, 0], tx[:, 1]), r0 + 0.005)
    assert np.allclose(tx[:, 2], ds.tx_positions[:, 2]) and np.allclose(t0, ds.t0_s)
    tx, rx, t0 = perturb(ds, "height", 0.01)
    assert np.allclose(rx[:, 2], ds.rx_positions[:, 2] + 0.01)
    _, _, t0 = perturb(ds, "group_delay", 2e-5)
    assert np.allclose(t0, ds.t0_s - 2e-5)
    with pytest.raises(ValueError, match="parameter"):
        perturb(ds, "tilt", 0.0)


@pytest.mark.parametrize("error_m", [0.006, -0.004], ids=["radius+6mm", "radius-4mm"])
def test_calibration_recovers_a_known_radius_error(error_m):
    ds, grid = _scan()
    tx, rx, _ = perturb(ds, "radius", error_m)  # the geometry as (wrongly) stated
    stated = ds.replace(tx_positions=tx, rx_positions=rx)
    fixed, cal = calibrate(stated, grid, "radius", span=0.012, step=0.001, apply=True, backend="numpy")
    assert abs(cal.estimate + error_m) < 0.001, cal.summary()
    assert cal.applied and not cal.at_edge and cal.uncertainty < 0.002
    assert np.allclose(fixed.tx_positions, perturb(stated, "radius", cal.estimate)[0])
    assert fixed.provenance[-1]["step"] == "calibrate"


@pytest.mark.parametrize("error_m", [0.006, -0.004], ids=["radius+6mm", "radius-4mm"])
def test_sector_agreement_recovers_a_known_radius_error(error_m):
    # the check that trusts no sharpness: 8 arcs of the turn imaged alone agree best at the truth
    ds, grid = _scan()
    tx, rx, _ = perturb(ds, "radius", error_m)
    stated = ds.replace(tx_positions=tx, rx_positions=rx)
    _, cal = calibrate(stated, grid, "radius", span=0.012, step=0.001, metric="sectors", backend="numpy")
    assert abs(cal.estimate + error_m) < 0.001, cal.summary()
    assert cal.metric_name == "sectors" and not cal.at_edge and cal.uncertainty < 0.002
    assert 0 < cal.metric.max() <= 1


def test_calibration_recovers_a_known_group_delay():
    ds, grid = _scan()
    stated = ds.replace(t0_s=ds.t0_s + 2.0e-5)  # 20 us of delay nobody stated
    _, cal = calibrate(stated, grid, "group_delay", span=4e-5, step=2e-6, backend="numpy")
    assert abs(cal.estimate - 2.0e-5) < 2e-6, cal.summary()
    fixed = apply_calibration(stated, cal)
    assert np.allclose(fixed.t0_s, stated.t0_s - cal.estimate)


def test_calibration_inputs_are_checked():
    ds, grid = _scan(n=8)
    with pytest.raises(ValueError, match="parameter"):
        calibrate(ds, grid, "azimuth")
    with pytest.raises(ValueError, match="step"):
        calibrate(ds, grid, "radius", span=0.001, step=0.002)
    with pytest.raises(TypeError, match="dataset"):
        calibrate(ds.signals, grid)
    with pytest.raises(ValueError, match="metric"):
        calibrate(ds, grid, "radius", metric="contrast")
    with pytest.raises(ValueError, match="sectors"):
        calibrate(ds, grid, "radius", metric="sectors", sectors=1)
    with pytest.raises(ValueError, match="sectors=8 needs at least 16 measurements"):
        calibrate(ds, grid, "radius", metric="sectors")
    assert set(PARAMETERS) == {"radius", "height", "group_delay"}
