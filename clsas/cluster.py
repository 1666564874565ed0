"""Dask's ``distributed``, imported where used: a missing package names the extra to install, and a
client from a scheduler address. Shared by the tiles on a cluster (:mod:`clsas.pipeline.tiling.dask`)
and the per-profile sparse step (:mod:`clsas.sparse.parallel`)."""

from __future__ import annotations

from .validate import install_hint

__all__ = ["connect", "import_distributed"]


def import_distributed():
    """``distributed``, or an ImportError that names the extra to install."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError("reconstruct(client=...) and --scheduler need dask.distributed: "
                          f"{install_hint('distributed')}") from exc
    return distributed


def connect(client):
    """A Client for ``client`` (itself, or a new one connected to the address), and whether we own it."""
    distributed = import_distributed()
    if isinstance(client, str):
        return distributed.Client(client, timeout="20s"), True
    return client, False
