"""One registry of the sparse methods. Each entry takes a dictionary and a signal and returns
:class:`Echoes`, capped at ``max_echoes`` (reported in ``Echoes.capped``); BPDN's grid answer is
read as one echo per run of neighbouring atoms everywhere (``superres``, imaging, benchmarks).

Signature of an entry::

    method(dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None, **options) -> Echoes

``lam`` absolute or ``lam_frac`` of lam_max (exactly one is given; :func:`sparse_echoes` fills
in :func:`lam_noise` when neither is). ``max_echoes=None`` is
:func:`clsas.sparse.atoms.default_max_echoes` (two per pulse length over the dictionary's span).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from .. import validate as v
from ..registry import Registry
from .atoms import Atom, Dictionary, default_max_echoes, margin_s
from .bpdn import ShiftOperator, _check, bpdn, group_atoms, lam_max
from .cbp import cbp_polar, cbp_taylor
from .metrics import Echoes
from .noise import lam_noise, noise_lam
from .refined import cbp_polar_refined
from .varpro import mainlobe_s

__all__ = ["SPARSE_METHODS", "cap_echoes", "sparse_echoes", "succeeded", "superres"]

SparseMethod = Callable[..., Echoes]

# statuses of a usable answer: converged, or stopped with the best point kept (max_iter: BPDN's
# gap not yet certified); anything else (a solver's "infeasible", an nlopt error) is not
_SUCCESS = ("optimal", "roundoff", "stalled", "max_eval", "max_time", "max_iter")


def _cap(max_echoes, dictionary) -> int:
    return default_max_echoes(dictionary) if max_echoes is None else v.positive_int("max_echoes", max_echoes)


def cap_echoes(echoes: Echoes, max_echoes: int, weights: np.ndarray | None = None) -> Echoes:
    """Keep the ``max_echoes`` strongest echoes (by ``weights``, default ``|amplitude|``); sets
    ``capped`` where some were dropped (``info["echoes_before_cap"]`` says how many there were)."""
    max_echoes = v.positive_int("max_echoes", max_echoes)
    if len(echoes) <= max_echoes:
        return echoes
    w = np.abs(echoes.amplitudes) if weights is None else np.asarray(weights, float)
    keep = np.sort(np.argsort(w, kind="stable")[::-1][:max_echoes])
    info = {**echoes.info, "echoes_before_cap": len(echoes), "max_echoes": max_echoes}
    return Echoes(echoes.delays_s[keep], echoes.amplitudes[keep], echoes.method, echoes.status, echoes.iterations,
                  echoes.time_s, info, echoes.fallback, True)


def _bpdn(dictionary: Dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None, tol: float = 1e-4,
          max_inner: int = 5000, group: bool = True, rel_threshold: float = 0.0,
          max_run: int | None = None, max_time_s: float | None = None, real_signal: bool = False,
          detect: bool = False, false_alarm: float = 0.01) -> Echoes:
    """BPDN on the grid (duality gap ``tol`` of the objective: 1e-4 is ample for an echo list;
    ``max_inner`` FISTA steps per working set, status ``max_iter`` where that was not enough). ``group``:
    one echo per run of neighbouring active atoms (:func:`group_atoms`; runs longer than the
    matched filter's half-power width, or ``max_run`` atoms, are cut); else one per atom.
    ``max_time_s``: a time budget (the best point kept, status ``max_time``, its gap in ``info``).
    ``real_signal``: fit the real part of ``b`` (see :func:`clsas.sparse.bpdn.bpdn`).
    ``detect``: then debias and detect (:func:`clsas.sparse.detect.detect_echoes`): the echoes'
    amplitudes refit by least squares at their delays, echoes added or dropped by the
    likelihood-ratio test at ``false_alarm`` that CBP-Polar's order step uses (weak echoes under
    lam's threshold, e.g. a tenth of their neighbours', are found; the delays stay on the grid)."""
    cap = _cap(max_echoes, dictionary)
    if not isinstance(detect, (bool, np.bool_)):
        raise TypeError(f"detect must be True or False, got {detect!r}")
    t = time.perf_counter()
    res = bpdn(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, tol=tol, max_inner=max_inner,
               max_time_s=max_time_s, real_signal=real_signal)
    info = {"lam": res.lam, "gap": res.gap, **res.info, "atoms": int(np.count_nonzero(res.x))}
    if group:
        if max_run is None:
            max_run = max(1, int(np.ceil(2 * mainlobe_s(dictionary.atom) / dictionary.delta)))
        taus, amps, weights = group_atoms(dictionary, res.x, rel_threshold=rel_threshold, max_run=max_run)
    else:
        mag = np.abs(res.x)
        on = np.flatnonzero(mag > max(rel_threshold * mag.max(initial=0.0), 0.0))
        taus, amps, weights = dictionary.taus[on], res.x[on], mag[on]
    if detect and len(taus):  # the first echo is lam's to detect (pure noise stays "nothing here")
        from .detect import detect_echoes

        taus, amps, found = detect_echoes(dictionary, b, taus, amplitudes, lam=res.lam, false_alarm=false_alarm,
                                          max_echoes=cap, real_signal=real_signal)
        weights = np.abs(amps)
        info["detect"] = found
    e = Echoes(taus, amps, "bpdn", res.status, res.iterations, time.perf_counter() - t, info)
    return cap_echoes(e, cap, weights[np.argsort(taus, kind="stable")])


def _cbp_taylor(dictionary: Dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None,
                rel_threshold: float = 1e-3, max_memory_gib: float = 4.0, real_signal: bool = False) -> Echoes:
    """CBP-Taylor (cvxpy), the ``max_echoes`` strongest echoes; refused up front beyond ``max_memory_gib``.
    It fits the analytic signal whatever ``real_signal`` says (its convex relaxation of complex
    amplitudes is not written on the real part)."""
    e = cbp_taylor(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, rel_threshold=rel_threshold,
                   max_memory_gib=max_memory_gib)
    return cap_echoes(e, _cap(max_echoes, dictionary))


def _cbp_polar_socp(dictionary: Dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None,
                    rel_threshold: float = 1e-3, max_memory_gib: float = 4.0, real_signal: bool = False) -> Echoes:
    """The convex CBP-Polar SOCP (positive amplitudes, so ``real_signal`` does not apply), the
    ``max_echoes`` strongest echoes."""
    e = cbp_polar(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes, rel_threshold=rel_threshold,
                  max_memory_gib=max_memory_gib)
    return cap_echoes(e, _cap(max_echoes, dictionary))


def _cbp_polar(dictionary: Dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None,
               rel_threshold: float = 0.02, bounds_s: tuple[float, float] | None = None,
               real_signal: bool = False, false_alarm: float = 0.01) -> Echoes:
    """Refined CBP-Polar (BPDN seeds, nlopt delays within ``bounds_s``, a likelihood-ratio order
    test at ``false_alarm``), capped inside; ``real_signal``: fit the real part of ``b`` (see
    :func:`clsas.sparse.refined.cbp_polar_refined`)."""
    return cbp_polar_refined(dictionary, b, lam, lam_frac=lam_frac, amplitudes=amplitudes,
                             max_echoes=_cap(max_echoes, dictionary), rel_threshold=rel_threshold, bounds_s=bounds_s,
                             real_signal=real_signal, false_alarm=false_alarm)


# name -> method(dictionary, b, lam, lam_frac, amplitudes, *, max_echoes, **options) -> Echoes; a new method
# registers itself where it is defined: SPARSE_METHODS.register("name", function)
SPARSE_METHODS: Registry[SparseMethod] = Registry("sparse method", "method")
SPARSE_METHODS.register("bpdn", _bpdn)
SPARSE_METHODS.register("cbp-taylor", _cbp_taylor)
SPARSE_METHODS.register("cbp-polar", _cbp_polar)
SPARSE_METHODS.register("cbp-polar-socp", _cbp_polar_socp)


#: a convex (cvxpy) method's time per recording, s, at a number of atoms (one per sample of the
#: window plus a pulse each side): about 350 s at 1470 atoms on a 2-core CPU; the time grows
#: about as the atoms' number to the power CONVEX_EXPONENT (the atoms are short: the problem is sparse)
CONVEX_S_PER_RECORDING = {"cbp-taylor": (350.0, 1470), "cbp-polar-socp": (350.0, 1470)}
CONVEX_EXPONENT = 1.5
#: a call estimated to take longer than this is announced before it starts
SLOW_CALL_S = 60.0


def convex_estimate_s(method: str, n_atoms) -> float | None:
    """A rough time (s) of a convex method's solve over ``n_atoms`` atoms (an array: one per
    recording, summed); None for the methods that are not convex programs."""
    if method not in CONVEX_S_PER_RECORDING:
        return None
    t_ref, k_ref = CONVEX_S_PER_RECORDING[method]
    return float(np.sum(t_ref * (np.asarray(n_atoms, float) / k_ref) ** CONVEX_EXPONENT))


#: the packages each method imports (the ``sparse`` extra); checked before any work
METHOD_NEEDS = {"cbp-taylor": ("cvxpy",), "cbp-polar": ("nlopt",), "cbp-polar-socp": ("cvxpy",)}


def require_solver(method: str, parameter: str = "method") -> None:
    """Refuse a method whose solver is not installed with an ImportError naming the package and the
    extra that brings it (not a bare ``ModuleNotFoundError`` from deep inside the solve)."""
    from importlib.util import find_spec

    missing = [m for m in METHOD_NEEDS.get(method, ()) if find_spec(m) is None]
    if missing:
        raise ImportError(f"{parameter}={method!r} needs {' and '.join(missing)} (the sparse extra), which is not "
                          f"installed: {v.install_hint('sparse')}; or use method='bpdn', which needs neither")


def _nothing(method: str, reason: str, t_start: float, info: dict) -> Echoes:
    """No echo, answered without a solve (``status`` ``"optimal"``, ``info["trivial"]`` the reason)."""
    return Echoes([], [], method, "optimal", 0, time.perf_counter() - t_start, {**info, "trivial": reason})


def _rescaled(e: Echoes, scale: float) -> Echoes:
    """``e`` found on ``b / scale``, in the units of ``b``: amplitudes and lam times ``scale``."""
    info = dict(e.info)
    for key in ("lam", "lam_max"):
        if key in info:
            info[key] = info[key] * scale
    for key in ("rss", "rss_floor"):
        if key in info:
            info[key] = float(info[key]) * scale * scale
    if isinstance(info.get("detect"), dict) and "rss" in info["detect"]:  # bpdn's detect step
        info["detect"] = {**info["detect"], "rss": float(info["detect"]["rss"]) * scale * scale}
    info["scale"] = scale
    return Echoes(e.delays_s, e.amplitudes * scale, e.method, e.status, e.iterations, e.time_s, info, e.fallback,
                  e.capped)


def sparse_echoes(method: str, dictionary: Dictionary, b, lam: float | None = None, *,
                  lam_frac: float | None = None, amplitudes: str = "complex", max_echoes: int | None = None,
                  noise_sigma: float | None = None, real_signal: bool = False, **options) -> Echoes:
    """The echoes of ``b`` by one of :data:`SPARSE_METHODS`.

    Every method sees ``b / max|b|`` and its amplitudes are scaled back, so the answer (echo
    count and delays) does not depend on the units of ``b`` (1e-200 to 1e200 alike). The trivial
    cases are answered without a solve, with no echo (``info["trivial"]`` says why): an all-zero
    or constant ``b`` (a DC level is no echo), and ``lam >= lam_max`` (or ``lam_frac >= 1``),
    where the convex problems' answer is exactly zero; so is the default ``lam`` on a profile
    of pure noise, whose largest correlation with an atom rarely reaches the noise threshold.

    Parameters
    ----------
    method : {"bpdn", "cbp-taylor", "cbp-polar", "cbp-polar-socp"}
    dictionary : Dictionary
    b : (n_samples,) array
        The signal (analytic for ``amplitudes="complex"``).
    lam, lam_frac : float, optional
        Absolute lam (in the units of ``b``), or a fraction of lam_max; default the noise
        threshold (:func:`noise_lam`) at ``noise_sigma``.
    amplitudes : {"positive", "real", "complex"}
    max_echoes : int, optional
        Echo cap; default :func:`clsas.sparse.atoms.default_max_echoes`.
    noise_sigma : float, optional
        The noise level per sample (units of ``b``), where it is known (e.g. from a noise-only
        recording); default estimated from ``b`` (:func:`clsas.sparse.noise_sigma`). Only used
        when neither ``lam`` nor ``lam_frac`` is given.
    real_signal : bool
        ``b`` (complex) is the analytic signal of a real recording: bpdn and cbp-polar then fit
        its real part, which models echoes cut by the window's edges exactly (the analytic
        signal of a cut echo, taken over the window, is not the cut analytic atom); the convex
        CBPs fit ``b`` as it is. :func:`superres` sets it for a real ``signal``.
    **options
        Passed to the method: ``tol``, ``max_inner``, ``max_time_s``, ``group``, ``rel_threshold``,
        ``max_run``, ``detect``, ``false_alarm`` (bpdn: ``detect=True`` debiases and detects by
        CBP-Polar's order test);
        ``rel_threshold``, ``max_memory_gib`` (the convex CBPs); ``bounds_s``, ``false_alarm`` (cbp-polar: the rate
        at which its order test admits an echo that is not there, default 0.01).
    """
    t_start = time.perf_counter()
    max_echoes, lam, lam_frac = _checked_choices(method, max_echoes, lam, lam_frac, noise_sigma)
    b = _checked_signal(dictionary, b, amplitudes, real_signal)
    scale = float(np.max(np.abs(b), initial=0.0))
    if scale == 0.0:
        return _nothing(method, "zero input", t_start, {"lam_max": 0.0})
    if np.all(b == b[0]):
        return _nothing(method, "constant input", t_start, {})
    bn = b / scale
    lam_n, lmax = _unit_lam(dictionary, bn, scale, amplitudes, lam, lam_frac, noise_sigma)
    if lam_n >= lmax or (lam_frac is not None and lam_frac >= 1):
        return _nothing(method, "lam >= lam_max", t_start, {"lam": lam_n * scale, "lam_max": lmax * scale})
    if real_signal:
        options["real_signal"] = True
    e = SPARSE_METHODS[method](dictionary, bn, lam_n, None, amplitudes, max_echoes=max_echoes, **options)
    return _rescaled(e, scale)


def _checked_choices(method: str, max_echoes, lam, lam_frac, noise_sigma):
    """:func:`sparse_echoes`'s method, echo cap and lam (at most one of ``lam``, ``lam_frac`` and
    ``noise_sigma``) checked: ``(max_echoes, lam, lam_frac)``."""
    v.choice("method", method, tuple(SPARSE_METHODS))
    if max_echoes is not None:
        max_echoes = v.positive_int("max_echoes", max_echoes)
    if lam is not None and lam_frac is not None:
        raise ValueError("give at most one of lam (absolute) and lam_frac (a fraction of lam_max)")
    lam = None if lam is None else v.non_negative("lam", lam)
    lam_frac = None if lam_frac is None else v.non_negative("lam_frac", lam_frac)
    if noise_sigma is not None and (lam is not None or lam_frac is not None):
        raise ValueError("noise_sigma sets lam: give it instead of lam and lam_frac, not with them")
    return max_echoes, lam, lam_frac


def _checked_signal(dictionary: Dictionary, b, amplitudes: str, real_signal: bool) -> np.ndarray:
    """``b`` checked against the dictionary and the amplitude model (complex where ``real_signal``)."""
    b = _check(dictionary, b, amplitudes)
    if real_signal and (amplitudes != "complex" or not np.iscomplexobj(b)):
        raise ValueError("real_signal=True needs amplitudes='complex' and b the analytic signal (complex)")
    return b


def _unit_lam(dictionary: Dictionary, bn: np.ndarray, scale: float, amplitudes: str, lam, lam_frac,
              noise_sigma) -> tuple[float, float]:
    """lam and lam_max for ``bn = b / scale``: lam from ``lam_frac`` of lam_max, ``lam``, the
    noise threshold at ``noise_sigma``, or else the noise level estimated from ``bn``."""
    lmax = lam_max(ShiftOperator(dictionary), bn, amplitudes)
    if lam_frac is not None:
        return lam_frac * lmax, lmax
    if lam is not None:
        return lam / scale, lmax
    if noise_sigma is not None:
        return noise_lam(dictionary, noise_sigma / scale, amplitudes), lmax
    return lam_noise(dictionary, bn, amplitudes), lmax


def succeeded(echoes: Echoes) -> bool:
    """Whether a method's answer is usable: a success status and finite delays and amplitudes."""
    return (not echoes.fallback and echoes.status.startswith(_SUCCESS)
            and bool(np.all(np.isfinite(echoes.delays_s)) and np.all(np.isfinite(echoes.amplitudes))))


def superres(signal, atom_shape, fs_hz: float, *, method: str = "cbp-polar", delta_s: float | None = None,
             lam: float | None = None, lam_frac: float | None = None, amplitudes: str = "complex",
             tau0_s: float | None = None, max_echoes: int | None = None, noise_sigma: float | None = None,
             remove_dc: bool = True, **options) -> Echoes:
    """Super-resolve the echoes in one signal.

    Parameters
    ----------
    signal : 1-D array
        Real recording (for ``amplitudes="complex"`` its analytic signal is taken) or an
        analytic signal.
    atom_shape : callable or 1-D array
        The pulse (see :class:`clsas.sparse.Atom`).
    method : {"bpdn", "cbp-taylor", "cbp-polar", "cbp-polar-socp"}
        See :data:`SPARSE_METHODS`; BPDN's atoms are grouped into echoes, one per run.
    delta_s : float, optional
        Grid spacing; default half a sample.
    lam, lam_frac : float
        Absolute lam, or a fraction of lam_max; default :func:`clsas.sparse.lam_noise`, the
        noise level estimated from the signal.
    tau0_s : float, optional
        The first atom's delay, s. Default minus the pulse length (rounded up to whole grid
        steps, :func:`clsas.sparse.atoms.margin_s`): a margin for echoes that start before the
        window, which every method then models as truncated echoes at their true (negative)
        delays, not as a swarm of echoes at the window's start. Echoes are thus reported from
        ``tau0_s`` on; ``tau0_s=0`` searches the window only (an echo cut by its start is then
        fitted by whatever atoms inside it explain it best, often several).
    max_echoes : int, optional
        Echo cap (default two per pulse length over the signal); ``capped`` says it was hit.
    noise_sigma : float, optional
        Known noise level per sample, in the signal's units (sets the default ``lam``).
    remove_dc : bool
        Subtract the signal's mean first, and each atom's mean over the window alike (a DC
        offset is no echo; a band-pass pulse has almost no mean of its own, but one that the
        window cuts has, and is still modelled exactly).
    **options
        Passed to the method (see :func:`sparse_echoes`).

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> from clsas.sparse import Echoes
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.2)
    >>> x = np.zeros(600)
    >>> x[100:100 + chirp.size] += chirp                   # two echoes 6 samples apart
    >>> x[106:106 + chirp.size] += 0.8 * chirp
    >>> x += 0.05 * np.random.default_rng(0).standard_normal(x.size)
    >>> echoes = clsas.superres(x, chirp, fs)            # CBP-Polar, complex amplitudes
    >>> [round(d * fs) for d in echoes.delays_s]          # delays in samples
    [100, 106]
    """
    v.choice("method", method, tuple(SPARSE_METHODS))
    require_solver(method)
    fs = v.sampling_rate("fs_hz", fs_hz)
    x, real_signal = _signal_to_fit(v.array("signal", signal, ndim=1, allow_complex=True), amplitudes, remove_dc)
    d = _superres_dictionary(atom_shape, fs, len(x), amplitudes, remove_dc, delta_s, tau0_s)
    _announce_slow_solve(method, d)
    return sparse_echoes(method, d, x, lam, lam_frac=lam_frac, amplitudes=amplitudes, max_echoes=max_echoes,
                         noise_sigma=noise_sigma, real_signal=real_signal, **options)


def _signal_to_fit(x: np.ndarray, amplitudes: str, remove_dc: bool) -> tuple[np.ndarray, bool]:
    """The signal :func:`superres` fits (its mean removed where ``remove_dc``; a real recording
    with complex amplitudes turned into its analytic signal), and whether it was real."""
    from ..physics.signals import analytic

    if remove_dc:
        x = x - np.mean(x)
    real_signal = amplitudes == "complex" and not np.iscomplexobj(x)
    if real_signal:
        peak = float(np.max(np.abs(x), initial=0.0))  # the transform at unit scale (no overflow at 1e200)
        x = analytic(x / peak) * peak if peak > 0 else x.astype(complex)
    if amplitudes != "complex" and np.iscomplexobj(x):
        raise ValueError("signal is complex: use amplitudes='complex'")
    return x, real_signal


def _superres_dictionary(atom_shape, fs: float, n_samples: int, amplitudes: str, remove_dc: bool,
                         delta_s: float | None, tau0_s: float | None) -> Dictionary:
    """:func:`superres`'s dictionary: the pulse over ``n_samples`` (centred where ``remove_dc``) on
    a grid of ``delta_s`` (default half a sample) from ``tau0_s`` (default minus the pulse length)."""
    atom = Atom(atom_shape, fs, n_samples, complex=amplitudes == "complex", centered=remove_dc)
    delta = 0.5 / fs if delta_s is None else v.positive("delta_s", delta_s)
    tau0 = -margin_s(atom, delta) if tau0_s is None else v.finite("tau0_s", tau0_s)
    return Dictionary(atom, delta, tau0)


def _announce_slow_solve(method: str, d: Dictionary) -> None:
    """A warning before a convex solve estimated to take longer than :data:`SLOW_CALL_S`."""
    est = convex_estimate_s(method, d.k)
    if est is not None and est > SLOW_CALL_S:
        logging.getLogger(__name__).warning(
            "superres: %s solves a convex program over %d atoms: roughly %.0f s on a 2-core CPU "
            "(method='cbp-polar' or 'bpdn' take seconds)", method, d.k, est)
