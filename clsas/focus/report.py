"""The AutofocusReport type: what :func:`clsas.autofocus` estimated, applied and concluded."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["AutofocusReport"]


@dataclass
class AutofocusReport:
    """What :func:`autofocus` estimated and whether the image got sharper.

    Attributes
    ----------
    improved : bool
        The corrected image is sharper than the input's (else the input was returned).
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

    def summary(self) -> str:
        """A few lines for people."""
        lines = [f"autofocus ({', '.join(self.methods)}; metric {self.metric}) on {self.device}: "
                 f"{self.metric_before:.4g} -> {self.metric_after:.4g} in {self.time_s:.1f} s"
                 + ("" if self.improved else " (not sharper: the input is returned)"),
                 f"  group delay {self.group_delay_s * 1e6:+.2f} us, "
                 f"timing jitter {self.timing_jitter_rms_s * 1e6:.2f} us RMS; air {self.temperature_c:.2f} C "
                 f"({self.temperature_offset_c:+.2f} C), c {self.c_mps:.2f} m/s"]
        if self.los_path_m is not None:
            lines.append(f"  line-of-sight corrections: {f'{self.n_basis} functions' if self.n_basis else 'per stop'}, "
                         f"{np.sqrt(np.mean(self.los_path_m ** 2)) / 2 * 1e3:.2f} mm RMS (one way)")
        lines += [f"  {n}" for n in self.notes]
        return "\n".join(lines)

    def as_dict(self) -> dict:
        """JSON-friendly summary (no per-measurement arrays)."""
        keep = ("improved", "metric", "metric_before", "metric_after", "methods", "group_delay_s",
                "timing_jitter_rms_s", "temperature_c", "c_mps", "temperature_offset_c", "n_basis", "direct_snr_db",
                "time_s", "backend", "device", "stages", "notes")
        out = {k: getattr(self, k) for k in keep}
        if self.los_path_m is not None:
            out["los_rms_m"] = float(np.sqrt(np.mean(self.los_path_m ** 2)) / 2)
        return out
