"""The ``"envelope"`` motion step of :func:`clsas.autofocus`: each stop's path to the brightest point,
read from the echo itself, its envelope first (no wavelength to wrap), then its phase.

A hand-held stop that is ``d`` off its stated place sees every echo earlier or later by the
change of its path, ``g . d`` for the point's two-way direction ``g``. For the image's brightest
point, each recording's compressed profile has the point's echo near the delay the stated
geometry predicts; where it actually peaks says how far the path is off, to a fraction of the
range resolution ``c / 2B`` (about 0.5 mm at 30 dB for a 10 kHz chirp), whatever the
wavelength. That is the first pass, and it needs no phase unwrapping, which is what makes the
phase-only steps fail once the motion is a sizeable part of a wavelength. The second pass,
from the positions the first gave, reads the echo's carrier phase and takes, per stop, the path
the phase gives that lies nearest the envelope's (the envelope picks the whole wavelengths).

Per stop the path changes are averaged over its recordings, and their constant and tilt
across the aperture (an image shift no echo tells from a reflector's place) are removed. The
path is *determined* where the envelope and the phase agree: in at least ``min_agree`` of the
stops the phase's path lies within a quarter wavelength of the envelope's without moving a
whole wavelength, and its RMS difference from the envelope's is within ``tolerance_m``. The
correction then moves each stop along its line of sight to the point; :func:`.track_step.where_check`
and the sub-aperture check of :func:`clsas.autofocus` still judge it.

What it cannot do: echoes of several reflectors within one range cell of the point mix in
each recording's window, and an extended target's brightest spot is a different patch from
each stop; there the envelope's peak wanders with the scene, not the motion, the phase and the
envelope disagree, and nothing is applied.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .motion import los_directions
from .track import gauge_free

__all__ = ["ENVELOPE_TOLERANCE_M", "MIN_AGREE", "envelope_step", "echo_delays"]

log = logging.getLogger("clsas.autofocus")

#: Share of the stops whose phase must agree with the envelope (within a quarter wavelength of
#: path) for the path to count as determined.
MIN_AGREE = 0.8
#: Largest RMS difference (one way) between the phase's and the envelope's paths, m.
ENVELOPE_TOLERANCE_M = 1e-3


def echo_delays(data: np.ndarray, tau0_s: np.ndarray, dtau_s: float, fc_hz: float, predicted_s: np.ndarray,
                half_window_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per recording, where the echo predicted at ``predicted_s`` peaks within ``half_window_s``.

    Parameters
    ----------
    data : (n_meas, n_lags) complex
        Compressed baseband profiles (clsas's convention: an echo at delay ``t`` reads
        ``a r(tau - t) exp(-2j pi fc t)`` with ``r`` the pulse's real, peaked autocorrelation).
    tau0_s, dtau_s, fc_hz : the profiles' time axis and carrier.
    predicted_s : (n_meas,) the delay the stated geometry predicts, s.
    half_window_s : how far from it the peak is looked for, s.

    Returns
    -------
    envelope_s : (n_meas,) delay of the envelope's peak (parabolic between samples), s
    phase_rad : (n_meas,) the echo's phase with the predicted delay's carrier removed:
        ``arg(p(envelope) exp(2j pi fc predicted))``
    strength : (n_meas,) the peak's magnitude over the window's median magnitude (NaN where the
        window lies outside the profile)
    """
    n_meas, n_lags = data.shape
    half = max(1, int(np.ceil(half_window_s / dtau_s)))
    centre = np.rint((predicted_s - tau0_s) / dtau_s).astype(np.int64)
    offs = np.arange(-half, half + 1)
    idx = centre[:, None] + offs[None, :]
    inside = (idx[:, 0] >= 1) & (idx[:, -1] <= n_lags - 2)
    idx = np.clip(idx, 1, n_lags - 2)
    rows = np.arange(n_meas)[:, None]
    mag2 = np.abs(data[rows, idx]) ** 2
    k = np.argmax(mag2, axis=1)
    at = idx[np.arange(n_meas), k]
    a, b, c = (np.abs(data[np.arange(n_meas), at + j]) ** 2 for j in (-1, 0, 1))
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    frac = np.clip(frac, -0.5, 0.5)
    envelope = tau0_s + (at + frac) * dtau_s
    # the value at the sub-sample peak (linear between samples), carrier of the prediction removed
    lo = np.where(frac >= 0, at, at - 1)
    w = np.where(frac >= 0, frac, 1 + frac)
    value = (1 - w) * data[np.arange(n_meas), lo] + w * data[np.arange(n_meas), lo + 1]
    phase = np.angle(value * np.exp(2j * np.pi * ((fc_hz * predicted_s) % 1.0)))
    strength = np.sqrt(mag2[np.arange(n_meas), k] / np.maximum(np.median(mag2, axis=1), 1e-300))
    strength = np.where(inside, strength, np.nan)
    return envelope, phase, strength


def _per_stop(x: np.ndarray, stop: np.ndarray, weight: np.ndarray) -> np.ndarray:
    n = int(stop.max()) + 1
    wsum = np.bincount(stop, weight, n)
    return np.bincount(stop, weight * x, n) / np.maximum(wsum, 1e-300)


def _pass(fo, shift, c, stop, move, point, phase: bool) -> dict:
    """One pass at positions ``move`` (n_meas, 3): per-stop path changes to ``point`` (two-way,
    true minus stated, m) from the envelope and (``phase``) the carrier."""
    ds, engine = fo.ds, fo.engine
    data, tau0 = engine.shifted_profiles(shift)
    p = engine.prof
    tx, rx = ds.tx_positions + move, ds.rx_positions + move
    cm = np.broadcast_to(np.asarray(c, float), (ds.n_meas,))
    predicted = (np.linalg.norm(point - tx, axis=1) + np.linalg.norm(point - rx, axis=1)) / cm
    f0, f1 = ds.chirp.get("f_start_hz"), ds.chirp.get("f_stop_hz")
    band = abs(f1 - f0) if f0 and f1 else 0.5 / p.dtau_s
    env, ph, strength = echo_delays(data, tau0, p.dtau_s, p.fc_hz, predicted, 0.6 / band)
    ok = np.isfinite(strength)
    weight = np.where(ok, np.nan_to_num(strength) ** 2, 0.0)
    d_env = np.where(ok, (env - predicted) * cm, 0.0)  # m of two-way path, per recording
    out = {"env": _per_stop(d_env, stop, weight), "found": float(np.mean(ok))}
    if phase:
        lam = cm / p.fc_hz
        common = np.angle(np.sum(weight * np.exp(1j * (ph + 2 * np.pi * d_env / lam))))
        d_ph = -(ph - common) / (2 * np.pi) * lam  # the phase's path, modulo a wavelength
        d_ph += np.rint((d_env - d_ph) / lam) * lam  # the whole wavelengths: the envelope's
        out["phase"] = _per_stop(d_ph, stop, weight)
        first = np.r_[0, np.flatnonzero(np.diff(stop)) + 1]
        out["agree"] = float(np.mean(np.abs(out["phase"] - out["env"]) <= 0.25 * lam[first]))
    return out


def envelope_step(fo, shift, c, stop, xy, tolerance_m: float, min_agree: float = MIN_AGREE
                  ) -> tuple[np.ndarray, dict]:
    """``(move, info)``: the displacement (n_meas, 3), m, along each stop's line of sight to the
    image's brightest point, and ``info`` with ``determined``, ``rms_m`` (one way),
    ``uncertainty_m`` (one way, the phase's RMS difference from the envelope's path over 2),
    ``agree`` and ``point_m``."""
    t = time.perf_counter()
    ds, engine, rep = fo.ds, fo.engine, fo.rep
    values = engine.image(shift, c)
    point = engine.grid.points()[int(np.argmax(np.abs(values)))]
    dirs = los_directions(ds, point)
    zero = np.zeros((ds.n_meas, 3))
    first = _pass(fo, shift, c, stop, zero, point, phase=False)
    p_env = gauge_free(first["env"], xy)
    move = (-0.5 * p_env[stop])[:, None] * dirs
    values = engine.image(shift, c, ds.tx_positions + move, ds.rx_positions + move)
    point = engine.grid.points()[int(np.argmax(np.abs(values)))]
    second = _pass(fo, shift, c, stop, move, point, phase=True)
    p = p_env + gauge_free(second["phase"], xy)
    diff = gauge_free(second["phase"] - second["env"], xy)
    info = {"point_m": point.tolist(), "found": second["found"], "agree": second["agree"],
            "rms_m": float(np.sqrt(np.mean(p**2)) / 2), "uncertainty_m": float(np.sqrt(np.mean(diff**2)) / 2)}
    info["determined"] = bool(info["agree"] >= min_agree and info["uncertainty_m"] <= tolerance_m
                              and info["found"] >= min_agree)
    info["time_s"] = time.perf_counter() - t
    rep.stages.append({"step": "envelope", **info})
    log.info("autofocus envelope: %.2f mm RMS (one way) to the point at %s; phase and envelope agree in %.0f %% "
             "of the stops (%.2f mm RMS apart)", info["rms_m"] * 1e3, np.round(point, 3).tolist(),
             100 * info["agree"], info["uncertainty_m"] * 1e3)
    return (-0.5 * p[stop])[:, None] * los_directions(ds, point), info
