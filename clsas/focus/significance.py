"""When an autofocus estimate is applied: only where it differs from the stated value by more
than its uncertainty allows, and by enough to change the image.

Sharpness moves every estimate a little, even on a scan with nothing wrong; applying such an
estimate changes a correct image for nothing. So an estimate is applied only where both tests
pass:

1. **Beyond its uncertainty**: ``|estimate - stated|`` exceeds the two-sided 95 % quantile of
   Student's t (with the estimate's degrees of freedom) times its standard uncertainty. An
   estimate from the two halves of the stops has one degree of freedom (the quantile is 12.7);
   one from the direct sound in n recordings has n - 1 (about 2).
2. **Large enough to matter**: the correction changes the delays by at least
   :data:`MIN_PERIODS` of a period of the band's highest frequency (across the aperture for
   the temperature, where a common part only shifts the image; as a whole for the delay, which
   moves the image). Smaller changes neither sharpen nor blur the image measurably.

The motion is judged by what it explains instead (:data:`MOTION_GAIN` in
:mod:`.stage_motion`): the disjoint sub-apertures' images must agree better after it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

from ..types.sanity import band_hz, grid_corners

__all__ = ["MIN_PERIODS", "CONFIDENCE", "Decision", "beyond_uncertainty", "delay_floor_s", "delay_spread_s",
           "judge"]

#: The least change of the delays worth applying, in periods of the band's highest frequency
#: (1/16: a phase change of 22.5 degrees at the top of the band, below 0.1 dB of peak loss).
MIN_PERIODS = 1 / 16

#: The two-sided confidence of the uncertainty test.
CONFIDENCE = 0.95


class Decision(NamedTuple):
    """Whether to apply an estimate (``apply``), and the reason in words (``why``)."""

    apply: bool
    why: str


def delay_floor_s(ds) -> float:
    """:data:`MIN_PERIODS` of a period of ``ds``'s highest frequency (:func:`clsas.types.sanity.band_hz`), s."""
    return MIN_PERIODS / band_hz(ds)[1]


def beyond_uncertainty(offset: float, uncertainty: float, dof: int) -> bool:
    """``|offset|`` beyond the :data:`CONFIDENCE` quantile of Student's t with ``dof`` degrees of
    freedom times ``uncertainty`` (an unknown uncertainty, NaN, passes: the other test decides)."""
    if not np.isfinite(uncertainty):
        return True
    return bool(abs(offset) > stats.t.ppf(0.5 + CONFIDENCE / 2, max(int(dof), 1)) * uncertainty)


def delay_spread_s(ds, grid, t0_new: np.ndarray, c_new: np.ndarray) -> float:
    """The largest change of the delays across the aperture that ``(t0_new, c_new)`` makes at the
    grid's corners and centre (the change's spread over the recordings; a common part only moves
    the image), s."""
    corners = grid_corners(grid)
    pts = np.r_[corners, corners.mean(axis=0)[None]]
    path = (np.linalg.norm(pts[None] - ds.tx_positions[:, None], axis=2)
            + np.linalg.norm(pts[None] - ds.rx_positions[:, None], axis=2))
    change = (path / np.asarray(c_new, float)[:, None] - np.asarray(t0_new, float)[:, None]
              - path / ds.c_per_meas[:, None] + ds.t0_s[:, None])
    return float(np.max(np.ptp(change, axis=0)))


def judge(offset: float, uncertainty: float, dof: int, effect_s: float, floor_s: float, unit: str = "") -> Decision:
    """Both tests of the module on one estimate: ``offset`` from the stated value (in ``unit``),
    its standard ``uncertainty`` with ``dof`` degrees of freedom, and the change ``effect_s`` it
    makes to the delays against ``floor_s``."""
    if not beyond_uncertainty(offset, uncertainty, dof):
        q = stats.t.ppf(0.5 + CONFIDENCE / 2, max(int(dof), 1))
        return Decision(False, f"{offset:+.3g} {unit} from the stated value is within {q:.3g} x its uncertainty "
                              f"{uncertainty:.2g} {unit} ({CONFIDENCE:.0%}): consistent with the stated value")
    if effect_s < floor_s:
        return Decision(False, f"it changes the delays by {effect_s * 1e6:.2g} us, under {floor_s * 1e6:.2g} us "
                              f"({MIN_PERIODS:g} of the band's shortest period): too small to change the image")
    return Decision(True, f"beyond its uncertainty, and it changes the delays by {effect_s * 1e6:.3g} us")
