"""Reconstruction on a Dask cluster (clsas.pipeline.tiling.dask): a LocalCluster of processes, no external service."""

import logging
import os
import signal
import subprocess
import sys
from contextlib import contextmanager

import numpy as np
import pytest
from conftest import TOL, needs_opencl, small_dataset

import clsas

# a cluster that stops answering fails its test after 5 minutes instead of holding the run (pytest-timeout)
pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def scene():
    ds = small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.01)
    return ds, grid, clsas.reconstruct(ds, grid, backend="numpy")


@contextmanager
def _local_cluster():
    distributed = pytest.importorskip("distributed")
    import dask

    # a gather from the killed worker gives up after 5 s instead of the default 30 s
    with dask.config.set({"distributed.comm.timeouts.connect": "5s"}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                     silence_logs=logging.ERROR) as cluster, distributed.Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def client():
    with _local_cluster() as c:
        yield c


def test_missing_distributed_names_the_extra(scene, monkeypatch):
    import clsas.pipeline.tiling.dask  # noqa: F401 - imported with distributed present, as it would be in use

    ds, grid, _ = scene
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"distributed\]"):
        clsas.reconstruct(ds, grid, backend="numpy", client="tcp://127.0.0.1:1")


def test_cluster_image_equals_the_single_process_one(scene, client, tmp_path):
    ds, grid, ref = scene
    seen = []
    image = clsas.reconstruct(ds, grid, backend="numpy", client=client, progress=lambda d, t: seen.append((d, t)))
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=1e-12 * np.abs(ref.values).max())
    tiles = image.provenance["tiles"]
    assert tiles["count"] >= 8  # at least 4 tiles per worker
    assert seen[-1] == (tiles["count"], tiles["count"])
    assert sum(d["tiles"] for d in tiles["devices"].values()) == tiles["count"]
    out = clsas.reconstruct(ds, grid, backend="numpy", client=client, out=tmp_path / "cluster.h5",
                            tile_shape=(5, 9, 17))
    assert out.lazy
    np.testing.assert_allclose(out.values[()], ref.values, rtol=0, atol=1e-6 * np.abs(ref.values).max())


def test_worker_device_plugin(client):
    from clsas.pipeline.tiling.dask import OpenCLDevicePlugin, worker_device

    with pytest.raises(ValueError, match="devices"):
        OpenCLDevicePlugin([])
    client.register_plugin(OpenCLDevicePlugin(["numpy"]))
    try:
        assert set(client.run(worker_device).values()) == {"numpy"}
    finally:
        client.unregister_worker_plugin(OpenCLDevicePlugin.name)
    assert set(client.run(worker_device).values()) == {None}


def test_sparse_step_on_the_cluster_equals_the_serial_one(client):
    """The per-recording sparse step in blocks on the workers: the same echoes, profiles and image."""
    ds = small_dataset([[0.02, -0.01, 0.5], [-0.03, 0.02, 0.53]], nx=4, ny=3, snr_db=30)
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.06), (-0.05, 0.05), (0.46, 0.56), 0.01)
    serial = clsas.reconstruct(ds, grid, "bpdn", backend="numpy")
    seen = []
    on = clsas.reconstruct(ds, grid, "bpdn", backend="numpy", client=client,
                           progress=lambda d, t: seen.append((d, t)))
    assert (ds.n_meas, ds.n_meas) in seen  # the sparse step reported its recordings
    assert len(on.echoes) == len(serial.echoes) == ds.n_meas
    assert sum(len(e) for e in serial.echoes) >= ds.n_meas  # echoes were found, not an empty comparison
    for a, b in zip(on.echoes, serial.echoes, strict=True):
        assert (a.status, a.fallback, len(a)) == (b.status, b.fallback, len(b))
        np.testing.assert_allclose(a.delays_s, b.delays_s, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.amplitudes, b.amplitudes, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(on.values, serial.values, rtol=0, atol=1e-9 * np.abs(serial.values).max())


def test_results_are_awaited_on_the_runs_own_client_loop(scene, client, monkeypatch):
    """as_completed given no loop waits on the *default* client's; with two clients in one process a
    run on the other one waited forever (seen once in 12 alternated runs), so the loop is passed."""
    import distributed

    ds, grid, ref = scene
    loops = []
    real = distributed.as_completed

    def spy(*args, **kwargs):
        loops.append(kwargs.get("loop"))
        return real(*args, **kwargs)

    monkeypatch.setattr(distributed, "as_completed", spy)
    image = clsas.reconstruct(ds, grid, backend="numpy", client=client, tile_shape=(11, 17, 17))
    assert loops and all(loop is client.loop for loop in loops)
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=1e-12 * np.abs(ref.values).max())


def test_sparse_blocks():
    from clsas.sparse.parallel import blocks

    assert blocks(10, 2) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    assert blocks(3, 4) == [(0, 1), (1, 2), (2, 3)]
    assert blocks(0, 2) == []
    with pytest.raises(ValueError, match="n_workers"):
        blocks(5, 0)


def test_sparse_step_refuses_a_client_that_is_not_one():
    from clsas.sparse.profiles import superres_profiles

    ds = small_dataset([[0.0, 0.0, 0.5]], nx=2, ny=1)
    with pytest.raises(TypeError, match="client"):
        superres_profiles(ds, np.tile([2.5e-3, 3.5e-3], (ds.n_meas, 1)), "bpdn", client=42)


def _cpu_devices(min_units=2):
    try:
        import pyopencl as pcl

        return [d for p in pcl.get_platforms() for d in p.get_devices()
                if d.type & pcl.device_type.CPU and d.max_compute_units >= min_units
                and d.partition_max_sub_devices >= 2]
    except Exception:  # noqa: BLE001 - no OpenCL at all: the test skips
        return []


@pytest.mark.skipif(not _cpu_devices(), reason="no OpenCL CPU device of 2+ compute units that can be split")
def test_a_worker_of_one_thread_gets_one_compute_unit(client):
    """Device fission: a 1-thread worker's CPU device is a sub-device of 1 compute unit (not every core),
    and the provenance says how many compute units each worker used."""
    import pyopencl as pcl

    from clsas.pipeline.tiling.dask import OpenCLDevicePlugin, worker_selection

    dev = _cpu_devices()[0]
    spec = next(f"{i}:{j}" for i, p in enumerate(pcl.get_platforms())
                for j, d in enumerate(p.get_devices()) if d.int_ptr == dev.int_ptr)
    whole, units = worker_selection("opencl", spec, threads=None)
    assert units == dev.max_compute_units and whole.queue.device.int_ptr == dev.int_ptr
    one, units = worker_selection("opencl", spec, threads=1)
    assert units == 1 and one.queue.device.max_compute_units == 1
    assert one.queue.device.int_ptr != dev.int_ptr
    assert worker_selection("opencl", spec, threads=1)[0].queue is one.queue  # memoised per process

    ds = small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.4, 0.56), 0.01)
    ref = clsas.reconstruct(ds, grid, backend="opencl", device=spec, formation="bp")
    client.register_plugin(OpenCLDevicePlugin([spec]))
    try:
        image = clsas.reconstruct(ds, grid, backend="opencl", client=client, formation="bp")
    finally:
        client.unregister_worker_plugin(OpenCLDevicePlugin.name)
    devices = image.provenance["tiles"]["devices"]
    assert devices and all(d["compute_units"] == 1 for d in devices.values()), devices
    assert all(", 1 CU)" in name for name in devices)
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=1e-5 * np.abs(ref.values).max())


@needs_opencl
def test_workers_form_their_tiles_from_records_uploaded_once(scene, client):
    """On OpenCL each worker uploads the profiles it was sent and makes their carrier records on
    its device for its first tile, and keeps them for every other tile it forms (the counts are
    the tiles' own provenance); the image equals the single-process one within bp's tolerance."""
    ds, grid, _ = scene
    ref = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    image = clsas.reconstruct(ds, grid, backend="opencl", formation="bp", client=client)
    tiles = image.provenance["tiles"]
    workers = len(tiles["devices"])
    assert tiles["count"] >= 8 and 1 <= workers <= 2
    assert tiles["records"] == {"uploaded": workers, "kept": tiles["count"] - workers}, tiles
    assert tiles["overlap"] is True  # runs of tiles per task, each formed with the next one's kernels beside it
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=TOL["backproject"] * np.abs(ref.values).max())


def test_tile_runs_give_every_worker_work():
    from clsas.pipeline.tiling.dask import MAX_TILES_PER_TASK, tile_runs

    assert tile_runs(list(range(8)), 2) == [[0, 1], [2, 3], [4, 5], [6, 7]]
    assert tile_runs(list(range(4)), 2) == [[0], [1], [2], [3]]  # two tasks per worker before runs of two
    assert tile_runs([0, 3, 4, 9, 10], 1) == [[0, 3], [4, 9], [10]]  # runs of what is pending, across gaps
    assert tile_runs([], 3) == []
    for n, workers in [(1, 1), (7, 3), (40, 2), (100, 1), (9, 16)]:
        runs = tile_runs(list(range(n)), workers)
        assert [i for r in runs for i in r] == list(range(n))  # every tile once, in order
        assert all(1 <= len(r) <= MAX_TILES_PER_TASK for r in runs)
        assert len(runs) >= min(n, 2 * workers)
    with pytest.raises(ValueError, match="workers"):
        tile_runs([0], 0)


class _Stop(Exception):
    pass


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=needs_opencl)])
def test_a_run_interrupted_inside_a_task_resumes_with_its_other_tiles(scene, client, tmp_path, monkeypatch, backend):
    """Tasks of several tiles, the run stopped after the first tile of the first task that came back
    (its other tiles formed but not written): the rerun forms every tile not written, each tile is
    written to the file once over both runs, and the file equals the untiled image (to bp's tolerance
    on OpenCL)."""
    from clsas.pipeline.tiling.dask import tile_runs
    from clsas.pipeline.tiling.store import TileFile

    ds, grid, _ = scene
    ref = clsas.reconstruct(ds, grid, backend=backend, formation="bp")
    shape = (2, 9, 17)
    n = len(clsas.pipeline.tiling.tile_grid(grid, shape))
    assert all(len(r) >= 2 for r in tile_runs(list(range(n)), 2))  # the first task back holds 2+ tiles
    written = []
    real = TileFile.write
    monkeypatch.setattr(TileFile, "write", lambda self, tile, values: (written.append(tile.index),
                                                                      real(self, tile, values)))

    def stop_after_1(done, total):
        if done >= 1:
            raise _Stop

    path = tmp_path / f"resume-{backend}.h5"
    with pytest.raises(_Stop):
        clsas.reconstruct(ds, grid, backend=backend, client=client, out=path, tile_shape=shape,
                          formation="bp", progress=stop_after_1)
    assert len(written) == 1
    seen = []
    image = clsas.reconstruct(ds, grid, backend=backend, client=client, out=path, tile_shape=shape,
                              formation="bp", progress=lambda d, t: seen.append(d))
    t = image.provenance["tiles"]
    assert seen[0] == 1 and t["formed_now"] == n - 1 and t["resumed"] == 1
    assert sorted(written) == list(range(n))  # each tile written once over both runs
    if backend == "opencl":
        assert t["overlap"] is True
    tol = TOL["backproject"] if backend == "opencl" else 1e-6
    np.testing.assert_allclose(image.values[()], ref.values, rtol=0, atol=tol * np.abs(ref.values).max())


def test_scheduler_address_from_the_command_line(client, tmp_path, capsys):
    from conftest import SCENE_TOML as SCENE

    from clsas.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    data = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(data), "-q", "--backend", "numpy"]) == 0
    address = client.scheduler.address
    # the command in its own process, as a user runs it (a second Client in this process, beside the
    # fixture's, could wait forever on as_completed)
    res = subprocess.run([sys.executable, "-m", "clsas.cli", "reconstruct", str(data), "-q", "--backend", "numpy",
                          "--scheduler", address, "--out", str(tmp_path / "image.h5")],
                         capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "peak (+0.020, -0.010, 0.600) m" in res.stdout
    image = clsas.Image.open(tmp_path / "image.h5")
    assert image.provenance["tiles"]["count"] >= 4 and image.provenance["source_path"] == "scan.h5"


def test_a_worker_killed_mid_run_still_gives_the_same_image(scene):
    """Last in the file, on a cluster of its own: the killed worker's restart does not meet other tests."""
    with _local_cluster() as client:
        _kill_one_worker_mid_run(scene, client)


HELD = "clsas-test-victim-holds-a-tile"


def _hold_the_first_tile():
    """Run on the victim worker: its first task says so (a cluster event) and never returns, so
    that the kill lands while it holds a tile, and the run cannot end before the kill."""
    import threading

    import distributed

    from clsas.pipeline.tiling import dask as tiling_dask

    def held(*args, **kwargs):
        distributed.Event(HELD).set()
        threading.Event().wait()

    tiling_dask._tiles_task = held  # the task is sent by name and found here, in this process


def _kill_one_worker_mid_run(scene, client):
    import distributed

    ds, grid, ref = scene
    victim_addr, victim = min(client.run(os.getpid).items(), key=lambda item: item[1])
    client.run(_hold_the_first_tile, workers=[victim_addr])
    holds = distributed.Event(HELD, client=client)
    killed = []

    def kill_once(done, total):
        if done >= 1 and not killed:
            assert holds.wait(timeout=120), "the victim worker never started a tile"
            os.kill(victim, signal.SIGKILL)
            killed.append(done)

    image = clsas.reconstruct(ds, grid, backend="numpy", client=client, tile_shape=(2, 17, 17), progress=kill_once)
    assert killed, "no tile was done: the victim was never killed"  # its held tile came from another worker
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=1e-12 * np.abs(ref.values).max())
    assert image.provenance["tiles"]["formed_now"] == image.provenance["tiles"]["count"]
