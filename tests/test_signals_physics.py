import numpy as np
import pytest

import clsas
from clsas.physics import air_absorption_db_per_m, resolution_limits, speed_of_sound


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


@pytest.mark.parametrize("f_hz, expected", [(20e3, 0.524), (30e3, 0.937), (50e3, 1.661)])
def test_iso9613_absorption(f_hz, expected):
    assert air_absorption_db_per_m(f_hz, 20.0, 50.0) == pytest.approx(expected, abs=0.0015)


def test_limits_of_the_paper_rig():
    lim = resolution_limits(20e3, 30e3, 1.0, 1.0, 18, 12, range_m=1.0)
    assert lim.range_resolution_m == pytest.approx(343.2 / 20e3, rel=1e-3)  # 1.7 cm, not 10 cm
    lam = lim.c_mps / 25e3
    assert lim.cross_range_resolution_m[0] == pytest.approx(lam / 2, rel=1e-6)
    assert lim.required_spacing_m == pytest.approx(lim.c_mps / 30e3 / 4)
    assert len(lim.warnings) == 2 and all("grating lobes" in w for w in lim.warnings)
    assert "undersampled" in lim.report()


def test_limits_well_sampled_has_no_warning():
    lim = resolution_limits(20e3, 30e3, 0.2, 0.2, 101, 101)
    assert lim.warnings == []
