"""Geometry calibration from the data: ring radius, transducer height and group delay by focus.

A turntable rig's stated geometry (the transducers' distance from the axis, their height, the
chain's group delay) is measured once with a ruler and a loopback; a few millimetres off
defocus an image at 20-30 kHz (a wavelength is 11-17 mm). :func:`calibrate` scans one such
parameter over a range around its stated value, forms the image at each candidate (the range
profiles are computed once, by :class:`clsas.focus.engine.FocusEngine`) and takes the value
where the focus metric (:mod:`clsas.focus.metrics`) peaks, refined by a parabola through the
best candidate and its neighbours.

Uncertainty: the same scan on two disjoint halves of the measurements (the first and second
half in order: for a turntable, two opposite half-turns, which look at the target from
different sides) gives two estimates. The uncertainty reported is their half-difference (the
spread of the mean of two estimates whose errors are independent) or the distance from the
whole data's estimate to their mean, whichever is larger. Their disagreement also flags a
model error that a single curve cannot show (e.g. an axis that is not where the geometry
says); their agreement does not prove the model right (a metric with two peaks can put both
halves on the same wrong one). The metric's curvature at the peak is reported too, as the
offset at which the log-metric drops by 0.01 (a width, not a standard deviation; with
``metric="sectors"``, where the sectors' mean correlation drops by 0.01).

``metric="sectors"`` trusts no sharpness: the measurements are cut into ``sectors`` (8)
disjoint runs in acquisition order (on a turntable, arcs of the turn that see the target from
different sides), each run is imaged alone, and the metric is the mean ``|.|``-correlation of
every pair of those images. A wrong path length moves each arc's image of a feature towards or
away from that arc, so the images agree best where the geometry is right; a sharper image
bought by focusing on one glint does not make them agree. On an extended target it is the
check to prefer. On the public AirSAS scans the two disagree (the own-data guide gives both,
from ``bench/airsas_compare.py --calibrate``).

What can and cannot be told apart: a ring radius error moves every path by about twice the
error (both transducers), and a group delay moves every path by ``c`` times the delay; over a
small target at the centre of a turntable the two are nearly the same change, so calibrate
one with the other fixed, and read the result as "the path length that focuses" unless the
other is known. Heights change the paths to a horizontal image plane only to second order:
they are weakly determined (a wide curve, a large uncertainty), and the report says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import validate as v
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset

__all__ = ["PARAMETERS", "CAL_METRICS", "Calibration", "apply_calibration", "calibrate", "perturb"]

log = logging.getLogger(__name__)

#: what :func:`calibrate` can estimate, with the unit of its offset
PARAMETERS = {"radius": "m", "height": "m", "group_delay": "s"}
#: the curves :func:`calibrate` can maximise: the focus metrics, and the sectors' agreement
CAL_METRICS = ("sharpness", "entropy", "sectors")
_DEFAULT_SPAN = {"radius": (0.02, 0.001), "height": (0.05, 0.005), "group_delay": (6e-5, 3e-6)}


@dataclass
class Calibration:
    """What :func:`calibrate` found for one parameter.

    Attributes
    ----------
    parameter : str
        ``"radius"`` (m, added to both transducers' distance from the rotation axis),
        ``"height"`` (m, added to both transducers' z) or ``"group_delay"`` (s, added to the
        chain's delay: ``t0_s`` goes down by it).
    estimate : float
        The offset that focuses best (full data), in the parameter's unit.
    uncertainty : float
        Half the difference between the two halves' estimates, or the distance from
        ``estimate`` to their mean, whichever is larger.
    halves : (float, float)
        The estimates from the first and the second half of the measurements.
    width : float
        Offset from the peak at which the log-metric has dropped by 0.01 (from the parabola);
        for ``metric="sectors"``, at which the sectors' mean correlation (0 to 1, not a log) has
        dropped by 0.01.
    offsets, metric : arrays
        The scanned offsets and the metric at each (full data).
    at_edge : bool
        The best candidate is at an end of the scanned range: the estimate is a bound only.
    applied : bool
        Whether the returned dataset carries the correction.
    notes : list of str
    """

    parameter: str
    estimate: float
    uncertainty: float
    halves: tuple[float, float]
    width: float
    offsets: np.ndarray
    metric: np.ndarray
    at_edge: bool = False
    applied: bool = False
    metric_name: str = "sharpness"
    notes: list = field(default_factory=list)

    @property
    def unit(self) -> str:
        return PARAMETERS[self.parameter]

    def summary(self) -> str:
        """One line for people, in mm or microseconds."""
        k, u = (1e6, "us") if self.unit == "s" else (1e3, "mm")
        a, b = self.halves
        text = (f"{self.parameter}: {self.estimate * k:+.2f} {u} +- {self.uncertainty * k:.2f} {u} "
                f"(halves {a * k:+.2f} and {b * k:+.2f} {u}; curve width {self.width * k:.2f} {u})"
                + ("; at the edge of the scanned range" if self.at_edge else "")
                + ("; applied" if self.applied else ""))
        return "\n  ".join([text, *self.notes])

    def as_dict(self) -> dict:
        return {"parameter": self.parameter, "unit": self.unit, "estimate": self.estimate,
                "uncertainty": self.uncertainty, "halves": list(self.halves), "width": self.width,
                "at_edge": self.at_edge, "applied": self.applied, "metric": self.metric_name,
                "offsets": self.offsets.tolist(), "metric_values": self.metric.tolist(), "notes": list(self.notes)}


def perturb(ds: Dataset, parameter: str, offset: float, *, axis_xy_m: tuple[float, float] = (0.0, 0.0)
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (tx, rx, t0_s) of ``ds`` with ``parameter`` moved by ``offset`` (see :class:`Calibration`).

    ``"radius"`` moves both transducers along the horizontal line from the rotation axis
    (vertical, through ``axis_xy_m``) to each of them; a transducer on the axis stays.
    """
    v.choice("parameter", parameter, tuple(PARAMETERS))
    offset = v.finite("offset", offset)
    tx, rx, t0 = ds.tx_positions.copy(), ds.rx_positions.copy(), ds.t0_s.copy()
    if parameter == "radius":
        for p in (tx, rx):
            d = p[:, :2] - np.asarray(axis_xy_m, float)
            r = np.hypot(d[:, 0], d[:, 1])
            scale = np.where(r > 0, (r + offset) / np.where(r > 0, r, 1.0), 1.0)
            p[:, :2] = np.asarray(axis_xy_m, float) + d * scale[:, None]
    elif parameter == "height":
        tx[:, 2] += offset
        rx[:, 2] += offset
    else:
        t0 -= offset
    return tx, rx, t0


def apply_calibration(ds: Dataset, cal: Calibration, *, axis_xy_m: tuple[float, float] = (0.0, 0.0)) -> Dataset:
    """The dataset with ``cal.estimate`` applied (positions or ``t0_s``), recorded in its provenance."""
    tx, rx, t0 = perturb(ds, cal.parameter, cal.estimate, axis_xy_m=axis_xy_m)
    step = {"step": "calibrate", "parameter": cal.parameter, "offset": float(cal.estimate),
            "unit": cal.unit, "uncertainty": float(cal.uncertainty)}
    return ds.replace(tx_positions=tx, rx_positions=rx, t0_s=t0, provenance=[*ds.provenance, step])


def _peak(offsets: np.ndarray, m: np.ndarray) -> tuple[float, float, bool]:
    """Parabolic peak of the sampled curve: (position, width at -0.01, at an edge)."""
    i = int(np.argmax(m))
    if i == 0 or i == len(m) - 1:
        return float(offsets[i]), float("nan"), True
    x, y = offsets[i - 1: i + 2], m[i - 1: i + 2]
    a, b, _ = np.polyfit(x - x[1], y, 2)
    if a >= 0:
        return float(offsets[i]), float("nan"), False
    peak = float(np.clip(-b / (2 * a), x[0] - x[1], x[2] - x[1]) + x[1])
    return peak, float(np.sqrt(0.01 / -a)), False


def _curve(engine, ds: Dataset, parameter: str, offsets: np.ndarray, axis_xy_m) -> np.ndarray:
    """The focus metric of ``ds``'s image at each offset (profiles computed once, by ``engine``)."""
    from .metrics import metric_and_weight

    out = np.empty(len(offsets))
    for k, off in enumerate(offsets):
        tx, rx, t0 = perturb(ds, parameter, off, axis_xy_m=axis_xy_m)
        values = engine.image(t0 - ds.t0_s, ds.c_per_meas, tx, rx)
        out[k] = metric_and_weight(values, engine.metric)[0]
    return out


def _sector_curve(engine, ds: Dataset, parameter: str, offsets: np.ndarray, axis_xy_m, sectors: int) -> np.ndarray:
    """The sectors' mean pairwise |.|-correlation at each offset (see the module docstring)."""
    which = (np.arange(ds.n_meas) * sectors) // ds.n_meas  # disjoint runs in acquisition order
    out = np.empty(len(offsets))
    iu = np.triu_indices(sectors, 1)
    for k, off in enumerate(offsets):
        tx, rx, t0 = perturb(ds, parameter, off, axis_xy_m=axis_xy_m)
        mag = np.abs(engine.stop_images(t0 - ds.t0_s, ds.c_per_meas, which, None, tx, rx)).astype(np.float64)
        norm = np.linalg.norm(mag, axis=1)
        gram = (mag @ mag.T) / np.maximum(np.outer(norm, norm), 1e-300)
        out[k] = float(gram[iu].mean())
    return out


def _checked(dataset, parameter: str, metric: str, sectors, span, step) -> tuple[float, float, int]:
    """:func:`calibrate`'s inputs checked by name, before any work: ``(span, step, sectors)``."""
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset, got {type(dataset).__name__}")
    v.choice("parameter", parameter, tuple(PARAMETERS))
    v.choice("metric", metric, CAL_METRICS)
    if metric == "sectors":
        sectors = v.positive_int("sectors", sectors)
        if sectors < 2:
            raise ValueError(f"sectors must be 2 or more, got {sectors}")
    d_span, d_step = _DEFAULT_SPAN[parameter]
    span = d_span if span is None else v.positive("span", span)
    step = d_step if step is None else v.positive("step", step)
    if step > span:
        raise ValueError(f"step ({step:g}) must not exceed span ({span:g})")
    if dataset.n_meas < 4:
        raise ValueError(f"calibrate needs at least 4 measurements, the dataset has {dataset.n_meas}")
    if metric == "sectors" and dataset.n_meas < 2 * sectors:
        raise ValueError(f"sectors={sectors} needs at least {2 * sectors} measurements (each half of the data is "
                         f"cut into that many), the dataset has {dataset.n_meas}")
    return span, step, sectors


def _estimate_with_halves(curve, dataset: Dataset, parameter: str, metric: str, offsets: np.ndarray) -> Calibration:
    """The curve's peak on the whole data, and its uncertainty from the peaks of the two halves."""
    full = curve(dataset)
    est, width, edge = _peak(offsets, full)
    half = dataset.n_meas // 2
    halves = tuple(_peak(offsets, curve(dataset.subset(rows)))[0]
                   for rows in (slice(0, half), slice(half, dataset.n_meas)))
    # the halves' spread, or how far the whole data's estimate lies from theirs, whichever is larger
    spread = max(abs(halves[0] - halves[1]) / 2, abs(est - 0.5 * (halves[0] + halves[1])))
    return Calibration(parameter=parameter, estimate=est, uncertainty=spread,
                       halves=(float(halves[0]), float(halves[1])), width=width, offsets=offsets, metric=full,
                       at_edge=edge, metric_name=metric)


def _caveats(cal: Calibration, span: float) -> list[str]:
    """What limits the estimate: a peak at the range's end, a curve wider than it, a parameter held fixed."""
    notes = []
    if cal.at_edge:
        notes.append("the metric is largest at the end of the scanned range: widen span")
    if np.isfinite(cal.width) and cal.width > span:
        notes.append("the curve is wider than the scanned range: the parameter is weakly determined")
    if cal.parameter in ("radius", "group_delay"):
        notes.append("radius and group delay move the paths nearly alike (2 dr ~ c dt): one was held fixed")
    return notes


def calibrate(
    dataset: Dataset,
    grid: VoxelGrid,
    parameter: str = "radius",
    *,
    span: float | None = None,
    step: float | None = None,
    metric: str = "sharpness",
    sectors: int = 8,
    apply: bool = False,
    axis_xy_m: tuple[float, float] = (0.0, 0.0),
    backend: str | None = None,
    device: Any = None,
) -> tuple[Dataset, Calibration]:
    """Estimate a geometry parameter from the data by focus (see the module docstring).

    Parameters
    ----------
    dataset : Dataset
        Preprocessed recordings (background and shared clutter removed: a static echo
        focuses too and pulls the estimate).
    grid : VoxelGrid
        Where the target is; a grid around it is faster and cleaner than the whole field.
    parameter : {"radius", "height", "group_delay"}
    span, step : float, optional
        Offsets ``-span .. +span`` in steps of ``step`` (m or s); defaults: radius 20 mm in
        1 mm, height 50 mm in 5 mm, group delay 60 us in 3 us.
    metric : {"sharpness", "entropy", "sectors"}
        The curve to maximise: a focus metric of the whole image, or (``"sectors"``) how well
        the images of ``sectors`` disjoint runs of the measurements agree (trusts no sharpness;
        the one to prefer on an extended target).
    sectors : int
        Runs of the measurements for ``metric="sectors"`` (2 or more; each half of the data,
        for the uncertainty, is cut into as many).
    apply : bool
        Return the dataset with the estimate applied (else the input, unchanged).
    axis_xy_m : (float, float)
        The rotation axis (``"radius"``), metres; the importers put it at the origin.
    backend, device : as for :func:`clsas.reconstruct`.

    Returns
    -------
    (Dataset, Calibration)
    """
    from .engine import FocusEngine

    span, step, sectors = _checked(dataset, parameter, metric, sectors, span, step)
    n = int(np.floor(span / step + 1e-9))
    offsets = step * np.arange(-n, n + 1)
    margin = span if parameter == "group_delay" else 2.5 * span / 300.0 + 1e-4

    def curve(ds: Dataset) -> np.ndarray:
        engine = FocusEngine(ds, grid, margin_s=margin, metric="sharpness" if metric == "sectors" else metric,
                             backend=backend, device=device)
        if metric == "sectors":
            return _sector_curve(engine, ds, parameter, offsets, axis_xy_m, sectors)
        return _curve(engine, ds, parameter, offsets, axis_xy_m)

    cal = _estimate_with_halves(curve, dataset, parameter, metric, offsets)
    cal.notes.extend(_caveats(cal, span))
    log.info("calibrate %s", cal.summary())
    if apply:
        out = apply_calibration(dataset, cal, axis_xy_m=axis_xy_m)
        cal.applied = True
        return out, cal
    return dataset, cal
