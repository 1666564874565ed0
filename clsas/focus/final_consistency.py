"""The last check of :func:`clsas.autofocus` with ``consistency_iter``: does the correction make the data consistent?

:func:`.consistency.data_consistency` on the input (with the direct sound's delay applied where
it was found: that is physics, not focus, and is never withdrawn) and on the corrected scan (the
first's noise floor reused). The *excess ratio* is the corrected scan's excess over the
first's: what the correction left of the part of the data that no target in the grid
explained. It needs no truth and trusts no image. (The bench's ratio,
:func:`bench.consistency_family.excess_ratio`, divides by the scan as recorded instead;
the two differ only on scans with direct sound.)

The thresholds below were set on the scene family's tuning seeds (3 mm hand motion) and checked
on held-out seeds: a low ratio marks a correction that took the local peak to within 1 dB of the
error-free image's, a high one a correction that did not (the figures are on the consistency
pages of ``bench/results``). A correction is withdrawn only over :data:`REVERT_RATIO` (the data
contradict it), not as soon as the data stop confirming it, which would discard right
corrections the data cannot see.
"""

from __future__ import annotations

import logging

from .consistency import data_consistency

__all__ = ["COMPLETE_RATIO", "CONFIRM_RATIO", "REVERT_RATIO", "consistency_gate"]

log = logging.getLogger("clsas.autofocus")

#: At most this excess ratio: the correction is complete to the model's precision.
COMPLETE_RATIO = 0.2
#: Over this the data contradict the correction (it leaves them less consistent than without it):
#: it is withdrawn. Between :data:`CONFIRM_RATIO` and this the data do not see it (a target in the
#: grid explains them either way, as a few points in a large grid can): kept as the other checks
#: decided, with a note. (Withdrawing over 0.9 discards a correct "points" correction on such a
#: scene.)
REVERT_RATIO = 1.1
#: Up to this the data confirm at least part of the correction.
CONFIRM_RATIO = 0.9


def consistency_gate(base, out, grid, rep, max_iter: int, selection) -> bool:
    """Judge ``out`` against ``base`` (the input with the direct sound's delay, where found) by
    data consistency; fill ``rep.check`` and a note.

    Returns False where the correction is to be withdrawn: its excess ratio is over
    :data:`REVERT_RATIO` (the data contradict it). Where ``out`` is ``base`` itself (nothing to
    judge), only its consistency is reported (``excess_after``).
    """
    first = data_consistency(base, grid, max_iter=max_iter, backend=selection)
    head = f"data consistency ({max_iter} iterations): {first.residual:.3f} of the data unexplained"
    if out is base:
        rep.check.update(excess_after=first.excess, noise_floor=first.floor)
        rep.stages.append({"step": "consistency", "iterations": max_iter, "residual_after": first.residual,
                           "floor": first.floor, "time_s": first.time_s})
        rep.notes.append(head + f" by any target in the grid, noise alone {first.floor:.3f}; an excess well over "
                         "the noise is an error in the geometry that no step found (or in the model)")
        return True
    after = data_consistency(out, grid, max_iter=max_iter, floor_of=first, backend=selection)
    rep.check.update(excess_before=first.excess, excess_after=after.excess, noise_floor=first.floor)
    rep.stages.append({"step": "consistency", "iterations": max_iter, "residual_before": first.residual,
                       "residual_after": after.residual, "floor": first.floor,
                       "time_s": first.time_s + after.time_s})
    head += f" before, {after.residual:.3f} after, noise alone {first.floor:.3f}"
    if first.excess > 0:
        ratio = after.excess / first.excess
    else:  # explained to the noise without the correction: it can only be contradicted
        ratio = float("inf") if after.excess > 0 else 1.0
    rep.check["excess_ratio"] = ratio
    passed = _judged(head, ratio, rep)
    rep.check["consistency_passed"] = passed
    return passed


def _judged(head: str, ratio: float, rep) -> bool:
    if ratio > REVERT_RATIO:
        rep.notes.append(head + f": the correction leaves the data less consistent than without it (excess ratio "
                         f"{ratio:.2f}, over {REVERT_RATIO:g}): the data contradict it")
        return False
    if ratio > CONFIRM_RATIO:
        rep.notes.append(head + f": the data do not see the correction (excess ratio {ratio:.2f}): a target in the "
                         "grid explains them with or without it, so they can neither confirm nor reject it; kept as "
                         "the other checks decided")
    elif ratio > COMPLETE_RATIO:
        rep.notes.append(head + f": the correction leaves {ratio:.0%} of the unexplained part: incomplete (on the "
                         "tuning family every such scene stayed over 1 dB below the error-free peak)")
    else:
        rep.notes.append(head + f": the correction leaves {ratio:.0%} of the unexplained part: complete to the "
                         f"model's precision (at most {COMPLETE_RATIO:.0%})")
    return True
