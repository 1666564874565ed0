"""The two-echo resolution task: draw a noisy profile of two echoes of the paper's chirp a
given separation apart, run a method on it, score it. Used by the benchmark (bench/, python -m
bench) and the tests; a sweep is a list of plain dicts, so it can be run anywhere and compared
row by row. The sparse methods run through :data:`clsas.sparse.SPARSE_METHODS`.

SNR convention: the power of one echo per sample over the pulse it occupies (its energy over
the pulse's length in samples), over the noise power per sample (E|n|^2 for complex noise).
Success: exactly two echoes found, each matched (Hungarian) within ``tol_b / B`` of a true one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from clsas.sparse.atoms import Atom, Dictionary
from clsas.sparse.metrics import Echoes, crb_delays, delay_error
from clsas.sparse.paper import GRID_DELTAS, GRID_LAM_FRACS, GRID_METHODS, grid_cell, grid_problem

__all__ = ["TwoEchoTask", "TASK_METHODS", "run_trial", "sweep", "summarise", "GRID_METHODS", "grid_problem",
           "grid_cell", "grid_sweep", "measured_like"]

TASK_METHODS = ("matched", "fmcw", "bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar", "ml2")


@dataclass(frozen=True)
class TwoEchoTask:
    """Profiles of ``n_samples`` at ``fs_hz``: two echoes of an LFM chirp, the first at
    ``first_delay_s`` plus a random fraction of a sample; delays are searched over a gate of
    ``gate_s`` around them."""

    fs_hz: float = 96e3
    f_start_hz: float = 20e3
    f_stop_hz: float = 30e3
    duration_s: float = 2e-3
    taper: float = 0.2
    n_samples: int = 1000
    first_delay_s: float = 3e-3
    gate_s: tuple = (2.5e-3, 3.8e-3)
    amplitudes: str = "complex"

    @property
    def bandwidth_hz(self) -> float:
        return abs(self.f_stop_hz - self.f_start_hz)

    @cached_property
    def waveform(self) -> np.ndarray:
        from clsas.physics.signals import lfm_chirp

        return lfm_chirp(self.f_start_hz, self.f_stop_hz, self.duration_s, self.fs_hz, taper=self.taper)

    @cached_property
    def atom(self) -> Atom:
        return Atom(self.waveform, self.fs_hz, self.n_samples, complex=self.amplitudes == "complex")

    def dictionary(self, delta_s: float | None = None) -> Dictionary:
        delta = 1.0 / self.fs_hz if delta_s is None else delta_s
        n = int(np.ceil((self.gate_s[1] - self.gate_s[0]) / delta)) + 1
        return Dictionary(self.atom, delta, self.gate_s[0], n)

    def draw(self, separation_b: float, snr_db: float, seed: int):
        """(signal, truth Echoes, noise sigma) for one trial."""
        rng = np.random.default_rng(seed)
        t1 = self.first_delay_s + rng.uniform(0, 1 / self.fs_hz)
        taus = np.array([t1, t1 + separation_b / self.bandwidth_hz])
        if self.amplitudes == "complex":
            amps = np.exp(2j * np.pi * rng.uniform(size=2))
        elif self.amplitudes == "real":
            amps = rng.choice([-1.0, 1.0], size=2)
        else:
            amps = np.ones(2)
        a = self.atom
        p_echo = np.sum(np.abs(a.matrix([t1])[:, 0]) ** 2) / len(self.waveform)
        sigma = float(np.sqrt(p_echo / 10 ** (snr_db / 10)))
        noise = rng.normal(size=a.n) + (1j * rng.normal(size=a.n) if a.complex else 0)
        noise *= sigma / (np.sqrt(2) if a.complex else 1.0)
        return a.matrix(taus) @ amps + noise, Echoes(taus, amps), sigma


def _peaks(y, taus, delta, scale, status):
    """Peaks of an envelope above half its maximum, refined by a parabola."""
    import scipy.signal

    pk, _ = scipy.signal.find_peaks(y, height=0.5 * y.max())
    out_t, out_a = [], []
    for k in pk:
        if 0 < k < len(y) - 1:
            den = y[k - 1] - 2 * y[k] + y[k + 1]
            off = 0.5 * (y[k - 1] - y[k + 1]) / den if den != 0 else 0.0
        else:
            off = 0.0
        out_t.append(taus[k] + off * delta)
        out_a.append(y[k] / scale)
    return Echoes(out_t, out_a, status)


def _envelope(task, b, oversample: int = 4):
    """(|correlation| with every atom of ``dictionary(1 / (oversample fs))``, that Dictionary),
    by :meth:`Atom.correlate` (FFT, O(n log n)); for a real atom, the envelope."""
    y_all = task.atom.correlate(b, oversample)
    d = task.dictionary(1.0 / (oversample * task.fs_hz))
    start = int(round(d.tau0 * oversample * task.fs_hz))
    return np.abs(y_all[start:start + len(d.taus)]), d


def _matched(task, b):
    """Peaks of the matched filter's envelope above half its maximum (parabolic refinement)."""
    y, d = _envelope(task, b)
    return _peaks(y, d.taus, d.delta, task.atom.norm**2, "matched")


def _fmcw(task, b):
    """FMCW (stretch processing): mix with the chirp delayed to the gate start, Fourier transform.

    The echoes arrive after the chirp has ended, so the local chirp is started at the gate's
    near edge (a delayed reference, as long-range FMCW does); the mixed window is the overlap
    of that reference with the gate's far edge, which sets the resolution.
    """
    from clsas.compression import compress

    chirp = {"f_start_hz": task.f_start_hz, "f_stop_hz": task.f_stop_hz, "duration_s": task.duration_s}
    start = int(task.gate_s[0] * task.fs_hz)  # the reference chirp starts here
    ref = start / task.fs_hz
    p = compress(np.real(b)[None, start:], task.waveform, task.fs_hz, method="fmcw", chirp=chirp, t0_s=0.0,
                 gate_s=(0.0, task.gate_s[1] - ref), backend="numpy")
    y = np.abs(p.data[0])
    taus = ref + p.tau0_s[0] + np.arange(p.n_lags) * p.dtau_s
    inside = (taus >= task.gate_s[0]) & (taus <= task.gate_s[1])
    return _peaks(np.where(inside, y, 0.0), taus, p.dtau_s, max(y.max(), 1e-30), "fmcw")


def _ml2(task, b):
    """Two-echo maximum likelihood, the number of echoes known: exhaustive pair search over
    the gate, then nlopt refinement (the task's reference)."""
    from clsas.sparse.varpro import VarPro, best_pair, mainlobe_s

    y, d = _envelope(task, b)
    centre = d.taus[int(np.argmax(y))]
    pair = best_pair(task.atom, b, centre, 2 * mainlobe_s(task.atom), task.amplitudes, n_grid=40)
    vp = VarPro(task.atom, b, task.amplitudes)
    taus, a, rss, status = vp.fit(pair, task.gate_s[0], task.gate_s[1], mainlobe_s(task.atom) / 16)
    return Echoes(taus, a, "ml2", status, vp.evals)


def run_trial(task: TwoEchoTask, method: str, separation_b: float, snr_db: float, seed: int, *,
              delta_s: float | None = None, lam_frac: float | None = None, tol_b: float = 0.25) -> dict:
    """One trial: a dict of the setting, success, delay errors, RMSE, sqrt(CRB), run time.

    The sparse methods run through :func:`clsas.sparse.sparse_echoes` with at most 8 echoes;
    BPDN's answer is read as one echo per run of neighbouring atoms (the fairest reading of a
    grid method's answer), atoms below 2 % of the largest ignored, as the convex CBPs' are.
    """
    from clsas.sparse import ShiftOperator, lam_max, lam_noise, sparse_echoes

    if method not in TASK_METHODS:
        raise ValueError(f"method must be one of {TASK_METHODS}, got {method!r}")
    b, truth, sigma = task.draw(separation_b, snr_db, seed)
    d = task.dictionary(delta_s)
    t = time.perf_counter()
    lam = None
    if method in ("bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar"):
        lam = (lam_frac * lam_max(ShiftOperator(d), b, task.amplitudes) if lam_frac is not None
               else lam_noise(d, b, task.amplitudes))
    if method == "matched":
        est = _matched(task, b)
    elif method == "fmcw":
        est = _fmcw(task, b)
    elif method == "ml2":
        est = _ml2(task, b)
    else:
        est = sparse_echoes(method, d, b, lam, amplitudes=task.amplitudes, max_echoes=8, rel_threshold=0.02)
    elapsed = time.perf_counter() - t
    err = delay_error(est, truth, tol_s=tol_b / task.bandwidth_hz)
    crb = crb_delays(task.atom, truth.delays_s, truth.amplitudes, sigma)
    return {
        "method": method, "separation_b": separation_b, "snr_db": snr_db, "seed": seed,
        "delta_s": d.delta, "lam_frac": lam_frac, "success": bool(err.success), "n_found": len(est),
        "rmse_s": err.rmse_s if err.success else float("nan"), "sqrt_crb_s": float(np.sqrt(np.mean(crb))),
        "time_s": elapsed, "status": est.status,
    }


def sweep(task: TwoEchoTask, methods, separations_b, snrs_db, trials: int, *, seed0: int = 0,
          progress=None, **kwargs) -> list[dict]:
    """Every method on the same noisy profiles (seed = seed0 + trial) for every setting."""
    rows = []
    total = len(methods) * len(separations_b) * len(snrs_db) * trials
    for sep in separations_b:
        for snr in snrs_db:
            for k in range(trials):
                for m in methods:
                    rows.append(run_trial(task, m, sep, snr, seed0 + k, **kwargs))
                    if progress is not None:
                        progress(len(rows), total)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per (method, separation, SNR): trials, success rate, RMSE over the successes,
    RMSE / sqrt(CRB), median run time."""
    keys = sorted({(r["method"], r["separation_b"], r["snr_db"]) for r in rows}, key=lambda k: (k[0], k[1], k[2]))
    out = []
    for m, sep, snr in keys:
        g = [r for r in rows if (r["method"], r["separation_b"], r["snr_db"]) == (m, sep, snr)]
        ok = [r for r in g if r["success"]]
        rmse = float(np.sqrt(np.mean([r["rmse_s"] ** 2 for r in ok]))) if ok else float("nan")
        crb = float(np.sqrt(np.mean([r["sqrt_crb_s"] ** 2 for r in g])))
        out.append({
            "method": m, "separation_b": sep, "snr_db": snr, "trials": len(g),
            "success_rate": len(ok) / len(g), "rmse_s": rmse, "rmse_over_crb": rmse / crb if ok else float("nan"),
            "sqrt_crb_s": crb, "median_time_s": float(np.median([r["time_s"] for r in g])),
        })
    return out


# -- the paper's Delta x lam grid (Fig. 6): two shifted decaying exponentials ---------------------

def grid_sweep(methods=GRID_METHODS, deltas=GRID_DELTAS, lam_fracs=GRID_LAM_FRACS, progress=None) -> list[dict]:
    """Every method at every (Delta, lam) cell, in a fixed order."""
    cells = [(m, d, lf) for d in deltas for lf in lam_fracs for m in methods]
    rows = []
    for m, d, lf in cells:
        rows.append(grid_cell(m, d, lf))
        if progress is not None:
            progress(len(rows), len(cells))
    return rows


# -- a recording that looks measured: what the imaging path meets on real scans ------------------

def measured_like(n_recordings: int = 4, *, seed: int = 0, snr_db: float = 20.0, n_samples: int = 1000,
                  fs_hz: float = 100e3, colour: bool = True):
    """Recordings like measured ones, and the gate to search, for timing the
    sparse methods on the imaging path (:func:`clsas.sparse.profiles.superres_profiles`).

    LFM 30 -> 10 kHz, 1 ms, Tukey 0.2, at ``fs_hz``; in each recording an extended reflector
    (a curve of 30 scatterers over 3-8 ms, random phases), a static clutter echo 10x stronger
    at 1.6 ms, an echo starting half a pulse before the gate (1-8.5 ms) and a strong one just
    past its end; the pulse coloured by a transducer band-pass (12-27 kHz, 2nd order) where
    ``colour``; white noise ``snr_db`` under the mean target echo power over its pulse.

    Returns
    -------
    (Dataset, gates_s)
        The recordings (positions all zero: only the delays matter here) and the
        (n_recordings, 2) gate, s.
    """
    import scipy.signal

    from clsas.physics.signals import lfm_chirp
    from clsas.types.dataset import Dataset

    wave = lfm_chirp(30e3, 10e3, 1e-3, fs_hz, taper=0.2)
    heard = wave
    if colour:
        b, a = scipy.signal.butter(2, [12e3, 27e3], btype="band", fs=fs_hz)
        heard = scipy.signal.lfilter(b, a, np.r_[wave, np.zeros(len(wave) // 4)])
    at = Atom(heard, fs_hz, n_samples, complex=True)
    gate = (1.0e-3, 8.5e-3)
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 1, 30)
    signals = np.empty((n_recordings, n_samples))
    for m in range(n_recordings):
        taus = 3e-3 + 5e-3 * s + 0.3e-3 * np.sin(2 * np.pi * (s + rng.uniform())) + rng.uniform(0, 1 / fs_hz, 30)
        amps = rng.uniform(0.3, 1, 30) * np.exp(2j * np.pi * rng.uniform(size=30))
        p_echo = np.sum(np.abs(at.matrix([4e-3])[:, 0].real) ** 2) / len(wave) * np.mean(np.abs(amps) ** 2)
        taus = np.r_[taus, 1.6e-3, gate[0] - 0.5e-3, gate[1] + 0.3e-3]
        amps = np.r_[amps, 10 * np.exp(0.3j), 2.0, 3.0]
        sigma = np.sqrt(p_echo / 10 ** (snr_db / 10))
        signals[m] = np.real(at.matrix(taus) @ amps) + sigma * rng.normal(size=n_samples)
    zeros = np.zeros((n_recordings, 3))
    return Dataset(signals, zeros, zeros, fs_hz, wave), np.tile(gate, (n_recordings, 1))
