"""NumPy twin of kernels/focus_metric.cl: a focus metric of a complex image from its sums, and its
weight per voxel, in the kernels' terms (``p = scale |I|^2``).

:func:`clsas.focus.metrics.metric_and_weight` is the same metric computed in one step on the host;
this module splits it as the device does: :func:`focus_moments` (the sums, added over the image),
:func:`from_moments` (the metric and the weight's two numbers, on the host) and
:func:`focus_weight` (the weight per voxel).
"""

from __future__ import annotations

import numpy as np

__all__ = ["focus_moments", "focus_weight", "from_moments"]


def focus_moments(values: np.ndarray, scale: float) -> np.ndarray:
    """``(max |I|^2, sum p, sum p^2, sum p log p)`` of the image ``values`` with ``p = scale |I|^2``."""
    i = np.asarray(values, np.complex128).ravel()
    q = i.real**2 + i.imag**2
    p = scale * q
    plogp = np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0)
    return np.array([q.max(initial=0.0), p.sum(), (p * p).sum(), plogp.sum()])


def from_moments(moments: np.ndarray, metric: str) -> tuple[float, float, float]:
    """``(M, a, b)``: the metric (that of :func:`~clsas.focus.metrics.metric_and_weight`) and the
    numbers of its weight ``G = I (a f(p) + b)`` from the sums of :func:`focus_moments` at ``scale``
    (``f(p) = p`` for ``"sharpness"``, ``log p`` for ``"entropy"``). ``a``, ``b`` are of the
    image at that scale: the weight of the unscaled image is ``scale`` times them.

    An image of zeros: ``(-inf, 0, 0)``.
    """
    _, e, s4, plogp = (float(x) for x in moments)
    if e <= 0:
        return -np.inf, 0.0, 0.0
    if metric == "sharpness":
        return float(np.log(s4 / e**2)), 4.0 / s4, -4.0 / e
    if metric == "entropy":
        h = float(np.log(e) - plogp / e)
        return -h, 2.0 / e, 2.0 / e * (h - np.log(e))
    raise ValueError(f"metric must be 'sharpness' or 'entropy', got {metric!r}")


def focus_weight(values: np.ndarray, scale: float, a: float, b: float, entropy: bool) -> np.ndarray:
    """``G = I (a f(p) + b)`` per voxel, ``f(p) = log p`` (0 where ``p = 0``) with ``entropy``, else ``p``."""
    i = np.asarray(values, np.complex128).ravel()
    p = scale * (i.real**2 + i.imag**2)
    if entropy:
        f = np.where(p > 0, a * np.log(np.where(p > 0, p, 1.0)) + b, 0.0)
    else:
        f = a * p + b
    return i * f
