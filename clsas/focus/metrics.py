"""Focus metrics of a complex image and their weights ``G`` (``dM = sum Re(conj(G) dI)``)."""

from __future__ import annotations

import numpy as np

__all__ = ["METRICS", "metric_and_weight"]

METRICS = ("sharpness", "entropy")


def metric_and_weight(values: np.ndarray, metric: str = "sharpness") -> tuple[float, np.ndarray]:
    """A focus metric to maximise and its weight per voxel.

    ``"sharpness"``: ``log(sum |I|^4 / (sum |I|^2)^2)`` (scale-free; the log of the intensity-
    squared sharpness over the energy squared). ``"entropy"``: minus the entropy of
    ``p = |I|^2 / sum |I|^2`` (nats). Both grow as the image focuses, and are unchanged when the
    image is scaled.

    Returns
    -------
    (float, (n_vox,) complex128)
        ``M`` and ``G`` with ``dM = sum_v Re(conj(G_v) dI_v)``.
    """
    i = np.asarray(values, np.complex128).ravel()
    p2 = i.real**2 + i.imag**2
    e = float(p2.sum())
    if e <= 0:
        return -np.inf, np.zeros_like(i)
    if metric == "sharpness":
        s4 = float((p2**2).sum())
        return float(np.log(s4 / e**2)), 4 * p2 * i / s4 - 4 * i / e
    if metric == "entropy":
        p = p2 / e
        logp = np.log(np.maximum(p, 1e-300))
        h = float(-(p * logp).sum())
        return -h, (2 * i / e) * (logp + h)
    raise ValueError(f"metric must be one of {', '.join(map(repr, METRICS))}, got {metric!r}")
