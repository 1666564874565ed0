"""Speed of sound, ISO 9613-1 air absorption, resolution limits and aperture sampling."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import validate as v

__all__ = [
    "speed_of_sound",
    "air_absorption_db_per_m",
    "Limits",
    "resolution_limits",
]

_PR_KPA = 101.325  # reference pressure
_T0_K = 293.15  # reference temperature
_T01_K = 273.16  # triple point of water


def _check_air(temperature_c: float, humidity_pct: float | None = None) -> float:
    t = v.finite("temperature_c", temperature_c)
    if t <= -273.15:
        raise ValueError(f"temperature_c must be above absolute zero, got {t:g}")
    if humidity_pct is not None:
        h = v.finite("humidity_pct", humidity_pct)
        if not 0 <= h <= 100:
            raise ValueError(f"humidity_pct must be in [0, 100], got {h:g}")
    return t


def speed_of_sound(temperature_c: float | np.ndarray = 20.0) -> float | np.ndarray:
    """Speed of sound in dry air, ``331.3 sqrt(1 + T/273.15)`` m/s (343.2 m/s at 20 C).

    ``temperature_c`` may be an array (one temperature per measurement, as logged during a
    scan); the result then has its shape.

    Parameters
    ----------
    temperature_c : float or numpy.ndarray
        Air temperature, degrees Celsius.

    Returns
    -------
    float or numpy.ndarray
        m/s.

    Examples
    --------
    >>> import clsas
    >>> round(float(clsas.speed_of_sound(20.0)), 1)
    343.2
    """
    if np.ndim(temperature_c) == 0:
        t = _check_air(temperature_c)
        return 331.3 * float(np.sqrt(1.0 + t / 273.15))
    t = v.array("temperature_c", temperature_c)
    if np.any(t <= -273.15):
        raise ValueError(f"temperature_c must be above absolute zero, got min {t.min():g}")
    return 331.3 * np.sqrt(1.0 + t / 273.15)


def air_absorption_db_per_m(
    f_hz: float | np.ndarray,
    temperature_c: float = 20.0,
    humidity_pct: float = 50.0,
    pressure_kpa: float = _PR_KPA,
) -> float | np.ndarray:
    """Pure-tone atmospheric absorption after ISO 9613-1:1993, in dB/m.

    At 20 C, 50 % RH and 101.325 kPa this gives 0.524 dB/m at 20 kHz, 0.937 at 30 kHz and
    1.661 at 50 kHz.

    Parameters
    ----------
    f_hz : float or numpy.ndarray
        Frequency, Hz.
    temperature_c : float
        Air temperature, degrees Celsius.
    humidity_pct : float
        Relative humidity, percent.
    pressure_kpa : float
        Atmospheric pressure, kPa.

    Returns
    -------
    float or numpy.ndarray
        Absorption, dB per metre of path.

    Examples
    --------
    >>> import clsas
    >>> round(float(clsas.air_absorption_db_per_m(30e3)), 3)
    0.937
    """
    t_c = _check_air(temperature_c, humidity_pct)
    pa = v.positive("pressure_kpa", pressure_kpa)
    f = np.asarray(f_hz, dtype=np.float64)
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("f_hz must be finite and >= 0")
    T = t_c + 273.15
    p_rel = pa / _PR_KPA
    c_sat = -6.8346 * (_T01_K / T) ** 1.261 + 4.6151
    h = humidity_pct * 10.0**c_sat / p_rel  # molar concentration of water vapour, %
    fr_o = p_rel * (24.0 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    fr_n = p_rel * (T / _T0_K) ** -0.5 * (9.0 + 280.0 * h * np.exp(-4.170 * ((T / _T0_K) ** (-1 / 3) - 1)))
    alpha = (
        8.686
        * f**2
        * (
            1.84e-11 / p_rel * (T / _T0_K) ** 0.5
            + (T / _T0_K) ** -2.5
            * (
                0.01275 * np.exp(-2239.1 / T) / (fr_o + f**2 / fr_o)
                + 0.1068 * np.exp(-3352.0 / T) / (fr_n + f**2 / fr_n)
            )
        )
    )
    return float(alpha) if np.ndim(alpha) == 0 else alpha


@dataclass(frozen=True)
class Limits:
    """Resolution limits of a scan configuration (all lengths in m)."""

    c_mps: float
    bandwidth_hz: float
    center_hz: float
    range_resolution_m: float
    cross_range_resolution_m: tuple[float, float]
    range_m: float
    absorption_db_per_m: dict[float, float]
    spacing_m: tuple[float, float]
    required_spacing_m: float
    undersampling: tuple[float, float]
    warnings: list[str] = field(default_factory=list)

    def report(self) -> str:
        """Human-readable summary, one quantity per line."""
        lines = [
            f"speed of sound            {self.c_mps:.1f} m/s",
            f"band                      {self.center_hz - self.bandwidth_hz / 2:.0f}-"
            f"{self.center_hz + self.bandwidth_hz / 2:.0f} Hz (B = {self.bandwidth_hz:.0f} Hz)",
            f"range resolution c/(2B)   {self.range_resolution_m * 100:.2f} cm",
            f"cross-range at {self.range_m:.2f} m      "
            f"{self.cross_range_resolution_m[0] * 100:.2f} cm (x) x "
            f"{self.cross_range_resolution_m[1] * 100:.2f} cm (y)  [lambda R / (2 D)]",
        ]
        for f, a in self.absorption_db_per_m.items():
            lines.append(
                f"air absorption {f / 1e3:5.1f} kHz   {a:.3f} dB/m "
                f"({2 * self.range_m * a:.1f} dB over the {2 * self.range_m:.2f} m round trip)"
            )
        lines.append(
            f"stop spacing              {self.spacing_m[0] * 1e3:.1f} mm (x) x "
            f"{self.spacing_m[1] * 1e3:.1f} mm (y); lambda_min/4 = "
            f"{self.required_spacing_m * 1e3:.2f} mm"
        )
        lines += [f"WARNING: {w}" for w in self.warnings]
        return "\n".join(lines)


def resolution_limits(
    f_start_hz: float,
    f_stop_hz: float,
    width_m: float,
    height_m: float,
    nx: int,
    ny: int,
    range_m: float = 1.0,
    temperature_c: float = 20.0,
    humidity_pct: float = 50.0,
) -> Limits:
    """Resolution limits of a raster scan.

    Range resolution is ``c / (2 B)``; cross-range resolution is the two-way diffraction limit
    ``lambda_c R / (2 D)`` for an aperture of size ``D``; stops must be no more than
    ``lambda_min / 4`` apart (round trip) for an image free of grating lobes.

    Parameters
    ----------
    f_start_hz, f_stop_hz : float
        The chirp's band, Hz.
    width_m, height_m, nx, ny : float, float, int, int
        The aperture's extent (metres) and its stops along x and y.
    range_m, temperature_c, humidity_pct : float
        Range of the target (metres); air (degrees Celsius, percent relative humidity).

    Returns
    -------
    Limits
        Resolutions, required spacing, undersampling and warnings (lengths in metres).

    Examples
    --------
    >>> limits = clsas.resolution_limits(20e3, 30e3, 1.0, 1.0, 18, 12, range_m=1.5)
    >>> round(limits.range_resolution_m, 4)                # c / 2B, not the paper's 10 cm
    0.0172
    """
    f1 = v.non_negative("f_start_hz", f_start_hz)
    f2 = v.non_negative("f_stop_hz", f_stop_hz)
    if f1 == f2:
        raise ValueError("f_start_hz and f_stop_hz must differ (zero bandwidth)")
    w = v.positive("width_m", width_m)
    h = v.positive("height_m", height_m)
    nx = v.positive_int("nx", nx)
    ny = v.positive_int("ny", ny)
    r = v.positive("range_m", range_m)
    c = speed_of_sound(temperature_c)
    band = abs(f2 - f1)
    fc = (f1 + f2) / 2
    lam_c = c / fc
    lam_min = c / max(f1, f2)
    dx = w / (nx - 1) if nx > 1 else np.inf
    dy = h / (ny - 1) if ny > 1 else np.inf
    need = lam_min / 4
    absorption = {
        f: float(air_absorption_db_per_m(f, temperature_c, humidity_pct)) for f in sorted({f1, f2})
    }
    warnings = []
    for axis, d, n in (("x", dx, nx), ("y", dy, ny)):
        if n > 1 and d > need:
            warnings.append(
                f"stops along {axis} are {d * 1e3:.1f} mm apart, {d / need:.1f}x the lambda/4 = "
                f"{need * 1e3:.2f} mm needed: the aperture is undersampled and the image will "
                "show grating lobes (ghost copies of each reflector)"
            )
        if n == 1:
            warnings.append(f"a single stop along {axis}: no cross-range resolution along {axis}")
    return Limits(
        c_mps=c,
        bandwidth_hz=band,
        center_hz=fc,
        range_resolution_m=c / (2 * band),
        cross_range_resolution_m=(lam_c * r / (2 * w), lam_c * r / (2 * h)),
        range_m=r,
        absorption_db_per_m=absorption,
        spacing_m=(float(dx), float(dy)),
        required_spacing_m=need,
        undersampling=(float(dx / need), float(dy / need)),
        warnings=warnings,
    )
