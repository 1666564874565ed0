"""Shared pieces of the preprocessing steps: the argument check and the provenance record."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..types.dataset import Dataset

log = logging.getLogger("clsas.preprocess")


def _check_ds(ds: Any) -> Dataset:
    if not isinstance(ds, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(ds).__name__}")
    return ds


def _step(ds: Dataset, name: str, **params) -> list[dict]:
    clean = {k: (float(p) if isinstance(p, np.floating | float) else p) for k, p in params.items()}
    return [*ds.provenance, {"step": name, **clean}]
