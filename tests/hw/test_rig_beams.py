"""A rig file's ``[beams]``: checked by name, stored a stop at a time with the scan,
read back as the dataset's beams, applied by the simulated microphone, kept across a resume."""

import h5py
import numpy as np
import pytest
from test_rig import rig_toml  # noqa: E402  (the rig tests' configuration)

import clsas
from clsas import rig
from clsas.rig import Faults, ScanAborted

BEAMS = """
[beams]
speaker = { model = "cone", half_angle_deg = 30 }
microphone = { model = "piston", diameter_m = 0.01 }
boresight = "normal"
normal = [0, 0, 1]
"""


def test_rig_without_beams_stores_none(tmp_path):
    cfg = rig.parse_rig_config(rig_toml(nx=2, ny=2))
    assert cfg.beams is None and cfg.beams_for(np.zeros((1, 3)), np.zeros((1, 3))) is None
    path = tmp_path / "omni.h5"
    rig.acquire(cfg, path, simulate=True)
    assert clsas.load(path).beams is None
    with h5py.File(path) as f:
        assert "beams" not in f


def test_rig_beams_are_stored_per_stop_and_read_back(tmp_path):
    cfg = rig.parse_rig_config(rig_toml(nx=3, ny=2, mics=2) + BEAMS)
    path = tmp_path / "beams.h5"
    rig.acquire(cfg, path, simulate=True)
    ds = clsas.load(path)
    assert ds.n_meas == 12 and ds.beams is not None and not ds.beams.is_omni
    assert ds.beams.specs() == {"speaker": {"model": "cone", "half_angle_deg": 30.0},
                                "microphone": {"model": "piston", "diameter_m": 0.01}}
    np.testing.assert_array_equal(ds.beams.tx_boresight, np.tile([0.0, 0.0, 1.0], (12, 1)))
    np.testing.assert_array_equal(ds.beams.rx_boresight, np.tile([0.0, 0.0, 1.0], (12, 1)))


def test_rig_beams_follow_the_axis_rule_at_each_measured_position(tmp_path):
    toml = rig_toml(nx=3, ny=2) + BEAMS.replace('boresight = "normal"\nnormal = [0, 0, 1]',
                                                'boresight = "axis"\naxis_point_m = [0, 0, 0]\naxis_dir = [0, 1, 0]')
    cfg = rig.parse_rig_config(toml)
    path = tmp_path / "axis.h5"
    rig.acquire(cfg, path, simulate=True)
    ds = clsas.load(path)
    want = clsas.physics.beam.axis_boresights(ds.tx_positions, (0, 0, 0), (0, 1, 0))
    np.testing.assert_allclose(ds.beams.tx_boresight, want, atol=1e-12)


def test_simulated_microphone_hears_through_the_beams(tmp_path):
    # a narrow cone facing away from the reflector: the echo is gone, the omni scan keeps it
    away = BEAMS.replace('half_angle_deg = 30', 'half_angle_deg = 10').replace("normal = [0, 0, 1]",
                                                                             "normal = [1, 0, 0]")
    loud = clsas.load(_scan(tmp_path / "omni.h5", rig_toml(nx=2, ny=1)))
    quiet = clsas.load(_scan(tmp_path / "away.h5", rig_toml(nx=2, ny=1) + away))
    assert np.abs(quiet.signals).max() < 0.2 * np.abs(loud.signals).max()


def _scan(path, toml):
    rig.acquire(rig.parse_rig_config(toml), path, simulate=True)
    return path


def test_resume_keeps_the_beams_in_step_with_the_signals(tmp_path):
    toml = rig_toml() + BEAMS
    ref = _scan(tmp_path / "ref.h5", toml)
    cfg = rig.parse_rig_config(toml)
    path = tmp_path / "scan.h5"
    with pytest.raises(ScanAborted):
        rig.acquire(cfg, path, simulate=True, faults=Faults(alarm_at_move=4))
    with h5py.File(path, "r+") as f:  # a crash after a stop's boresights, before its signals
        for name in ("beams/tx_boresight", "beams/rx_boresight"):
            f[name].resize(f[name].shape[0] + 1, axis=0)
    assert clsas.load(path).beams.n_meas == clsas.load(path).n_meas == 3
    rig.acquire(cfg, path, resume=True, simulate=True)
    a, b = clsas.load(ref), clsas.load(path)
    np.testing.assert_array_equal(a.signals, b.signals)
    np.testing.assert_array_equal(a.beams.tx_boresight, b.beams.tx_boresight)
    with h5py.File(path) as f:
        assert f["beams/tx_boresight"].shape == (12, 3)


@pytest.mark.parametrize("table, match", [
    ('[beams]\nspeker = { model = "cone", half_angle_deg = 30 }\n', r"speker.*did you mean 'speaker'"),
    ('[beams]\nspeaker = { model = "cone", half_angle_deg = 200 }\n', r"beams\.speaker"),
    ('[beams]\nspeaker = { model = "horn" }\n', r"beams\.speaker"),
    ('[beams]\nboresight = "sideways"\n', r"boresight"),
    ('[beams]\nboresight = "normal"\nnormal = [0, 0, 0]\n', r"normal"),
], ids=["unknown-key", "cone-angle", "model", "rule", "zero-normal"])
def test_rig_beams_errors_name_the_key(table, match):
    with pytest.raises(clsas.config.ConfigError, match=match):
        rig.parse_rig_config(rig_toml() + "\n" + table)


def test_store_refuses_a_stop_without_the_beams_its_file_has(tmp_path):
    from clsas.rig.store import ScanFile

    cfg = rig.parse_rig_config(rig_toml() + BEAMS)
    b = cfg.beams_for(np.zeros((1, 3)), np.array([[0.02, 0.0, 0.0]]))
    store = ScanFile.create(tmp_path / "x.h5", fs_hz=96e3, waveform=np.ones(4), n_samples=8, n_mics=1, n_stops=2,
                            temperature_c=20.0, humidity_pct=50.0, c_mps=343.0, chirp={}, config_text="", beams=b)
    row = {"signals": np.zeros(8), "tx_m": np.zeros(3), "rx_m": np.zeros((1, 3)), "t0_s": 0.0,
           "stage_m": np.zeros(3), "timestamp": 0.0, "loopback": np.zeros(8)}
    with pytest.raises(ValueError, match="beams: .* created with transducer beams, and stop 0 comes without"):
        store.append(0, **row)
    store.append(0, **row, beams=b)
    store.close()
    assert clsas.load(tmp_path / "x.h5").beams.n_meas == 1
