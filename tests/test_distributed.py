"""Reconstruction on a Dask cluster (clsas.tiling.dask): a LocalCluster of processes, no external service."""

import logging
import os
import signal
import subprocess
import sys
from contextlib import contextmanager

import numpy as np
import pytest
from conftest import small_dataset

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
    import clsas.tiling.dask  # noqa: F401 - imported with distributed present, as it would be in use

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
    from clsas.tiling.dask import OpenCLDevicePlugin, worker_device

    with pytest.raises(ValueError, match="devices"):
        OpenCLDevicePlugin([])
    client.register_plugin(OpenCLDevicePlugin(["numpy"]))
    try:
        assert set(client.run(worker_device).values()) == {"numpy"}
    finally:
        client.unregister_worker_plugin(OpenCLDevicePlugin.name)
    assert set(client.run(worker_device).values()) == {None}


def test_scheduler_address_from_the_command_line(client, tmp_path, capsys):
    from test_cli import SCENE

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


def _kill_one_worker_mid_run(scene, client):
    ds, grid, ref = scene
    pids = client.run(os.getpid)
    victim = sorted(pids.values())[0]
    killed = []

    def kill_once(done, total):
        if done >= 1 and not killed:
            os.kill(victim, signal.SIGKILL)
            killed.append(victim)

    image = clsas.reconstruct(ds, grid, backend="numpy", client=client, tile_shape=(2, 17, 17), progress=kill_once)
    assert killed, "the run ended before a worker could be killed"
    np.testing.assert_allclose(image.values, ref.values, rtol=0, atol=1e-12 * np.abs(ref.values).max())
    assert image.provenance["tiles"]["formed_now"] == image.provenance["tiles"]["count"]
