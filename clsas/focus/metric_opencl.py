"""OpenCL plans for kernels/focus_metric.cl: the focus metric of an image the backprojection left on
the device (:attr:`clsas.Image.on_device`), and its weight written straight into the gradient
plan's planes, so that an autofocus step's image, metric and gradient never leave the device.

The NumPy twin is :mod:`clsas.focus.metric_numpy`.
"""

from __future__ import annotations

import logging

import numpy as np

from ..cl import DeviceRows, Plan
from . import metric_numpy as twin

__all__ = ["FocusMomentsPlan", "FocusWeightPlan", "device_metric"]

log = logging.getLogger(__name__)

_ITEMS = 1024  # work-items of a call: each adds its own voxels, the host adds their sums
_SPAN = 1e6  # the scaled peak p = scale max |I|^2 is kept within [1 / _SPAN, _SPAN]


def _selftest_image(vec: int, rng=None) -> np.ndarray:
    """Voxels not a multiple of VEC, a zero voxel, amplitudes over six decades."""
    rng = rng or np.random.default_rng(3)
    n = 7 * vec + 3
    img = (rng.normal(size=n) + 1j * rng.normal(size=n)) * 10.0 ** rng.uniform(-3, 3, n)
    img[2] = 0
    return img.astype(np.complex64)


class FocusMomentsPlan(Plan):
    """The image's sums (``focus_moments``) for images of ``n_vox`` voxels."""

    KERNEL = "focus_moments"
    SOURCES = ("focus_metric.cl",)

    def __init__(self, n_vox: int, queue=None, vec=None, n_items: int | None = None):
        super().__init__(queue, vec)
        self.n_vox = int(n_vox)
        self.n_items = int(n_items or max(1, min(_ITEMS, -(-self.n_vox // self.vec))))
        self.d_partial = self.alloc(16 * self.n_items, "w")
        self.scale = 1.0  # kept from the last image: an autofocus's images keep their level

    def run(self, image, scale: float) -> np.ndarray:
        """The sums of the complex image in the device buffer ``image`` at ``scale`` (float64, added
        on the host), as :func:`clsas.focus.metric_numpy.focus_moments`."""
        self.begin()
        self.launch((self.n_items,), image, np.int32(self.n_vox), np.float32(scale), self.d_partial)
        part = self.read(self.d_partial, (self.n_items, 4), np.float32).astype(np.float64)
        return np.array([part[:, 0].max(), *part[:, 1:].sum(axis=0)])

    def __call__(self, image) -> tuple[np.ndarray, float]:
        """``(sums, scale)``: the sums at a scale that keeps the scaled peak near 1 (the last call's
        when it does, else measured from this image's peak: a second pass)."""
        sums = self.run(image, self.scale)
        peak = sums[0] * self.scale
        if sums[0] > 0 and np.isfinite(sums).all() and 1 / _SPAN <= peak <= _SPAN:
            return sums, self.scale
        if not 0 < sums[0] < np.inf:
            return sums, self.scale  # zeros, or beyond float's range: the caller decides
        self.scale = 1.0 / float(sums[0])
        sums = self.run(image, self.scale)
        scale = self.scale
        if not np.isfinite(sums).all():  # a peak beyond what float can rescale: not kept for the next image
            self.scale = 1.0
        return sums, scale

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        img = _selftest_image(vec)
        plan = cls(len(img), queue=queue, vec=vec, n_items=3)
        buf = plan.upload(img.view(np.float32), np.float32)
        got = plan.run(buf, 0.25)
        want = twin.focus_moments(img, 0.25)
        return float(np.max(np.abs(got - want) / np.maximum(np.abs(want), 1e-30)))


class FocusWeightPlan(Plan):
    """The weight ``G = I (a f(p) + b)`` (``focus_weight``) into two float planes of ``n_pad``."""

    KERNEL = "focus_weight"
    SOURCES = ("focus_metric.cl",)

    def __init__(self, n_vox: int, n_pad: int, entropy: bool, queue=None, vec=None, n_items: int | None = None):
        self.entropy = bool(entropy)
        super().__init__(queue, vec)
        self.n_vox, self.n_pad = int(n_vox), int(n_pad)
        if self.n_pad < self.n_vox:
            raise ValueError(f"n_pad={n_pad} is below n_vox={n_vox}")
        self.n_items = int(n_items or max(1, min(4 * _ITEMS, -(-self.n_pad // self.vec))))

    def defines(self) -> dict:
        return {"ENTROPY": 1} if self.entropy else {}

    def __call__(self, image, scale: float, a: float, b: float, weight_re, weight_im) -> None:
        """Write the weight of the image in ``image`` into the planes ``weight_re``, ``weight_im``
        (device buffers of ``n_pad`` floats, padding 0), in order on this plan's queue."""
        self.begin()
        self.launch((self.n_items,), image, np.int32(self.n_vox), np.int32(self.n_pad), np.float32(scale),
                    np.float32(a), np.float32(b), weight_re, weight_im)

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        img = _selftest_image(vec)
        err = 0.0
        for entropy in (False, True):
            plan = cls(len(img), len(img) + vec, entropy, queue=queue, vec=vec, n_items=2)
            buf = plan.upload(img.view(np.float32), np.float32)
            re, im = plan.alloc(4 * plan.n_pad), plan.alloc(4 * plan.n_pad)
            scale = 1.0 / float(np.max(np.abs(img)) ** 2)
            a, b = (0.5, -2.0) if entropy else (3.0, -1.5)
            plan(buf, scale, a, b, re, im)
            got = plan.read(re, (plan.n_pad,), np.float32) + 1j * plan.read(im, (plan.n_pad,), np.float32)
            want = np.zeros(plan.n_pad, complex)
            want[: len(img)] = twin.focus_weight(img, scale, a, b, entropy)
            err = max(err, float(np.max(np.abs(got - want)) / np.max(np.abs(want))))
        return err


def device_metric(moments: FocusMomentsPlan, weights: FocusWeightPlan | None, rows: DeviceRows, metric: str,
                  weight_re=None, weight_im=None) -> float | None:
    """The metric of the image in ``rows`` (one row of ``n_vox`` complex values on the plans'
    queue), and, with ``weights``, its weight written into ``weight_re``/``weight_im``; None where
    the image is beyond float's range on the device (the caller computes it on the host)."""
    sums, scale = moments(rows.buffer)
    if not np.isfinite(sums).all():
        log.info("focus metric: image values beyond float's range on the device; computed on the host")
        return None
    m, a, b = twin.from_moments(sums, metric)
    if weights is not None:
        weights(rows.buffer, scale, scale * a, scale * b, weight_re, weight_im)
    return m
