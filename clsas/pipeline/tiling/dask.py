"""Tiles on a Dask cluster: one task per run of a few tiles, the profiles sent to each worker once.

``reconstruct(..., client=Client or "tcp://scheduler:8786")``. The client process compresses the
recordings into range profiles, scatters them to every worker once (``broadcast=True``), and
submits one task per run of consecutive pending tiles (:func:`tile_runs`: up to
:data:`MAX_TILES_PER_TASK`, and at least two tasks per worker where there are tiles enough). A
worker forms its run in turn (:func:`clsas.pipeline.tiling.tiles.form_in_turn`: bp on OpenCL
runs the next tile's kernels while the last tile is read back); a task's tiles come back when it
finishes and are written to the file (or the in-memory image) there, each once, so a rerun of an
interrupted file forms only the tiles not written. A worker lost mid-run is replaced by Dask,
which forms its tiles again elsewhere (a tile is a pure function of the profiles and its
sub-grid, so the image is the same); each task may also be retried twice after an error.

Which OpenCL device a worker uses: the one ``PYOPENCL_CTX`` names in the worker's environment
(one worker per GPU: ``PYOPENCL_CTX=0:0 dask worker ADDRESS --nthreads 1``, then ``0:1`` for the
next), or the one :class:`OpenCLDevicePlugin` assigns, else the preferred device. Give GPU
workers one thread each so that a GPU forms one tile at a time (:func:`run_on_cluster` also
takes Dask worker ``resources``, e.g. ``{"GPU": 1}`` with ``dask worker --resources GPU=1``;
``reconstruct`` does not pass any).

How many cores a worker uses on a CPU device: as many as it has threads. PoCL runs a kernel on
every core of the host, so two 1-thread workers would each spread over both cores and contend;
:func:`worker_selection` gives a worker of N threads a sub-device of N compute units (device
fission), and the compute units each worker used are in ``image.provenance["tiles"]["devices"]``.
"""

from __future__ import annotations

import logging
import os

from ... import cl
from ...cluster import connect, import_distributed
from .tiles import form_in_turn

__all__ = ["MAX_TILES_PER_TASK", "OpenCLDevicePlugin", "connect", "import_distributed", "n_workers",
           "run_on_cluster", "tile_runs", "worker_device", "worker_selection"]

log = logging.getLogger(__name__)

MAX_TILES_PER_TASK = 4  # a worker holds this many tiles' values until its task returns

try:  # the plugin must be a WorkerPlugin for Client.register_plugin; without distributed it is never registered
    from distributed import WorkerPlugin as _PluginBase
except ImportError:  # pragma: no cover - import_distributed() says what to install
    _PluginBase = object

_WORKER_DEVICE: dict = {"device": None}  # set on a worker by OpenCLDevicePlugin


class OpenCLDevicePlugin(_PluginBase):
    """A Dask worker plugin that gives each worker its own OpenCL device.

    ``client.register_plugin(OpenCLDevicePlugin(["0:0", "0:1"]))``: the worker named ``i`` (an
    integer, as ``LocalCluster`` and ``dask worker --name i`` name them) gets ``devices[i % n]``;
    other names get the device by a stable hash of the name.

    Parameters
    ----------
    devices : list of str
        OpenCL devices as ``"P:D"`` (see ``clsas devices``), or ``"numpy"``.
    """

    name = "clsas-opencl-device"

    def __init__(self, devices: list[str]):
        if not devices or not all(isinstance(d, str) for d in devices):
            raise ValueError(f"devices must be a non-empty list of 'P:D' strings, got {devices!r}")
        self.devices = list(devices)

    def setup(self, worker) -> None:
        name = str(worker.name)
        i = int(name) if name.isdigit() else sum(name.encode())
        _WORKER_DEVICE["device"] = self.devices[i % len(self.devices)]
        log.info("worker %s: OpenCL device %s", name, _WORKER_DEVICE["device"])

    def teardown(self, worker) -> None:
        _WORKER_DEVICE["device"] = None


def worker_device() -> str | None:
    """The device this worker was given by :class:`OpenCLDevicePlugin` (None: the default)."""
    return _WORKER_DEVICE["device"]


def _worker_threads() -> int | None:
    """Threads of the Dask worker this runs on (None outside a worker)."""
    try:
        from distributed import get_worker

        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None


def worker_selection(requested, device=None, threads: int | None = None) -> tuple[cl.Selection, int | None]:
    """The device selection of a worker with ``threads`` threads, and the compute units it uses.

    A CPU device with more compute units than the worker has threads (PoCL makes one thread per
    core) is split by device fission (``clCreateSubDevices``, ``CL_DEVICE_PARTITION_BY_COUNTS``)
    and the worker gets a sub-device of ``threads`` compute units: a worker of 1 thread then
    uses 1 core, so that 2 such workers on 2 cores do not both spread over both. A GPU, a device
    that cannot be split, or ``threads=None`` keeps the whole device.

    Parameters
    ----------
    requested : str
        The backend request (``"auto"``, ``"opencl"``, ``"numpy"``).
    device : None, "P:D" or "numpy"
        The worker's device (see :class:`OpenCLDevicePlugin`).
    threads : int, optional
        The worker's threads (default: the Dask worker's, where this runs on one).

    Returns
    -------
    (Selection, int or None)
        The selection and its device's compute units (None on NumPy).
    """
    if device == "numpy":
        return cl.select("numpy"), None
    selection = cl.select(requested, device)
    if not selection.opencl:
        return selection, None
    whole = selection.queue.device
    threads = _worker_threads() if threads is None else int(threads)
    if threads is None or not cl.is_cpu(whole) or whole.max_compute_units <= threads:
        return selection, int(whole.max_compute_units)
    queue = cl.sub_device_queue(whole.int_ptr, threads)
    if queue is None:
        return selection, int(whole.max_compute_units)
    return cl.select(requested, queue), int(queue.device.max_compute_units)


def _tiles_task(profiles, grids, formation, options, requested, force, overlap):
    """A task: form a run of tiles in turn on this worker's device (a sub-device of its threads'
    compute units); one ``(values, device, seconds, compute_units, bp, overlapped)`` per tile."""
    selection, units = worker_selection(requested, worker_device())
    # the worker's own copy of the profiles, shared by its tasks, made read-only: bp's resident path then
    # uploads it and makes its records on the device for the first tile, and keeps them for the others
    profiles.data.flags.writeable = False
    cu = "" if units is None else f", {units} CU"
    overlap = overlap and len(grids) > 1  # one tile has nothing to overlap
    return [(vals, f"{dev} (pid {os.getpid()}{cu})", seconds, units, bp, overlapped)
            for vals, dev, seconds, bp, overlapped in form_in_turn(profiles, grids, formation, options,
                                                                   selection, force, overlap)]


def tile_runs(pending: list[int], workers: int, most: int = MAX_TILES_PER_TASK) -> list[list[int]]:
    """``pending`` cut into runs of consecutive entries, one task each: as long as leaves at least
    two tasks per worker (so that every worker has work and a slow one does not hold the end),
    between 1 and ``most`` tiles.

    >>> tile_runs(list(range(8)), workers=2)
    [[0, 1], [2, 3], [4, 5], [6, 7]]
    >>> tile_runs([1, 2, 5, 6, 7, 8], workers=1)
    [[1, 2, 5], [6, 7, 8]]
    """
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if not isinstance(most, int) or most < 1:
        raise ValueError(f"most must be a positive integer, got {most!r}")
    size = max(1, min(most, len(pending) // (2 * workers)))
    return [list(pending[k:k + size]) for k in range(0, len(pending), size)]


def n_workers(client) -> int:
    """Workers on the cluster (at least 1)."""
    c, own = connect(client)
    try:
        return max(1, len(c.scheduler_info()["workers"]))
    finally:
        if own:
            c.close()


def run_on_cluster(client, profiles, tiles, pending, formation, options, requested, force, resources=None,
                   overlap: bool = True):
    """Yield ``(tile, values, device, seconds, compute_units, bp, overlapped)`` for the ``pending``
    tiles, formed on the cluster in runs of a few tiles per task (:func:`tile_runs`), each task's
    tiles as soon as it finishes (``device`` names the worker's process and compute units;
    ``bp``: :func:`clsas.pipeline.tiling.tiles.bp_record`; ``overlapped``: formed with
    the next tile's kernels beside its read back)."""
    distributed = import_distributed()
    c, own = connect(client)
    try:
        prof = c.scatter(profiles, broadcast=True, hash=False)
        futures = {}
        for run in tile_runs(list(pending), max(1, len(c.scheduler_info()["workers"]))):
            f = c.submit(_tiles_task, prof, [tiles[i].grid for i in run], formation, options, requested, force,
                         overlap, pure=False, retries=2, resources=resources,
                         key=f"clsas-tiles-{run[0]}-{run[-1]}-{os.urandom(4).hex()}")
            futures[f.key] = (f, run)
        # as_completed waits on the loop it is given, else the *default* client's: with two clients in
        # one process (a LocalCluster's and another) the default one's loop may never see these futures
        for f, formed in distributed.as_completed([f for f, _ in futures.values()], loop=c.loop,
                                                  with_results=True):
            _, run = futures.pop(f.key)
            f.release()
            for i, (vals, device, seconds, units, bp, overlapped) in zip(run, formed, strict=True):
                yield tiles[i], vals, device, seconds, units, bp, overlapped
        del prof
    finally:
        if own:
            c.close()
