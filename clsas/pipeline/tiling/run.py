"""Form an image tile by tile: in one process, over several OpenCL devices, or on a Dask cluster.

Each tile is formed by the chosen formation on its own sub-grid (:func:`clsas.formation.form`),
so a tile equals an in-memory reconstruction of that tile; for ``"bp"`` a tiled image equals
the whole-grid one to rounding (float64 on NumPy; float32 on OpenCL, where the voxel positions
are computed from each tile's own origin). The tiles go to a chunked file
(:class:`~clsas.pipeline.tiling.store.TileFile`) or to an array in memory.

Several devices (``device=[...]``): one thread per device takes the next tile as soon as it is
free, so each device forms a share of the tiles proportional to its measured throughput (the
tiles and pairs/s of each are reported in ``image.provenance["tiles"]``). Each thread forms its
tiles in turn as one device does (:func:`~clsas.pipeline.tiling.tiles.form_in_turn`: bp on OpenCL
runs the next tile's kernels while the last one is read back), taking a tile from the shared
queue only as it hands the previous one on. Two entries naming the same device share its queue
and take turns on it.
"""

from __future__ import annotations

import logging
import queue as _queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ... import cl
from ...formation.guard import available_memory_bytes
from ...physics.geometry import VoxelGrid
from ...types.image import Image
from ...types.profiles import Profiles
from .store import open_store, request_digest
from .tiles import form_in_turn, profile_bytes, read_only, rss_bytes, tile_grid, tile_shape_for

__all__ = ["TiledRequest", "TileTally", "form_tiled"]

log = logging.getLogger(__name__)

_WORKER_BASE_BYTES = 400e6  # a Dask worker's own memory (Python, NumPy, pyopencl, PoCL) before a tile


@dataclass(frozen=True)
class TiledRequest:
    """What the pipeline asked of a tiled run (checked by :func:`clsas.pipeline.tiling.check_request`)."""

    out: object = None  # Path of an .h5 file, or None (the image in memory)
    max_memory: float | None = None  # bytes
    client: object = None  # a distributed.Client, a scheduler address, or None
    tile_shape: tuple[int, int, int] | None = None
    devices: tuple = ()  # several devices on this host (empty: the one selection)
    overlap: bool = True  # per device or worker: the next tile's kernels run while the last one is read and written


@dataclass
class TileTally:
    """What a tiled run's tiles report, added up: tiles and busy seconds per device (for the
    throughput each device showed), where bp took its records, the bp kernel variants with each
    one's worst stated bound, and how many tiles ran beside the previous one's read back."""

    tiles: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    pairs: dict = field(default_factory=dict)
    units: dict = field(default_factory=dict)
    records: dict = field(default_factory=dict)  # tiles per source of bp's device records
    variants: dict = field(default_factory=dict)  # tiles per bp kernel variant
    bounds: dict = field(default_factory=dict)  # bp kernel variant -> its stated error bound
    overlapped: int = 0  # tiles whose kernels ran beside the previous tile's read back

    def add(self, device: str, seconds: float, pairs: float, units: int | None = None,
            bp: dict | None = None, overlapped: bool = False) -> None:
        self.overlapped += bool(overlapped)
        bp = bp or {}
        if bp.get("records") is not None:
            self.records[bp["records"]] = self.records.get(bp["records"], 0) + 1
        if bp.get("variant") is not None:
            self.variants[bp["variant"]] = self.variants.get(bp["variant"], 0) + 1
            bound, held = bp.get("error_bound"), self.bounds.get(bp["variant"])  # the worst tile's
            self.bounds[bp["variant"]] = bound if held is None or (bound is not None and bound > held) else held
        self.tiles[device] = self.tiles.get(device, 0) + 1
        self.seconds[device] = self.seconds.get(device, 0.0) + seconds
        self.pairs[device] = self.pairs.get(device, 0.0) + pairs
        self.units[device] = units

    def report(self) -> dict:
        return {d: {"tiles": self.tiles[d], "busy_s": round(self.seconds[d], 3),
                    "pairs_per_s": self.pairs[d] / self.seconds[d] if self.seconds[d] > 0 else None,
                    "compute_units": self.units[d]}
                for d in self.tiles}


def form_tiled(profiles: Profiles, grid: VoxelGrid, formation: str, options: dict, selection: cl.Selection,
               request: TiledRequest, *, progress: Callable[[int, int], None] | None = None,
               force: bool = False) -> Image:
    """Form ``profiles`` on ``grid`` in tiles (see the module notes).

    Returns an Image whose ``values`` are in memory, or None where they went to ``request.out``
    (the pipeline then finishes the file with :func:`clsas.pipeline.tiling.finish`).
    """
    selections = [cl.select(selection.requested, d) if not _is_numpy(d) else cl.select("numpy")
                  for d in request.devices] or [selection]
    profiles = read_only(profiles)  # the device records of the first tile serve the others
    kind = "numpy" if any(not s.opencl for s in selections) else "opencl"
    n_parallel = _n_parallel(request.client, selections)
    shape = request.tile_shape or _auto_shape(grid, profiles, kind, request, n_parallel)
    tiles = tile_grid(grid, shape)
    log.info("tiles: %d of %s voxels over %d %s", len(tiles), " x ".join(map(str, shape)), n_parallel,
             "Dask workers" if request.client is not None else "device(s)")
    store = values = None
    if request.out is not None:
        store = open_store(request.out, grid, tiles, shape,
                         request_digest(profiles, grid, formation, options, kind, shape))
        pending = store.pending
    else:
        values = _image_array(grid, kind, force)
        pending = list(range(len(tiles)))
    done = len(tiles) - len(pending)
    tally = TileTally()
    t0 = time.perf_counter()
    try:
        if progress is not None:
            progress(done, len(tiles))
        for tile, vals, device, seconds, units, bp, overlapped in _run(profiles, tiles, pending, formation,
                                                                       options, selections, request, force):
            if store is not None:
                store.write(tile, vals)
            else:
                values[tile.slices] = vals
            tally.add(device, seconds, float(tile.size) * profiles.n_meas, units, bp, overlapped)
            done += 1
            if progress is not None:
                progress(done, len(tiles))
    finally:
        if store is not None:
            store.close()
    devices = sorted(tally.tiles) or [selections[0].device]
    prov = {"tiles": {"shape": list(shape), "count": len(tiles), "formed_now": len(pending),
                      "resumed": len(tiles) - len(pending), "devices": tally.report()}}
    if tally.records:  # bp's resident path: where each tile's carrier records came from
        prov["tiles"]["records"] = dict(tally.records)
        prov["tiles"]["overlap"] = tally.overlapped > 0
    if tally.variants:  # bp's kernel variants, tiles each, and the error each states
        prov["tiles"]["bp_variants"] = {k: {"tiles": n, "error_bound": tally.bounds[k]}
                                        for k, n in tally.variants.items()}
    return Image(values, grid, "bp", kind, "; ".join(devices),
                 {"form_tiles": time.perf_counter() - t0}, provenance=prov)


def _image_array(grid: VoxelGrid, kind: str, force: bool) -> np.ndarray:
    """The whole image in memory (no ``out``): refused where it would not fit, unless forced."""
    dtype = np.complex64 if kind == "opencl" else np.complex128
    need = grid.size * np.dtype(dtype).itemsize
    avail = available_memory_bytes()
    if avail is not None and need > 0.8 * avail and not force:
        raise ValueError(f"grid: the image alone needs {need / 1e9:.3g} GB, {avail / 1e9:.3g} GB available; give "
                         "out='image.h5' to form it into a file, or force=True")
    return np.zeros(grid.shape, dtype)


def _is_numpy(device) -> bool:
    return isinstance(device, str) and device == "numpy"


def _n_parallel(client, selections) -> int:
    if client is None:
        return len(selections)
    from .dask import n_workers

    return n_workers(client)


def _auto_shape(grid, profiles, kind, request: TiledRequest, n_parallel: int) -> tuple[int, int, int]:
    """Tiles within the budget, and at least 4 per worker (Dask) or device (where there are several);
    a Dask worker holds the values of the run of tiles its task returns together (``max_memory`` is
    each worker's budget there)."""
    held = 1
    if request.client is not None:
        from .dask import MAX_TILES_PER_TASK

        fixed, held = _WORKER_BASE_BYTES + profile_bytes(profiles), MAX_TILES_PER_TASK
    else:
        fixed = rss_bytes() + profile_bytes(profiles)
        if request.out is None:  # the image itself is held in memory
            fixed += grid.size * (8 if kind == "opencl" else 16)
    budget = request.max_memory
    if budget is not None and request.client is None and n_parallel > 1:
        budget = fixed + (budget - fixed) / n_parallel  # that many tiles in flight at once
    min_tiles = 4 * n_parallel if n_parallel > 1 or request.client is not None else 1
    if budget is None and request.out is not None:  # a file without a budget: tiles of a tenth of free memory
        avail = available_memory_bytes()
        budget = fixed + 0.1 * avail if avail else None
    return tile_shape_for(grid, kind, max_memory=budget, fixed_bytes=int(fixed), min_tiles=min_tiles,
                          held_tiles=held)


def _units(selection: cl.Selection) -> int | None:
    """The compute units of the selection's OpenCL device (None on NumPy)."""
    return int(selection.queue.device.max_compute_units) if selection.opencl else None


def _run(profiles, tiles, pending, formation, options, selections, request, force):
    """Yield ``(tile, values, device, seconds, compute_units, bp, overlapped)`` for each pending
    tile, as they finish (``bp``: :func:`clsas.pipeline.tiling.tiles.bp_record`;
    ``overlapped``: formed with the next tile's kernels running beside its read back)."""
    if request.client is not None:
        from .dask import run_on_cluster

        yield from run_on_cluster(request.client, profiles, tiles, pending, formation, options,
                                  selections[0].requested, force, overlap=request.overlap)
    elif len(selections) == 1:
        yield from _run_one(profiles, tiles, pending, formation, options, selections[0], request.overlap, force)
    else:
        yield from _run_threads(profiles, tiles, pending, formation, options, selections, request.overlap, force)


def _run_one(profiles, tiles, pending, formation, options, selection, overlap: bool, force):
    """The tiles on one device, one after the other (:func:`~clsas.pipeline.tiling.tiles.form_in_turn`:
    bp on OpenCL forms the next tile's kernels while the last one is read back and written)."""
    units = _units(selection)
    grids = (tiles[i].grid for i in pending)
    for i, formed in zip(pending, form_in_turn(profiles, grids, formation, options, selection, force, overlap),
                         strict=True):
        vals, device, seconds, bp, overlapped = formed
        yield tiles[i], vals, device, seconds, units, bp, overlapped


def _run_threads(profiles, tiles, pending, formation, options, selections, overlap: bool, force):
    """One thread per device, each taking the next tile from a shared queue when it is free (at most
    one tile ahead of the one it hands on: :func:`~clsas.pipeline.tiling.tiles.form_in_turn`);
    results as they finish."""
    todo: _queue.Queue = _queue.Queue()
    for i in pending:
        todo.put(i)
    results: _queue.Queue = _queue.Queue(maxsize=len(selections))  # tiles in flight stay bounded
    locks: dict = {}
    for s in selections:  # one lock per OpenCL queue: a kernel's arguments are set per call
        locks.setdefault(id(s.queue) if s.opencl else id(s), threading.Lock())
    stop = threading.Event()

    def worker(sel):
        lock = locks[id(sel.queue) if sel.opencl else id(sel)]
        taken: deque = deque()  # the tiles this thread took, in the order their images come

        def grids():
            while not stop.is_set():
                try:
                    i = todo.get_nowait()
                except _queue.Empty:
                    return
                taken.append(i)
                yield tiles[i].grid

        formed = form_in_turn(profiles, grids(), formation, options, sel, force, overlap)
        try:
            while True:
                with lock:  # the enqueues of the next tile and the wait for this one's image
                    out = next(formed, None)
                if out is None:
                    return
                vals, device, seconds, bp, overlapped = out
                results.put((tiles[taken.popleft()], vals, device, seconds, _units(sel), bp, overlapped))
        except Exception as exc:  # noqa: BLE001 - handed to the caller's thread and raised there
            results.put(exc)
        finally:
            formed.close()

    threads = [threading.Thread(target=worker, args=(s,), daemon=True) for s in selections]
    for t in threads:
        t.start()
    try:
        for _ in range(len(pending)):
            item = results.get()
            if isinstance(item, Exception):
                raise item
            yield item
    finally:
        stop.set()
        while any(t.is_alive() for t in threads):  # let each finish its tiles; drop what they still hand in
            try:
                results.get(timeout=0.1)
            except _queue.Empty:
                pass
        for t in threads:
            t.join()
