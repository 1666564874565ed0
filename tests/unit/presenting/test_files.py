"""Files that open anywhere: xarray reads the image and scan files, .vti and .npy exports."""

import json

import numpy as np
import pytest

import clsas
from clsas.presenting.export import read_vti, to_npy, to_vti
from clsas.types.image import Image, source_provenance

xr = pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")


@pytest.fixture
def image(rng):
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.05, 0.05), (1.0, 1.2), 0.02)
    vals = rng.standard_normal(grid.shape) + 1j * rng.standard_normal(grid.shape)
    return Image(vals, grid, method="bp", provenance={"note": "test"})


@pytest.fixture
def scan():
    ap = clsas.raster_aperture(3, 2, 1.0, 1.0)
    ds = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, 1.0]])), ap,
                        clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1), 96e3)
    return ds.replace(temperature_c=np.linspace(20.0, 21.0, ds.n_meas),
                      provenance=[{"step": "dc"}])


def test_xarray_reads_image_coordinates(tmp_path, image, scan):
    scan_path = scan.save(tmp_path / "scan.h5")
    image.provenance.update(source_provenance(scan, scan_path))
    path = image.save(tmp_path / "image.h5")
    with xr.open_dataset(path, engine="h5netcdf", phony_dims="access") as x:
        assert x["values"].dims == ("x_m", "y_m", "z_m")
        for name in ("x_m", "y_m", "z_m"):
            np.testing.assert_array_equal(x[name].values, getattr(image.grid, name))
            assert x[name].attrs["units"] == "m"
        np.testing.assert_allclose(x["values"].values, image.values)
        prov = json.loads(x.attrs["provenance_json"])
    assert prov["method"] == "bp" and prov["formation"] == "bp" and prov["note"] == "test"
    assert prov["source_sha256"] == __import__("hashlib").sha256(scan_path.read_bytes()).hexdigest()
    # c followed the new temperatures (at the scene's 50 % RH): the scan says so after its own steps
    assert [p["step"] for p in prov["dataset_provenance"]] == ["dc", "speed_of_sound"]
    assert prov["dataset_provenance"][-1]["c_mps_source"] == "cramer1993 at 50 % RH"
    assert prov["spacing_m"] == pytest.approx([0.02, 0.02, 0.02])
    back = Image.load(path)
    np.testing.assert_array_equal(back.values, image.values)
    assert back.provenance["source_sha256"] == prov["source_sha256"]


def test_xarray_reads_scan_with_named_dims(tmp_path, scan):
    path = scan.save(tmp_path / "scan.h5")
    with xr.open_dataset(path, engine="h5netcdf", phony_dims="access") as x:
        assert not any(d.startswith("phony_dim") for d in x.dims)
        assert x["signals"].dims == ("measurement", "sample")
        assert x["tx_positions"].dims == ("measurement", "xyz")
        assert x["temperature_c"].dims == ("measurement",)
        assert list(x["xyz"].values) == ["x", "y", "z"]
    back = clsas.load(path)
    np.testing.assert_allclose(back.signals, scan.signals.astype(np.float32))
    np.testing.assert_allclose(back.temperature_c, scan.temperature_c)


def test_image_load_reads_old_files(tmp_path, image):
    import h5py

    path = tmp_path / "old.h5"
    with h5py.File(path, "w") as f:  # the layout written before dimension scales
        f.create_dataset("values", data=image.values).attrs["units"] = "arbitrary"
        for name in ("x_m", "y_m", "z_m"):
            f.create_dataset(name, data=getattr(image.grid, name)).attrs["units"] = "m"
        f.attrs.update(method="bpdn", backend="numpy", device="NumPy (float64)", time_total_s=1.5)
    back = Image.load(path)
    np.testing.assert_array_equal(back.values, image.values)
    assert back.method == "bpdn" and back.timings_s == {"total": 1.5} and back.provenance == {}


def test_vti_round_trip(tmp_path, image):
    path = to_vti(image, tmp_path / "image.vti")
    back = read_vti(path)
    np.testing.assert_allclose(back["magnitude"], np.abs(image.values), rtol=1e-6)
    np.testing.assert_allclose(back["db"], image.db(-120.0), atol=1e-4)
    np.testing.assert_allclose(back["origin"], [-0.1, -0.05, 1.0])
    np.testing.assert_allclose(back["spacing"], [0.02, 0.02, 0.02])


def test_npy_with_sidecar(tmp_path, image):
    npy, side = to_npy(image, tmp_path / "image.npy")
    np.testing.assert_allclose(np.load(npy), np.abs(image.values), rtol=1e-6)
    meta = json.loads(side.read_text())
    assert meta["scale"] == pytest.approx([0.02, 0.02, 0.02])
    assert meta["translate"] == pytest.approx([-0.1, -0.05, 1.0])


def test_cli_reconstruct_plot_and_export(tmp_path, capsys):
    from clsas.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text("""
[chirp]
f_start_hz = 20000.0
f_stop_hz = 30000.0
duration_s = 0.002
fs_hz = 96000.0

[aperture]
nx = 5
ny = 4
width_m = 0.3
height_m = 0.2

[[points]]
position_m = [0.02, -0.01, 0.6]

[grid]
x_m = [-0.06, 0.06]
y_m = [-0.04, 0.04]
z_m = [0.56, 0.64]
spacing_m = 0.01
""")
    data = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(data), "-q", "--backend", "numpy"]) == 0
    assert main(["reconstruct", str(data), "-q", "--backend", "numpy", "--plot", str(tmp_path / "p.svg"),
                 "--dynamic-range", "25"]) == 0
    assert (tmp_path / "p.svg").stat().st_size > 1000
    image = Image.load(tmp_path / "scan-image.h5")
    assert image.provenance["source_path"] == "scan.h5" and len(image.provenance["source_sha256"]) == 64
    assert main(["export", str(tmp_path / "scan-image.h5"), str(tmp_path / "out.vti")]) == 0
    np.testing.assert_allclose(read_vti(tmp_path / "out.vti")["magnitude"], np.abs(image.values), rtol=1e-5)
    assert main(["export", str(tmp_path / "scan-image.h5"), str(tmp_path / "out.npy")]) == 0
    assert (tmp_path / "out.json").exists()
    assert main(["reconstruct", str(data), "-q", "--backend", "numpy", "--plot", str(tmp_path / "p.gif")]) == 2
