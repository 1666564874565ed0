"""The per-recording sparse step on a Dask cluster: one task per block of recordings.

:func:`clsas.sparse.profiles.superres_profiles` finds each recording's echoes on its own (its
window, its atom, its dictionary); nothing is shared between recordings, so the recordings are
split into contiguous blocks and each block is a Dask task. The step's state (the dataset, the
gates, the atom's waveform and the method's options) is scattered to every worker once
(``broadcast=True``), not sent with each task; the blocks come back as they finish and are put
in their rows, so the profiles and echoes equal those of the serial step (the same code on the
same numbers; run times aside). A worker lost mid-run is replaced by Dask and its blocks formed
again elsewhere; each task may also be retried twice after an error.

``reconstruct(dataset, grid, method="cbp-polar", client=...)`` uses it for the sparse step and
the same cluster for the tiles of the image.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable

import numpy as np

__all__ = ["blocks", "echoes_on_cluster"]

log = logging.getLogger(__name__)


def blocks(n: int, n_workers: int, per_worker: int = 4) -> list[tuple[int, int]]:
    """Contiguous ``(start, stop)`` blocks of ``n`` recordings: about ``per_worker`` per worker.

    Parameters
    ----------
    n : int
        Recordings.
    n_workers : int
        Workers on the cluster.
    per_worker : int
        Blocks per worker (more evens out recordings that take longer than others).
    """
    if n < 0 or n_workers < 1 or per_worker < 1:
        raise ValueError(f"blocks: need n >= 0, n_workers >= 1, per_worker >= 1, got {n}, {n_workers}, {per_worker}")
    size = max(1, math.ceil(n / (n_workers * per_worker)))
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def _block_task(job, start: int, stop: int) -> list:
    """A task: ``job.echoes(m)`` for the recordings ``start:stop`` (on a worker)."""
    return [job.echoes(m) for m in range(start, stop)]


def echoes_on_cluster(job, client, n_lags: int, progress: Callable[[int, int], None] | None = None,
                      per_worker: int = 4) -> tuple[np.ndarray, list]:
    """Every recording's echoes, found on the cluster (see the module notes).

    Parameters
    ----------
    job : clsas.sparse.profiles._Recordings
        The step's state; its :meth:`echoes` ``(m)`` gives ``(Echoes, matched row or None)``.
    client : distributed.Client or str
        A Dask client or a scheduler address.
    n_lags : int
        Length of a profile row.
    progress : callable(done, total), optional
        Recordings done, after each block.
    per_worker : int
        Blocks per worker.

    Returns
    -------
    (ndarray (n_meas, n_lags) complex128, list of Echoes)
        The matched-filter rows of the recordings the method failed on (zero elsewhere), and
        every recording's echoes, in recording order.
    """
    from ..cluster import connect, import_distributed

    if not isinstance(client, str) and not (hasattr(client, "submit") and hasattr(client, "scatter")):
        raise TypeError(f"client must be a distributed.Client or a scheduler address, got {type(client).__name__}")
    distributed = import_distributed()
    n = job.dataset.n_meas
    data = np.zeros((n, n_lags), np.complex128)
    echoes: list = [None] * n
    c, own = connect(client)
    try:
        parts = blocks(n, max(1, len(c.scheduler_info()["workers"])), per_worker)
        remote = c.scatter(job, broadcast=True, hash=False)
        tag = os.urandom(4).hex()
        futures = {}
        for start, stop in parts:
            f = c.submit(_block_task, remote, start, stop, pure=False, retries=2,
                         key=f"clsas-sparse-{start}-{stop}-{tag}")
            futures[f.key] = (f, start, stop)
        log.info("sparse step: %d recordings in %d blocks on the cluster", n, len(parts))
        done = 0
        for f, results in distributed.as_completed([f for f, _, _ in futures.values()], loop=c.loop,
                                                   with_results=True):  # this client's loop, not the default's
            _, start, stop = futures.pop(f.key)
            f.release()
            for m, (e, row) in zip(range(start, stop), results, strict=True):
                echoes[m] = e
                if row is not None:
                    data[m] = row
            done += stop - start
            if progress is not None:
                progress(done, n)
        del remote
    finally:
        if own:
            c.close()
    return data, echoes

