"""Removal of what every recording shares (the room and the fixture seen in every ping)."""

from __future__ import annotations

import numpy as np

from .. import validate as v
from ..types.dataset import Dataset
from ._base import _check_ds, _step, log

__all__ = ["COMMON_STATISTICS", "remove_common"]

#: what :func:`remove_common` subtracts at each delay
COMMON_STATISTICS = ("mean", "median")


def remove_common(ds: Dataset, statistic: str = "mean") -> Dataset:
    """Subtract what every recording shares: the mean (or median) over the measurements at
    each delay.

    On a turntable, the room, the turntable's rim and the fixture turn with nothing (or turn
    into themselves): their echoes are the same in every ping, while the target's move from
    ping to ping. An empty-scene scan removes most of them, but not what changed between the
    two scans (the air, a cable, the level); the shared part left is what draws rings centred
    on the axis. The same holds for a fixed rig where the target moves relative to the
    transducers.

    What it also removes (an honest note): any part of the wanted echo that is the same in
    every recording. On a turntable that is a reflector on the axis (its range never changes)
    and the rotation-invariant part of a target centred on it (a disc, a ring about the axis);
    on a planar scan of a target in front of the aperture, the target's echo changes slowly
    from stop to stop, so much of it is shared and subtracted (``tests/unit/preprocess/test_preprocess_common.py``
    measures both). Use it for turntable scans and rigs where the target moves; not for a
    planar scan of a static scene.

    Parameters
    ----------
    statistic : {"mean", "median"}
        The estimate of the shared part: the mean is linear (an image of the result is the
        image minus the image of the shared part); the median ignores a target that appears
        in fewer than half of the recordings at that delay (it is not linear).

    Notes
    -----
    All recordings must start at the same time (one ``t0_s``), or "the same delay" would mean
    different samples. The air may differ from ping to ping (``temperature_c`` per
    measurement): a shared echo at path p then arrives at p/c of each ping, which this
    sample-wise estimate does not follow (0.1 % of c moves an echo at 1.7 m by 5 us).
    The background (if still attached) is treated alike.
    """
    ds = _check_ds(ds)
    v.choice("statistic", statistic, COMMON_STATISTICS)
    if ds.n_meas < 2:
        raise ValueError(f"remove_common needs at least 2 recordings, the dataset has {ds.n_meas}")
    spread = float(np.ptp(ds.t0_s)) * ds.fs_hz
    if spread > 1e-3:
        raise ValueError(f"remove_common: the recordings start at different times (t0_s spans {spread:.3g} "
                         "samples); the shared part is taken sample by sample, so they must share one t0_s")
    stat = np.mean if statistic == "mean" else np.median

    def strip(x: np.ndarray) -> np.ndarray:
        return x - stat(x, axis=0, keepdims=True)

    before = float(np.sqrt(np.mean(ds.signals**2)))
    sig = strip(ds.signals)
    after = float(np.sqrt(np.mean(sig**2)))
    log.info("shared part (%s over %d recordings) removed: RMS %.3g -> %.3g", statistic, ds.n_meas, before, after)
    bg = None if ds.background is None else strip(ds.background)
    return ds.replace(signals=sig, background=bg,
                      provenance=_step(ds, "common", statistic=statistic, rms_before=before, rms_after=after))
