"""UFF (USTB's ultrasound file format, HDF5): import, export, round trip, and files that
``pyuff-ustb`` (the format's Python implementation) writes and reads."""

import h5py
import numpy as np
import pytest

import clsas
import clsas.io
from clsas.cli import main
from clsas.physics.geometry import Aperture

FS = 200e3
C = float(clsas.speed_of_sound(20.0, 50.0))  # m/s, the air of the simulations (a Scene's default: 20 C, 50 % RH)
TARGET = np.array([0.01, -0.02, 0.30])
WAVE = clsas.lfm_chirp(20e3, 40e3, 0.5e-3, FS, taper=0.2)


def _fmc_array(n=6, pitch=0.02):
    """A fixed line array at z = 0 (x from -, y = 0): element positions (n, 3)."""
    x = (np.arange(n) - (n - 1) / 2) * pitch
    return np.column_stack([x, np.zeros(n), np.zeros(n)])


def _echo(t_arrival, n_samples, t_first):
    """The waveform placed at ``t_arrival`` on the axis ``t_first + n / FS`` (FFT delay)."""
    n_fft = 2 * n_samples
    spec = np.fft.rfft(WAVE, n_fft)
    f = np.fft.rfftfreq(n_fft, 1 / FS)
    return np.fft.irfft(spec * np.exp(-2j * np.pi * f * (t_arrival - t_first)), n_fft)[:n_samples]


def _ustb_time(src, delay, elem, p, c=C):
    """USTB's das.m: (|s - p| + k |s|) / c - delay + |p - e| / c, k = -1 behind the probe."""
    k = -1.0 if src[2] < -1e-3 else 1.0
    return (np.linalg.norm(src - p) + k * np.linalg.norm(src)) / c - delay + np.linalg.norm(p - elem) / c


def _pyuff_file(path, sources, delays, elements, *, t_first=1.2e-3, n_samples=800, pulse=True):
    """A UFF file written by pyuff-ustb itself, its echoes placed by USTB's timing formula."""
    pyuff = pytest.importorskip("pyuff_ustb")
    data = np.zeros((n_samples, len(elements), len(sources)))
    for w, (s, d) in enumerate(zip(sources, delays, strict=True)):
        for e, el in enumerate(elements):
            data[:, e, w] = _echo(_ustb_time(s, d, el, TARGET), n_samples, t_first)
    seq = []
    for s, d in zip(sources, delays, strict=True):
        src = pyuff.Point()
        src.xyz = s
        seq.append(pyuff.Wave(wavefront=pyuff.Wavefront.spherical, source=src, delay=d, sound_speed=C))
    geometry = np.zeros((7, len(elements)))
    geometry[:3] = elements.T
    cd = pyuff.ChannelData(sampling_frequency=FS, initial_time=t_first, sound_speed=C, modulation_frequency=0.0,
                           sequence=seq, probe=pyuff.Probe(geometry=geometry, origin=pyuff.Point()), data=data,
                           pulse=pyuff.Pulse(center_frequency=30e3, fractional_bandwidth=0.67, phase=0.0,
                                             waveform=WAVE) if pulse else None)
    cd.write(str(path), "channel_data", ignore_missing_compulsory_fields=True)  # no apodization objects
    return data


def _grid():
    return clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.27, 0.33), 0.005)


def _peak_at_target(ds, tol_m=0.0051):
    peak = clsas.reconstruct(ds, _grid(), backend="numpy").peaks(1)[0].position_m
    assert np.linalg.norm(peak - TARGET) <= tol_m, peak


def _moving_rig(temps=None, seed=3):
    """A planar scan with the speaker and the microphone on one stage, simulated by clsas."""
    ap = clsas.raster_aperture(4, 3, 0.12, 0.08)
    temps = np.linspace(19.0, 21.0, ap.n_meas) if temps is None else temps
    ds = clsas.simulate(clsas.Scene(TARGET[None, :]), ap, WAVE, FS, temperature_c=temps, snr_db=40, seed=seed,
                        t0_s=-1e-4)
    return ds.replace(chirp={"f_start_hz": 20e3, "f_stop_hz": 40e3, "duration_s": 0.5e-3, "taper": 0.2},
                      provenance=[{"step": "simulate"}], background=ds.signals * 0.01)


def test_round_trip_keeps_the_measurements_exactly(tmp_path):
    ds = _moving_rig()
    path = clsas.io.export_uff(ds, tmp_path / "scan.uff")
    back = clsas.io.import_uff(path)
    assert back.n_meas == ds.n_meas and back.fs_hz == ds.fs_hz
    np.testing.assert_allclose(back.signals, ds.signals.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(back.tx_positions, ds.tx_positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.rx_positions, ds.rx_positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.t0_s, ds.t0_s, rtol=0, atol=1e-13)
    np.testing.assert_allclose(back.c_per_meas, ds.c_per_meas, rtol=1e-12)
    np.testing.assert_allclose(back.temperature_c, ds.temperature_c)
    np.testing.assert_allclose(back.waveform, ds.waveform)
    np.testing.assert_allclose(back.background, ds.background.astype(np.float32), rtol=0, atol=0)
    assert back.chirp == ds.chirp
    prov = back.provenance[0]
    assert prov["step"] == "import" and prov["format"] == "uff" and prov["history"] == [{"step": "simulate"}]
    # a moving rig fills the diagonal of the waves x elements matrix; the rest holds zeros
    with h5py.File(path) as f:
        data = f["channel_data/data"][()]
        assert data.shape == (ds.n_meas, ds.n_meas, ds.n_samples)
        assert np.count_nonzero(np.any(data != 0, axis=2)) == ds.n_meas
        # only the measured recordings take room in the file (one chunk each)
        assert f["channel_data/data"].id.get_storage_size() == ds.n_meas * ds.n_samples * 4
    _peak_at_target(back)


def test_full_matrix_reads_without_the_clsas_group(tmp_path):
    elements = _fmc_array()
    tx = np.repeat(elements, len(elements), axis=0)
    rx = np.tile(elements, (len(elements), 1))
    ds = clsas.simulate(clsas.Scene(TARGET[None, :]), Aperture(tx, rx, tx), WAVE, FS, temperature_c=20.0, snr_db=40,
                        seed=1, t0_s=2e-4)
    path = clsas.io.export_uff(ds, tmp_path / "fmc.uff")
    with h5py.File(path, "a") as f:
        del f["clsas"]  # as another program would write it: every (wave, element) pair measured
        assert f["channel_data/data"].shape == (6, 6, ds.n_samples)
    back = clsas.io.import_uff(path)
    assert back.n_meas == 36 and "history" not in back.provenance[0]
    np.testing.assert_allclose(back.signals, ds.signals.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(back.tx_positions, tx, atol=1e-12)
    np.testing.assert_allclose(back.rx_positions, rx, atol=1e-12)
    np.testing.assert_allclose(back.t0_s, 2e-4, atol=1e-13)
    np.testing.assert_allclose(back.c_per_meas, C)


def test_pyuff_reads_the_export_and_ustb_timing_focuses_it(tmp_path):
    pyuff = pytest.importorskip("pyuff_ustb")
    ds = _moving_rig(temps=20.0)
    path = clsas.io.export_uff(ds, tmp_path / "scan.uff")
    cd = pyuff.Uff(str(path)).read("channel_data")
    assert cd.data.shape == (ds.n_samples, ds.n_meas, ds.n_meas)
    assert isinstance(cd.probe, pyuff.Probe) and cd.probe.xyz.shape == (ds.n_meas, 3)
    assert len(cd.sequence) == ds.n_meas and cd.sequence[0].wavefront == pyuff.Wavefront.spherical
    np.testing.assert_allclose([w.source.xyz for w in cd.sequence], ds.tx_positions, atol=1e-12)
    np.testing.assert_allclose(cd.probe.xyz, ds.rx_positions, atol=1e-12)
    np.testing.assert_allclose(np.ravel(cd.pulse.waveform), ds.waveform)
    # USTB's delay-and-sum timing on what pyuff read: the matched-filtered echo of every
    # measured pair peaks at the target's predicted time
    t_axis = float(cd.initial_time) + np.arange(ds.n_samples) / float(cd.sampling_frequency)
    c = float(cd.sound_speed)
    for m in range(ds.n_meas):
        wave = cd.sequence[m]
        t = _ustb_time(wave.source.xyz, float(wave.delay), cd.probe.xyz[m], TARGET, c)
        mf = np.abs(np.correlate(cd.data[:, m, m], ds.waveform, mode="full")[len(ds.waveform) - 1:])
        assert abs(t_axis[np.argmax(mf)] - t) < 2.5 / FS


@pytest.mark.parametrize("kind", ["sta", "diverging"])
def test_a_file_written_by_pyuff_images_its_target(tmp_path, kind):
    elements = _fmc_array()
    if kind == "sta":  # each element fires alone; USTB's examples set delay = r/c
        sources = elements
        delays = np.linalg.norm(sources, axis=1) / C
    else:  # virtual sources 20 mm behind the probe
        sources = np.column_stack([elements[::2, 0], np.zeros(3), np.full(3, -0.02)])
        delays = np.array([1e-5, 0.0, -1e-5])
    _pyuff_file(tmp_path / "foreign.uff", sources, delays, elements)
    assert clsas.io.detect_format(tmp_path / "foreign.uff") == "uff"
    ds = clsas.io.import_scan(tmp_path / "foreign.uff")
    assert ds.n_meas == len(sources) * len(elements) and ds.provenance[0]["format"] == "uff"
    np.testing.assert_allclose(ds.tx_positions[:: len(elements)], sources, atol=1e-12)
    _peak_at_target(ds.replace(c_mps=C))


def test_detect_cli_import_and_export(tmp_path, capsys):
    ds = _moving_rig()
    ds.save(tmp_path / "scan.h5")
    assert not clsas.io.is_uff(tmp_path / "scan.h5")  # a clsas dataset file is not UFF
    assert main(["export", str(tmp_path / "scan.h5"), str(tmp_path / "scan.uff")]) == 0
    assert "scan.uff" in capsys.readouterr().out
    assert clsas.io.is_uff(tmp_path / "scan.uff") and "uff" in clsas.io.IMPORTERS
    assert main(["import", str(tmp_path / "scan.uff"), str(tmp_path / "back.h5")]) == 0
    assert "(uff)" in capsys.readouterr().out
    back = clsas.load(tmp_path / "back.h5")
    np.testing.assert_allclose(back.t0_s, ds.t0_s, atol=1e-13)
    np.testing.assert_allclose(back.background, ds.background, rtol=1e-6, atol=1e-9 * np.abs(ds.background).max())


def _tamper(path, fn):
    with h5py.File(path, "a") as f:
        fn(f)
    return path


def test_errors_name_the_file_and_the_field(tmp_path):
    ds = _moving_rig(temps=20.0).replace(background=None)
    with pytest.raises(FileNotFoundError, match="no file"):
        clsas.io.import_uff(tmp_path / "none.uff")
    (tmp_path / "text.uff").write_text("not hdf5")
    with pytest.raises(ValueError, match=r"text\.uff is not an HDF5 file"):
        clsas.io.import_uff(tmp_path / "text.uff")
    ds.save(tmp_path / "ds.h5")
    with pytest.raises(ValueError, match=r"ds\.h5 holds no uff\.channel_data group"):
        clsas.io.import_uff(tmp_path / "ds.h5")
    with pytest.raises(ValueError, match="frame must be"):
        clsas.io.import_uff(clsas.io.export_uff(ds, tmp_path / "a.uff"), frame=1)

    def fresh(name):
        p = clsas.io.export_uff(ds, tmp_path / name)
        return _tamper(p, lambda f: f.__delitem__("clsas"))

    plane = _tamper(fresh("plane.uff"), lambda f: f["channel_data/sequence/sequence_0002/wavefront"].__setitem__(
        (), np.array([[0.0]])))
    with pytest.raises(ValueError, match=r"plane\.uff:/channel_data/sequence/sequence_0002: a plane wave"):
        clsas.io.import_uff(plane)
    iq = _tamper(fresh("iq.uff"), lambda f: f["channel_data/modulation_frequency"].__setitem__((), [[5e6]]))
    with pytest.raises(ValueError, match=r"iq\.uff:/channel_data: demodulated \(IQ\)"):
        clsas.io.import_uff(iq)

    def nan(f):
        d = f["channel_data/data"]
        d[0, 0, 5] = np.nan

    with pytest.raises(ValueError, match=r"nan\.uff:/channel_data/data holds NaN"):
        clsas.io.import_uff(_tamper(fresh("nan.uff"), nan))
    nopulse = _tamper(fresh("nopulse.uff"), lambda f: f.__delitem__("channel_data/pulse"))
    with pytest.raises(ValueError, match=r"no pulse/waveform .* waveform="):
        clsas.io.import_uff(nopulse)
    assert clsas.io.import_uff(nopulse, waveform=WAVE).n_meas == ds.n_meas ** 2
    noprobe = _tamper(fresh("noprobe.uff"), lambda f: f.__delitem__("channel_data/probe"))
    with pytest.raises(ValueError, match=r"noprobe\.uff:/channel_data: no 'probe' field"):
        clsas.io.import_uff(noprobe)

    def second(f):
        f.copy("channel_data", "channel_data_2")

    two = _tamper(fresh("two.uff"), second)
    with pytest.raises(ValueError, match=r"several channel data groups .* location="):
        clsas.io.import_uff(two)
    assert clsas.io.import_uff(two, location="channel_data_2").n_meas == ds.n_meas ** 2


def test_background_and_export_refusals(tmp_path):
    ds = _moving_rig(temps=20.0).replace(background=None)
    scan = clsas.io.export_uff(ds, tmp_path / "scan.uff")
    other = clsas.io.export_uff(ds.subset(slice(0, 6)), tmp_path / "short.uff")
    with pytest.raises(ValueError, match=r"background .*short\.uff has 6 measurements"):
        clsas.io.import_uff(scan, background=other)
    with_bg = clsas.io.import_uff(scan, background=scan)
    np.testing.assert_array_equal(with_bg.background, with_bg.signals)
    with pytest.raises(ValueError, match="exists .* overwrite=True"):
        clsas.io.export_uff(ds, scan)
    with pytest.raises(ValueError, match="max_bytes"):
        clsas.io.export_uff(ds, tmp_path / "big.uff", max_bytes=1000)
    twice = ds.subset(np.array([0, 0, 1]))
    with pytest.raises(ValueError, match="same speaker, microphone and t0_s"):
        clsas.io.export_uff(twice, tmp_path / "twice.uff")
    with pytest.raises(TypeError, match="dataset must be a clsas.Dataset"):
        clsas.io.export_uff(ds.signals, tmp_path / "x.uff")
    with pytest.raises(ValueError, match="location must be"):
        clsas.io.export_uff(ds, tmp_path / "y.uff", location="a/b")


def test_frames_a_single_wave_and_complex_rf(tmp_path):
    pyuff = pytest.importorskip("pyuff_ustb")
    elements = _fmc_array(4)
    src = elements[1]
    data = _pyuff_file(tmp_path / "one.uff", src[None, :], [0.0], elements)  # (time, element, 1 wave)
    cd = pyuff.Uff(str(tmp_path / "one.uff")).read("channel_data")
    point = pyuff.Point()
    point.xyz = src
    cd.sequence = pyuff.Wave(wavefront=pyuff.Wavefront.spherical, source=point, delay=0.0, sound_speed=C)
    frames = np.stack([np.zeros_like(data), data], axis=-1)  # frame 0 empty, frame 1 the echoes
    cd.data = frames + 0j  # complex RF: modulation frequency 0
    cd.write(str(tmp_path / "frames.uff"), "channel_data", ignore_missing_compulsory_fields=True)
    ds = clsas.io.import_uff(tmp_path / "frames.uff", frame=1)
    assert ds.n_meas == 4
    np.testing.assert_allclose(ds.signals, data[:, :, 0].T)
    np.testing.assert_allclose(ds.tx_positions, np.repeat(src[None, :], 4, axis=0), atol=1e-12)
    assert not np.any(clsas.io.import_uff(tmp_path / "frames.uff").signals)
    with pytest.raises(ValueError, match="frame must be < 2"):
        clsas.io.import_uff(tmp_path / "frames.uff", frame=2)
