"""Transducer beams: directivity models, boresights per measurement, and the two-way weight.

A :class:`Beam` is a one-way amplitude pattern ``B(theta)`` (1 on the boresight) of a speaker or
a microphone, ``theta`` the angle between its boresight and the direction to a point:

- :class:`Omni`: 1 everywhere (clsas's behaviour before beams).
- :class:`Piston`: a baffled circular piston of diameter ``D``,
  ``|2 J1(k a sin theta) / (k a sin theta)|`` with ``k = 2 pi f / c`` and ``a = D / 2``.
- :class:`Cone`: a smooth beam of given -6 dB half-angle (or f-number ``N``, half-angle
  ``atan(1 / (2 N))``): ``B = 2^-((theta / half_angle)^2)``, the same at every frequency.
- :class:`Table`: a measured pattern, amplitude at given angles (linear interpolation, 0 past
  the last angle).

:class:`Beams` holds the speaker's and the microphone's beam and their boresights, (n_meas, 3)
unit vectors. The formations and the simulator evaluate a pattern through the same table
(:func:`lookup_table`): ``n`` samples uniform in ``u = sin(theta / 2)`` (0 on the boresight, 1
straight behind), so a narrow beam keeps many samples; the OpenCL kernel (kernels/beam.cl) and
the NumPy twin (:func:`pair_weights`) interpolate the same table linearly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from .. import validate as v

__all__ = ["Beam", "Omni", "Piston", "Cone", "Table", "Beams", "beam_from_spec", "planar_boresights",
           "axis_boresights", "lookup_table", "pair_weights", "BeamWeights", "beam_weights", "BEAM_MODES",
           "LUT_SIZE", "gate_level", "angular_weights", "facing",
           "weights_at_cos"]

BEAM_MODES = ("none", "limited", "weighted")
LUT_SIZE = 1024
MODELS = ("omni", "piston", "cone", "table")


class Beam:
    """A one-way amplitude pattern; subclasses define :meth:`pattern`."""

    model: ClassVar[str] = ""

    def pattern(self, theta_rad: np.ndarray, f_hz: float | np.ndarray, c_mps: float) -> np.ndarray:
        """One-way amplitude at angle ``theta_rad`` off the boresight and frequency ``f_hz``
        (broadcast together), for sound speed ``c_mps``; 1 on the boresight."""
        raise NotImplementedError

    def to_spec(self) -> dict:
        """The beam as a plain dict (stored in the dataset file and written in TOML)."""
        raise NotImplementedError

    def pattern_grid(self, theta_rad: np.ndarray, f_hz: np.ndarray, c_mps: float) -> np.ndarray:
        """``pattern`` on every angle of ``theta_rad`` (any shape) times every frequency of
        ``f_hz`` (1-D): shape ``theta_rad.shape + f_hz.shape`` (the simulator's fast path)."""
        f = np.asarray(f_hz, float)
        if not self.frequency_dependent:
            p = self.pattern(theta_rad, 0.0 if f.size == 0 else float(f[0]), c_mps)
            return np.broadcast_to(p[..., None], (*np.shape(theta_rad), f.size))
        return self.pattern(np.asarray(theta_rad)[..., None], f, c_mps)

    frequency_dependent: ClassVar[bool] = False

    @property
    def is_omni(self) -> bool:
        return False


@dataclass(frozen=True)
class Omni(Beam):
    """Omnidirectional: 1 at every angle."""

    model: ClassVar[str] = "omni"

    def pattern(self, theta_rad, f_hz, c_mps):
        return np.ones(np.broadcast(np.asarray(theta_rad), np.asarray(f_hz)).shape)

    def to_spec(self) -> dict:
        return {"model": "omni"}

    @property
    def is_omni(self) -> bool:
        return True


@dataclass(frozen=True)
class Piston(Beam):
    """A baffled circular piston of diameter ``diameter_m``, m."""

    diameter_m: float
    model: ClassVar[str] = "piston"
    frequency_dependent: ClassVar[bool] = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "diameter_m", v.positive("diameter_m", self.diameter_m))

    def pattern(self, theta_rad, f_hz, c_mps):
        from scipy.special import j1

        x = np.pi * np.asarray(f_hz, float) * self.diameter_m / c_mps * np.sin(np.asarray(theta_rad, float))
        safe = np.where(np.abs(x) < 1e-9, 1.0, x)
        out = np.abs(np.where(np.abs(x) < 1e-9, 1.0, 2 * j1(safe) / safe))
        # a baffled piston radiates nothing behind its baffle
        return np.where(np.cos(theta_rad) > 0, out, 0.0)

    def pattern_grid(self, theta_rad, f_hz, c_mps):
        """As :meth:`Beam.pattern_grid`, through a table of ``|2 J1(x) / x|`` (step 0.005 in
        x, error < 1e-6)."""
        from scipy.special import j1

        th = np.asarray(theta_rad, float)
        f = np.asarray(f_hz, float)
        s = np.where(np.cos(th) > 0, np.abs(np.sin(th)), 0.0)
        scale = np.pi * self.diameter_m / c_mps
        x_max = scale * max(float(np.abs(f).max(initial=0.0)), 1.0) + 0.01
        xs = np.arange(0.0, x_max + 0.005, 0.005)
        tab = np.ones_like(xs)
        tab[1:] = np.abs(2 * j1(xs[1:]) / xs[1:])
        out = np.interp((s[..., None] * (scale * np.abs(f))).ravel(), xs, tab).reshape(*th.shape, f.size)
        return np.where((np.cos(th) > 0)[..., None], out, 0.0)

    def to_spec(self) -> dict:
        return {"model": "piston", "diameter_m": self.diameter_m}


@dataclass(frozen=True)
class Cone(Beam):
    """A smooth beam whose one-way amplitude is 1/2 (-6 dB) at ``half_angle_deg``.

    ``Cone.from_f_number(N)``: half-angle ``atan(1 / (2 N))``.
    """

    half_angle_deg: float
    model: ClassVar[str] = "cone"

    def __post_init__(self) -> None:
        h = v.positive("half_angle_deg", self.half_angle_deg)
        if h >= 180:
            raise ValueError(f"half_angle_deg must be < 180, got {h:g}")
        object.__setattr__(self, "half_angle_deg", h)

    @classmethod
    def from_f_number(cls, f_number: float) -> Cone:
        n = v.positive("f_number", f_number)
        return cls(float(np.degrees(np.arctan(1 / (2 * n)))))

    def pattern(self, theta_rad, f_hz, c_mps):
        t = np.asarray(theta_rad, float) / np.radians(self.half_angle_deg)
        return np.broadcast_to(2.0 ** -(t * t), np.broadcast(t, np.asarray(f_hz)).shape).copy()

    def to_spec(self) -> dict:
        return {"model": "cone", "half_angle_deg": self.half_angle_deg}


@dataclass(frozen=True)
class Table(Beam):
    """A measured pattern: one-way amplitude at increasing angles from 0, degrees (linear
    interpolation, 0 beyond the last angle); normalised to 1 at 0."""

    angles_deg: tuple
    amplitudes: tuple
    model: ClassVar[str] = "table"

    def __post_init__(self) -> None:
        a = v.array("angles_deg", np.asarray(self.angles_deg, float), ndim=1)
        b = v.array("amplitudes", np.asarray(self.amplitudes, float), shape=(len(a),))
        if len(a) < 2 or a[0] != 0 or np.any(np.diff(a) <= 0) or a[-1] > 180:
            raise ValueError("angles_deg must increase from 0 to at most 180 (at least two angles), "
                             f"got {a.tolist()}")
        if np.any(b < 0) or b[0] <= 0:
            raise ValueError(f"amplitudes must be >= 0 with amplitudes[0] > 0, got {b.tolist()}")
        object.__setattr__(self, "angles_deg", tuple(a.tolist()))
        object.__setattr__(self, "amplitudes", tuple((b / b[0]).tolist()))

    def pattern(self, theta_rad, f_hz, c_mps):
        t = np.degrees(np.asarray(theta_rad, float))
        out = np.interp(t, self.angles_deg, self.amplitudes, right=0.0)
        return np.broadcast_to(out, np.broadcast(t, np.asarray(f_hz)).shape).copy()

    def to_spec(self) -> dict:
        return {"model": "table", "angles_deg": list(self.angles_deg), "amplitudes": list(self.amplitudes)}


_SPEC_KEYS = {"omni": (), "piston": ("diameter_m",), "cone": ("half_angle_deg", "f_number"),
              "table": ("angles_deg", "amplitudes")}


def beam_from_spec(spec: Any, name: str = "beam") -> Beam:
    """A :class:`Beam` from a dict such as ``{"model": "piston", "diameter_m": 0.006}`` (or a
    Beam, returned as is); unknown models and keys are refused naming ``name``."""
    if isinstance(spec, Beam):
        return spec
    if spec is None:
        return Omni()
    if isinstance(spec, str):
        spec = {"model": spec}
    if not isinstance(spec, dict):
        raise TypeError(f"{name} must be a clsas.physics.beam.Beam or a dict with a 'model', got {type(spec).__name__}")
    model = v.choice(f"{name}.model", spec.get("model"), MODELS)
    unknown = set(spec) - {"model", *_SPEC_KEYS[model]}
    if unknown:
        raise ValueError(f"{name}: unknown key(s) {sorted(unknown)} for model {model!r}; "
                         f"known: {', '.join(_SPEC_KEYS[model]) or 'none'}")
    if model == "omni":
        return Omni()
    if model == "cone" and ("half_angle_deg" in spec) == ("f_number" in spec):
        raise ValueError(f"{name}: a cone takes exactly one of half_angle_deg and f_number")
    try:  # the model's own checks, named after the transducer they concern
        if model == "piston":
            return Piston(_need(spec, "diameter_m", name))
        if model == "cone":
            return Cone(spec["half_angle_deg"]) if "half_angle_deg" in spec else Cone.from_f_number(spec["f_number"])
        return Table(tuple(_need(spec, "angles_deg", name)), tuple(_need(spec, "amplitudes", name)))
    except (ValueError, TypeError) as exc:
        if str(exc).startswith(f"{name}:"):
            raise
        raise type(exc)(f"{name}: {exc}") from None


def _need(spec: dict, key: str, name: str) -> Any:
    if key not in spec:
        raise ValueError(f"{name}: model {spec['model']!r} needs {key!r}")
    return spec[key]


@dataclass(frozen=True)
class Beams:
    """The speaker's and the microphone's beam and their boresights per measurement.

    Parameters
    ----------
    speaker, microphone : Beam or dict
        One-way patterns (a dict goes through :func:`beam_from_spec`).
    tx_boresight, rx_boresight : (3,) or (n_meas, 3) array
        Where each transducer points, per measurement (normalised here); a (3,) vector is
        the same for every measurement (a planar rig: ``(0, 0, 1)``, the scan normal).
    n_meas : int
        Measurements.
    """

    speaker: Beam
    microphone: Beam
    tx_boresight: np.ndarray
    rx_boresight: np.ndarray
    n_meas: int

    def __post_init__(self) -> None:
        n = v.positive_int("n_meas", self.n_meas)
        object.__setattr__(self, "speaker", beam_from_spec(self.speaker, "speaker"))
        object.__setattr__(self, "microphone", beam_from_spec(self.microphone, "microphone"))
        object.__setattr__(self, "tx_boresight", v.unit_rows("tx_boresight", self.tx_boresight, n))
        object.__setattr__(self, "rx_boresight", v.unit_rows("rx_boresight", self.rx_boresight, n))

    @property
    def is_omni(self) -> bool:
        """Both transducers omnidirectional (the weight is 1 everywhere)."""
        return self.speaker.is_omni and self.microphone.is_omni

    def subset(self, index: Any) -> Beams:
        tx, rx = self.tx_boresight[index], self.rx_boresight[index]
        return Beams(self.speaker, self.microphone, tx, rx, len(tx))

    def specs(self) -> dict:
        return {"speaker": self.speaker.to_spec(), "microphone": self.microphone.to_spec()}


def planar_boresights(n_meas: int, normal: Any = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(n_meas, 3) boresights of a planar rig: every transducer faces ``normal`` (+z, the
    scan plane's normal, by default)."""
    return v.unit_rows("normal", normal, v.positive_int("n_meas", n_meas)).copy()


def axis_boresights(positions_m: Any, axis_point_m: Any = (0.0, 0.0, 0.0),
                    axis_dir: Any = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(n, 3) boresights of a turntable or cylindrical scan: from each position straight
    toward the rotation axis (through ``axis_point_m`` along ``axis_dir``), perpendicular to it."""
    p = v.array("positions_m", positions_m, shape=(None, 3))
    a = v.unit_rows("axis_dir", axis_dir, 1)[0]
    rel = p - v.array("axis_point_m", axis_point_m, shape=(3,))
    radial = rel - np.outer(rel @ a, a)
    if np.any(np.linalg.norm(radial, axis=1) == 0):
        raise ValueError("positions_m: a position on the rotation axis has no direction toward it")
    return v.unit_rows("boresight", -radial, len(p))


def lookup_table(beam: Beam, fc_hz: float, c_mps: float, n: int = LUT_SIZE) -> np.ndarray:
    """(n,) float64 pattern samples uniform in ``u = sin(theta / 2)`` from 0 to 1 (theta from
    0 to 180 degrees), at frequency ``fc_hz`` and sound speed ``c_mps``."""
    u = np.linspace(0.0, 1.0, n)
    return np.asarray(beam.pattern(2 * np.arcsin(u), fc_hz, c_mps), float).reshape(n)


def gate_level(floor_db: float) -> float:
    """The two-way amplitude a pair needs to be kept by ``beam="limited"``."""
    return float(10 ** (v.finite("beam_floor_db", floor_db) / 20))


def _lut_eval(lut: np.ndarray, cos_theta: np.ndarray) -> np.ndarray:
    """The table at ``cos theta`` (linear interpolation in u = sqrt((1 - cos theta) / 2))."""
    n = len(lut)
    u = np.sqrt(np.clip(0.5 - 0.5 * cos_theta, 0.0, 1.0)) * (n - 1)
    i0 = np.minimum(np.floor(u), n - 2).astype(np.int64)
    w = u - i0
    return (1 - w) * lut[i0] + w * lut[i0 + 1]


def pair_weights(luts: tuple[np.ndarray, np.ndarray], tx_m: np.ndarray, rx_m: np.ndarray, tx_dir: np.ndarray,
                 rx_dir: np.ndarray, points_m: np.ndarray, gate: float | None) -> np.ndarray:
    """Two-way weight of one measurement at each point: the speaker's table times the
    microphone's, or (``gate`` given, ``beam="limited"``) 1 where that product is at least
    ``gate`` and 0 elsewhere. The twin of kernels/beam.cl's ``beam_weight``.

    Parameters
    ----------
    luts : (tx table, rx table), each (n,) from :func:`lookup_table`
    tx_m, rx_m, tx_dir, rx_dir : (3,) positions, m, and unit boresights of the measurement, or
        (n_vox, 3): each point's own measurement (FFBP's leaves)
    points_m : (n_vox, 3) m

    Returns
    -------
    (n_vox,) float64
    """
    dt = points_m - tx_m
    dr = points_m - rx_m
    ct = np.sum(dt * tx_dir, axis=-1) / np.maximum(np.linalg.norm(dt, axis=1), 1e-30)
    cr = np.sum(dr * rx_dir, axis=-1) / np.maximum(np.linalg.norm(dr, axis=1), 1e-30)
    w = _lut_eval(luts[0], ct) * _lut_eval(luts[1], cr)
    return w if gate is None else (w >= gate).astype(float)


@dataclass(frozen=True)
class BeamWeights:
    """What a formation needs to weight pairs: the two tables (speaker, microphone), (2, n)
    float64, the boresights (n_meas, 3) each, and the gate (None: weighted)."""

    luts: np.ndarray
    tx_dir: np.ndarray
    rx_dir: np.ndarray
    gate: float | None


def beam_weights(beams: Beams | None, mode: str, fc_hz: float, c_mps: float | np.ndarray,
                 floor_db: float = -12.0, n: int = LUT_SIZE) -> BeamWeights | None:
    """The weights of ``beam=mode`` (:data:`BEAM_MODES`) for ``beams``, or None where nothing
    is weighted (``"none"``, no beams, or both omnidirectional).

    The patterns are evaluated at ``fc_hz`` and the mean of ``c_mps``. ``"limited"`` keeps the
    pairs whose two-way amplitude is at least ``floor_db`` (default -12 dB: inside each
    transducer's -6 dB beam when speaker and microphone are together); ``"weighted"`` scales
    every pair by its two-way amplitude.
    """
    mode = v.choice("beam", mode, BEAM_MODES)
    gate = gate_level(floor_db)
    if mode == "none" or beams is None or beams.is_omni:
        return None
    if not isinstance(beams, Beams):
        raise TypeError(f"beams must be clsas.physics.beam.Beams, got {type(beams).__name__}")
    c = float(np.mean(c_mps))
    luts = np.stack([lookup_table(beams.speaker, fc_hz, c, n), lookup_table(beams.microphone, fc_hz, c, n)])
    return BeamWeights(luts, beams.tx_boresight, beams.rx_boresight, gate if mode == "limited" else None)


def angular_weights(weights: BeamWeights, sin_theta: np.ndarray) -> np.ndarray:
    """The two-way weight of a plane-wave component at ``sin_theta`` off the boresight (both
    transducers facing the same way, as on a planar rig): the angular twin of
    :func:`pair_weights` for the wavenumber-domain formations (0 where ``|sin_theta| > 1``)."""
    s = np.abs(np.asarray(sin_theta, float))
    return np.where(s <= 1.0, weights_at_cos(weights, np.sqrt(np.clip(1.0 - s * s, 0.0, 1.0))), 0.0)


def weights_at_cos(weights: BeamWeights, cos_theta: np.ndarray) -> np.ndarray:
    """The two-way weight (or gate) of ``weights`` where both transducers see a direction at
    ``cos_theta`` from their common boresight."""
    w = _lut_eval(weights.luts[0], cos_theta) * _lut_eval(weights.luts[1], cos_theta)
    return w if weights.gate is None else (w >= weights.gate).astype(float)


def facing(weights: BeamWeights, normal: np.ndarray, tol: float = 1e-3) -> bool:
    """Whether every boresight of ``weights`` is ``normal`` (a unit vector) to within ``tol``."""
    n = np.asarray(normal, float)
    return bool(np.all(weights.tx_dir @ n >= 1 - tol) and np.all(weights.rx_dir @ n >= 1 - tol))
