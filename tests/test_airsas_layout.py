"""The AirSAS importer on a synthetic scan written exactly in the published files' layout
(github awreed/CSAS_Deconvolution_INR, airsas_data/: number formats, header, two microphone
columns, the waveform name with 'tukeywin'): geometry, handedness option and zero angle."""

import numpy as np
import pytest

import clsas
import clsas.io

# the published scans' SysParams.csv, as written there (MATLAB-style engineering notation)
SYSPARAMS = """Speaker x,0.000000E+0
Speaker y,-848.500000E-3
Speaker z,285.000000E-3
Mic1 x,0.000000E+0
Mic1 y,-861.500000E-3
Mic1 z,247.000000E-3
Mic2 x,0.000000E+0
Mic2 y,-861.500000E-3
Mic2 z,216.000000E-3
Center x,0.000000E+0
Center y,0.000000E+0
Center z,177.500000E-3
Fs,100.000000E+3
Group Delay,62.329317E+0
Input Range,0.000000E+0
Output Range,3.500000E+0
Input Device,USB-4431
Output Device,USB-4431
Bit Depth,24
"""
WAVE_NAME = "LFM_3.00E+4Hz_1.00E+4Hz_1.00E-3s_5.00E-1V_tukeywin_1.00E-1"
SPEAKER, MIC1, CENTER = np.array([0, -0.8485, 0.285]), np.array([0, -0.8615, 0.247]), np.array([0, 0, 0.1775])
HEIGHT_M = 0.150
# an asymmetric target (an L): its handedness shows in the image
TARGET = np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0], [0.0, 0.03, 0.0]])


def _truth(p, angles_deg):
    """The published convention, written out: the rig point p at turntable angle a is at
    R_z(+a)(p - Center) + (0, 0, height) in the target's frame."""
    a = np.deg2rad(angles_deg)
    d = p - CENTER
    return np.c_[np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1],
                 np.full(len(a), d[2] + HEIGHT_M)]


def _write(folder, pings=36):
    folder.mkdir()
    angles = np.arange(pings) * 360.0 / pings
    temps = np.full(pings, 21.622)
    wave = clsas.lfm_chirp(30e3, 10e3, 1e-3, 100e3, 0.1)
    tx, rx = _truth(SPEAKER, angles), _truth(MIC1, angles)
    ds = clsas.simulate(clsas.Scene(TARGET, np.ones(len(TARGET))), clsas.Aperture(tx, rx, tx), wave, 100e3,
                        n_samples=1000, t0_s=-62.329317 / 100e3, temperature_c=temps, snr_db=40, seed=1)
    for i in range(pings):  # two columns, like the published Flight files (mic 2: noise here)
        cols = np.c_[ds.signals[i], 0.005 + 1e-4 * np.sin(np.arange(1000))]
        np.savetxt(folder / f"Flight-{i + 1:06d}.csv", cols, fmt="%.9f", delimiter=",")
    rows = ["Flight #,Angle,Height,Temp,Waveform"]
    rows += [f"{i + 1:.3f},{angles[i]:.3f},{HEIGHT_M * 1e3:.3f},{temps[i]:.3f},0.000" for i in range(pings)]
    (folder / "Coordinates.csv").write_text("\n".join(rows) + "\n")
    (folder / "SysParams.csv").write_text(SYSPARAMS)
    (folder / "WaveformParams.csv").write_text(WAVE_NAME + "\n")
    np.savetxt(folder / "Waveforms.csv", wave[:, None], fmt="%.9f")
    return angles


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    folder = tmp_path_factory.mktemp("airsas") / "small_features_cutout_20k"
    return folder, _write(folder)


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
