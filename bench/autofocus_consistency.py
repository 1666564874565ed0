"""Does the data pin the stops' paths on extended targets? A data-consistency probe.

    python -m bench.autofocus_consistency [--seeds 0 1 2 3 4 5] [--rms-mm 3] [--alphas 0 0.3 0.6 1]
                                          [--out bench/results]

Sharpness and image energy over-fit on the scene family's planes and sphere caps (the eighth
session's note): the truth is not their maximum. This probe asks the question the other way
round, of the measurements themselves, on each family scene (:func:`clsas.synthesis.scene_family.family_scene`,
with the true clock and speed of sound, so that only the motion is unknown):

- **the objective**: the relative residual ``|y - A x| / |y|`` of the range profiles ``y``
  against the model ``A x`` (:class:`clsas.inverse.ImagingOperator` with the compressed pulse, on
  the scene's grid), ``x`` fitted by 10 LSQR iterations; ``y`` read with each stop's path
  correction ``p_s``;
- **the update**: each stop's phase ``arg sum conj(A x) y`` over its profiles, unwrapped in
  time and fitted in the hand's band plus the tilt (as ``"points"`` does), turned into a path,
  the gauge (constant and tilt) removed; 6 passes;
- **the starts**: ``p = alpha * truth`` for each ``--alphas`` (0: no knowledge; 1: the truth,
  which shows whether the truth is a fixed point of the update).

Printed and written per scene and start: the residual and the wrapped phase error against the
truth (rad RMS, gauge removed) before and after the passes, and the local peak against the
error-free image (as :mod:`bench.autofocus_family` scores it).

Writes ``<date>-autofocus-consistency.{json,md}`` under --out. It is a probe, not a method: nothing
in :func:`clsas.autofocus` uses it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from pathlib import Path

import numpy as np
from scipy.sparse.linalg import lsqr

import clsas
from bench.autofocus_family import local_peak_db
from clsas.focus.engine import FocusEngine
from clsas.focus.motion import stops_of
from clsas.focus.points import smooth_unwrapped
from clsas.focus.track import DEFAULT_CUTOFF_HZ, gauge_free, smooth_basis
from clsas.inverse.operator import ImagingOperator, compressed_pulse
from clsas.synthesis.scene_family import family_scene
from clsas.types.profiles import Profiles

INNER = 10  # LSQR iterations per model fit
PASSES = 6


def truth_paths(fs, stop: np.ndarray) -> np.ndarray:
    """Per stop, the two-way path error towards the grid's centre (true minus stated), m."""
    ds, tr = fs.dataset, fs.dataset.truth
    centre = fs.grid.points().mean(axis=0)

    def path(tx, rx):
        return np.linalg.norm(centre - tx, axis=1) + np.linalg.norm(centre - rx, axis=1)

    e = path(tr["tx_positions"], tr["rx_positions"]) - path(ds.tx_positions, ds.rx_positions)
    n = int(stop.max()) + 1
    return np.bincount(stop, e, n) / np.bincount(stop, None, n)


class Probe:
    """One scene with its true clock and speed of sound, its profiles and its truth."""

    def __init__(self, seed: int, rms_m: float):
        self.fs = fs = family_scene(seed, rms_m=rms_m)
        tr = fs.dataset.truth
        self.c = np.broadcast_to(np.asarray(tr["c_mps"], float), (fs.dataset.n_meas,)).copy()
        self.ds = fs.dataset.replace(t0_s=np.asarray(tr["t0_s"], float), c_mps=self.c)
        self.engine = FocusEngine(self.ds, fs.grid, margin_s=2e-4)
        p = self.engine.prof
        self.pulse = compressed_pulse(self.ds.waveform, self.ds.fs_hz, p.dtau_s, p.fc_hz)
        self.stop, self.t_stop, self.xy = stops_of(self.ds)
        self.n = len(self.t_stop)
        first = np.r_[0, np.flatnonzero(np.diff(self.stop)) + 1]
        self.to_path = self.c[first] / (2 * np.pi * p.fc_hz)
        self.basis = smooth_basis(self.t_stop, self.xy, DEFAULT_CUTOFF_HZ)
        self.truth = truth_paths(fs, self.stop)

    def model(self, p_stop: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``(model, data, residual)``: the profiles as read with ``p_stop``, the model fitted to them."""
        pr = self.engine.prof
        data, tau0 = self.engine._shifted(-p_stop[self.stop] / self.c)
        prof = Profiles(data, tau0, pr.dtau_s, pr.fc_hz, pr.method, pr.backend, tx_positions=self.ds.tx_positions,
                        rx_positions=self.ds.rx_positions, c_mps=self.c)
        a = ImagingOperator(prof, self.fs.grid, pulse=self.pulse)
        x = lsqr(a, a.data, iter_lim=INNER)[0]
        m = (a @ x).reshape(self.ds.n_meas, -1)
        y = a.data.reshape(self.ds.n_meas, -1)
        return m, y, float(np.linalg.norm(y - m) / np.linalg.norm(y))

    def phase_error(self, p_stop: np.ndarray) -> float:
        """Wrapped phase error against the truth, rad RMS, gauge removed."""
        r = gauge_free(p_stop - self.truth, self.xy) / self.to_path
        return float(np.sqrt(np.mean(np.angle(np.exp(1j * r)) ** 2)))

    def passes(self, p_stop: np.ndarray) -> tuple[np.ndarray, list[float]]:
        """:data:`PASSES` updates from ``p_stop`` (module docstring), and the residual before each and after."""
        res = []
        for _ in range(PASSES):
            m, y, r = self.model(p_stop)
            res.append(r)
            zm = np.sum(np.conj(m) * y, axis=1)
            z = np.bincount(self.stop, zm.real, self.n) + 1j * np.bincount(self.stop, zm.imag, self.n)
            p_stop = gauge_free(p_stop - smooth_unwrapped(z, self.t_stop, self.basis) * self.to_path, self.xy)
        res.append(self.model(p_stop)[2])
        return p_stop, res

    def peak_db(self, p_stop: np.ndarray, point: np.ndarray, ref_db: float) -> float:
        ds = self.ds.replace(t0_s=self.ds.t0_s - p_stop[self.stop] / self.c)
        return local_peak_db(ds, point) - ref_db


def probe_scene(seed: int, rms_m: float, alphas) -> list[dict]:
    pb = Probe(seed, rms_m)
    clean = np.abs(clsas.reconstruct(pb.fs.clean, pb.fs.grid).values).ravel()
    point = pb.fs.grid.points()[int(np.argmax(clean))]
    ref = local_peak_db(pb.fs.clean, point)
    rows = []
    for a in alphas:
        t = time.perf_counter()
        start = float(a) * pb.truth
        p, res = pb.passes(start)
        rows.append({"seed": seed, "kind": pb.fs.kind, "n_stops": pb.n, "alpha": float(a), "device": pb.engine.device,
                     "phase_error_start_rad": pb.phase_error(start), "phase_error_end_rad": pb.phase_error(p),
                     "residual_start": res[0], "residual_end": res[-1],
                     "peak_start_db": pb.peak_db(start, point, ref), "peak_end_db": pb.peak_db(p, point, ref),
                     "time_s": time.perf_counter() - t})
        r = rows[-1]
        print(f"seed {seed} {pb.fs.kind:6s} alpha {a:g}: phase {r['phase_error_start_rad']:.2f} -> "
              f"{r['phase_error_end_rad']:.2f} rad, residual {r['residual_start']:.3f} -> {r['residual_end']:.3f}, "
              f"peak {r['peak_start_db']:.2f} -> {r['peak_end_db']:.2f} dB ({r['time_s']:.0f} s)", flush=True)
    return rows


def markdown(rows: list[dict], args) -> str:
    out = [f"# Data-consistency probe on the autofocus family, {args.rms_mm:g} mm hand motion\n",
           f"Seeds {', '.join(map(str, args.seeds))}; true clock and speed of sound; {PASSES} passes of "
           f"{INNER} LSQR iterations; device: {', '.join(sorted({r['device'] for r in rows}))}; "
           f"{sum(r['time_s'] for r in rows):.0f} s. `python -m bench.autofocus_consistency`.\n",
           "| seed | kind | start (x truth) | phase error, rad | residual | local peak, dB |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['seed']} | {r['kind']} | {r['alpha']:g} | {r['phase_error_start_rad']:.2f} -> "
                   f"{r['phase_error_end_rad']:.2f} | {r['residual_start']:.3f} -> {r['residual_end']:.3f} | "
                   f"{r['peak_start_db']:.2f} -> {r['peak_end_db']:.2f} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--rms-mm", type=float, default=3.0)
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.0, 0.3, 0.6, 1.0])
    ap.add_argument("--out", default="bench/results")
    args = ap.parse_args(argv)
    if args.rms_mm <= 0 or not np.isfinite(args.rms_mm):
        ap.error(f"--rms-mm must be positive, got {args.rms_mm}")
    if any(s < 0 for s in args.seeds):
        ap.error("--seeds must be non-negative")
    if any(not np.isfinite(a) for a in args.alphas):
        ap.error("--alphas must be finite")
    rows = [r for s in args.seeds for r in probe_scene(s, args.rms_mm * 1e-3, args.alphas)]
    stem = Path(args.out) / f"{dt.date.today().isoformat()}-autofocus-consistency"
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps({"seeds": args.seeds, "rms_mm": args.rms_mm, "rows": rows},
                                                    indent=1))
    stem.with_suffix(".md").write_text(markdown(rows, args))
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
