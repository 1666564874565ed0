"""Importers: a folder of WAV/CSV recordings with a positions table, and the AirSAS layout."""

import logging

import numpy as np
import pytest
import scipy.io.wavfile

import clsas
import clsas.io
from clsas.cli import main
from clsas.physics.geometry import Aperture

FS = 100e3
GD = 62.33  # samples
CENTER = np.array([0.02, -0.01, 0.25])  # turntable centre in the rig's frame, m
SPEAKER = np.array([0.87, 0.03, 0.30])
MICS = np.array([[0.87, -0.03, 0.30], [0.87, -0.06, 0.31]])
HEIGHT_MM = 20.0
TARGET = np.array([0.04, -0.03, 0.0])  # in the target's (turntable's) frame
CHIRP = {"f_start_hz": 30e3, "f_stop_hz": 10e3, "duration_s": 1e-3, "taper": 0.1}
WAVE_NAME = "LFM_3.000000E+4Hz_1.000000E+4Hz_1.000000E-3s_1.000000E+0V_0.000000E+0s_1.000000E-1"


def _on_turntable(p, angles_deg):
    """Where the fixed rig point p is in the target's frame at each turntable angle (the
    reader's convention with angle_sign=+1), written out independently of the reader."""
    out = []
    for a in np.deg2rad(angles_deg):
        d = p - CENTER
        out.append([np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1],
                    d[2] + HEIGHT_MM / 1000])
    return np.array(out)


def _write_airsas(folder, *, pings=36, mics=1, temps=None, signals=None, seed=0):
    """An AirSAS folder: a point target on a turntable, simulated with clsas.synthesis.simulation."""
    folder.mkdir()
    angles = np.arange(pings) * 360.0 / pings
    temps = 20.0 + 2.0 * np.arange(pings) / pings if temps is None else temps
    wave = clsas.lfm_chirp(CHIRP["f_start_hz"], CHIRP["f_stop_hz"], CHIRP["duration_s"], FS, CHIRP["taper"])
    if signals is None:
        cols = []
        for m in range(mics):
            tx, rx = _on_turntable(SPEAKER, angles), _on_turntable(MICS[m], angles)
            ds = clsas.simulate(clsas.Scene(TARGET[None, :]), Aperture(tx, rx, tx), wave, FS,
                                n_samples=700, t0_s=-GD / FS, temperature_c=temps, snr_db=30, seed=seed + m)
            cols.append(ds.signals)
        signals = np.stack(cols, axis=2)  # (pings, samples, mics)
    for i in range(pings):
        np.savetxt(folder / f"Flight-{i + 1:06d}.csv", signals[i], fmt="%.7e", delimiter=",")
    lines = ["Flight #,Angle,Height,Temp,Waveform"]
    lines += [f"{i + 1},{angles[i]:.1f},{HEIGHT_MM:.1f},{temps[i]:.3f},0" for i in range(pings)]
    (folder / "Coordinates.csv").write_text("\n".join(lines) + "\n")
    sysp = [f"Speaker {a},{v}" for a, v in zip("xyz", SPEAKER, strict=True)]
    for m in range(2):
        sysp += [f"Mic{m + 1} {a},{v}" for a, v in zip("xyz", MICS[m], strict=True)]
    sysp += [f"Center {a},{v}" for a, v in zip("xyz", CENTER, strict=True)]
    sysp += [f"Fs,{FS:.0f}", f"Group Delay,{GD}", "Operator,someone", "Turntable,Velmex B4872"]
    (folder / "SysParams.csv").write_text("\n".join(sysp) + "\n")
    (folder / "WaveformParams.csv").write_text(WAVE_NAME + ",1\n")
    np.savetxt(folder / "Waveforms.csv", wave[:, None], fmt="%.7e", delimiter=",")
    return angles, temps, signals


def test_airsas_positions_t0_air_and_waveform(tmp_path):
    angles, temps, signals = _write_airsas(tmp_path / "scan", pings=12)
    ds = clsas.io.import_airsas(tmp_path / "scan")
    assert ds.n_meas == 12 and ds.n_samples == 700 and ds.fs_hz == FS
    np.testing.assert_allclose(ds.tx_positions, _on_turntable(SPEAKER, angles), atol=1e-12)
    np.testing.assert_allclose(ds.rx_positions, _on_turntable(MICS[0], angles), atol=1e-12)
    np.testing.assert_allclose(ds.tx_positions[:, 2], SPEAKER[2] - CENTER[2] + 0.02)
    np.testing.assert_allclose(ds.t0_s, -GD / FS)
    np.testing.assert_allclose(ds.temperature_c, temps, atol=1e-3)
    assert ds.air_varies and ds.c_per_meas[-1] > ds.c_per_meas[0]
    np.testing.assert_allclose(ds.signals, signals[:, :, 0], rtol=1e-6, atol=1e-12)
    assert ds.chirp == pytest.approx(CHIRP)
    np.testing.assert_allclose(ds.waveform, clsas.lfm_chirp(30e3, 10e3, 1e-3, FS, 0.1))
    rec = clsas.io.import_airsas(tmp_path / "scan", waveform="recorded")
    np.testing.assert_allclose(rec.waveform, ds.waveform, atol=1e-6)
    prov, air = ds.provenance
    assert prov["step"] == "import" and prov["format"] == "airsas" and prov["group_delay_samples"] == GD
    # the scans log no humidity: c from each ping's temperature at an assumed 50 % RH, and it says so
    assert ds.humidity_pct == 50.0
    np.testing.assert_allclose(ds.c_per_meas, clsas.speed_of_sound(ds.temperature_c, 50.0), rtol=1e-14)
    assert air["step"] == "speed_of_sound" and air["c_mps_source"] == "cramer1993 at 50 % RH (assumed: not logged)"
    mirrored = clsas.io.import_airsas(tmp_path / "scan", angle_sign=-1)
    np.testing.assert_allclose(mirrored.tx_positions[3], _on_turntable(SPEAKER, [-angles[3]])[0], atol=1e-12)


def test_airsas_image_of_a_point_target_lands_on_it(tmp_path):
    _write_airsas(tmp_path / "scan", pings=36)
    ds = clsas.io.import_airsas(tmp_path / "scan")
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.0, 0.0), 0.005)
    image = clsas.reconstruct(ds, grid, backend="numpy")
    (peak,) = image.peaks(1)
    assert np.linalg.norm(np.asarray(peak.position_m) - TARGET) <= 0.0075
    # the other turntable direction mirrors the scene about the x axis (y -> -y)
    mirrored = clsas.reconstruct(clsas.io.import_airsas(tmp_path / "scan", angle_sign=-1), grid, backend="numpy")
    (peak,) = mirrored.peaks(1)
    assert np.linalg.norm(np.asarray(peak.position_m) - TARGET * [1, -1, 1]) <= 0.0075


def test_airsas_two_microphones_and_background(tmp_path):
    angles, _, _ = _write_airsas(tmp_path / "scan", pings=6, mics=2)
    rng = np.random.default_rng(1)
    room = rng.normal(size=(6, 700, 2)) * 1e-3
    _write_airsas(tmp_path / "empty", pings=6, mics=2, signals=room)
    ds = clsas.io.import_airsas(tmp_path / "scan", microphones="all", background=tmp_path / "empty")
    assert ds.n_meas == 12  # ping-major: ping 0 mic 1, ping 0 mic 2, ping 1 mic 1, ...
    np.testing.assert_allclose(ds.rx_positions[1::2], _on_turntable(MICS[1], angles), atol=1e-12)
    np.testing.assert_allclose(ds.tx_positions[0::2], ds.tx_positions[1::2])
    np.testing.assert_allclose(ds.background, room.transpose(0, 2, 1).reshape(12, 700), rtol=1e-6)
    assert ds.provenance[0]["background"] == str(tmp_path / "empty")


def test_airsas_mismatched_background_names_it(tmp_path):
    _write_airsas(tmp_path / "scan", pings=6)
    _write_airsas(tmp_path / "empty", pings=5, signals=np.zeros((5, 700, 1)))
    with pytest.raises(ValueError, match=r"empty.*5 measurements.*6"):
        clsas.io.import_airsas(tmp_path / "scan", background=tmp_path / "empty")
    _write_airsas(tmp_path / "short", pings=6, signals=np.zeros((6, 600, 1)))
    with pytest.raises(ValueError, match=r"short has 600 samples"):
        clsas.io.import_airsas(tmp_path / "scan", background=tmp_path / "short")


def test_airsas_errors_name_the_file(tmp_path):
    _write_airsas(tmp_path / "scan", pings=4, signals=np.zeros((4, 50, 1)))
    flight = tmp_path / "scan" / "Flight-000003.csv"
    flight.write_text("0.0\n0.1\nabc\n0.2\n")
    with pytest.raises(ValueError, match=r"Flight-000003\.csv, line 3, column 1: 'abc' is not a number"):
        clsas.io.import_airsas(tmp_path / "scan")
    flight.unlink()
    with pytest.raises(FileNotFoundError, match=r"ping 3 .*Flight-000003\.csv.*Coordinates\.csv, line 4"):
        clsas.io.import_airsas(tmp_path / "scan")
    sysp = tmp_path / "scan" / "SysParams.csv"
    good = sysp.read_text()
    sysp.write_text(good.replace("Fs,100000", "Fs,fast"))
    with pytest.raises(ValueError, match=r"SysParams\.csv, line \d+: fs = 'fast' is not a number"):
        clsas.io.import_airsas(tmp_path / "scan")
    sysp.write_text(good.replace("Center y", "Centre y"))
    with pytest.raises(ValueError, match=r"SysParams\.csv: no 'center y' row"):
        clsas.io.import_airsas(tmp_path / "scan")
    sysp.write_text(good)
    coords = tmp_path / "scan" / "Coordinates.csv"
    coords.write_text(coords.read_text().replace("3,180.0", "3,south"))
    with pytest.raises(ValueError, match=r"Coordinates\.csv, line 4, column 'Angle': 'south'"):
        clsas.io.import_airsas(tmp_path / "scan")
    with pytest.raises(FileNotFoundError, match=r"no SysParams\.csv in"):
        clsas.io.import_airsas(tmp_path)


def _write_wav_folder(folder):
    """Two stops: a 2-microphone float32 WAV, and a shorter mono int16 WAV."""
    folder.mkdir()
    rng = np.random.default_rng(3)
    a = rng.normal(size=(400, 2)).astype(np.float32) * 0.1
    b = (rng.normal(size=300) * 3000).astype(np.int16)
    scipy.io.wavfile.write(folder / "stop-0.wav", 96000, a)
    scipy.io.wavfile.write(folder / "stop-1.wav", 96000, b)
    (folder / "positions.csv").write_text(
        "File,tx_x,tx_y,tx_z,rx_x,rx_y,rx_z,rx2_x,rx2_y,rx2_z,temperature_c,t0_s\n"
        "stop-0.wav,0.0,0.1,0.0,0.05,0.1,0.0,-0.05,0.1,0.0,21.5,0.001\n"
        "stop-1.wav,0.1,0.1,0.0,0.15,0.1,0.0,,,,22.5,\n")
    (folder / "import.toml").write_text(
        "[recording]\nfs_hz = 96000.0\n"
        "[chirp]\nf_start_hz = 20000.0\nf_stop_hz = 30000.0\nduration_s = 0.002\ntaper = 0.1\n"
        "[delay]\ngroup_delay_samples = 48.0\n[air]\nhumidity_pct = 40.0\n")
    return a, b


def test_folder_of_wav_files(tmp_path, caplog):
    a, b = _write_wav_folder(tmp_path / "scan")
    with caplog.at_level(logging.WARNING, logger="clsas.io"):
        ds = clsas.io.import_folder(tmp_path / "scan")
    assert "padded with zeros to 400" in caplog.text and "stop-1.wav" in caplog.text
    assert ds.n_meas == 3 and ds.n_samples == 400 and ds.fs_hz == 96000
    np.testing.assert_allclose(ds.signals[0], a[:, 0])
    np.testing.assert_allclose(ds.signals[1], a[:, 1])
    np.testing.assert_allclose(ds.signals[2, :300], b / 32768.0)
    assert np.all(ds.signals[2, 300:] == 0)
    assert ds.loopback is None
    np.testing.assert_allclose(ds.rx_positions, [[0.05, 0.1, 0], [-0.05, 0.1, 0], [0.15, 0.1, 0]])
    np.testing.assert_allclose(ds.tx_positions, [[0, 0.1, 0], [0, 0.1, 0], [0.1, 0.1, 0]])
    np.testing.assert_allclose(ds.t0_s, np.array([0.001, 0.001, 0.0]) - 48.0 / 96000)
    np.testing.assert_allclose(ds.temperature_c, [21.5, 21.5, 22.5])
    assert ds.humidity_pct == 40.0
    np.testing.assert_allclose(ds.c_per_meas, clsas.speed_of_sound(np.array([21.5, 21.5, 22.5]), 40.0), rtol=1e-14)
    assert ds.provenance[-1]["c_mps_source"] == "cramer1993 at 40 % RH"
    np.testing.assert_allclose(ds.waveform, clsas.lfm_chirp(20e3, 30e3, 0.002, 96000, 0.1))
    assert ds.chirp["f_stop_hz"] == 30e3 and "[chirp]" in ds.config
    prov = ds.provenance[0]
    assert prov["format"] == "folder" and prov["padded"] and prov["settings"] == "import.toml"


def test_folder_of_csv_files_with_a_waveform_file_and_background(tmp_path):
    folders = {}
    for name, scale in (("scan", 1.0), ("empty", 0.01)):
        folder = tmp_path / name
        folder.mkdir()
        t = np.arange(64) / 48000.0
        rows = []
        for i in range(3):
            sig = scale * np.sin(2 * np.pi * 5e3 * t + i)
            np.savetxt(folder / f"r{i}.csv", np.column_stack([t, sig]), delimiter=",", fmt="%.9g",
                       header="time_s,mic", comments="")
            rows.append(f"r{i}.csv,{i * 0.01},0,0,{i * 0.01 + 0.02},0,0")
        (folder / "positions.csv").write_text("file,tx_x,tx_y,tx_z,rx_x,rx_y,rx_z\n" + "\n".join(rows) + "\n")
        np.savetxt(folder / "waveform.csv", np.sin(np.arange(32)), fmt="%.9g")
        folders[name] = folder
    ds = clsas.io.import_folder(folders["scan"], background=folders["empty"])
    assert ds.fs_hz == pytest.approx(48000.0) and ds.n_meas == 3 and ds.n_samples == 64
    np.testing.assert_allclose(ds.waveform, np.sin(np.arange(32)), atol=1e-8)
    np.testing.assert_allclose(ds.background, 0.01 * ds.signals, atol=1e-9)
    assert ds.temperature_c == 20.0 and np.all(ds.t0_s == 0)
    chirp = {"f_start_hz": 5e3, "f_stop_hz": 10e3, "duration_s": 2e-4}
    ds2 = clsas.io.import_folder(folders["scan"], waveform=chirp, fs_hz=48000.0)
    assert len(ds2.waveform) == round(2e-4 * 48000)
    rec = folders["scan"] / "r1.csv"
    lines = rec.read_text().splitlines()
    lines[2] = lines[2].split(",")[0] + ",n/a"
    rec.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"r1\.csv, line 3, column 2 \('mic'\): 'n/a' is not a number"):
        clsas.io.import_folder(folders["scan"])


def test_folder_loopback_channel(tmp_path):
    folder = tmp_path / "scan"
    folder.mkdir()
    data = (np.arange(2 * 50 * 3).reshape(2, 50, 3) * 1000).astype(np.int32)
    for i in range(2):
        scipy.io.wavfile.write(folder / f"s{i}.wav", 48000, data[i])
    (folder / "positions.csv").write_text(
        "file,tx_x,tx_y,tx_z,rx1_x,rx1_y,rx1_z,rx2_x,rx2_y,rx2_z\n"
        "s0.wav,0,0,0,0.1,0,0,0.2,0,0\ns1.wav,0,0.1,0,0.1,0.1,0,0.2,0.1,0\n")
    (folder / "clsas-import.toml").write_text("[recording]\nloopback_channel = 3\n")
    ds = clsas.io.import_folder(folder, waveform=np.ones(8))
    assert ds.n_meas == 4 and ds.fs_hz == 48000
    np.testing.assert_allclose(ds.signals, data[:, :, :2].transpose(0, 2, 1).reshape(4, 50) / 2.0**31)
    np.testing.assert_allclose(ds.loopback, data[:, :, 2] / 2.0**31)
    np.testing.assert_allclose(ds.rx_positions[3], [0.2, 0.1, 0])


def test_folder_errors_name_file_line_table_and_key(tmp_path):
    _write_wav_folder(tmp_path / "scan")
    scan = tmp_path / "scan"
    toml = scan / "import.toml"
    good = toml.read_text()
    toml.write_text(good.replace("humidity_pct", "humidity"))
    with pytest.raises(ValueError, match=r"import\.toml: unknown key 'humidity' in table \[air\]"):
        clsas.io.import_folder(scan)
    toml.write_text(good + "[stage]\nspeed = 1\n")
    with pytest.raises(ValueError, match=r"import\.toml: unknown table or key 'stage'"):
        clsas.io.import_folder(scan)
    toml.write_text(good.replace("fs_hz = 96000.0", "fs_hz = 48000.0"))
    with pytest.raises(ValueError, match=r"stop-0\.wav is sampled at 96000 Hz, but fs_hz is 48000"):
        clsas.io.import_folder(scan)
    toml.write_text(good)
    pos = scan / "positions.csv"
    good_pos = pos.read_text()
    pos.write_text(good_pos.replace("0.15,0.1", "0.15,north"))
    with pytest.raises(ValueError, match=r"positions\.csv, line 3, column 'rx1_y': 'north' is not a number"):
        clsas.io.import_folder(scan)
    pos.write_text(good_pos.replace("temperature_c", "temprature_c"))
    with pytest.raises(ValueError, match=r"positions\.csv, line 1: unknown column 'temprature_c'"):
        clsas.io.import_folder(scan)
    pos.write_text(good_pos.replace("stop-1.wav", "stop-9.wav"))
    with pytest.raises(FileNotFoundError, match=r"stop-9\.wav \(named in .*positions\.csv, line 3\)"):
        clsas.io.import_folder(scan)
    pos.write_text(good_pos.replace("-0.05,0.1,0.0,21.5", ",,,21.5"))
    with pytest.raises(ValueError, match=r"line 2: stop-0\.wav has 2 channels; give .* rx2_x"):
        clsas.io.import_folder(scan)
    pos.unlink()
    with pytest.raises(FileNotFoundError, match=r"positions\.csv"):
        clsas.io.import_folder(scan)
    with pytest.raises(FileNotFoundError, match=r"no folder"):
        clsas.io.import_folder(tmp_path / "nowhere")


def test_detect_format(tmp_path):
    _write_airsas(tmp_path / "air", pings=2, signals=np.zeros((2, 10, 1)))
    _write_wav_folder(tmp_path / "wav")
    assert clsas.io.detect_format(tmp_path / "air") == "airsas"
    assert clsas.io.detect_format(tmp_path / "wav") == "folder"
    with pytest.raises(ValueError, match="layout not recognised"):
        clsas.io.detect_format(tmp_path)


def test_cli_import(tmp_path, capsys):
    _write_airsas(tmp_path / "scan", pings=8, signals=np.ones((8, 100, 1)))
    _write_airsas(tmp_path / "empty", pings=8, signals=np.zeros((8, 100, 1)))
    out = tmp_path / "scan.h5"
    assert main(["import", str(tmp_path / "scan"), str(out), "--background", str(tmp_path / "empty")]) == 0
    text = capsys.readouterr().out
    assert "airsas" in text and "8 measurements x 100 samples" in text and "100000 Hz" in text
    assert "clsas reconstruct" in text and str(out) in text
    ds = clsas.load(out)
    assert ds.n_meas == 8 and ds.background is not None and ds.provenance[0]["format"] == "airsas"
    np.testing.assert_allclose(ds.t0_s, -GD / FS)
    assert main(["import", str(tmp_path / "scan"), str(out), "--format", "folder", "--overwrite"]) == 2
    assert "positions.csv" in capsys.readouterr().err
    # without --overwrite the existing scan is not replaced: one line naming it, before any reading
    before = out.read_bytes()
    assert main(["import", str(tmp_path / "scan"), str(out)]) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "--overwrite" in err and err.count("\n") == 1
    assert out.read_bytes() == before
    assert main(["import", str(tmp_path / "scan"), str(out), "--overwrite"]) == 0
