"""The image and the focus gradient as functions of per-measurement delay shifts and c.

Range profiles are computed once (over the grid's delay gate widened by a margin); a shift
``delta_m`` reads measurement m's analytic profile ``delta_m`` later (``s_m(tau - delta_m)``,
what raising its ``t0_s`` by ``delta_m`` does), by moving the profile's time axis and turning
its baseband phase, so the image and its gradient come from the backprojection kernel and the
gradient kernel (or their NumPy twins) without recompressing.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from .. import cl as _cl
from ..compression import Profiles, compress
from ..formation.bp import Backprojector
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from ..types.image import Image
from ..types.rangegate import plan_reconstruction
from . import gradient_numpy as twin
from .gradient_opencl import FocusGradientPlan
from .metric_opencl import FocusMomentsPlan, FocusWeightPlan, device_metric
from .metrics import metric_and_weight

__all__ = ["FocusEngine"]

log = logging.getLogger(__name__)


class FocusEngine:
    """Images and focus gradients of one dataset on one grid.

    Parameters
    ----------
    dataset : Dataset
    grid : VoxelGrid
    margin_s : float
        How far beyond the grid's delay gate the profiles reach, s (the largest delay change
        the search may make: group delay, motion).
    rel_margin : float
        And this fraction of the gate's delays (the largest relative change of c).
    metric : str
        See :func:`clsas.focus.metrics.metric_and_weight`.
    backend, device : as for :func:`clsas.reconstruct`
        (``backend`` may be a :class:`clsas.cl.Selection`, resolved once and shared by the
        compression, the backprojection and the gradient; each kernel that will not build
        falls back to its twin on ``"auto"`` with one warning and raises on ``"opencl"``).
    metric_on_device : bool
        On OpenCL, compute the focus metric and its weight from the image the backprojection left
        on the device (default); False: on the host from the image read back, the weight written
        back (kept for comparison: ``python -m bench.focus_step``).
    """

    def __init__(self, dataset: Dataset, grid: VoxelGrid, *, margin_s: float = 5e-4, rel_margin: float = 0.0,
                 metric: str = "sharpness",
                 backend: str | _cl.Selection | None = None, device: Any = None, force: bool = False,
                 metric_on_device: bool = True):
        if not isinstance(metric_on_device, bool):
            raise TypeError(f"metric_on_device must be True or False, got {metric_on_device!r}")
        self.ds, self.grid, self.metric = dataset, grid, metric
        self.selection = _cl.select(backend, device)
        plan = plan_reconstruction(dataset, grid, [])
        gate = (max(0.0, plan.gate_s[0] * (1 - rel_margin) - margin_s), plan.gate_s[1] * (1 + rel_margin) + margin_s)
        self.prof: Profiles = compress(dataset, gate_s=gate, backend=self.selection)
        self.bp = Backprojector(grid, backend=self.selection, force=force)
        self._grad_plan = None
        self._grad_selection = self.selection  # NumPy once the gradient kernel fell back
        self._stop_bp: Backprojector | None = None
        self._moments: FocusMomentsPlan | None = None
        self._weights: FocusWeightPlan | None = None
        # NumPy once a metric kernel fell back (or asked for)
        self._metric_selection = self.selection if metric_on_device else _cl.select("numpy")
        self.n_images = 0
        self.n_gradients = 0
        self.n_device_metrics = 0  # evaluations whose metric (and weight) came from the image on the device

    @property
    def backend(self) -> str:
        """``"opencl"`` where the images and the gradient both run there, else ``"numpy"``."""
        return "opencl" if (self.bp.backend == "opencl" and self._grad_selection.opencl) else "numpy"

    @property
    def device(self) -> str:
        return self.bp.selection.device

    def _shifted(self, shift_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self.prof
        rot = np.exp(-2j * np.pi * ((p.fc_hz * shift_s) % 1.0))
        return p.data * rot[:, None], p.tau0_s + shift_s

    def image(self, shift_s: np.ndarray, c_mps: np.ndarray, tx: np.ndarray | None = None,
              rx: np.ndarray | None = None) -> np.ndarray:
        """(n_vox,) complex image with per-measurement shifts (s), speeds (m/s) and positions."""
        return np.asarray(self._form(shift_s, c_mps, tx, rx).values).ravel()

    def _form(self, shift_s, c_mps, tx, rx) -> Image:
        p = self.prof
        data, tau0 = self._shifted(shift_s)
        prof = Profiles(data, tau0, p.dtau_s, p.fc_hz, p.method, p.backend,
                        tx_positions=self.ds.tx_positions if tx is None else tx,
                        rx_positions=self.ds.rx_positions if rx is None else rx, c_mps=c_mps)
        self.n_images += 1
        return self.bp(prof)

    def stop_images(self, shift_s: np.ndarray, c_mps: np.ndarray, stop: np.ndarray, voxels: np.ndarray | None = None,
                    tx: np.ndarray | None = None, rx: np.ndarray | None = None) -> np.ndarray:
        """(n_stops, n) complex64: each stop's own image (the sum of its measurements'
        backprojections) at the grid's voxels ``voxels`` (flat indices; default all).

        The image at these shifts, speeds and positions is the sum of the rows. The stops'
        images come from the backprojection kernel (or its twin), one stop at a time.
        """
        p = self.prof
        data, tau0 = self._shifted(shift_s)
        tx = self.ds.tx_positions if tx is None else tx
        rx = self.ds.rx_positions if rx is None else rx
        c = np.broadcast_to(np.asarray(c_mps, float), (p.n_meas,))
        n_stops = int(stop.max()) + 1
        out = np.empty((n_stops, self.grid.size if voxels is None else len(voxels)), np.complex64)
        if self._stop_bp is None:
            self._stop_bp = Backprojector(self.grid, backend=self.bp.selection, force=True)
        for s in range(n_stops):
            rows = np.flatnonzero(stop == s)
            prof = Profiles(data[rows], tau0[rows], p.dtau_s, p.fc_hz, p.method, p.backend,
                            tx_positions=tx[rows], rx_positions=rx[rows], c_mps=c[rows])
            values = np.asarray(self._stop_bp(prof).values).ravel()
            out[s] = values if voxels is None else values[voxels]
        self.n_images += n_stops
        return out

    def sums(self, shift_s: np.ndarray, c_mps: np.ndarray, weight: np.ndarray, tx: np.ndarray | None = None,
             rx: np.ndarray | None = None) -> np.ndarray:
        """(n_meas, 5) gradient sums (see :func:`clsas.focus.gradient_numpy.focus_gradient`) at these
        shifts, speeds and positions (default: the dataset's)."""
        p = self.prof
        data, tau0 = self._shifted(shift_s)
        args = (data, tau0, p.dtau_s, p.fc_hz, self.ds.tx_positions if tx is None else tx,
                self.ds.rx_positions if rx is None else rx, c_mps)
        self.n_gradients += 1
        plan = self._gradient_plan()
        if plan is not None:
            return plan(*args, weight)
        if weight is None:
            raise ValueError("weight: None only where the gradient kernel runs (its planes hold the weight)")
        return twin.focus_gradient(*args, self.grid.points(), weight)

    def _gradient_plan(self) -> FocusGradientPlan | None:
        """The gradient kernel's plan (built on first use), None on NumPy."""
        if self._grad_plan is None and self._grad_selection.opencl:
            p = self.prof
            self._grad_plan, self._grad_selection = self._grad_selection.plan(
                lambda q: FocusGradientPlan(self.grid, p.n_meas, p.n_lags, queue=q))
        return self._grad_plan

    def evaluate(self, shift_s: np.ndarray, c_mps: np.ndarray, gradient: bool = True, tx: np.ndarray | None = None,
                 rx: np.ndarray | None = None):
        """``(M, sums or None, image)`` at these shifts, speeds and positions.

        On OpenCL, where the backprojection leaves the image on the device, the metric and its
        weight are computed there (kernels/focus_metric.cl) and the weight goes to the gradient
        kernel without leaving the device (``n_device_metrics`` counts these); elsewhere on the host
        (:func:`clsas.focus.metrics.metric_and_weight`, the same metric in double precision).
        """
        image = self._form(shift_s, c_mps, tx, rx)
        values = np.asarray(image.values).ravel()
        m = self._metric_on_device(image, gradient)
        if m is not None:
            self.n_device_metrics += 1
            return m, (self.sums(shift_s, c_mps, None, tx, rx) if gradient else None), values
        m, g = metric_and_weight(values, self.metric)
        return m, (self.sums(shift_s, c_mps, g, tx, rx) if gradient else None), values

    def _metric_on_device(self, image: Image, gradient: bool) -> float | None:
        """The metric of ``image`` from its device buffer, its weight written into the gradient
        plan's planes (``gradient``); None where the image or a kernel is not there."""
        rows = image.on_device
        if rows is None or not self._metric_selection.opencl:
            return None
        grad = self._gradient_plan() if gradient else None
        if gradient and grad is None:
            return None
        queue = rows.queue if grad is None else grad.queue
        if not rows.valid(queue, image.values) or (self._moments is not None and self._moments.queue is not queue):
            return None
        if self._moments is None:
            n_vox = self.grid.size
            self._moments, self._metric_selection = self._metric_selection.plan(lambda q: FocusMomentsPlan(n_vox, q))
        if gradient and self._weights is None and self._moments is not None:
            n_vox, n_pad, entropy = self.grid.size, grad.n_pad, self.metric == "entropy"
            self._weights, self._metric_selection = self._metric_selection.plan(
                lambda q: FocusWeightPlan(n_vox, n_pad, entropy, q))
        if self._moments is None or (gradient and self._weights is None):
            return None
        if gradient:
            return device_metric(self._moments, self._weights, rows, self.metric, grad.d_wre, grad.d_wim)
        return device_metric(self._moments, None, rows, self.metric)
