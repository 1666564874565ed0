"""Per-stop phases by coordinate ascent: a global start for motion of a wavelength or more.

With the line-of-sight error about a radian of two-way phase or more, the image is incoherent
and a gradient search from zero climbs to a wrong local optimum. Here each stop's image
``A_s(v)`` (the sum of its measurements' backprojections) is formed once, and the image is
``I = sum_s exp(j phi_s) A_s``. Holding every other stop fixed, the sharpness
``S = sum |I|^4 / (sum |I|^2)^2`` is a ratio of trigonometric polynomials of ``phi_s`` of degree
2 and 1, known in closed form from three sums over the voxels; its global maximum over
``phi_s`` is taken (on ``n_phase`` points) and the sweep goes on to the next stop, in a
shuffled order, until a sweep gains less than ``tol``. Each stop jumps to its best phase given
the rest, not a small step up the slope, which is what lets the search leave the incoherent
start (coordinate descent on backprojected images, after Ash, IEEE GRSL 9(1), 2012).

The phases are then read as line-of-sight paths: ``phi_s = 2 pi fc p_s / c`` (a path longer by
``p_s`` turns the stop's echo by that much), unwrapped along the stops' time order, which is
where the motion is smooth (a hand moves less than a quarter wavelength between pings).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

__all__ = ["PHASE_MIN_GAIN", "stop_phase_search", "phase_to_path"]

log = logging.getLogger(__name__)

#: The least rise of the focus metric (log-sharpness, or minus the entropy in nats, on the whole
#: image) for which :func:`clsas.autofocus` keeps the phases: per-stop
#: phases fitted to a scan without motion (its noise) raise it by about 0.02; 3 mm RMS of motion
#: corrected raises it by 0.7 (demo mannequin) to 3 (four points). Below this, the gradient
#: steps that follow start from zero.
PHASE_MIN_GAIN = 0.05


def conditional_best(rest: np.ndarray, a_s: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> tuple[int, float]:
    """Index into the phase table of the best ``phi`` for ``rest + exp(j phi) a_s``, and its log-sharpness.

    ``|rest + e a|^2 = q + 2 Re(e b)`` with ``q = |rest|^2 + |a|^2``, ``b = conj(rest) a``; so
    ``sum |I|^4 = sum q^2 + 2 sum |b|^2 + Re(e 4 sum q b) + Re(e^2 2 sum b^2)`` and
    ``sum |I|^2 = sum q + Re(e 2 sum b)``.
    """
    q = rest.real**2 + rest.imag**2 + a_s.real**2 + a_s.imag**2
    b = np.conj(rest) * a_s
    s4 = (q * q).sum() + 2 * (b.real**2 + b.imag**2).sum() + (e1 * (4 * (q * b).sum())).real \
        + (e2 * (2 * (b * b).sum())).real
    s2 = q.sum() + (e1 * (2 * b.sum())).real
    with np.errstate(divide="ignore", invalid="ignore"):
        val = np.log(np.maximum(s4, 1e-300)) - 2 * np.log(np.maximum(s2, 1e-300))
    k = int(np.argmax(val))
    return k, float(val[k])


def _log_sharpness(values: np.ndarray) -> float:
    p2 = values.real**2 + values.imag**2
    e = float(p2.sum())
    return float(np.log((p2 * p2).sum() / e**2)) if e > 0 else -np.inf


def stop_phase_search(
    stop_images: np.ndarray,
    *,
    sweeps: int = 4,
    tol: float = 2e-3,
    n_phase: int = 256,
    seed: int = 0,
    history: list | None = None,
    callback: Callable[[str, int, float], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Maximise the sharpness over one phase per stop, by exact coordinate ascent.

    Parameters
    ----------
    stop_images : (n_stops, n_vox) complex
        Each stop's image (:meth:`clsas.focus.engine.FocusEngine.stop_images`).
    sweeps : int
        Most passes over the stops.
    tol : float
        Stop when a sweep raises the log-sharpness by less than this.
    n_phase : int
        Phases tried per stop (the step is ``2 pi / n_phase`` rad).
    seed : int
        Seed of the shuffled order of each sweep.
    history, callback
        The log-sharpness after each sweep is appended to ``history`` and passed to
        ``callback("phase", len(history), metric)``.

    Returns
    -------
    (phases (n_stops,) rad in [-pi, pi), info dict with ``metric`` per sweep)
    """
    a = np.asarray(stop_images)
    n_stops = a.shape[0]
    table = -np.pi + 2 * np.pi * np.arange(n_phase) / n_phase
    e1, e2 = np.exp(1j * table), np.exp(2j * table)
    phi = np.zeros(n_stops)
    image = a.sum(axis=0, dtype=np.complex128)
    m = _log_sharpness(image)
    info = {"metric_start": m, "metrics": [], "sweeps": 0}
    rng = np.random.default_rng(seed)
    for _ in range(sweeps):
        m_prev = m
        for s in rng.permutation(n_stops):
            a_s = a[s].astype(np.complex128)
            rest = image - np.exp(1j * phi[s]) * a_s
            k, m = conditional_best(rest, a_s, e1, e2)
            phi[s] = table[k]
            image = rest + e1[k] * a_s
        m = _log_sharpness(image)  # afresh: no drift from the running sums
        info["metrics"].append(m)
        info["sweeps"] += 1
        if history is not None:
            history.append(m)
            if callback is not None:
                callback("phase", len(history), m)
        log.info("autofocus phase: sweep %d, sharpness %.5g", info["sweeps"], m)
        if m - m_prev < tol:
            break
    return phi, info


def phase_to_path(phi: np.ndarray, c_stop: np.ndarray, fc_hz: float) -> np.ndarray:
    """Per-stop phases (rad, in time order) to path corrections (m), unwrapped along time.

    ``p_s = unwrap(phi)_s c_s / (2 pi fc)``, less its mean (a constant path is a range shift
    that no focus metric sees).
    """
    p = np.unwrap(np.asarray(phi, float)) * np.asarray(c_stop, float) / (2 * np.pi * fc_hz)
    return p - p.mean()
