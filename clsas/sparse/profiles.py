"""Super-resolved range profiles for imaging: each recording's echoes are found by one of the
sparse methods (:data:`clsas.sparse.SPARSE_METHODS`) on the analytic transmit waveform, then
rendered as narrow pulses into baseband profiles that backprojection takes as it takes the
matched filter's.

Measured recordings are not simulations: echoes straddle the gate's edges, clutter and extended
reflectors fill it, the recorded pulse is not quite the transmitted one. So the dictionary
reaches a guard band beyond the gate on each side (echoes there explain the energy that spills
into the window, and are then dropped), each recording is capped at ``max_echoes`` echoes, and a
recording the method fails on (an exception, a non-finite answer, a failed status) is imaged by
its matched filter instead of aborting the image; both are reported per recording in its
:class:`~clsas.sparse.Echoes` and in one summary log line each."""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable

import numpy as np

from .. import validate as v
from ..physics.signals import analytic
from ..types.dataset import Dataset
from ..types.profiles import Profiles, center_frequency
from .registry import SPARSE_METHODS

__all__ = ["SPARSE_OPTIONS", "superres_profiles"]

log = logging.getLogger(__name__)

# the options reconstruct(..., sparse={...}) accepts
_EMPTY_WINDOW = "empty window: the gate lies outside the recording"  # an Echoes' status
SPARSE_OPTIONS = ("delta_s", "lam", "lam_frac", "render_width_s", "max_echoes", "guard_s", "method_options",
                  "absorption", "pulse")


def _failure_kind(exc: BaseException) -> str:
    """A short name for the summary line: ``nlopt invalid_argument``, ``FloatingPointError``..."""
    text = str(exc)
    if "nlopt " in text:
        word = text.split("nlopt ", 1)[1].split()[0]
        return f"nlopt {word}"
    return type(exc).__name__


def _one(method, x, atom, delta, tau0, n_atoms, gate_rel, lam, lam_frac, max_echoes, options):
    """Echoes of one recording (delays relative to its window), or a failure: (Echoes, kind)."""
    from . import Dictionary, Echoes, sparse_echoes, succeeded

    t_start = time.perf_counter()
    try:
        d = Dictionary(atom, delta, tau0, n_atoms)
        # x is the analytic signal of a real recording: bpdn and cbp-polar fit the recording itself
        # (real_signal), exact for echoes cut by the window, and CBP-Polar's BIC counts n samples
        e = sparse_echoes(method, d, x, lam, lam_frac=lam_frac, amplitudes="complex", max_echoes=max_echoes,
                          **{"real_signal": True, **options})
    except Exception as exc:  # noqa: BLE001 - any failure of a solver on one recording is that recording's
        e, kind = None, _failure_kind(exc)
        reason = f"{type(exc).__name__}: {exc}"[:200]
    else:
        if succeeded(e):
            inside = (e.delays_s >= gate_rel[0]) & (e.delays_s <= gate_rel[1])
            info = {**e.info, "outside_gate": int(np.count_nonzero(~inside))}
            return Echoes(e.delays_s[inside], e.amplitudes[inside], e.method, e.status, e.iterations, e.time_s, info,
                          False, e.capped), None
        finite = np.all(np.isfinite(e.delays_s)) and np.all(np.isfinite(e.amplitudes))
        kind = f"status {e.status}" if finite else "non-finite"
        reason = kind
    return Echoes([], [], method, f"fallback: {reason}", 0, time.perf_counter() - t_start,
                  {"fallback_kind": kind}, True, False), kind


def _check_options(method: str, method_options: dict | None) -> dict:
    """``method_options`` checked against the method's keyword arguments (a wrong name is the
    caller's error, raised once here, not a failure of every recording)."""
    import inspect

    from .registry import require_solver

    require_solver(method)
    options = dict(method_options or {})
    params = inspect.signature(SPARSE_METHODS[method]).parameters
    known = {k for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY} - {"max_echoes"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"method_options: {method} takes {sorted(known)}, got unknown {unknown}")
    return options


def _matched_row(x, atom, fc, offset, gate_rel, taus_abs) -> np.ndarray:
    """The matched filter's baseband profile of one recording at the delays ``taus_abs`` (zero
    outside its gate), scaled as rendered echoes: an echo of amplitude a peaks at |a|.

    The analytic correlation with the atom peaks at ``a |atom|^2`` on an echo of amplitude a,
    so it is divided by the atom's energy; it is rotated to baseband with the delay after the
    transmit start (``offset`` + the delay in the window), as rendered echoes are.
    """
    os_ = 4
    c = atom.correlate(x, os_)
    period = len(c) / (os_ * atom.fs)
    tau = np.arange(len(c)) / (os_ * atom.fs)
    tau = np.where(tau >= period / 2, tau - period, tau)  # circular: the upper half is negative delays
    order = np.argsort(tau)
    tau, c = tau[order], c[order] * np.exp(-2j * np.pi * fc * (tau[order] + offset)) / atom.norm**2
    rel = taus_abs - offset
    out = np.interp(rel, tau, c.real) + 1j * np.interp(rel, tau, c.imag)
    return np.where((rel >= gate_rel[0]) & (rel <= gate_rel[1]), out, 0.0)


def _summarise(method, echoes, n_meas, t_total):
    found = sum(len(e) for e in echoes)
    log.info("%s: %d echoes in %d recordings, %.2f s", method, found, n_meas, t_total)
    kinds = Counter(e.info.get("fallback_kind", "?") for e in echoes if e.fallback)
    if kinds:
        why = ", ".join(f"{k} x{n}" for k, n in kinds.most_common())
        log.warning("%s: %d of %d recordings fell back to the matched filter (%s)", method, sum(kinds.values()),
                    n_meas, why)
    capped = [e for e in echoes if e.capped]
    if capped:
        caps = sorted({e.info.get("max_echoes", len(e)) for e in capped})
        log.warning("%s: the echo cap (max_echoes=%s) was hit in %d of %d recordings; the strongest echoes were "
                    "kept", method, "/".join(str(c) for c in caps), len(capped), n_meas)


def superres_profiles(dataset: Dataset, gates_s: np.ndarray, method: str = "cbp-polar", *, delta_s: float | None = None,
                      lam: float | None = None, lam_frac: float | None = None, render_width_s: float | None = None,
                      max_echoes: int | None = None, guard_s: float | None = None, method_options: dict | None = None,
                      progress: Callable[[int, int], None] | None = None, absorption: bool = False,
                      pulse=None, client=None) -> tuple[Profiles, list]:
    """Super-resolve every recording of ``dataset`` within its delay gate.

    Parameters
    ----------
    gates_s : (n_meas, 2) array
        Delays after the transmit start to search, per measurement, s.
    method : {"bpdn", "cbp-taylor", "cbp-polar"}
        A sparse method (:data:`clsas.sparse.SPARSE_METHODS`), with complex amplitudes (echoes
        have unknown phase).
    delta_s : float, optional
        Dictionary spacing; default one sample.
    lam, lam_frac : float, optional
        Absolute lam or a fraction of lam_max; default the noise level of each recording
        (:func:`clsas.sparse.lam_noise`).
    render_width_s : float, optional
        Each echo becomes a Gaussian pulse of this standard deviation and peak ``|a|`` in the
        profile (default 0.05 / B, B the waveform's -20 dB bandwidth); the profile step is a
        quarter of it.
    max_echoes : int, optional
        Echoes per recording at most (guard band included); default two per pulse length
        over the dictionary's span (:func:`clsas.sparse.default_max_echoes`). Where a
        recording has more, the strongest are kept and ``Echoes.capped`` is set.
    guard_s : float, optional
        The dictionary reaches this far beyond each end of the gate, so that echoes
        straddling the gate's edges are explained (and then dropped) instead of being
        mistaken for echoes inside it; default the waveform's length.
    method_options : dict, optional
        Passed to the method (see :func:`clsas.sparse.sparse_echoes`).
    absorption : bool
        Model air absorption in the atom: the waveform after the gate's mean two-way path
        (``c`` x its mean delay) of the recording's air (:func:`clsas.sparse.absorbed_pulse`,
        ISO 9613-1, as :func:`clsas.simulate` applies it); ``info["path_m"]`` says which path.
    pulse : 1-D array, optional
        The atom's waveform, sampled at the dataset's rate: the transmit waveform as the
        recordings hear it, through the speaker's and the microphone's response (the waveform
        filtered by a known response, e.g. ``scipy.signal.lfilter(b, a, waveform)`` or
        ``np.convolve(waveform, impulse_response)``, or a pulse recorded at a known distance).
        Default the dataset's transmit waveform. An atom that is not the pulse the echoes carry
        leaves a residual at every echo, and the methods explain it with spurious echoes
        beside the true ones. Absorption, where asked for, is applied to it.
    client : distributed.Client or str, optional
        A Dask cluster: blocks of recordings, one task each (:mod:`clsas.sparse.parallel`).

    Returns
    -------
    (Profiles, list of Echoes)
        The rendered profiles (baseband at the waveform's centre frequency, all rows on one
        delay grid) and the echoes of each measurement (delays after the transmit start,
        inside its gate). A recording the method failed on has ``fallback=True``, its
        reason in ``status``, no echoes, and its matched-filter profile in the rows.
    """
    SPARSE_METHODS.check(method)
    fs, wave = dataset.fs_hz, dataset.waveform  # the profiles' centre frequency and render width
    heard = _atom_waveform(dataset, pulse)  # the atom's waveform
    gates, delta, guard, max_echoes, options = _checked(dataset, gates_s, heard, method, delta_s, guard_s,
                                                        max_echoes, lam, lam_frac, method_options)
    fc = center_frequency(wave, fs)
    width = v.positive("render_width_s", _render_width(wave, fs) if render_width_s is None else render_width_s)
    lo, dtau, grid = _render_grid(gates, width)
    job = _Recordings(dataset, gates, heard, method, delta, guard, lam, lam_frac, max_echoes, options, absorption,
                      fc, grid)
    t_start = time.perf_counter()
    data, echoes = job.all(progress, client)
    _summarise(method, echoes, dataset.n_meas, time.perf_counter() - t_start)
    _render(data, echoes, grid, lo, dtau, width, fc)
    return _profiles(dataset, data, lo, dtau, fc, method, time.perf_counter() - t_start), echoes


def _render_grid(gates: np.ndarray, width: float) -> tuple[float, float, np.ndarray]:
    """The common delay grid of the rendered profiles, s: every gate, and room for a pulse's
    tails, in steps of a quarter of the render ``width``; ``(start, step, grid)``."""
    dtau = width / 4
    lo, hi = float(gates[:, 0].min()) - 4 * width, float(gates[:, 1].max()) + 4 * width
    return lo, dtau, lo + dtau * np.arange(int(np.ceil((hi - lo) / dtau)) + 1)


def _profiles(dataset: Dataset, data: np.ndarray, lo: float, dtau: float, fc: float, method: str,
              time_s: float) -> Profiles:
    """The rendered rows ``data`` as the dataset's profiles (every row from delay ``lo``, step ``dtau``, s)."""
    return Profiles(data, np.full(dataset.n_meas, lo), dtau, fc, method, "numpy",
                    tx_positions=dataset.tx_positions, rx_positions=dataset.rx_positions, c_mps=dataset.c_mps,
                    timings_s={"superres": time_s}, beams=dataset.beams)


def _checked(dataset: Dataset, gates_s, heard: np.ndarray, method: str, delta_s, guard_s, max_echoes, lam,
             lam_frac, method_options):
    """:func:`superres_profiles`'s arguments checked: (gates, delta, guard, max_echoes, options)."""
    fs = dataset.fs_hz
    gates = v.array("gates_s", gates_s, shape=(dataset.n_meas, 2))
    if np.any(gates[:, 1] < gates[:, 0]):
        raise ValueError("gates_s rows must be (min, max) with min <= max")
    delta = 1.0 / fs if delta_s is None else v.positive("delta_s", delta_s)
    guard = len(heard) / fs if guard_s is None else v.non_negative("guard_s", guard_s)
    if max_echoes is not None:
        max_echoes = v.positive_int("max_echoes", max_echoes)
    if lam is not None and lam_frac is not None:
        raise ValueError("give at most one of lam (absolute) and lam_frac (a fraction of lam_max)")
    for name, value in (("lam", lam), ("lam_frac", lam_frac)):
        if value is not None:
            v.non_negative(name, value)
    return gates, delta, guard, max_echoes, _check_options(method, method_options)


def _atom_waveform(dataset: Dataset, pulse) -> np.ndarray:
    """The atom's waveform: ``pulse`` (checked), else the dataset's transmit waveform."""
    if pulse is None:
        return dataset.waveform
    heard = v.array("pulse", pulse, ndim=1)
    if not np.any(heard):
        raise ValueError("pulse (the atom's waveform) is all zeros")
    if len(heard) > dataset.n_samples:
        raise ValueError(f"pulse has {len(heard)} samples, more than the recordings' {dataset.n_samples}")
    return heard


def _render_width(wave: np.ndarray, fs: float) -> float:
    """The default render width: 0.05 / B, B the waveform's -20 dB bandwidth, s."""
    spec = np.abs(np.fft.rfft(wave, 8 * len(wave)))
    f = np.fft.rfftfreq(8 * len(wave), 1 / fs)
    band = f[spec >= 0.1 * spec.max()]
    return 0.05 / max(band.max() - band.min(), fs / len(wave))


def _render(data: np.ndarray, echoes: list, grid: np.ndarray, lo: float, dtau: float, width: float,
            fc: float) -> None:
    """Add each echo to its row of ``data`` as a Gaussian of sigma ``width`` (s) and peak ``|a|``,
    at baseband (``fc``, Hz) on the delay ``grid = lo + dtau * arange`` (s)."""
    n_lags = len(grid)
    reach = int(np.ceil(5 * width / dtau))
    for m, e in enumerate(echoes):
        for tau, a in zip(e.delays_s, e.amplitudes, strict=True):
            k0 = int(round((tau - lo) / dtau))
            ks = np.arange(max(0, k0 - reach), min(n_lags, k0 + reach + 1))
            g = np.exp(-0.5 * ((grid[ks] - tau) / width) ** 2)
            data[m, ks] += a * np.exp(-2j * np.pi * fc * tau) * g


class _Recordings:
    """The per-recording step of :func:`superres_profiles`: each recording's window, atom,
    dictionary span and echoes (:meth:`echoes`), all of them in turn (:meth:`all`)."""

    def __init__(self, dataset: Dataset, gates: np.ndarray, heard: np.ndarray, method: str, delta: float,
                 guard: float, lam, lam_frac, max_echoes, options: dict, absorption: bool, fc: float,
                 grid: np.ndarray):
        n = dataset.n_meas
        self.dataset, self.gates, self.heard, self.method = dataset, gates, heard, method
        self.delta, self.guard, self.lam, self.lam_frac = delta, guard, lam, lam_frac
        self.max_echoes, self.options, self.absorption, self.fc, self.grid = max_echoes, options, absorption, fc, grid
        self.t0 = np.zeros(n) if dataset.t0_s is None else np.broadcast_to(np.asarray(dataset.t0_s, float), (n,))
        self.air_t = np.broadcast_to(np.asarray(dataset.temperature_c, float), (n,))
        self.air_h = np.broadcast_to(np.asarray(dataset.humidity_pct, float), (n,))
        self.air_c = None if dataset.c_mps is None else np.broadcast_to(np.asarray(dataset.c_mps, float), (n,))

    def all(self, progress: Callable[[int, int], None] | None, client=None) -> tuple[np.ndarray, list]:
        """(n_meas, n_lags) the matched-filter rows of the recordings the method failed on
        (zero elsewhere), and every recording's Echoes. ``progress(done, n)`` after each
        recording but those whose window is empty; with a Dask ``client``, in blocks on the
        cluster (:func:`clsas.sparse.parallel.echoes_on_cluster`, the same result)."""
        if client is not None:
            from .parallel import echoes_on_cluster

            return echoes_on_cluster(self, client, len(self.grid), progress)
        n = self.dataset.n_meas
        data = np.zeros((n, len(self.grid)), np.complex128)
        echoes = []
        for m in range(n):
            e, row = self.echoes(m)
            echoes.append(e)
            if row is not None:
                data[m] = row
            if progress is not None and e.status != _EMPTY_WINDOW:
                progress(m + 1, n)
        return data, echoes

    def _atom(self, m: int, n_window: int):
        """The atom of recording ``m`` (absorbed over its gate's mean path where asked) and that path, m."""
        from ..physics.sound import speed_of_sound
        from . import Atom, absorbed_pulse

        fs = self.dataset.fs_hz
        if not self.absorption:
            return Atom(self.heard, fs, n_window, complex=True), None
        temp, hum = float(self.air_t[m]), float(self.air_h[m])
        c = speed_of_sound(temp, hum) if self.air_c is None else float(self.air_c[m])
        path_m = c * 0.5 * float(self.gates[m, 0] + self.gates[m, 1])
        return Atom(absorbed_pulse(self.heard, fs, path_m, temperature_c=temp, humidity_pct=hum), fs, n_window,
                    complex=True), path_m

    def echoes(self, m: int):
        """(Echoes of recording ``m``, delays after the transmit start; its matched-filter row
        where the method failed, else None)."""
        from . import Echoes

        ds, gates, fs = self.dataset, self.gates, self.dataset.fs_hz
        gate_s = (float(gates[m, 0]), float(gates[m, 1]))
        # the samples that echoes from the gate can reach, and the delays (from that first sample)
        s_lo = max(0, int(np.floor((gates[m, 0] - self.t0[m]) * fs)) - 2)
        s_hi = min(ds.n_samples, int(np.ceil((gates[m, 1] - self.t0[m]) * fs)) + len(self.heard) + 2)
        if s_hi - s_lo < 2:
            return Echoes([], [], self.method, _EMPTY_WINDOW, info={"gate_s": gate_s}), None
        x = analytic(np.asarray(ds.signals[m, s_lo:s_hi], float))
        atom, path_m = self._atom(m, s_hi - s_lo)
        offset = self.t0[m] + s_lo / fs  # delay after the transmit start of the window's first sample
        gate_rel = (gates[m, 0] - offset, gates[m, 1] - offset)
        tau0 = gate_rel[0] - self.guard
        n_atoms = max(2, int(np.ceil((gate_rel[1] + self.guard - tau0) / self.delta)) + 1)
        e, failed = _one(self.method, x, atom, self.delta, tau0, n_atoms, gate_rel, self.lam, self.lam_frac,
                         self.max_echoes, self.options)
        row = _matched_row(x, atom, self.fc, offset, gate_rel, self.grid) if failed is not None else None
        e.delays_s = e.delays_s + offset  # after the transmit start
        e.info["gate_s"] = gate_s
        if path_m is not None:
            e.info["path_m"] = path_m
        return e, row
