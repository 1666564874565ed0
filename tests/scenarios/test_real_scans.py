"""Measured-looking scans: preprocessing, per-measurement air, input at the profile stage.

The recordings come from :func:`clsas.synthetic.turntable_scan`: a turntable (circular)
geometry, an extended target, strong static clutter present in the scan and in a separate
empty-scene scan, the direct sound, DC and hum, air warming during the scan and a group delay
the recordings do not know about.
"""

import numpy as np
import pytest
from conftest import BACKENDS, TOL, needs_opencl, width_or_skip

import clsas
from clsas import preprocess as pp
from clsas.synthesis.synthetic import turntable_scan

GRID = clsas.VoxelGrid.from_bounds((-0.15, 0.15), (-0.15, 0.15), (0.0, 0.0), 0.004)


def tcr(image, box):
    """Peak |v| inside the box over RMS |v| outside it, dB."""
    X, Y, Z = np.meshgrid(image.grid.x_m, image.grid.y_m, image.grid.z_m, indexing="ij")
    inside = np.ones(X.shape, bool)
    for ax, (lo, hi) in zip((X, Y, Z), box, strict=True):
        inside &= (ax >= lo - 1e-9) & (ax <= hi + 1e-9)
    mag = np.abs(image.values)
    return 20 * np.log10(mag[inside].max() / np.sqrt(np.mean(mag[~inside] ** 2)))


def near_target(image, target, tol_m):
    peak = image.peaks(1)[0].position_m
    return np.min(np.linalg.norm(target - peak, axis=1)) <= tol_m


@pytest.fixture(scope="module")
def scan():
    return turntable_scan(90)


@pytest.fixture(scope="module")
def quiet_scan():
    """The target alone (no clutter, no direct sound, no hum), the same drifting air."""
    return turntable_scan(90, clutter_db=-300, direct_db=-300, dc=0.0, hum=0.0, snr_db=60)


def test_background_subtraction_recovers_the_target(scan):
    base = dict(group_delay_samples=62.33, dc=True, bandpass=True)
    before = clsas.reconstruct(pp.apply(scan.dataset, **base), GRID, backend="numpy")
    cleaned = pp.apply(scan.dataset, **base, background=scan.background, blank_direct=True)
    after = clsas.reconstruct(cleaned, GRID, backend="numpy")
    box = scan.target_box_m
    assert tcr(after, box) > tcr(before, box) + 6
    assert near_target(after, scan.target_m, 0.01)
    steps = [p["step"] for p in cleaned.provenance]
    # speed_of_sound: the scan's c came from its temperature at an assumed 50 % RH
    assert steps == ["synthetic", "speed_of_sound", "group_delay", "dc", "bandpass", "background", "blank_direct"]
    rec = cleaned.provenance[5]
    assert rec["rms_after"] < 0.3 * rec["rms_before"]  # the static clutter is gone


def test_background_recorded_in_other_air_is_stretched_to_the_scan(scan):
    # static clutter alone, the empty scene 6 C warmer than the scan: subtracting it as
    # recorded leaves much of the clutter; stretched to the scan's air it cancels
    # (in dry air: how well the stretch cancels moves between -34 and -23 dB with the exact pair of
    # speeds, dry or humid, 18.0/24.0 C giving -33 dB dry and -24 dB at 50 % RH; that spread is
    # the stretch's, not the air's, and this test keeps the pair it was written for)
    ds = pp.remove_delay(scan.dataset, scan.group_delay_s)
    cold = turntable_scan(90, temperature_c=(18.0, 18.0), background_temperature_c=18.0, snr_db=200, humidity_pct=0.0)
    warm = turntable_scan(90, temperature_c=(24.0, 24.0), background_temperature_c=24.0, snr_db=200, humidity_pct=0.0)
    scan_ds = pp.remove_delay(cold.background, cold.group_delay_s)
    bg = pp.remove_delay(warm.background, warm.group_delay_s)
    assert ds.n_meas == scan_ds.n_meas
    stretched = pp.subtract_background(scan_ds, bg)
    as_recorded = pp.subtract_background(scan_ds, bg.signals)  # an array: no air to match
    gated = slice(150, 700)  # past the direct sound, the clutter's echoes
    rms = [np.sqrt(np.mean(d.signals[:, gated] ** 2)) for d in (scan_ds, as_recorded, stretched)]
    assert rms[2] < 0.05 * rms[0], rms  # better than -26 dB
    assert rms[1] > 5 * rms[2], rms


def test_per_measurement_sound_speed_restores_focus(quiet_scan):
    still = turntable_scan(90, clutter_db=-300, direct_db=-300, dc=0.0, hum=0.0, snr_db=60,
                           temperature_c=(23.0, 23.0))
    ref = clsas.reconstruct(pp.remove_delay(still.dataset, still.group_delay_s), GRID, backend="numpy")
    ds = pp.remove_delay(quiet_scan.dataset, quiet_scan.group_delay_s)
    assert ds.air_varies and ds.c_per_meas[-1] > ds.c_per_meas[0] * 1.008  # 20 -> 26 C
    per_ping = clsas.reconstruct(ds, GRID, backend="numpy")
    one_c = clsas.reconstruct(ds.replace(c_mps=float(ds.c_per_meas.mean())), GRID, backend="numpy")

    def corr(a):
        return abs(np.vdot(a.values, ref.values)) / np.linalg.norm(a.values) / np.linalg.norm(ref.values)

    assert corr(per_ping) > 0.98
    assert corr(one_c) < 0.8
    assert np.abs(one_c.values).max() < 0.8 * np.abs(per_ping.values).max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_per_measurement_sound_speed_on_every_backend(quiet_scan, backend):
    ds = pp.remove_delay(quiet_scan.dataset, quiet_scan.group_delay_s)
    img = clsas.reconstruct(ds, GRID, backend=backend)
    ref = clsas.reconstruct(ds, GRID, backend="numpy")
    err = np.abs(img.values - ref.values).max() / np.abs(ref.values).max()
    assert err < TOL["backproject"] * 10  # the compression's float32 too
    assert near_target(img, quiet_scan.target_m, 0.008)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_backproject_kernel_per_measurement_c_equals_twin(quiet_scan, vec):
    from clsas.formation import bp_numpy as twin
    from clsas.formation.bp_opencl import BackprojectPlan

    width_or_skip("backproject", vec)
    ds = pp.remove_delay(quiet_scan.dataset, quiet_scan.group_delay_s)
    p = clsas.compress(ds, gate_s=(3e-3, 6.5e-3), backend="numpy")
    c = ds.c_per_meas
    got = BackprojectPlan(GRID, p.n_meas, p.n_lags, vec=vec, chunk=13)(
        p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, c)
    want = twin.backproject(p.data, p.tau0_s, p.dtau_s, p.fc_hz, ds.tx_positions, ds.rx_positions, c,
                            GRID.points())
    assert np.abs(got - want).max() / np.abs(want).max() < TOL["backproject"]


def test_unknown_group_delay_defocuses_and_its_removal_restores(quiet_scan):
    raw = clsas.reconstruct(quiet_scan.dataset, GRID, backend="numpy")
    fixed = clsas.reconstruct(pp.apply(quiet_scan.dataset, group_delay_samples=62.33), GRID, backend="numpy")
    assert near_target(fixed, quiet_scan.target_m, 0.008)
    assert np.abs(fixed.values).max() > 2 * np.abs(raw.values).max()


def test_preprocessing_steps_do_what_they_say():
    fs, n = 100e3, 2000
    t = np.arange(n) / fs
    sig = 0.3 + np.sin(2 * np.pi * 60 * t) + np.sin(2 * np.pi * 20e3 * t)
    ds = clsas.Dataset(np.tile(sig, (2, 1)), np.zeros((2, 3)), np.tile([0.05, 0, 0], (2, 1)), fs,
                       clsas.lfm_chirp(10e3, 30e3, 1e-3, fs, taper=0.1),
                       chirp={"f_start_hz": 30e3, "f_stop_hz": 10e3}, temperature_c=20.0)
    dc = pp.remove_dc(ds)
    assert abs(dc.signals.mean()) < 1e-12
    bp = pp.bandpass(ds)
    spec = np.abs(np.fft.rfft(bp.signals[0, 500:1500] * np.hanning(1000)))
    f = np.fft.rfftfreq(1000, 1 / fs)
    assert spec[np.argmin(abs(f - 20e3))] > 1e4 * spec[f < 1e3].max()  # hum and DC: > 80 dB down
    bl = pp.blank_direct(ds, guard_s=0.0, taper_s=1e-4)
    end = int((0.05 / ds.c_per_meas[0] + 1e-3) * fs)
    assert np.all(bl.signals[:, :end] == 0) and np.allclose(bl.signals[:, end + 11:], ds.signals[:, end + 11:])
    d2 = pp.remove_delay(ds, 62.33 / fs)
    assert np.allclose(d2.t0_s, -62.33 / fs) and np.array_equal(d2.signals, ds.signals)
    steps = [p["step"] for p in pp.apply(ds, dc=True, bandpass=(15e3, 25e3)).provenance]
    assert steps == ["speed_of_sound", "dc", "bandpass"]
    assert [p["step"] for p in ds.provenance] == ["speed_of_sound"]  # the input is not changed


def test_provenance_and_background_survive_the_file(tmp_path, scan):
    ds = pp.attach_background(scan.dataset, scan.background)
    ds = pp.apply(ds, group_delay_samples=62.33, dc=True)
    back = clsas.load(ds.save(tmp_path / "scan.h5"))
    assert back.provenance == ds.provenance
    assert np.allclose(back.background, ds.background, rtol=1e-6, atol=1e-6 * np.abs(ds.background).max())
    assert np.allclose(back.c_mps, ds.c_mps) and np.allclose(back.temperature_c, ds.temperature_c)


@pytest.mark.parametrize("call, match", [
    (lambda ds: pp.bandpass(ds, 10e3, 60e3), "Nyquist"),
    (lambda ds: pp.bandpass(ds, 30e3, 20e3), "f_hi_hz"),
    (lambda ds: pp.subtract_background(ds), "no background"),
    (lambda ds: pp.subtract_background(ds, np.zeros((3, 10))), "3 recordings"),
    (lambda ds: pp.subtract_background(ds, np.full((2, 10), np.nan)), "NaN"),
    (lambda ds: pp.remove_delay(ds, np.inf), "delay_s"),
    (lambda ds: pp.from_table(ds, {"dc": True, "bandpas": True}), "bandpas"),
    (lambda ds: pp.apply(ds, bandpass={"f_low": 1}), "f_low"),
    (lambda ds: pp.apply(ds, dc="yes"), "dc"),
    (lambda ds: pp.blank_direct(ds, taper_s=-1), "taper_s"),
], ids=["nyquist", "inverted", "no-background", "count", "nan", "inf-delay", "table-key", "option", "flag",
        "taper"])
def test_preprocessing_refuses_bad_input(call, match):
    ds = clsas.Dataset(np.random.default_rng(0).normal(size=(2, 400)), np.zeros((2, 3)), np.ones((2, 3)), 96e3,
                       clsas.lfm_chirp(20e3, 30e3, 1e-3, 96e3))
    with pytest.raises((ValueError, TypeError), match=match):
        call(ds)


def test_dataset_air_per_measurement_is_validated():
    sig, pos = np.zeros((3, 50)), np.zeros((3, 3))
    with pytest.raises(ValueError, match="temperature_c"):
        clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=[20, 21])
    with pytest.raises(ValueError, match="c_mps"):
        clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), c_mps=[343, -1, 343])
    with pytest.raises(ValueError, match="humidity_pct"):
        clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), humidity_pct=[50, 50, 150])
    same = clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=[21, 21, 21])
    # humidity not logged: 50 % assumed
    assert not same.air_varies and same.c_mps == pytest.approx(clsas.speed_of_sound(21, 50))


def test_profiles_from_elsewhere_image_like_the_library_s_own(quiet_scan):
    ds = pp.remove_delay(quiet_scan.dataset, quiet_scan.group_delay_s)
    own = clsas.compress(ds, lag_step=1, backend="numpy")
    want = clsas.backproject(own, GRID, backend="numpy")
    rf = own.carrier().real  # what a user's own pulse compression would hand over: real, at the carrier
    ext = clsas.Profiles.from_range_profiles(rf, tau0_s=own.tau0_s, dtau_s=own.dtau_s,
                                             tx_positions=ds.tx_positions, rx_positions=ds.rx_positions,
                                             c_mps=ds.c_mps, fc_hz=own.fc_hz)
    got = clsas.reconstruct(ext, GRID, backend="numpy")
    err = np.abs(got.values - want.values).max() / np.abs(want.values).max()
    assert err < 0.05  # the analytic signal of a windowed real profile: edge effects only
    assert near_target(got, quiet_scan.target_m, 0.008)
    base = clsas.Profiles.from_range_profiles(own.data, tau0_s=own.tau0_s, dtau_s=own.dtau_s, baseband=True,
                                              tx_positions=ds.tx_positions, rx_positions=ds.rx_positions,
                                              c_mps=ds.c_mps, fc_hz=own.fc_hz)
    assert np.allclose(clsas.reconstruct(base, GRID, backend="numpy").values, want.values)
    # baseband rows sampled below twice the carrier (every third lag: 1/dtau 33 kHz, fc 20 kHz) are valid
    half = clsas.Profiles.from_range_profiles(own.data[:, ::3], tau0_s=own.tau0_s, dtau_s=3 * own.dtau_s,
                                              baseband=True, tx_positions=ds.tx_positions,
                                              rx_positions=ds.rx_positions, c_mps=ds.c_mps, fc_hz=own.fc_hz)
    assert 2 * own.fc_hz > 1 / half.dtau_s
    assert near_target(clsas.reconstruct(half, GRID, backend="numpy"), quiet_scan.target_m, 0.008)
    with pytest.raises(ValueError, match="fc_hz is required"):
        clsas.Profiles.from_range_profiles(own.data, tau0_s=0, dtau_s=1e-5, baseband=True,
                                           tx_positions=ds.tx_positions, rx_positions=ds.rx_positions, c_mps=343)
    with pytest.raises(ValueError, match="needs the recordings"):
        clsas.reconstruct(base, GRID, method="cbp-polar")


def test_cli_preprocess_and_reconstruct_with_a_box(tmp_path, capsys):
    from clsas.cli import main

    sc = turntable_scan(36)
    sc.dataset.save(tmp_path / "scan.h5")
    sc.background.save(tmp_path / "empty.h5")
    sub = tmp_path / "cfg"
    sub.mkdir()
    (sub / "pre.toml").write_text('[preprocess]\ngroup_delay_samples = 62.33\ndc = true\nbandpass = true\n'
                                  'background = "../empty.h5"\nblank_direct = true\n')
    assert main(["preprocess", str(tmp_path / "scan.h5"), str(tmp_path / "clean.h5"),
                 "--config", str(sub / "pre.toml")]) == 0
    clean = clsas.load(tmp_path / "clean.h5")
    assert [p["step"] for p in clean.provenance][1:] == ["speed_of_sound", "group_delay", "dc", "bandpass",
                                                          "background", "blank_direct"]
    assert clean.provenance[5]["source"].endswith("empty.h5")
    capsys.readouterr()
    box = "--box=-0.11,0.11,-0.11,0.11,-0.03,0.03"
    grid = "--grid=-0.15,0.15,-0.15,0.15,0,0"
    assert main(["reconstruct", str(tmp_path / "clean.h5"), grid, "--spacing", "0.005", box, "-q",
                 "--backend", "numpy"]) == 0
    after = float(capsys.readouterr().out.split("target-to-clutter ratio")[1].split(":")[1].split("dB")[0])
    assert main(["reconstruct", str(tmp_path / "scan.h5"), grid, "--spacing", "0.005", box, "-q", "--backend",
                 "numpy", "--preprocess", "--group-delay-samples", "62.33", "--dc", "--bandpass"]) == 0
    before = float(capsys.readouterr().out.split("target-to-clutter ratio")[1].split(":")[1].split("dB")[0])
    assert after > before + 6
    assert main(["preprocess", str(tmp_path / "scan.h5"), str(tmp_path / "x.h5")]) == 2  # nothing to do
    (sub / "bad.toml").write_text("[preprocess]\nbandpas = true\n")
    assert main(["preprocess", str(tmp_path / "scan.h5"), str(tmp_path / "x.h5"), "--config",
                 str(sub / "bad.toml")]) == 2
    assert "bandpas" in capsys.readouterr().err


def test_reconstruct_passes_absorption_to_the_sparse_atom():
    from conftest import small_dataset

    ds = small_dataset([[0.02, -0.01, 0.6]], nx=3, ny=3)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.55, 0.65), 0.01)
    img = clsas.reconstruct(ds, grid, method="bpdn", sparse={"absorption": True}, backend="numpy")
    assert img.peaks(1)[0].index == grid.index_of([0.02, -0.01, 0.6])
    with pytest.raises(ValueError, match="absorbtion"):
        clsas.reconstruct(ds, grid, method="bpdn", sparse={"absorbtion": True}, backend="numpy")
