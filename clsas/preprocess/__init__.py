"""Preprocessing of measured recordings: DC removal, band-pass, background subtraction,
removal of what every recording shares, direct-path blanking, group-delay removal.

Each step takes a :class:`~clsas.types.dataset.Dataset` and returns a new one (the input is not
changed) whose ``provenance`` ends with a record of the step and its parameters, so an image
file can say what was done to its data. :func:`preprocess` runs several steps in a fixed,
sensible order and is what the ``[preprocess]`` table of a scene or preprocessing file and
``clsas preprocess`` call::

    ds = clsas.preprocess.apply(ds, dc=True, bandpass=True, background=empty_scan,
                          blank_direct=True, group_delay_s=62.33 / ds.fs_hz)

The order is: group delay (it only moves ``t0_s``), DC, band-pass, the clock from the direct
sound (it only moves ``t0_s``), background subtraction,
shared-clutter removal (:func:`remove_common`), direct-path blanking. Band-passing before
subtracting means the same filter is applied to the background recordings (they are filtered
with the scan).
"""

from .background import attach_background, subtract_background
from .chain import PREPROCESS_KEYS, apply, from_table
from .common import COMMON_STATISTICS, remove_common
from .direct import blank_direct, clock_from_direct
from .filters import bandpass, chirp_band, remove_dc, remove_delay

__all__ = [
    "COMMON_STATISTICS", "PREPROCESS_KEYS", "apply", "attach_background", "bandpass", "blank_direct",
    "chirp_band", "clock_from_direct", "from_table", "remove_common", "remove_dc", "remove_delay",
    "subtract_background",
]
