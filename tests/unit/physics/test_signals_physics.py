import numpy as np
import pytest

import clsas
from clsas.physics.sound import air_absorption_db_per_m, cramer_speed_of_sound, resolution_limits, speed_of_sound


def test_chirp_sweeps_from_f_start_to_f_stop():
    fs = 192e3
    x = clsas.lfm_chirp(20e3, 30e3, 10e-3, fs)
    assert x.shape == (1920,)
    phase = np.unwrap(np.angle(clsas.analytic(x)))
    f_inst = np.diff(phase) * fs / (2 * np.pi)
    mid = slice(200, -200)  # the Hilbert transform rings at hard edges
    expected = np.linspace(20e3, 30e3, len(f_inst))[mid]
    assert np.max(np.abs(f_inst[mid] - expected)) < 150


def test_taper_smooths_edges():
    x = clsas.lfm_chirp(20e3, 30e3, 5e-3, 96e3, taper=0.2)
    assert abs(x[0]) < 1e-12 and abs(x[-1]) < 1e-12


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(f_stop_hz=50e3), "Nyquist"),
        (dict(fs_hz=0.0), "fs_hz"),
        (dict(fs_hz=-96e3), "fs_hz"),
        (dict(f_start_hz=float("nan")), "f_start_hz"),
        (dict(duration_s=1e-6), "duration_s"),
        (dict(taper=1.5), "taper"),
    ],
    ids=["f_stop-above-nyquist", "zero-fs", "negative-fs", "nan-f_start", "too-short", "taper>1"],
)
def test_chirp_rejects_bad_input(kwargs, match):
    args = dict(f_start_hz=20e3, f_stop_hz=30e3, duration_s=5e-3, fs_hz=96e3)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        clsas.lfm_chirp(**args)


def test_speed_of_sound():
    assert speed_of_sound(20.0) == pytest.approx(343.2, abs=0.05)
    assert speed_of_sound(0.0) == pytest.approx(331.3)


@pytest.mark.parametrize("t_c", [-10.0, 0.0, 20.0, 21.59, 35.0, np.array([15.0, 20.0, 25.0])],
                         ids=["-10C", "0C", "20C", "21.59C", "35C", "array"])
def test_dry_limit_is_the_dry_formula_exactly(t_c):
    dry = 331.3 * np.sqrt(1.0 + np.asarray(t_c) / 273.15)  # clsas's formula before humidity
    np.testing.assert_array_equal(speed_of_sound(t_c), dry)
    np.testing.assert_array_equal(speed_of_sound(t_c, humidity_pct=0.0), dry)
    np.testing.assert_array_equal(speed_of_sound(t_c, humidity_pct=0.0, pressure_kpa=80.0), dry)


def test_cramer_1993_known_values():
    # Cramer's own absolute values (the formula as published), 101.325 kPa, 400 ppm CO2: 343.99 m/s
    # at 20 C and 50 % RH, the figure speed-of-sound calculators built on Cramer give (e.g. NPL's)
    assert cramer_speed_of_sound(20.0, 50.0) == pytest.approx(343.99, abs=0.01)
    assert cramer_speed_of_sound(20.0, 0.0) == pytest.approx(343.36, abs=0.01)
    # clsas keeps its dry formula and takes Cramer's humid/dry ratio: +0.63 m/s at 20 C, 50 % RH
    assert speed_of_sound(20.0, 50.0) == pytest.approx(343.84, abs=0.01)
    assert speed_of_sound(20.0, 50.0) / speed_of_sound(20.0) == pytest.approx(
        cramer_speed_of_sound(20.0, 50.0) / cramer_speed_of_sound(20.0, 0.0), rel=1e-12)


def _ideal_gas_humid_ratio(t_c, h_pct):
    """c(humid) / c(dry) of an ideal mixture of dry air and water vapour (Magnus saturation
    pressure): an estimate independent of Cramer's fit."""
    r = 8.314462618
    x = h_pct / 100 * 611.2 * np.exp(17.62 * t_c / (243.12 + t_c)) / 101325.0
    m_dry, m_water, cp_dry, cp_water = 28.9645e-3, 18.01528e-3, 3.5 * r, 33.58
    gamma = ((1 - x) * cp_dry + x * cp_water) / ((1 - x) * (cp_dry - r) + x * (cp_water - r))
    return np.sqrt(gamma / 1.4 * m_dry / ((1 - x) * m_dry + x * m_water))


@pytest.mark.parametrize("t_c, h_pct", [(10.0, 50.0), (20.0, 50.0), (25.0, 100.0), (30.0, 90.0)])
def test_humidity_increment_agrees_with_an_ideal_gas_mixture(t_c, h_pct):
    gain = speed_of_sound(t_c, h_pct) - speed_of_sound(t_c)
    assert gain == pytest.approx(speed_of_sound(t_c) * (_ideal_gas_humid_ratio(t_c, h_pct) - 1), rel=0.03)


def test_speed_of_sound_rises_with_humidity():
    h = np.linspace(0.0, 100.0, 21)
    for t_c in (0.0, 20.0, 30.0):
        c = speed_of_sound(np.full_like(h, t_c), h)
        assert np.all(np.diff(c) > 0)
    assert speed_of_sound(20.0, 50.0, pressure_kpa=90.0) > speed_of_sound(20.0, 50.0)  # more vapour per mole


def test_speed_of_sound_takes_per_measurement_air():
    t, h = np.array([19.0, 20.0, 21.0]), np.array([40.0, 50.0, 60.0])
    got = speed_of_sound(t, h)
    assert got.shape == (3,)
    np.testing.assert_allclose(got, [speed_of_sound(a, b) for a, b in zip(t, h, strict=True)], rtol=1e-14)
    np.testing.assert_allclose(speed_of_sound(t, 50.0), [speed_of_sound(a, 50.0) for a in t], rtol=1e-14)
    assert isinstance(speed_of_sound(20.0, 50.0), float)


@pytest.mark.parametrize("humidity, error, match", [
    (float("nan"), ValueError, "humidity_pct must be finite"),
    (float("inf"), ValueError, "humidity_pct must be finite"),
    (-1.0, ValueError, r"humidity_pct must be in \[0, 100\].*got -1"),
    (100.5, ValueError, r"humidity_pct must be in \[0, 100\].*got 100.5"),
    (np.array([50.0, 120.0]), ValueError, r"humidity_pct must be in \[0, 100\].*got 50 to 120"),
    (np.array([50.0, np.nan]), ValueError, "humidity_pct"),
    ("humid", TypeError, "humidity_pct"),
], ids=["nan", "inf", "negative", "above-100", "array-above-100", "array-nan", "text"])
def test_speed_of_sound_refuses_bad_humidity(humidity, error, match):
    with pytest.raises(error, match=match):
        speed_of_sound(20.0, humidity)


def test_speed_of_sound_refuses_bad_pressure_and_temperature():
    with pytest.raises(ValueError, match="pressure_kpa"):
        speed_of_sound(20.0, 50.0, pressure_kpa=0.0)
    with pytest.raises(ValueError, match="temperature_c"):
        speed_of_sound(float("nan"), 50.0)
    with pytest.raises(ValueError, match="temperature_c"):
        speed_of_sound(np.array([20.0, -300.0]), 50.0)


def test_dataset_and_scene_take_c_from_their_humidity():
    sig, pos = np.zeros((2, 50)), np.zeros((2, 3))
    ds = clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=21.59)  # humidity not logged
    assert ds.humidity_pct == 50.0 and ds.c_mps == speed_of_sound(21.59, 50.0)
    step = ds.provenance[-1]
    assert step["step"] == "speed_of_sound" and step["humidity_assumed"]
    assert step["c_mps_source"] == "cramer1993 at 50 % RH (assumed: not logged)"
    warm = ds.replace(temperature_c=25.0)  # c follows the temperature, the humidity still assumed
    assert warm.c_mps == speed_of_sound(25.0, 50.0) and warm.provenance[-1]["humidity_assumed"]
    dry = clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=21.59, humidity_pct=0.0)
    assert dry.c_mps == speed_of_sound(21.59) and not dry.provenance[-1]["humidity_assumed"]
    per = clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=20.0, humidity_pct=[30.0, 70.0])
    np.testing.assert_allclose(per.c_mps, speed_of_sound(20.0, np.array([30.0, 70.0])), rtol=1e-14)
    given = clsas.Dataset(sig, pos, pos, 96e3, np.ones(4), temperature_c=20.0, c_mps=343.0)
    assert given.c_mps == 343.0 and given.provenance == []  # a stated c is kept as stated
    assert clsas.Scene(np.zeros((1, 3)), temperature_c=30.0, humidity_pct=90.0).c_mps == speed_of_sound(30.0, 90.0)
    with pytest.raises(ValueError, match="humidity_pct"):
        clsas.Scene(np.zeros((1, 3)), humidity_pct=float("nan"))


def test_humid_scene_reconstructed_with_its_own_air_focuses_on_the_point():
    """30 C, 90 % RH: 0.6 % faster than dry air. The simulated dataset carries the scene's air,
    so reconstruct() uses the speed simulate() did and the point is in focus; dry air would put
    it ~3 mm too close."""
    target = np.array([0.01, -0.01, 0.55])
    fs = 96e3
    wave = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    scene = clsas.Scene(target[None, :], temperature_c=30.0, humidity_pct=90.0)
    ds = clsas.simulate(scene, clsas.raster_aperture(15, 11, 0.4, 0.3), wave, fs)
    assert ds.humidity_pct == 90.0 and ds.c_mps == pytest.approx(speed_of_sound(30.0, 90.0), rel=1e-14)
    grid = clsas.VoxelGrid(np.array([0.01]), np.array([-0.01]), np.linspace(0.53, 0.57, 81))  # 0.5 mm in range
    z = clsas.reconstruct(ds, grid, backend="numpy").peaks(1)[0].position_m[2]
    assert z == pytest.approx(target[2], abs=0.00051)
    z_dry = clsas.reconstruct(ds.replace(c_mps=speed_of_sound(30.0)), grid, backend="numpy").peaks(1)[0].position_m[2]
    assert target[2] - z_dry > 0.002


@pytest.mark.parametrize("f_hz, expected", [(20e3, 0.524), (30e3, 0.937), (50e3, 1.661)])
def test_iso9613_absorption(f_hz, expected):
    assert air_absorption_db_per_m(f_hz, 20.0, 50.0) == pytest.approx(expected, abs=0.0015)


def test_limits_of_the_paper_rig():
    lim = resolution_limits(20e3, 30e3, 1.0, 1.0, 18, 12, range_m=1.0)
    assert lim.c_mps == speed_of_sound(20.0, 50.0)  # the air the limits are computed for
    assert lim.range_resolution_m == pytest.approx(343.84 / 20e3, rel=1e-4)  # 1.7 cm, not 10 cm
    lam = lim.c_mps / 25e3
    assert lim.cross_range_resolution_m[0] == pytest.approx(lam / 2, rel=1e-6)
    assert lim.required_spacing_m == pytest.approx(lim.c_mps / 30e3 / 4)
    assert len(lim.warnings) == 2 and all("grating lobes" in w for w in lim.warnings)
    assert "undersampled" in lim.report()


def test_limits_well_sampled_has_no_warning():
    lim = resolution_limits(20e3, 30e3, 0.2, 0.2, 101, 101)
    assert lim.warnings == []
