"""Tiles on a Dask cluster: one task per tile, the profiles sent to each worker once.

``reconstruct(..., client=Client or "tcp://scheduler:8786")``. The client process compresses the
recordings into range profiles, scatters them to every worker once (``broadcast=True``), and
submits one task per tile; the tiles come back as they finish and are written to the file (or
the in-memory image) there. A worker lost mid-run is replaced by Dask, which forms its tiles
again elsewhere (a tile is a pure function of the profiles and its sub-grid, so the image is
the same); each task may also be retried twice after an error.

Which OpenCL device a worker uses: the one ``PYOPENCL_CTX`` names in the worker's environment
(one worker per GPU: ``PYOPENCL_CTX=0:0 dask worker ADDRESS --nthreads 1``, then ``0:1`` for the
next), or the one :class:`OpenCLDevicePlugin` assigns, else the preferred device. Give GPU
workers one thread each so that a GPU forms one tile at a time (:func:`run_on_cluster` also
takes Dask worker ``resources``, e.g. ``{"GPU": 1}`` with ``dask worker --resources GPU=1``;
``reconstruct`` does not pass any).
"""

from __future__ import annotations

import logging
import os

from .. import cl
from ..validate import install_hint
from .tiles import form_tile

__all__ = ["OpenCLDevicePlugin", "import_distributed", "n_workers", "run_on_cluster", "worker_device"]

log = logging.getLogger(__name__)

try:  # the plugin must be a WorkerPlugin for Client.register_plugin; without distributed it is never registered
    from distributed import WorkerPlugin as _PluginBase
except ImportError:  # pragma: no cover - import_distributed() says what to install
    _PluginBase = object

_WORKER_DEVICE: dict = {"device": None}  # set on a worker by OpenCLDevicePlugin


def import_distributed():
    """``distributed``, or an ImportError that names the extra to install."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError("reconstruct(client=...) and --scheduler need dask.distributed: "
                          f"{install_hint('distributed')}") from exc
    return distributed


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


def _tile_task(profiles, grid, formation, options, requested, force):
    """A task: form one tile on this worker's device."""
    device = worker_device()
    selection = cl.select("numpy") if device == "numpy" else cl.select(requested, device)
    vals, dev, seconds = form_tile(profiles, grid, formation, options, selection, force)
    return vals, f"{dev} (pid {os.getpid()})", seconds


def _client(client):
    """A Client for ``client`` (itself, or a new one connected to the address), and whether we own it."""
    distributed = import_distributed()
    if isinstance(client, str):
        return distributed.Client(client, timeout="20s"), True
    return client, False


def n_workers(client) -> int:
    """Workers on the cluster (at least 1)."""
    c, own = _client(client)
    try:
        return max(1, len(c.scheduler_info()["workers"]))
    finally:
        if own:
            c.close()


def run_on_cluster(client, profiles, tiles, pending, formation, options, requested, force, resources=None):
    """Yield ``(tile, values, device, seconds)`` for the ``pending`` tiles, formed on the cluster."""
    distributed = import_distributed()
    c, own = _client(client)
    try:
        prof = c.scatter(profiles, broadcast=True, hash=False)
        futures = {}
        for i in pending:
            f = c.submit(_tile_task, prof, tiles[i].grid, formation, options, requested, force, pure=False,
                         retries=2, resources=resources, key=f"clsas-tile-{i}-{os.urandom(4).hex()}")
            futures[f.key] = (f, i)
        for f, (vals, device, seconds) in distributed.as_completed([f for f, _ in futures.values()],
                                                                     with_results=True):
            _, i = futures.pop(f.key)
            f.release()
            yield tiles[i], vals, device, seconds
        del prof
    finally:
        if own:
            c.close()
