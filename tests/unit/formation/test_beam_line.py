"""Omega-k for 2-D line scans: the 2-D Stolt step against exact backprojection."""

import numpy as np
import pytest

import clsas
from clsas.formation import error_to_signal_db
from clsas.physics.beam import Beams, Cone, Piston


def _line_scan(n=40, pitch=0.15e-3, beams=None):
    fs = 12.5e6
    wave = clsas.lfm_chirp(1e6, 4e6, 4e-6, fs, taper=0.2)
    ap = clsas.raster_aperture(n, 1, (n - 1) * pitch, 0.0, tx_offset_m=(0, 0, 0), rx_offset_m=(0, 0, 0))
    pins = np.array([[-1.0e-3, 0, 0.010], [0.5e-3, 0, 0.011], [1.5e-3, 0.2e-3, 0.012], [0, 0, 0.013]])
    if beams is not None:
        beams = Beams(beams, beams, (0, 0, 1), (0, 0, 1), ap.n_meas)
    return clsas.compress(clsas.simulate(clsas.Scene(pins), ap, wave, fs, c_mps=1480.0, beams=beams),
                          backend="numpy")


@pytest.mark.parametrize("ys", [(0.0, 0.0), (-0.4e-3, 0.4e-3)], ids=["slice", "volume"])
def test_line_scan_omega_k_matches_bp(ys):
    """Four pins under a lambda/4 line of 40 stops: within -30 dB of backprojection on an x-z slice
    through the line and on a small volume beside it (distances from the line differ per column)."""
    prof = _line_scan()
    grid = clsas.VoxelGrid.from_bounds((-2e-3, 2e-3), ys, (0.009, 0.014), 0.2e-3)
    ref = clsas.formation.form(prof, grid, "bp", backend="numpy")
    img = clsas.formation.form(prof, grid, "omega-k", backend="numpy")
    assert img.provenance["omega_k"]["line_axis"] == "x"
    assert error_to_signal_db(img, ref) < -30


def test_line_scan_refuses_beams_and_grids_it_cannot_image():
    prof = _line_scan(n=8, beams=Piston(3e-3))
    grid = clsas.VoxelGrid.from_bounds((-1e-3, 1e-3), (0, 0), (0.009, 0.011), 0.5e-3)
    from dataclasses import replace

    along = replace(prof, beams=Beams(Piston(3e-3), Piston(3e-3), (0.5, 0, 1), (0.5, 0, 1), prof.n_meas))
    with pytest.raises(ValueError, match="across the line"):
        clsas.formation.form(along, grid, "omega-k", backend="numpy")
    img = clsas.formation.form(along, grid, "omega-k", backend="numpy", beam="none")
    assert np.isfinite(img.values).all()
    with pytest.raises(ValueError, match="off it"):
        clsas.formation.form(prof, clsas.VoxelGrid.from_bounds((-1e-3, 1e-3), (0, 0), (0, 0.01), 0.5e-3),
                             "omega-k", backend="numpy", beam="none")
    with pytest.raises(ValueError, match="upsample"):
        clsas.formation.form(prof, grid, "omega-k", backend="numpy", beam="none", upsample=2)


@pytest.mark.parametrize("mode", ["limited", "weighted"])
def test_line_scan_omega_k_weights_plane_waves_like_bp(mode):
    """Pins under a dense line of 15-degree cones: omega-k's angular weighting and bp's per-pair weights
    agree to -21.6 dB where the weight is smooth ("weighted", -9.8 dB without omega-k's weighting) and
    -17.3 dB where it is a gate ("limited", -15.7 dB without): the stationary-phase equivalence of a
    pair's angle and a plane wave's holds where the weight varies slowly."""
    prof = _line_scan(beams=Cone(15.0))
    grid = clsas.VoxelGrid.from_bounds((-2e-3, 2e-3), (-0.4e-3, 0.4e-3), (0.009, 0.014), 0.2e-3)
    ref = clsas.formation.form(prof, grid, "bp", backend="numpy", beam=mode)
    img = clsas.formation.form(prof, grid, "omega-k", backend="numpy", beam=mode)
    omni = clsas.formation.form(prof, grid, "bp", backend="numpy", beam="none")
    err = error_to_signal_db(img, ref)
    assert err < (-20 if mode == "weighted" else -15)
    assert err < error_to_signal_db(omni, ref) - (5 if mode == "weighted" else 0)


def test_beam_bench_report_is_written(tmp_path):
    """The directional bench's Markdown and JSON from a result of its shape (the run itself is the
    benchmark's, not a test's)."""
    from bench import beams

    row = {"formation": "bp", "options": {"beam": "limited"}, "label": "bp limited", "time_s": 1.0,
           "surface_share": 1.0, "error_vs_bp_limited_db": -600.0, "error_vs_omega_k_limited_db": -3.0,
           "abs_corr_vs_omega_k": 0.93}
    res = {"device": "cpu", "load_before": (1, 1, 1), "load_after": (1, 1, 1),
           "planar": {"what": "case", "rows": [row, {"formation": "ffbp", "options": {}, "label": "ffbp default",
                                                     "refused": "ffbp cannot apply transducer beams"}]},
           "floors": [{"floor_db": -12.0, "error_db": -3.0, "abs_corr": 0.9, "surface_share": 1.0}],
           "line": {"what": "line", "omega_k_s": 1.0, "bp_s": 1.0, "error_db": -39.0, "abs_corr": 1.0}}
    paths = beams.write(res, tmp_path, "x")
    text = paths["md"].read_text()
    assert "| bp | limited | 1.00 s | 100 % | reference | -3.0 dB | 0.930 |" in text
    assert "refused: ffbp cannot apply" in text and paths["json"].exists()


def test_hankel_series_matches_scipy():
    from scipy.special import hankel1

    from clsas.formation.omega_k_line import hankel1_1

    x = np.geomspace(0.1, 5000, 2001)
    np.testing.assert_allclose(hankel1_1(x), hankel1(1, x), rtol=1e-7)
