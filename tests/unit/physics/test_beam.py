"""Beam models, boresights, the dataset file, the configuration table and the c_mps warning."""

import logging

import numpy as np
import pytest

import clsas
from clsas.io.config import ConfigError
from clsas.physics.beam import (
    Beams,
    Cone,
    Omni,
    Piston,
    Table,
    angular_weights,
    axis_boresights,
    beam_from_spec,
    beam_weights,
    lookup_table,
    pair_weights,
    planar_boresights,
)
from clsas.synthesis.scenes import parse_config
from clsas.types.dataset import AIR_FALLBACK


def test_piston_pattern_is_one_on_axis_and_zero_at_its_first_null():
    c, f, d = 1480.0, 2.5e6, 6e-3
    beam = Piston(d)
    ka = np.pi * f * d / c
    first_null = np.arcsin(3.8317059702 / ka)
    got = beam.pattern(np.array([0.0, first_null, np.pi * 0.75]), f, c)
    assert got[0] == pytest.approx(1.0)
    assert got[1] == pytest.approx(0.0, abs=1e-8)
    assert got[2] == 0.0  # behind the baffle
    # the -6 dB one-way half-angle: 2 J1(x) / x = 1/2 at x = 2.2152
    assert beam.pattern(np.arcsin(2.2152 / ka), f, c) == pytest.approx(0.5, abs=1e-3)
    # the fast grid the simulator uses agrees with the exact pattern
    th = np.linspace(0, 0.5, 41)
    fs = np.array([1e6, 2.5e6, 4e6])
    np.testing.assert_allclose(beam.pattern_grid(th, fs, c), beam.pattern(th[:, None], fs, c), atol=2e-6)


def test_cone_and_f_number_and_table():
    cone = Cone(10.0)
    assert cone.pattern(np.radians(10.0), 1e6, 1480.0) == pytest.approx(0.5)
    assert Cone.from_f_number(2.0).half_angle_deg == pytest.approx(np.degrees(np.arctan(0.25)))
    tab = Table((0, 10, 20), (2.0, 1.0, 0.0))
    np.testing.assert_allclose(tab.pattern(np.radians([0, 5, 15, 30]), 1e6, 1480.0), [1.0, 0.75, 0.25, 0.0])
    assert Omni().pattern(np.array([0.0, 3.0]), 1e6, 1480.0).tolist() == [1.0, 1.0]


@pytest.mark.parametrize("spec, match", [
    ({"model": "pistn", "diameter_m": 0.006}, "beam.model"),
    ({"model": "piston"}, "needs 'diameter_m'"),
    ({"model": "piston", "diameter": 0.006}, "unknown key"),
    ({"model": "piston", "diameter_m": -1.0}, "diameter_m"),
    ({"model": "cone", "half_angle_deg": 10, "f_number": 2}, "exactly one"),
    ({"model": "table", "angles_deg": [5, 10], "amplitudes": [1, 0]}, "angles_deg"),
    ({"model": "table", "angles_deg": [0, 10], "amplitudes": [1]}, "amplitudes"),
], ids=["model", "missing", "unknown-key", "negative", "cone-both", "table-from-0", "table-shape"])
def test_every_beam_option_is_checked_by_name(spec, match):
    with pytest.raises(ValueError, match=match):
        beam_from_spec(spec)


def test_boresights_planar_turntable_and_given():
    assert planar_boresights(3).tolist() == [[0, 0, 1]] * 3
    pos = np.array([[1.0, 0.0, 0.2], [0.0, -2.0, 0.0]])
    np.testing.assert_allclose(axis_boresights(pos), [[-1, 0, 0], [0, 1, 0]])
    b = Beams(Piston(0.01), "omni", [[0, 0, 2], [0, 1, 1]], (0, 0, 1), 2)
    np.testing.assert_allclose(b.tx_boresight[1], [0, 2**-0.5, 2**-0.5])
    assert not b.is_omni and Beams("omni", None, (0, 0, 1), (0, 0, 1), 2).is_omni
    with pytest.raises(ValueError, match="tx_boresight"):
        Beams(Omni(), Omni(), (0, 0, 0), (0, 0, 1), 2)
    with pytest.raises(ValueError, match="rx_boresight"):
        Beams(Omni(), Omni(), (0, 0, 1), np.ones((3, 3)), 2)
    with pytest.raises(ValueError, match="on the rotation axis"):
        axis_boresights(np.array([[0.0, 0.0, 1.0]]))


def test_pair_weights_follow_the_analytic_pattern():
    """The table (uniform in sin(theta/2)) reproduces the cone pattern to 1e-4 at every angle."""
    cone = Cone(12.0)
    luts = (lookup_table(cone, 1e6, 1480.0), lookup_table(Omni(), 1e6, 1480.0))
    ang = np.radians(np.linspace(0, 60, 25))
    pts = np.c_[np.sin(ang), np.zeros_like(ang), np.cos(ang)] * 0.05
    w = pair_weights(luts, np.zeros(3), np.zeros(3), np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), pts, None)
    np.testing.assert_allclose(w, cone.pattern(ang, 1e6, 1480.0), atol=1e-4)
    gated = pair_weights(luts, np.zeros(3), np.zeros(3), np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), pts, 0.5)
    assert gated.tolist() == (ang <= np.radians(12.0) + 1e-9).astype(float).tolist()
    bw = beam_weights(Beams(cone, Omni(), (0, 0, 1), (0, 0, 1), 1), "weighted", 1e6, 1480.0)
    np.testing.assert_allclose(angular_weights(bw, np.sin(ang)), cone.pattern(ang, 1e6, 1480.0), atol=1e-4)
    assert beam_weights(None, "limited", 1e6, 1480.0) is None
    with pytest.raises(ValueError, match="beam"):
        beam_weights(None, "gated", 1e6, 1480.0)


def _dataset(n=4, **kw):
    tx = np.c_[np.arange(n) * 0.01, np.zeros((n, 2))]
    return clsas.Dataset(np.zeros((n, 50)), tx, tx, 1e6, np.ones(5), **kw)


def test_beams_round_trip_through_the_file_and_subset(tmp_path):
    tilt = np.c_[np.zeros((4, 1)), np.linspace(0, 0.2, 4), np.ones(4)]
    beams = Beams({"model": "table", "angles_deg": [0, 10, 30], "amplitudes": [1, 0.5, 0]},
                  Cone.from_f_number(1.5), tilt, (0, 0, 1), 4)
    ds = _dataset(beams=beams, c_mps=1480.0)
    back = clsas.load(ds.save(tmp_path / "b.h5"))
    assert back.beams.specs() == beams.specs()
    np.testing.assert_allclose(back.beams.tx_boresight, beams.tx_boresight)
    np.testing.assert_allclose(back.subset(slice(1, 3)).beams.tx_boresight, beams.tx_boresight[1:3])
    # a file without beams (every file written before beams were stored) loads as omnidirectional
    assert clsas.load(_dataset(c_mps=1480.0).save(tmp_path / "o.h5")).beams is None
    with pytest.raises(ValueError, match="n_meas=4"):
        _dataset(beams=Beams(Omni(), Omni(), (0, 0, 1), (0, 0, 1), 3), c_mps=1480.0)


def test_dataset_says_loudly_when_it_assumes_air(caplog, tmp_path):
    with caplog.at_level(logging.WARNING, logger="clsas.types.dataset"):
        ds = _dataset()
    assert any("c_mps" in r.message and "assuming air" in r.message for r in caplog.records)
    assert AIR_FALLBACK in ds.provenance and ds.c_mps == pytest.approx(343.84, abs=0.01)  # 20 C at the assumed 50 % RH
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="clsas.types.dataset"):
        _dataset(c_mps=1480.0)
        _dataset(temperature_c=25.0)
        clsas.load(ds.save(tmp_path / "a.h5"))  # the flag travels in the file; no second warning
    assert not caplog.records
    assert AIR_FALLBACK in clsas.load(tmp_path / "a.h5").provenance


SCENE = """
[chirp]
fs_hz = 96000.0
[aperture]
nx = 3
ny = 2
width_m = 0.1
height_m = 0.1
[[points]]
position_m = [0.0, 0.0, 1.0]
[beams]
speaker = { model = "piston", diameter_m = 0.02 }
microphone = { model = "cone", f_number = 1.0 }
{extra}
"""


def test_beams_table_in_a_scene_file():
    cfg = parse_config(SCENE.replace("{extra}", ""), "s.toml")
    assert cfg.beams.specs()["speaker"] == {"model": "piston", "diameter_m": 0.02}
    assert cfg.beams.tx_boresight.shape == (6, 3)
    cfg = parse_config(SCENE.replace("{extra}", 'boresight = "axis"\naxis_point_m = [0.0, 1.0, 0.0]'), "s.toml")
    assert cfg.beams.tx_boresight[0, 1] > 0.9
    for extra, match in [('boresight = "down"', "beams.boresight"), ("diameter_m = 1.0", "unknown key 'diameter_m'"),
                         ('speaker = { model = "piston" }', "needs 'diameter_m'")]:
        text = SCENE.replace("{extra}", extra)
        if extra.startswith("speaker"):
            text = text.replace('speaker = { model = "piston", diameter_m = 0.02 }\n', "")
        with pytest.raises(ConfigError, match=match):
            parse_config(text, "s.toml")
