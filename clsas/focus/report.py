"""The AutofocusReport type: what :func:`clsas.autofocus` estimated, applied and concluded."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["AutofocusReport", "ParameterEstimate"]


@dataclass
class ParameterEstimate:
    """One parameter as the scan determined it (or not).

    Attributes
    ----------
    name : str
        ``"group_delay"``, ``"timing"``, ``"temperature"``, ``"motion"``.
    unit : str
    estimate : float
        The estimate (before the decision to apply it), in ``unit``; NaN where not estimated.
    uncertainty : float
        Its standard uncertainty, in ``unit`` (from the two halves of the stops, or the scatter
        of the direct arrivals); NaN where unknown.
    determined : bool
        The scan constrains it (see ``how``).
    applied : bool
        It is in the returned dataset (determined, and the check passed).
    how : str
        How it was estimated and judged, and why not applied where not.
    """

    name: str
    unit: str
    estimate: float = float("nan")
    uncertainty: float = float("nan")
    determined: bool = False
    applied: bool = False
    how: str = ""

    def as_dict(self) -> dict:
        return {"estimate": self.estimate, "uncertainty": self.uncertainty, "unit": self.unit,
                "determined": self.determined, "applied": self.applied, "how": self.how}

    def line(self) -> str:
        state = ("applied" if self.applied else "determined, not applied") if self.determined else "not determined"
        return f"{self.name}: {self.estimate:+.4g} +- {self.uncertainty:.2g} {self.unit} ({state}; {self.how})"


@dataclass
class AutofocusReport:
    """What :func:`autofocus` estimated and whether the image got sharper.

    Attributes
    ----------
    improved : bool
        A correction was applied and passed the check (images of two disjoint halves of the
        stops agree better after it, each corrected with the other half's motion estimate);
        else the input was returned (``notes`` say why). Not "sharper": sharpness over-fits.
    metric, metric_before, metric_after : str, float, float
        The focus metric and its value on the input and on the returned dataset.
    history : list of float
        The metric at every image the search formed, in order.
    methods : list of str
        What was tried; ``notes`` says what was found or skipped and why.
    t0_s : (n_meas,) array
        The estimated time of sample 0 (stated ``t0_s`` where no delay was estimated), s.
    group_delay_s : float
        Stated minus estimated ``t0_s``, median over measurements (the unknown delay), s.
    timing_jitter_rms_s : float
        RMS of the per-measurement delay about that median, s.
    temperature_c, c_mps : float
        Estimated air temperature (°C) and speed of sound (m/s, mean over measurements).
    temperature_offset_c : float
        Estimated minus stated temperature, °C.
    los_path_m : (n_stops,) array
        Estimated true-minus-stated bistatic path per stop at the focus centre, m.
    position_correction_m : (n_meas, 3) array
        What was added to the positions: half the path correction along the line of sight.
    stop_index : (n_meas,) array
        The stop of each measurement.
    focus_centre_m : (3,) array
        Where the lines of sight point (the image's intensity centroid), m.
    n_basis : int
        Functions of the motion basis (after the unobservable ones were removed).
    direct_snr_db : float
        Median level of the direct sound over the matched filter's RMS elsewhere (NaN: none).
    time_s : float
    stages : list of dict
        Per step: name, metric after, evaluations, time.
    notes : list of str
    parameters : dict of str to ParameterEstimate
        Per parameter (``group_delay``, ``timing``, ``temperature``, ``motion``): estimate,
        uncertainty, determined, applied.
    check : dict
        The held-out check: ``coherence_before``, ``coherence_heldout`` (motion of the other
        half), ``coherence_after`` (the returned correction), ``passed``, ``motion_passed``; with
        ``consistency_iter``, ``excess_after`` and ``noise_floor``, and where a correction was
        judged ``excess_before``, ``excess_ratio`` and ``consistency_passed``
        (:mod:`clsas.focus.final_consistency`).
    """

    improved: bool = False
    metric: str = "sharpness"
    metric_before: float = float("nan")
    metric_after: float = float("nan")
    history: list = field(default_factory=list)
    methods: list = field(default_factory=list)
    t0_s: np.ndarray | None = None
    group_delay_s: float = 0.0
    timing_jitter_rms_s: float = 0.0
    temperature_c: float = float("nan")
    c_mps: float = float("nan")
    temperature_offset_c: float = 0.0
    los_path_m: np.ndarray | None = None
    position_correction_m: np.ndarray | None = None
    stop_index: np.ndarray | None = None
    focus_centre_m: np.ndarray | None = None
    n_basis: int = 0
    direct_snr_db: float = float("nan")
    time_s: float = 0.0
    backend: str = ""
    device: str = ""
    stages: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    parameters: dict = field(default_factory=dict)
    check: dict = field(default_factory=dict)

    def summary(self) -> str:
        """A few lines for people."""
        lines = [f"autofocus ({', '.join(self.methods)}; metric {self.metric}) on {self.device}: "
                 f"{self.metric_before:.4g} -> {self.metric_after:.4g} in {self.time_s:.1f} s"
                 + ("" if self.improved else " (the data-consistency check withdrew the correction: the input is "
                                             "returned)" if self.check.get("consistency_passed") is False
                    else " (nothing applied that passed the check: the input is returned)"),
                 f"  group delay {self.group_delay_s * 1e6:+.2f} us, "
                 f"timing jitter {self.timing_jitter_rms_s * 1e6:.2f} us RMS; air {self.temperature_c:.2f} C "
                 f"({self.temperature_offset_c:+.2f} C), c {self.c_mps:.2f} m/s"]
        if self.los_path_m is not None:
            lines.append(f"  line-of-sight corrections: {f'{self.n_basis} functions' if self.n_basis else 'per stop'}, "
                         f"{np.sqrt(np.mean(self.los_path_m ** 2)) / 2 * 1e3:.2f} mm RMS (one way)")
        lines += [f"  {p.line()}" for p in self.parameters.values()]
        consistency = ("excess_before", "excess_after", "excess_ratio", "noise_floor", "consistency_passed")
        if self.check:
            lines.append("  check (disjoint halves of the stops): coherence "
                         + ", ".join(f"{k} {v:.3f}" for k, v in self.check.items()
                                     if isinstance(v, float) and k not in consistency)
                         + f"; {'passed' if self.check.get('passed') else 'failed'}")
        c = self.check
        if "excess_after" in c:
            before = f"{c['excess_before']:.3f} -> " if "excess_before" in c else ""
            ratio = f" (ratio {c['excess_ratio']:.2f})" if "excess_ratio" in c else ""
            lines.append(f"  data consistency: unexplained beyond the noise {before}{c['excess_after']:.3f}{ratio}"
                         + ("" if c.get("consistency_passed", True) else "; the correction was withdrawn"))
        lines += [f"  {n}" for n in self.notes]
        return "\n".join(lines)

    def as_dict(self) -> dict:
        """JSON-friendly summary (no per-measurement arrays)."""
        keep = ("improved", "metric", "metric_before", "metric_after", "methods", "group_delay_s",
                "timing_jitter_rms_s", "temperature_c", "c_mps", "temperature_offset_c", "n_basis", "direct_snr_db",
                "time_s", "backend", "device", "stages", "notes")
        out = {k: getattr(self, k) for k in keep}
        out["parameters"] = {k: p.as_dict() for k, p in self.parameters.items()}
        out["check"] = dict(self.check)
        if self.los_path_m is not None:
            out["los_rms_m"] = float(np.sqrt(np.mean(self.los_path_m ** 2)) / 2)
        return out
