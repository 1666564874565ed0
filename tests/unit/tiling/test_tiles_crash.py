"""Out-of-core HDF5 files survive a writer killed mid-run (clsas.pipeline.tiling.store): a tile is marked
done only after its values are flushed, a file killed at any moment opens, and the run started
again forms exactly the tiles not marked, giving the image an uninterrupted run gives."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import clsas

pytestmark = pytest.mark.timeout(300)

TESTS = Path(__file__).resolve().parents[2]  # conftest.py's folder
TILE = (1, 9, 17)  # 21 tiles of one x-plane each

# the writer: the scene of `scene` below, formed tile by tile into argv[1]; with argv[2] == "mid-tile"
# it writes half of tile 3's values, flushes them, and kills itself before the tile is marked; with
# "stepped" it waits after each tile for a line on its stdin, so that the test says how many tiles
# it forms before a kill from outside
WRITER = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, {tests!r})
    from conftest import small_dataset
    import clsas
    from clsas.pipeline.tiling import store

    if sys.argv[2] == "mid-tile":
        whole = store.TileFile.write

        def write(self, tile, values):
            if tile.index == 3:
                half = values.reshape(tile.grid.shape)[:, :4]
                self._f["values"][tile.slices[0], 0:4, :] = half
                self._f.flush()
                os.kill(os.getpid(), signal.SIGKILL)
            whole(self, tile, values)

        store.TileFile.write = write
    ds = small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.04, 0.04), (0.4, 0.56), 0.01)

    def progress(done, total):
        print("tile", done, total, flush=True)
        if sys.argv[2] == "stepped":
            sys.stdin.readline()

    clsas.reconstruct(ds, grid, backend="numpy", out=sys.argv[1], tile_shape={tile!r}, progress=progress)
""").format(tests=str(TESTS), tile=TILE)


@pytest.fixture(scope="module")
def scene():
    from conftest import small_dataset

    ds = small_dataset([[0.02, -0.01, 0.5]], nx=6, ny=5)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.04, 0.04), (0.4, 0.56), 0.01)
    return ds, grid, clsas.reconstruct(ds, grid, backend="numpy").values


def _writer(path, mode="run") -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS.parent), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-c", WRITER, str(path), mode], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _marked(path) -> np.ndarray:
    """The tiles the file marks done (the file must open: a kill may not corrupt it)."""
    with h5py.File(path, "r") as f:
        return f["tiles_done"][()].astype(bool)


def _check_marked_tiles(path, ref) -> np.ndarray:
    """Every tile marked done holds its whole, final values."""
    from clsas.pipeline.tiling import tile_grid

    done = _marked(path)
    with h5py.File(path, "r") as f:
        values = f["values"]
        for t in tile_grid(clsas.VoxelGrid(f["x_m"][()], f["y_m"][()], f["z_m"][()]), TILE):
            if done[t.index]:
                np.testing.assert_allclose(values[t.slices], ref[t.slices], rtol=0, atol=1e-6 * np.abs(ref).max())
    return done


def test_a_writer_killed_mid_tile_resumes_with_the_tile_formed_again(scene, tmp_path):
    ds, grid, ref = scene
    path = tmp_path / "image.h5"
    proc = _writer(path, "mid-tile")
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == -signal.SIGKILL, err
    done = _check_marked_tiles(path, ref)
    assert list(np.flatnonzero(done)) == [0, 1, 2]  # tile 3 was half-written, not marked
    with h5py.File(path, "r") as f:
        assert not f.attrs["complete"]
        half = f["values"][3, 0:4, :]
    assert np.abs(half).max() > 0  # its half did reach the file (the kill came after the flush)
    image = clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=TILE)
    tiles = image.provenance["tiles"]
    assert (tiles["resumed"], tiles["formed_now"]) == (3, tiles["count"] - 3)
    np.testing.assert_allclose(image.values[()], ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    assert not path.with_name(path.name + ".part").exists()


@pytest.mark.slow
def test_a_writer_killed_at_random_moments_still_gives_the_image(scene, tmp_path):
    """SIGKILL from outside at three moments of a run: after 1, 3 and 5 more tiles, at a random
    delay into the next one (the writer forms one tile per line the test sends it, so the kill
    lands in that tile or in the wait after it, never after the run's end); the file opens each
    time, its marked tiles are whole, and the last run, resumed in this process, gives the image
    of an uninterrupted run."""
    ds, grid, ref = scene
    path = tmp_path / "image.h5"
    rng = np.random.default_rng(0)
    marked = 0
    for more in (1, 3, 5):
        proc = _writer(path, "stepped")
        seen = 0
        for line in proc.stdout:  # the first line is the tiles already done
            seen += line.startswith("tile ")
            proc.stdin.write("\n")  # form the next tile
            proc.stdin.flush()
            if seen > more:
                break
        time.sleep(float(rng.uniform(0, 0.02)))  # somewhere in that tile (~15 ms here) or the wait after it
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=60)
        done = _check_marked_tiles(path, ref)
        assert marked + more <= done.sum() <= marked + more + 1
        marked = int(done.sum())
    image = clsas.reconstruct(ds, grid, backend="numpy", out=path, tile_shape=TILE)
    assert image.provenance["tiles"]["resumed"] == marked
    np.testing.assert_allclose(image.values[()], ref, rtol=0, atol=1e-6 * np.abs(ref).max())
