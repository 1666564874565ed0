"""Speed of sound, ISO 9613-1 air absorption, resolution limits and aperture sampling."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import validate as v

__all__ = [
    "speed_of_sound",
    "cramer_speed_of_sound",
    "speed_of_sound_source",
    "ASSUMED_HUMIDITY_PCT",
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


_DRY_C0_MPS = 331.3  # clsas's dry-air speed at 0 C, m/s
_CO2_FRACTION = 4e-4  # mole fraction of CO2 in Cramer's formula (its humid/dry ratio barely depends on it)
# assumed where an object has a temperature but states no humidity (the Dataset's default): indoor air
# is 30-60 % RH, and the dry formula is biased low for all of it
ASSUMED_HUMIDITY_PCT = 50.0
# the name of the formula that turns (temperature, humidity) into c, as provenance records it
HUMID_FORMULA = "cramer1993"
DRY_FORMULA = "dry 331.3 sqrt(1 + T/273.15)"


def _dry(t):
    return _DRY_C0_MPS * np.sqrt(1.0 + t / 273.15)


def _temperature(temperature_c) -> float | np.ndarray:
    """The temperature, checked: a float, or a float array of the same shape."""
    if np.ndim(temperature_c) == 0:
        return _check_air(temperature_c)
    t = v.array("temperature_c", temperature_c)
    if np.any(t <= -273.15):
        raise ValueError(f"temperature_c must be above absolute zero, got min {t.min():g}")
    return t


def _humidity(humidity_pct) -> float | np.ndarray:
    """The relative humidity, checked: finite, in [0, 100] %; a float or a float array."""
    if np.ndim(humidity_pct) == 0:
        h = v.finite("humidity_pct", humidity_pct)
        lo = hi = h
    else:
        h = v.array("humidity_pct", humidity_pct)
        lo, hi = (float(h.min()), float(h.max())) if h.size else (0.0, 0.0)
    if lo < 0 or hi > 100:
        got = f"{lo:g}" if lo == hi else f"{lo:g} to {hi:g}"
        raise ValueError(f"humidity_pct must be in [0, 100] percent relative humidity, got {got}")
    return h


def cramer_speed_of_sound(temperature_c, humidity_pct, pressure_kpa: float = _PR_KPA,
                          co2_fraction: float = _CO2_FRACTION):
    """Speed of sound in humid air after Cramer (1993), m/s, the paper's own absolute value.

    O. Cramer, "The variation of the specific heat ratio and the speed of sound in air with
    temperature, pressure, humidity, and CO2 concentration", J. Acoust. Soc. Am. 93(5),
    2510-2516 (1993): the zero-frequency speed, its eq. (15) with the coefficients of its
    Table III; the water-vapour mole fraction from the relative humidity with Davis's (1992)
    saturation vapour pressure and enhancement factor (as Cramer uses them). Valid for 0-30 C,
    75-102 kPa, up to 0.06 water-vapour mole fraction and 1 % CO2.

    :func:`speed_of_sound` uses only this formula's humid/dry ratio; this function is here for
    comparison (at 0 % RH and 400 ppm CO2 it is 0.13-0.15 m/s above clsas's dry formula over 0-30 C).

    Parameters
    ----------
    temperature_c, humidity_pct : float or numpy.ndarray
        Air temperature (degrees Celsius) and relative humidity (percent); broadcast together.
    pressure_kpa : float
        Atmospheric pressure, kPa.
    co2_fraction : float
        Mole fraction of carbon dioxide (4e-4: 400 ppm).

    Returns
    -------
    float or numpy.ndarray
        m/s.
    """
    t = _temperature(temperature_c)
    h = _humidity(humidity_pct)
    p = v.positive("pressure_kpa", pressure_kpa) * 1e3  # Pa
    xc = v.non_negative("co2_fraction", co2_fraction)
    k = t + 273.15
    p_sv = np.exp(1.2378847e-5 * k**2 - 1.9121316e-2 * k + 33.93711047 - 6.3431645e3 / k)  # Pa (Davis 1992)
    f = 1.00062 + 3.14e-8 * p + 5.6e-7 * t**2  # enhancement factor
    xw = h / 100.0 * f * p_sv / p  # mole fraction of water vapour
    c = (331.5024 + 0.603055 * t - 0.000528 * t**2
         + (51.471935 + 0.1495874 * t - 0.000782 * t**2) * xw
         + (-1.82e-7 + 3.73e-8 * t - 2.93e-10 * t**2) * p
         + (-85.20931 - 0.228525 * t + 5.91e-5 * t**2) * xc
         - 2.835149 * xw**2 - 2.15e-13 * p**2 + 29.179762 * xc**2 + 0.000486 * xw * p * xc)
    return float(c) if np.ndim(c) == 0 else c


def speed_of_sound(temperature_c: float | np.ndarray = 20.0, humidity_pct: float | np.ndarray | None = None,
                   pressure_kpa: float = _PR_KPA) -> float | np.ndarray:
    """Speed of sound in air, m/s: dry, or humid after Cramer (1993).

    ``humidity_pct=None`` gives dry air, ``331.3 sqrt(1 + T/273.15)`` (343.2 m/s at 20 C),
    exactly as before humidity was taken into account. A relative humidity gives that dry value
    times Cramer's (1993) ratio of the humid-air to the dry-air speed at the same temperature and
    pressure (:func:`cramer_speed_of_sound`), so that 0 % gives exactly the dry value and
    ``pressure_kpa`` acts only through the humidity (the dry formula has no pressure). Water
    vapour makes air faster: at 20 C, 50 % RH is 0.18 % (0.63 m/s) faster than dry air; Cramer's
    own absolute value (343.99 m/s there) is 0.15 m/s above this one, the difference between his
    and clsas's dry-air formulas, which the ratio leaves out so as not to move every dry result.

    ``temperature_c`` and ``humidity_pct`` may be arrays (one value per measurement, as logged
    during a scan); they broadcast together and the result has their shape.

    Parameters
    ----------
    temperature_c : float or numpy.ndarray
        Air temperature, degrees Celsius.
    humidity_pct : float or numpy.ndarray, optional
        Relative humidity, percent, in [0, 100]; None: dry air (the formula clsas used before).
    pressure_kpa : float
        Atmospheric pressure, kPa (used with a humidity only).

    Returns
    -------
    float or numpy.ndarray
        m/s.

    Examples
    --------
    >>> import clsas
    >>> round(float(clsas.speed_of_sound(20.0)), 1)
    343.2
    >>> round(float(clsas.speed_of_sound(20.0, humidity_pct=50.0)), 2)
    343.84
    """
    t = _temperature(temperature_c)
    dry = _dry(t)
    if humidity_pct is None:
        return float(dry) if np.ndim(dry) == 0 else dry
    h = _humidity(humidity_pct)
    c = dry * (cramer_speed_of_sound(t, h, pressure_kpa) / cramer_speed_of_sound(t, 0.0, pressure_kpa))
    return float(c) if np.ndim(c) == 0 else c


def speed_of_sound_source(humidity_pct: float | np.ndarray | None, assumed: bool = False) -> str:
    """How :func:`speed_of_sound` turns a temperature into c with this humidity, in words (for
    provenance): e.g. ``"cramer1993 at 50 % RH (assumed: not logged)"``."""
    if humidity_pct is None:
        return DRY_FORMULA
    h = np.asarray(humidity_pct, float)
    at = f"{float(h.flat[0]):g} % RH" if h.size and np.all(h == h.flat[0]) else \
        f"{float(h.min()):g}-{float(h.max()):g} % RH (per measurement)"
    return f"{HUMID_FORMULA} at {at}" + (" (assumed: not logged)" if assumed else "")


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


def _sampling_warnings(axes, need: float) -> list[str]:
    """What a raster's stop spacing along each axis ((name, spacing, stops)) means for an image
    whose stops must be ``need`` apart at most: grating lobes, or no cross-range resolution."""
    warnings = []
    for axis, d, n in axes:
        if n > 1 and d > need:
            warnings.append(
                f"stops along {axis} are {d * 1e3:.1f} mm apart, {d / need:.1f}x the lambda/4 = "
                f"{need * 1e3:.2f} mm needed: the aperture is undersampled and the image will "
                "show grating lobes (ghost copies of each reflector)"
            )
        if n == 1:
            warnings.append(f"a single stop along {axis}: no cross-range resolution along {axis}")
    return warnings


def resolution_limits(f_start_hz: float, f_stop_hz: float, width_m: float, height_m: float, nx: int, ny: int,
                      range_m: float = 1.0, temperature_c: float = 20.0, humidity_pct: float = 50.0) -> Limits:
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
        Range of the target (metres); air (degrees C, % RH: c of humid air, absorption).

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
    f1, f2 = _checked_band(f_start_hz, f_stop_hz)
    w, h = v.positive("width_m", width_m), v.positive("height_m", height_m)
    nx, ny = v.positive_int("nx", nx), v.positive_int("ny", ny)
    r = v.positive("range_m", range_m)
    c = speed_of_sound(temperature_c, humidity_pct)
    band, fc = abs(f2 - f1), (f1 + f2) / 2
    lam_c = c / fc
    dx, dy = _stop_spacing(w, nx), _stop_spacing(h, ny)
    need = c / max(f1, f2) / 4  # a quarter of the shortest wavelength
    return Limits(
        c_mps=c,
        bandwidth_hz=band,
        center_hz=fc,
        range_resolution_m=c / (2 * band),
        cross_range_resolution_m=(lam_c * r / (2 * w), lam_c * r / (2 * h)),
        range_m=r,
        absorption_db_per_m={f: float(air_absorption_db_per_m(f, temperature_c, humidity_pct))
                             for f in sorted({f1, f2})},
        spacing_m=(float(dx), float(dy)),
        required_spacing_m=need,
        undersampling=(float(dx / need), float(dy / need)),
        warnings=_sampling_warnings((("x", dx, nx), ("y", dy, ny)), need),
    )


def _checked_band(f_start_hz: float, f_stop_hz: float) -> tuple[float, float]:
    """The chirp's start and stop frequencies checked (>= 0, a non-zero band), Hz."""
    f1 = v.non_negative("f_start_hz", f_start_hz)
    f2 = v.non_negative("f_stop_hz", f_stop_hz)
    if f1 == f2:
        raise ValueError("f_start_hz and f_stop_hz must differ (zero bandwidth)")
    return f1, f2


def _stop_spacing(extent_m: float, n: int) -> float:
    """The spacing of ``n`` stops over ``extent_m``, m (inf for a single stop)."""
    return extent_m / (n - 1) if n > 1 else np.inf
