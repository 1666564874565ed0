"""Tiles through bp's resident OpenCL path: the profiles' carrier records made on the device once
and kept for every tile, one plan for every tile, the next tile's kernels overlapping the last
tile's read back; each against the untiled image."""

import numpy as np
import pytest
from conftest import TOL, needs_opencl, small_dataset

import clsas
from clsas import cl
from clsas.pipeline.tiling import TiledRequest, form_tiled, tile_grid
from clsas.pipeline.tiling.tiles import profile_bytes

pytestmark = needs_opencl


@pytest.fixture(scope="module")
def scene():
    ds = small_dataset([[0.02, -0.01, 0.5], [-0.05, 0.04, 0.45]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.01)
    whole = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    return ds, grid, whole


def _close(values, ref):
    assert np.abs(values - ref).max() <= TOL["backproject"] * np.abs(ref).max()


def _bp_plans():
    """The bp plans :func:`clsas.cl.reused` holds now."""
    return cl.reused_plans("backproject")


def test_tiles_take_the_records_once_and_equal_the_whole_image(scene):
    """The first tile makes the records from the compression's rows on the device, every other
    tile keeps them; one plan (buffers of one tile, not the grid) forms them all."""
    ds, grid, whole = scene
    assert whole.provenance["bp"]["records"] == "rows"
    cl.release_reused()
    shape = (5, 9, 17)
    tiled = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", tile_shape=shape)
    n = len(tile_grid(grid, shape))
    assert tiled.provenance["tiles"]["records"] == {"rows": 1, "kept": n - 1}
    assert tiled.provenance["tiles"]["overlap"] is True
    # the kernel every tile ran and its stated error (the exact float kernel: no bound)
    assert tiled.provenance["tiles"]["bp_variants"] == {"plain": {"tiles": n, "error_bound": None}}
    _close(tiled.values, whole.values)
    plans = _bp_plans()
    # one tile's voxels, padded to whole work-groups (a tuned local size pads further)
    assert len(plans) == 1 and plans[0].capacity < 2 * int(np.prod(shape)) + plans[0].per_group
    assert 2 * int(np.prod(shape)) < grid.size
    assert plans[0].image_buffers == 2  # two image buffers took turns


def test_tiles_in_memory_read_no_profile_back(scene, monkeypatch):
    """Tiles formed in memory on the device that compressed the profiles take them from the
    device rows for every tile: sizing the tiles and keeping the records read nothing back."""
    from clsas.cl import DeviceRows

    ds, grid, whole = scene
    reads = []
    read = DeviceRows._read

    def counted(rows):
        reads.append(rows.n_rows)
        return read(rows)

    monkeypatch.setattr(DeviceRows, "_read", counted)
    prof = clsas.compress(ds, backend="opencl")
    shape = (5, 9, 17)
    tiled = form_tiled(prof, grid, "bp", {}, cl.select("opencl"), TiledRequest(tile_shape=shape))
    n = len(tile_grid(grid, shape))
    assert tiled.provenance["tiles"]["records"] == {"rows": 1, "kept": n - 1}
    unread = profile_bytes(prof)  # what sizing the tiles counts for them
    assert reads == [] and not prof.on_device.is_read, "the profiles were read back"
    _close(tiled.values, whole.values)
    assert prof.data.dtype == np.complex64 and profile_bytes(prof) == unread  # the same count once read


def test_out_of_core_within_a_budget_is_resident_and_equals_the_whole_image(scene, tmp_path):
    """A file formed under a memory budget: several tiles, each from the records kept on the
    device, the file equal to the whole in-memory image; the device holds one tile's buffers."""
    ds, _, _ = scene
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.005)  # 45k voxels, 2.5 MB
    whole = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    # h5py, plans
    clsas.reconstruct(ds, grid, backend="opencl", formation="bp", out=tmp_path / "warm.h5", tile_shape=(10, 33, 33))
    cl.release_reused()
    budget = clsas.pipeline.tiling.rss_bytes() + 2e6
    image = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", out=tmp_path / "image.h5", max_memory=budget)
    t = image.provenance["tiles"]
    assert t["count"] > 1 and t["records"] == {"rows": 1, "kept": t["count"] - 1}
    _close(image.values[()], whole.values)
    (plan,) = _bp_plans()
    assert plan.capacity < int(np.prod(t["shape"])) + plan.per_group  # one tile, padded to whole work-groups


def test_writeable_profiles_are_uploaded_once(scene):
    """Profiles made elsewhere (writeable data, no device rows): uploaded for the first tile,
    the records kept for the others; the same image as the whole grid's."""
    ds, grid, whole = scene
    prof = clsas.compress(ds, backend="numpy", gate_s=whole.plan.gate_s)
    given = clsas.Profiles.from_range_profiles(prof.data, tau0_s=prof.tau0_s, dtau_s=prof.dtau_s,
                                               tx_positions=prof.tx_positions, rx_positions=prof.rx_positions,
                                               c_mps=prof.c_mps, fc_hz=prof.fc_hz, baseband=True)
    assert given.data.flags.writeable and given.on_device is None
    alone = clsas.backproject(given, grid, backend="opencl")
    assert alone.provenance["bp"]["records"] == "uploaded"
    tiled = clsas.reconstruct(given, grid, backend="opencl", formation="bp", tile_shape=(11, 17, 5))
    n = tiled.provenance["tiles"]["count"]
    assert tiled.provenance["tiles"]["records"] == {"uploaded": 1, "kept": n - 1}
    assert given.data.flags.writeable  # the caller's array is left as it was
    _close(tiled.values, alone.values)
    _close(tiled.values, whole.values)


@pytest.mark.parametrize("shape", [(5, 17, 17), (4, 9, 5), (21, 17, 17)], ids=lambda s: "x".join(map(str, s)))
def test_overlapped_tiles_equal_the_sequential_ones(scene, shape):
    """Tiles formed with the next tile's kernels overlapping the last one's read back, and one
    after the other: the same values to the last bit (the same kernels on the same records), in
    memory and equal to the whole image."""
    ds, grid, whole = scene
    prof = clsas.compress(ds, backend="opencl", gate_s=whole.plan.gate_s)
    sel = cl.select("opencl")
    runs = {}
    for overlap in (True, False):
        image = form_tiled(prof, grid, "bp", {}, sel, TiledRequest(tile_shape=shape, overlap=overlap))
        # one tile (the whole grid) has nothing to overlap with
        assert image.provenance["tiles"]["overlap"] is (overlap and image.provenance["tiles"]["count"] > 1)
        runs[overlap] = image.values
    assert np.array_equal(runs[True], runs[False])
    _close(runs[True], whole.values)


@pytest.fixture(params=["transfer queue", "copy queue"])
def read_queue(request, monkeypatch):
    """The default queue the images are read on (the plan's own on a CPU device), and a second
    queue of the same device (a GPU's default), run here on the CPU runtimes."""
    if request.param == "copy queue":
        from clsas.formation import bp_opencl

        monkeypatch.setattr(bp_opencl, "transfer_queue", cl.copy_queue)
    return request.param


def test_transfer_queue_is_the_queue_on_a_cpu_and_the_copy_queue_a_second_one():
    q = cl.get_queue()
    copy = cl.copy_queue(q)
    assert copy is not q and copy.context == q.context and copy.device == q.device and cl.copy_queue(q) is copy
    assert cl.transfer_queue(q) is (q if cl.is_cpu(q.device) else copy)


def test_overlap_on_either_read_queue_equals_the_sequential_tiles(scene, read_queue):
    ds, grid, whole = scene
    prof = clsas.compress(ds, backend="opencl", gate_s=whole.plan.gate_s)
    sel = cl.select("opencl")
    runs = [form_tiled(prof, grid, "bp", {}, sel, TiledRequest(tile_shape=(3, 17, 17), overlap=o)).values
            for o in (True, False)]
    assert np.array_equal(runs[0], runs[1])
    _close(runs[0], whole.values)


def test_pending_images_collected_out_of_order(read_queue):
    """Three tiles enqueued before any is collected (more than the two image buffers), then
    collected last first: each equals its own image formed alone (a buffer is not overwritten
    before its read back ends)."""
    from clsas.formation.bp import Backprojector

    ds = small_dataset([[0.0, 0.0, 0.5]], nx=5, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.4, 0.6), 0.01)
    prof = clsas.compress(ds, backend="opencl")
    tiles = tile_grid(grid, (7, 21, 21))
    alone = [Backprojector(t.grid, backend="opencl")(prof).values for t in tiles]
    pending = [Backprojector(t.grid, backend="opencl").enqueue(prof) for t in tiles]
    for p, want in reversed(list(zip(pending, alone, strict=True))):
        assert np.array_equal(p.result().values, want)


_RSS_RUN = """
import os, sys, tempfile
sys.path.insert(0, {tests!r})
import clsas
from conftest import small_dataset
from clsas.pipeline.tiling import peak_rss_bytes, rss_bytes
ds = small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)
warm = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.01)
d = tempfile.mkdtemp()
clsas.reconstruct(ds, warm, backend="opencl", formation="bp", out=os.path.join(d, "warm.h5"), tile_shape=(5, 17, 17))
grid = clsas.VoxelGrid.from_bounds((-0.25, 0.25), (-0.25, 0.25), (0.3, 0.8), 0.005)
budget = rss_bytes() + 25e6
# the tiles the budget gives; the first run also compiles what the runtime specialises for their launches
first = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", out=os.path.join(d, "first.h5"),
                          max_memory=budget)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")  # the peak resident memory (VmHWM) restarts from the current one
shape = tuple(first.provenance["tiles"]["shape"])
image = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", out=os.path.join(d, "again.h5"), tile_shape=shape)
t = image.provenance["tiles"]
print(grid.size, t["count"], t["records"].get("kept", 0), budget, peak_rss_bytes())
"""


@pytest.mark.slow  # a child process that forms 101³ voxels twice; the margin is the budget's 25 MB
def test_out_of_core_peak_memory_stays_within_the_budget():
    """In a process of its own: a 101³ grid whose image alone (56 bytes a voxel on OpenCL) would
    take more than twice the 25 MB the budget leaves, formed into a file in tiles through the
    resident path with overlap in the tiles the budget gives, twice; the process's peak resident
    memory during the second run stays under the budget (the first also holds the runtime's
    compilation for these launches: PoCL's compiler took up to 25 MB more)."""
    import subprocess
    import sys
    from pathlib import Path

    tests = str(Path(__file__).resolve().parents[2])
    res = subprocess.run([sys.executable, "-c", _RSS_RUN.format(tests=tests)], capture_output=True, text=True,
                         timeout=300, cwd=str(Path(tests).parent))
    assert res.returncode == 0, res.stderr[-3000:]
    voxels, count, kept, budget, peak = (float(x) for x in res.stdout.split()[-5:])
    assert voxels * 56 > 2 * 25e6 and count > 1 and kept == count - 1
    assert peak <= budget, f"peak RSS {peak / 1e6:.0f} MB over the budget {budget / 1e6:.0f} MB"


def test_tiles_formed_in_turn_take_at_most_one_grid_ahead(scene):
    """form_in_turn takes each grid only as the previous image is handed on (bp's form_tiles holds
    one tile's kernels enqueued beside the last one's read back, no more), so that threads sharing
    a queue of tiles keep sharing it; the overlapped tiles equal the sequential ones."""
    from clsas.pipeline.tiling.tiles import form_in_turn

    ds, grid, whole = scene
    prof = clsas.compress(ds, backend="opencl", gate_s=whole.plan.gate_s)
    tiles = tile_grid(grid, (3, 17, 17))
    for overlap in (True, False):
        taken = []

        def grids(taken=taken):
            for t in tiles:
                taken.append(t.index)
                yield t.grid

        handed = 0
        for vals, _, seconds, bp, overlapped in form_in_turn(prof, grids(), "bp", {}, cl.select("opencl"),
                                                             overlap=overlap):
            handed += 1
            assert len(taken) <= handed + (1 if overlap else 0), (len(taken), handed)
            # each tile's kernels beside the previous tile's read back: all but the first
            assert overlapped is (overlap and handed > 1) and seconds >= 0
            assert bp["records"] in ("uploaded", "rows", "kept")
            _close(vals, whole.values[tiles[handed - 1].slices])
        assert handed == len(tiles) == len(taken)


@pytest.mark.parametrize("overlap", [True, False], ids=["overlapped", "sequential"])
def test_several_device_threads_form_their_tiles_in_turn(scene, overlap):
    """Two entries of one OpenCL device (two threads sharing its queue, taking turns on it): each
    thread forms the tiles it takes in turn (overlapped where asked), every tile once, the records
    made once per thread and kept for its other tiles; the image equals the untiled one within
    bp's tolerance."""
    ds, grid, whole = scene
    prof = clsas.compress(ds, backend="opencl", gate_s=whole.plan.gate_s)
    dev = cl.get_queue().device
    shape = (2, 17, 17)
    image = form_tiled(prof, grid, "bp", {}, cl.select("opencl"),
                       TiledRequest(tile_shape=shape, devices=(dev, dev), overlap=overlap))
    t = image.provenance["tiles"]
    assert t["overlap"] is overlap
    assert sum(d["tiles"] for d in t["devices"].values()) == t["count"] == len(tile_grid(grid, shape))
    assert sum(t["records"].values()) == t["count"] and t["records"].get("kept", 0) >= t["count"] - 2, t
    _close(image.values, whole.values)
