import h5py
import numpy as np
import pytest
from conftest import small_dataset

import clsas


def test_dataset_round_trip(tmp_path):
    ds = small_dataset([[0.0, 0.0, 0.5]], snr_db=10)
    ds.config = "[chirp]\nfs_hz = 96000.0\n"
    path = ds.save(tmp_path / "scan.h5")
    back = clsas.load(path)
    np.testing.assert_allclose(back.signals, ds.signals.astype(np.float32))
    for name in ("tx_positions", "rx_positions", "waveform", "t0_s", "stage_positions"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ds, name))
    assert back.fs_hz == ds.fs_hz and back.c_mps == ds.c_mps
    assert back.chirp == ds.chirp and back.config == ds.config
    with h5py.File(path) as f:  # readable with plain h5py, every array with units
        assert f["signals"].dtype == np.float32
        assert all("units" in f[k].attrs for k in f)
        assert f.attrs["format_version"] == 1 and "clsas_version" in f.attrs


def test_simulated_noise_is_seeded_and_at_the_requested_snr():
    clean = small_dataset([[0.0, 0.0, 0.5]])
    a = small_dataset([[0.0, 0.0, 0.5]], snr_db=10)
    b = small_dataset([[0.0, 0.0, 0.5]], snr_db=10)
    np.testing.assert_array_equal(a.signals, b.signals)
    noise = a.signals - clean.signals
    snr = 10 * np.log10(np.mean(clean.signals**2) / np.mean(noise**2))
    assert snr == pytest.approx(10, abs=0.2)


def test_simulated_echo_has_spreading_and_absorption():
    near = small_dataset([[0.0, 0.0, 0.5]], nx=1, ny=1, width=0, height=0)
    far = small_dataset([[0.0, 0.0, 1.0]], nx=1, ny=1, width=0, height=0)
    ratio_db = 20 * np.log10(np.abs(near.signals).max() / np.abs(far.signals).max())
    # 1/(r r) spreading: 12 dB per doubling, plus ~0.7 dB/m ISO absorption over 1 m more path
    assert 12.2 < ratio_db < 13.5


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(signals=np.full((2, 10), np.nan)), "NaN"),
        (dict(tx_positions=np.zeros((3, 3))), "tx_positions"),
        (dict(fs_hz=0), "fs_hz"),
        (dict(c_mps=-343.0), "c_mps"),
        (dict(signals=np.zeros(10)), "signals must be 2-D"),
    ],
    ids=["nan-signals", "tx-shape", "zero-fs", "negative-c", "1-D-signals"],
)
def test_dataset_rejects_bad_input(change, match):
    args = dict(signals=np.zeros((2, 10)), tx_positions=np.zeros((2, 3)), rx_positions=np.zeros((2, 3)),
                fs_hz=96e3, waveform=np.ones(4))
    args.update(change)
    with pytest.raises(ValueError, match=match):
        clsas.Dataset(**args)


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        clsas.load(tmp_path / "nothing.h5")


def test_save_refuses_an_existing_file_unless_told(tmp_path):
    """Dataset.save and Image.save never replace a file silently: FileExistsError naming it, or
    overwrite=True."""
    ds = clsas.Dataset(np.zeros((1, 100)), np.zeros((1, 3)), np.full((1, 3), 0.04), 96e3, np.ones(10))
    path = ds.save(tmp_path / "scan.h5")
    with pytest.raises(FileExistsError, match=r"scan\.h5 exists \(Dataset\.save: pass overwrite=True"):
        ds.save(path)
    ds.replace(config="second").save(path, overwrite=True)
    assert clsas.load(path).config == "second"
    grid = clsas.VoxelGrid.from_bounds((-0.01, 0.01), (-0.01, 0.01), (0.5, 0.52), 0.01)
    image = clsas.Image(np.zeros(grid.shape, np.complex64), grid)
    image.save(tmp_path / "image.h5")
    with pytest.raises(FileExistsError, match=r"image\.h5 exists \(Image\.save"):
        image.save(tmp_path / "image.h5")
    image.save(tmp_path / "image.h5", overwrite=True)
