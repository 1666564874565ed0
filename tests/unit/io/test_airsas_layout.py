"""The AirSAS importer on a synthetic scan written exactly in the published files' layout
(github awreed/CSAS_Deconvolution_INR, airsas_data/: number formats, header, two microphone
columns, the waveform name with 'tukeywin'): geometry, handedness option and zero angle."""

import numpy as np
import pytest
from airsas_kit import HEIGHT_M, MIC1, SPEAKER, TARGET, write_scan
from airsas_kit import truth_positions as _truth

import clsas
import clsas.io


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    folder = tmp_path_factory.mktemp("airsas") / "small_features_cutout_20k"
    return folder, write_scan(folder)


def test_published_layout_geometry(scan):
    folder, angles = scan
    ds = clsas.io.import_airsas(folder)
    np.testing.assert_allclose(ds.tx_positions, _truth(SPEAKER, angles), atol=1e-9)
    np.testing.assert_allclose(ds.rx_positions, _truth(MIC1, angles), atol=1e-9)
    # angle 0: the speaker where SysParams.csv puts it (-y), 0.4075 m above the image plane
    np.testing.assert_allclose(ds.tx_positions[0], [0, -0.8485, 0.2575], atol=1e-12)
    # angle 90: turned counter-clockwise (seen from above) in the target's frame
    np.testing.assert_allclose(ds.tx_positions[9], [0.8485, 0, 0.2575], atol=1e-12)
    np.testing.assert_allclose(ds.t0_s, -62.329317 / 100e3)
    assert ds.chirp == pytest.approx({"f_start_hz": 30e3, "f_stop_hz": 10e3, "duration_s": 1e-3, "taper": 0.1})
    two = clsas.io.import_airsas(folder, microphones="all")
    assert two.n_meas == 2 * ds.n_meas
    np.testing.assert_allclose(two.rx_positions[1, 2], 0.216 - 0.1775 + HEIGHT_M)


def test_owners_frame_option(scan):
    """angle_sign=-1, zero_angle_deg=180: the data owners' frame (transducers at 0.85 m-ish,
    angle 90 - a), i.e. the default mirrored in y."""
    folder, angles = scan
    default = clsas.io.import_airsas(folder)
    owners = clsas.io.import_airsas(folder, angle_sign=-1, zero_angle_deg=180)
    np.testing.assert_allclose(owners.tx_positions, default.tx_positions * [1, -1, 1], atol=1e-9)
    th = np.deg2rad(90 - angles)
    np.testing.assert_allclose(owners.tx_positions[:, :2], 0.8485 * np.c_[np.cos(th), np.sin(th)], atol=1e-9)
    assert owners.provenance[0]["zero_angle_deg"] == 180.0
    turned = clsas.io.import_airsas(folder, zero_angle_deg=90)
    np.testing.assert_allclose(turned.tx_positions[0], default.tx_positions[9], atol=1e-9)
    with pytest.raises(ValueError, match="zero_angle_deg"):
        clsas.io.import_airsas(folder, zero_angle_deg=float("nan"))


def test_default_image_keeps_the_targets_handedness(scan):
    """The L comes out as simulated with the default (not mirrored), and mirrored in y in
    the owners' frame."""
    folder, _ = scan
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.1), (-0.06, 0.06), (0, 0), 0.003)
    for kw, sign in (({}, 1), ({"angle_sign": -1, "zero_angle_deg": 180}, -1)):
        image = clsas.reconstruct(clsas.io.import_airsas(folder, **kw), grid, backend="numpy")
        found = np.array([p.position_m for p in image.peaks(3, min_separation_m=0.015)])
        for t in TARGET * [1, sign, 1]:
            assert np.min(np.linalg.norm(found - t, axis=1)) < 0.006, (kw, found)


def test_radius_option(scan):
    folder, angles = scan
    ds = clsas.io.import_airsas(folder, radius_m=0.85, microphones="all")
    for p in (ds.tx_positions, ds.rx_positions):
        np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), 0.85)
    default = clsas.io.import_airsas(folder, microphones="all")
    np.testing.assert_allclose(ds.rx_positions[:, 2], default.rx_positions[:, 2])
    np.testing.assert_allclose(np.arctan2(ds.tx_positions[:, 1], ds.tx_positions[:, 0]),
                               np.arctan2(default.tx_positions[:, 1], default.tx_positions[:, 0]))
    assert ds.provenance[0]["radius_m"] == 0.85
    with pytest.raises(ValueError, match="radius_m"):
        clsas.io.import_airsas(folder, radius_m=-1.0)


def test_compare_bench_places_peaks_between_pixels():
    """``bench/airsas_compare.py`` judges peaks between the owners' 1.5 mm pixels: a Gaussian's
    log is a parabola, so its 3 x 3 fit returns the true sub-pixel centre, where the pixel
    maximum is up to half a pixel off in each axis."""
    from bench import airsas_compare as mod
    i, j = np.meshgrid(np.arange(20.0), np.arange(20.0), indexing="ij")
    ci, cj = 9.37, 10.6
    mag = np.exp(-((i - ci) ** 2 / 8.0 + (j - cj) ** 2 / 5.0))
    pi, pj = np.unravel_index(np.argmax(mag), mag.shape)
    assert (pi, pj) == (9, 11)
    got = mod._quadratic_peak(mag, pi, pj)
    np.testing.assert_allclose(got, (ci, cj), atol=1e-9)
    assert mod._quadratic_peak(mag, 0, pj)[0] == 0  # on the edge: the pixel along that axis
    assert mod._quadratic_peak(np.ones((5, 5)), 2, 2) == (2, 2)  # flat: no parabola
