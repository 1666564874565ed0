"""Grating lobes: where an undersampled planar aperture puts copies of a bright reflector.

With stops ``d`` apart along x, a reflector at range ``R`` has grating lobes at cross-range
offsets ``k lambda R / (2 d)`` (k = +-1, +-2, ...; two-way path) at the same range, wherever
``d > lambda / 4``. A peak that sits on such a lobe of a brighter peak may not be a reflector
at all; :func:`grating_lobe_notes` says which peaks those are.
"""

from __future__ import annotations

import numpy as np

__all__ = ["stop_spacing", "grating_lobe_notes"]


def stop_spacing(positions_m: np.ndarray, axis: int) -> float | None:
    """Typical spacing of the stops along ``axis`` (the median gap between distinct
    coordinates), m, or None if the stops do not spread along it."""
    vals = np.unique(np.round(np.asarray(positions_m)[:, axis], 6))
    if len(vals) < 2:
        return None
    return float(np.median(np.diff(vals)))


def grating_lobe_notes(peaks, tx_m: np.ndarray, rx_m: np.ndarray, fc_hz: float, c_mps: float,
                       tolerance: float = 0.1, max_order: int = 2) -> list[str]:
    """For each peak (strongest first), ``""`` or a note that it may be a grating lobe.

    Only for a planar aperture facing z (the raster rigs): a weaker peak is flagged when its
    range from the aperture's centre is within a range-resolution cell of a brighter peak's and
    its x and y offsets from it are whole multiples (not both zero, at most ``max_order``) of
    the lobe spacing ``lambda R / (2 d)`` at the centre frequency, within ``tolerance`` of a
    spacing. A chirp's lobes smear with frequency, and a scene may hold real reflectors on a
    lattice, so the note says "possibly".
    """
    mid = 0.5 * (np.asarray(tx_m) + np.asarray(rx_m))
    notes = [""] * len(peaks)
    if len(peaks) < 2 or np.ptp(mid[:, 2]) > 1e-3:
        return notes
    lam = c_mps / fc_hz
    d = [stop_spacing(mid, 0), stop_spacing(mid, 1)]
    if all(s is None or s <= lam / 4 for s in d):
        return notes  # sampled finely enough: no grating lobes
    centre = mid.mean(axis=0)
    for j, pj in enumerate(peaks):
        for i in range(j):
            pi = peaks[i]
            r = float(np.linalg.norm(pi.position_m - centre))
            if abs(float(np.linalg.norm(pj.position_m - centre)) - r) > max(lam, 0.02 * r):
                continue
            ks = []
            for ax, s in enumerate(d):
                off = pj.position_m[ax] - pi.position_m[ax]
                if s is None or s <= lam / 4:
                    ks.append(0 if abs(off) < 0.5 * lam else None)
                    continue
                step = lam * max(abs(pi.position_m[2] - centre[2]), 1e-6) / (2 * s)
                k = round(off / step)
                ks.append(k if abs(off / step - k) <= tolerance and abs(k) <= max_order else None)
            if None not in ks and any(ks):
                notes[j] = f"possibly a grating lobe of peak {i + 1}"
                break
    return notes
