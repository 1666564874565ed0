"""Tiled, out-of-core reconstruction (clsas.pipeline.tiling) and lazily opened images."""

import numpy as np
import pytest
from conftest import BACKENDS, TOL, needs_opencl, small_dataset

import clsas
from clsas.pipeline.tiling import parse_bytes, tile_grid, tile_shape_for
from clsas.pipeline.tiling.tiles import chunk_shape


@pytest.fixture(scope="module")
def scene():
    ds = small_dataset([[0.02, -0.01, 0.5], [-0.05, 0.04, 0.45]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.01)
    return ds, grid


@pytest.fixture(scope="module")
def reference(scene):
    ds, grid = scene
    return {b: clsas.reconstruct(ds, grid, backend=b) for b in ("numpy",)}


def _same(a, b):
    """Equal to float64 rounding (the NumPy twin's sums may round differently on another tile shape)."""
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())


def test_tiles_cover_the_grid_once():
    grid = clsas.VoxelGrid(np.arange(7.0), np.arange(5.0), np.arange(3.0))
    count = np.zeros(grid.shape, int)
    tiles = tile_grid(grid, (3, 2, 3))
    for t in tiles:
        count[t.slices] += 1
        np.testing.assert_array_equal(t.grid.x_m, grid.x_m[t.slices[0]])
        np.testing.assert_array_equal(t.grid.y_m, grid.y_m[t.slices[1]])
    assert (count == 1).all()
    assert [t.index for t in tiles] == list(range(len(tiles))) and len(tiles) == 3 * 3 * 1


def test_tile_shape_follows_the_budget():
    grid = clsas.VoxelGrid(np.arange(100.0), np.arange(50.0), np.arange(40.0))
    whole = tile_shape_for(grid, "opencl")
    assert whole == grid.shape
    small = tile_shape_for(grid, "opencl", max_memory=10e6, fixed_bytes=2e6)
    assert np.prod(small) * 56 <= 0.6 * 8e6 and small[1:] == (50, 40)
    tiny = tile_shape_for(grid, "numpy", max_memory=0.2e6, fixed_bytes=0)
    assert tiny[0] == 1 and tiny[1] < 50
    assert np.prod(tile_shape_for(grid, "opencl", min_tiles=8)) <= grid.size / 8 + 50 * 40
    with pytest.raises(ValueError, match="max_memory"):
        tile_shape_for(grid, "opencl", max_memory=1e6, fixed_bytes=2e6)
    assert np.prod(chunk_shape((100, 50, 40))) * 8 <= 4 << 20


def test_tile_shape_leaves_room_for_the_tiles_a_worker_holds():
    """A Dask worker returns a run of tiles together: with 4 held, each voxel costs its forming
    (56 bytes on OpenCL) and the values of 3 more tiles (8 bytes each), all within the budget."""
    grid = clsas.VoxelGrid(np.arange(100.0), np.arange(50.0), np.arange(40.0))
    held = tile_shape_for(grid, "opencl", max_memory=10e6, fixed_bytes=2e6, held_tiles=4)
    assert np.prod(held) * (56 + 3 * 8) <= 0.6 * 8e6 < (held[0] + 1) * 50 * 40 * (56 + 3 * 8)
    assert np.prod(held) < np.prod(tile_shape_for(grid, "opencl", max_memory=10e6, fixed_bytes=2e6))
    with pytest.raises(ValueError, match="held_tiles"):
        tile_shape_for(grid, "opencl", held_tiles=0)


@pytest.mark.parametrize("text, n", [("2GB", 2e9), ("500 MB", 5e8), ("1.5GiB", 1.5 * 2**30), (1e6, 1e6)],
                         ids=["GB", "MB", "GiB", "number"])
def test_parse_bytes(text, n):
    assert parse_bytes(text) == pytest.approx(n)


@pytest.mark.parametrize("kwargs, err, match", [
    ({"out": "image.txt"}, ValueError, "out must end in"),
    ({"out": "/no/such/folder/image.h5"}, ValueError, "folder"),
    ({"out": 3}, TypeError, "out must be a path"),
    ({"max_memory": "lots"}, ValueError, "max_memory"),
    ({"max_memory": -1}, ValueError, "max_memory"),
    ({"client": 42}, TypeError, "client"),
    ({"tile_shape": (0, 1, 1)}, ValueError, "tile_shape"),
    ({"tile_shape": (1, 1)}, ValueError, "tile_shape"),
    ({"device": []}, ValueError, "device"),
], ids=["suffix", "folder", "out-type", "memory-text", "memory-negative", "client-type", "tile-zero",
        "tile-2d", "device-empty"])
def test_arguments_checked_before_any_work(scene, monkeypatch, kwargs, err, match):
    ds, grid = scene

    def no_work(*a, **k):
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr("clsas.pipeline.reconstruction.plan_reconstruction", no_work)
    with pytest.raises(err, match=match):
        clsas.reconstruct(ds, grid, backend="numpy", **kwargs)


def test_tiled_numpy_equals_the_whole_image(scene, reference):
    ds, grid = scene
    tiled = clsas.reconstruct(ds, grid, backend="numpy", tile_shape=(7, 9, 5))
    _same(tiled.values, reference["numpy"].values)
    t = tiled.provenance["tiles"]
    assert t["count"] == 3 * 2 * 4 and t["formed_now"] == t["count"]
    assert tiled.provenance["formation"] == "bp"


@needs_opencl
def test_tiled_opencl_equals_the_whole_image_to_float32(scene, reference):
    ds, grid = scene
    tiled = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", tile_shape=(5, 17, 17))
    ref = reference["numpy"].values
    assert tiled.backend == "opencl" and tiled.values.dtype == np.complex64
    assert np.abs(tiled.values - ref).max() <= TOL["backproject"] * np.abs(ref).max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_out_of_core_file_equals_in_memory_tiles(scene, tmp_path, backend):
    ds, grid = scene
    shape = (4, 17, 17)
    path = tmp_path / "image.h5"
    image = clsas.reconstruct(ds, grid, backend=backend, out=path, tile_shape=shape, max_memory="4GB")
    assert image.lazy and image.method == "bp"
    for tile in tile_grid(grid, shape)[::2]:  # a sample of tiles, each against its own in-memory image
        alone = clsas.reconstruct(ds, tile.grid, backend=backend)
        np.testing.assert_array_equal(image.values[tile.slices], alone.values.astype(np.complex64))
    again = clsas.Image.load(path)  # the eager reader reads the same file
    assert again.grid.shape == grid.shape and again.provenance["tiles"]["count"] == len(tile_grid(grid, shape))


def test_lazy_image_answers_like_the_in_memory_one(scene, reference, tmp_path):
    ds, grid = scene
    mem = reference["numpy"]
    path = mem.save(tmp_path / "mem.h5")
    lazy = clsas.Image.open(path)
    assert lazy.lazy and not mem.lazy
    for k, sep in ((1, 0.0), (3, 0.03), (5, 0.0)):
        want, got = mem.peaks(k, sep), lazy.peaks(k, sep)
        assert [p.index for p in got] == [p.index for p in want]
    assert lazy.max_magnitude() == pytest.approx(np.abs(mem.values).max())
    for axis in "xyz":
        np.testing.assert_allclose(lazy.projection(axis), mem.projection(axis))
        np.testing.assert_array_equal(lazy.section(axis, 2), mem.section(axis, 2))
    np.testing.assert_allclose(lazy.db(-40), mem.db(-40))
    small = lazy.reduced(max_voxels=200)
    assert small.grid.size <= 4 * 200 and not small.lazy
    assert np.abs(small.values).max() == pytest.approx(np.abs(mem.values).max())
    copy = clsas.Image.load(lazy.save(tmp_path / "copy.h5"))
    np.testing.assert_array_equal(copy.values, mem.values)
    from clsas.presenting.export import export, read_vti

    export(lazy, tmp_path / "lazy.vti")
    np.testing.assert_allclose(read_vti(tmp_path / "lazy.vti")["magnitude"], np.abs(mem.values), rtol=1e-6)


def test_lazy_image_of_a_dask_array(scene, reference):
    da = pytest.importorskip("dask.array")
    mem = reference["numpy"]
    lazy = clsas.Image(da.from_array(mem.values, chunks=(4, 8, 8)), mem.grid)
    assert lazy.lazy
    assert [p.index for p in lazy.peaks(3, 0.03)] == [p.index for p in mem.peaks(3, 0.03)]
    np.testing.assert_allclose(lazy.projection("y"), mem.projection("y"))


def test_lazy_picture(scene, reference, tmp_path):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    lazy = clsas.Image.open(reference["numpy"].save(tmp_path / "p.h5"))
    lazy.plot(tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 0


class _Stop(Exception):
    pass


def test_interrupted_run_resumes_without_forming_tiles_again(scene, tmp_path, reference):
    ds, grid = scene
    path = tmp_path / "resume.h5"
    shape = (3, 17, 17)
    n = len(tile_grid(grid, shape))

    def stop_after_3(done, total):
        if done >= 3:
            raise _Stop

    with pytest.raises(_Stop):
        clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=shape, progress=stop_after_3)
    with pytest.raises(ValueError, match="unfinished"):
        clsas.Image.open(path)
    seen = []
    image = clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=shape,
                              progress=lambda d, t: seen.append(d))
    assert seen[0] == 3 and image.provenance["tiles"]["formed_now"] == n - 3
    np.testing.assert_array_equal(image.values[()], reference["numpy"].values.astype(np.complex64))


def test_a_file_of_another_request_is_refused(scene, tmp_path):
    ds, grid = scene
    path = tmp_path / "other.h5"
    clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=(6, 17, 17))
    with pytest.raises(ValueError, match="another request"):
        clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=(3, 17, 17))
    (tmp_path / "plain.h5").write_bytes(b"")
    with pytest.raises((ValueError, OSError)):
        clsas.reconstruct(ds, grid, backend="numpy", out=tmp_path / "plain.h5")


def test_budget_bounds_the_tiles(scene):
    ds, _ = scene
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.005)
    budget = clsas.pipeline.tiling.rss_bytes() + grid.size * 16 + 3e6
    image = clsas.reconstruct(ds, grid, backend="numpy", max_memory=budget)
    assert image.provenance["tiles"]["count"] > 1
    _same(image.values, clsas.reconstruct(ds, grid, backend="numpy").values)
    with pytest.raises(ValueError, match="max_memory"):
        clsas.reconstruct(ds, grid, backend="numpy", max_memory="1MB")


@needs_opencl
def test_several_devices_share_the_tiles(scene, reference):
    """The same OpenCL device listed twice and the NumPy twin beside it: every tile formed once,
    the image equal to one device's, each entry's tiles and throughput reported."""
    from clsas import cl

    ds, grid = scene
    dev = cl.get_queue().device
    image = clsas.reconstruct(ds, grid, backend="auto", device=[dev, dev, "numpy"], formation="bp",
                              tile_shape=(2, 17, 17))
    ref = reference["numpy"].values
    assert np.abs(image.values - ref).max() <= TOL["backproject"] * np.abs(ref).max()
    devices = image.provenance["tiles"]["devices"]
    assert sum(d["tiles"] for d in devices.values()) == image.provenance["tiles"]["count"]
    assert all(d["pairs_per_s"] > 0 for d in devices.values())


def test_several_numpy_devices(scene, reference):
    ds, grid = scene
    image = clsas.reconstruct(ds, grid, backend="numpy", device=["numpy", "numpy"], tile_shape=(3, 17, 17))
    _same(image.values, reference["numpy"].values)


@pytest.mark.parametrize("formation", ["ffbp", "omega-k"])
def test_fast_formations_tile_by_tile(scene, formation):
    """A fast formation's tile is that formation's image of the tile."""
    ds, grid = scene
    shape = (11, 17, 17)
    image = clsas.reconstruct(ds, grid, backend="numpy", formation=formation, tile_shape=shape)
    tile = tile_grid(grid, shape)[1]
    alone = clsas.reconstruct(ds, tile.grid, backend="numpy", formation=formation)
    np.testing.assert_allclose(image.values[tile.slices], alone.values, rtol=0, atol=1e-9 * np.abs(alone.values).max())


def test_cli_reconstruct_out_of_core(tmp_path, capsys):
    from conftest import SCENE_TOML as SCENE

    from clsas.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    data = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(data), "-q", "--backend", "numpy"]) == 0
    assert main(["reconstruct", str(data), "-q", "--backend", "numpy", "--out", str(tmp_path / "mem.h5")]) == 0
    assert main(["reconstruct", str(data), "-q", "--png", "--backend", "numpy", "--max-memory", "4GB",
                 "--out", str(tmp_path / "tiled.h5")]) == 0
    out = capsys.readouterr().out
    assert "peak (+0.020, -0.010, 0.600) m" in out
    tiled, mem = clsas.Image.open(tmp_path / "tiled.h5"), clsas.Image.load(tmp_path / "mem.h5")
    np.testing.assert_allclose(tiled.values[()], mem.values, rtol=0, atol=1e-6 * np.abs(mem.values).max())
    assert tiled.provenance["source_path"] == "scan.h5" and tiled.provenance["compression"] == "matched"
    assert (tmp_path / "tiled.png").stat().st_size > 1000
    assert main(["reconstruct", str(data), "-q", "--max-memory", "lots", "--out", str(tmp_path / "x.h5")]) == 2
    assert main(["reconstruct", str(data), "-q", "--max-memory", "1GB", "--out", str(tmp_path / "x.txt")]) == 2


def test_zarr_store_equals_the_hdf5_file_and_resumes(scene, reference, tmp_path):
    pytest.importorskip("zarr", minversion="3")
    ds, grid = scene
    shape = (3, 17, 17)

    def stop_after_2(done, total):
        if done >= 2:
            raise _Stop

    with pytest.raises(_Stop):
        clsas.reconstruct(ds, grid, backend="numpy", out=tmp_path / "i.zarr", tile_shape=shape, progress=stop_after_2)
    with pytest.raises(ValueError, match="unfinished"):
        clsas.Image.open(tmp_path / "i.zarr")
    image = clsas.reconstruct(ds, grid, backend="numpy", out=tmp_path / "i.zarr", tile_shape=shape)
    assert image.lazy and image.provenance["tiles"]["formed_now"] == len(tile_grid(grid, shape)) - 2
    ref = reference["numpy"]
    np.testing.assert_array_equal(image.values[:], ref.values.astype(np.complex64))
    assert [p.index for p in image.peaks(3, 0.03)] == [p.index for p in ref.peaks(3, 0.03)]
    again = clsas.pipeline.tiling.update_attrs(image, {"note": "kept"})
    assert clsas.Image.open(tmp_path / "i.zarr").provenance["note"] == "kept" and again.lazy


def test_missing_zarr_names_the_extra(scene, tmp_path, monkeypatch):
    import sys

    ds, grid = scene
    monkeypatch.setitem(sys.modules, "zarr", None)
    with pytest.raises(ImportError, match=r"zarr\]"):
        clsas.reconstruct(ds, grid, backend="numpy", out=tmp_path / "x.zarr")


def test_the_tally_keeps_each_variants_worst_bound():
    """A tiled image states, per bp kernel variant, the largest bound any of its tiles ran under
    (the range expansion's depends on each tile's geometry)."""
    from clsas.pipeline.tiling.run import TileTally

    tally = TileTally()
    for bound in (1e-4, 3e-4, 2e-4):
        tally.add("dev", 1.0, 1.0, bp={"variant": "range_expansion", "error_bound": bound, "records": "kept"})
    tally.add("dev", 1.0, 1.0, bp={"variant": "plain", "error_bound": None, "records": "kept"})
    assert tally.variants == {"range_expansion": 3, "plain": 1}
    assert tally.bounds == {"range_expansion": 3e-4, "plain": None} and tally.records == {"kept": 4}
