"""Stress figures of the sparse methods: CBP-Polar's nlopt stops, extra echoes on
real recordings (tapered and hard-edged chirps), and the false-alarm rate on pure noise.

    python -m bench.bench_stress [--stalls 50] [--edges 20] [--noise 200] [--out bench/results]

``--stalls N``: the K-echo profiles (bench.kecho.draw_k: K = 2, 3, 4, 5 echoes 2/B apart,
amplitude ratio 1 and 0.5, 10 dB, seeds 0..N-1), refined CBP-Polar as the K-echo table runs it;
counts every nlopt fit's status (``stalled`` is L-BFGS's runtime_error, the best point kept),
the answers' statuses and their success (each delay within 0.25 / B).

``--edges N``: N real recordings of 160 samples at 96 kHz, two echoes of a 20-30 kHz 0.4 ms
chirp (amplitudes 1 and 0.6, the second 30-80 samples after the first), noise 0.01 per sample
(about 37 dB); Tukey 0.2 and hard-edged (taper 0) chirps. Per method through ``superres`` at
its defaults: profiles with exactly the two echoes (each within 0.25 sample), with more.

``--noise N``: N pure-noise recordings (160 samples of unit white noise), per method: how many
return an echo (the stated rate is at most 1 %).

Writes <date>-stress-<host>.json and .md; each row carries the load average at its start.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import importlib
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import clsas
from clsas.sparse import superres

FS = 96e3
N = 160
CASES = [("bpdn", "complex"), ("cbp-polar", "complex"), ("cbp-taylor", "positive"), ("cbp-polar-socp", "positive")]


def _load() -> float:
    return os.getloadavg()[0]


def stalls(n_seeds: int) -> dict:
    from bench.kecho import draw_k, task_for
    from clsas.sparse import delay_error, lam_noise, sparse_echoes

    varpro = importlib.import_module("clsas.sparse.varpro")
    counts: collections.Counter = collections.Counter()
    fit = varpro.VarPro.fit

    def counted(self, *args, **kwargs):
        out = fit(self, *args, **kwargs)
        counts["fits"] += 1
        counts["fits " + out[3].split(" (")[0]] += 1
        return out

    load, t = _load(), time.perf_counter()
    varpro.VarPro.fit = counted
    try:
        for k in (2, 3, 4, 5):
            for ratio in (1.0, 0.5):
                for seed in range(n_seeds):
                    task = task_for(k, 2.0)
                    b, truth, _ = draw_k(task, k, ratio, 2.0, 10.0, seed)
                    d = task.dictionary()
                    e = sparse_echoes("cbp-polar", d, b, lam_noise(d, b, "complex"), amplitudes="complex",
                                      max_echoes=max(2 * k, 8), rel_threshold=0.02)
                    ok = delay_error(e, truth, tol_s=0.25 / task.bandwidth_hz).success
                    counts["profiles"] += 1
                    counts["answers " + e.status.split(" (")[0]] += 1
                    counts["succeeded"] += bool(ok)
    finally:
        varpro.VarPro.fit = fit
    return {**dict(counts), "time_s": time.perf_counter() - t, "load": load}


def _profile(pulse, delays, amps):
    """Real echoes of ``pulse`` (band-limited shifts) in N samples."""
    spec = np.fft.rfft(pulse, 4 * N)
    f = np.fft.rfftfreq(4 * N, 1 / FS)
    x = np.zeros(N)
    for tau, a in zip(delays, amps, strict=True):
        x += a * np.fft.irfft(spec * np.exp(-2j * np.pi * f * (tau + N / FS)), 4 * N)[N:2 * N]
    return x


def edges(n: int) -> list[dict]:
    rows = []
    for taper in (0.2, 0.0):
        pulse = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=taper)
        for method, amplitudes in CASES:
            rng = np.random.default_rng(7)
            load, t, exact, more = _load(), time.perf_counter(), 0, 0
            for _ in range(n):
                t1 = 40 + rng.uniform(0, 1)
                t2 = t1 + 30 + rng.uniform(0, 50)
                x = _profile(pulse, [t1 / FS, t2 / FS], [1.0, 0.6]) + 0.01 * rng.normal(size=N)
                e = superres(x, pulse, FS, method=method, amplitudes=amplitudes)
                exact += len(e) == 2 and bool(np.allclose(e.delays_s * FS, [t1, t2], atol=0.25))
                more += len(e) > 2
            rows.append({"taper": taper, "method": method, "profiles": n, "exactly_two": exact, "more_than_two": more,
                         "time_per_profile_s": (time.perf_counter() - t) / n, "load": load})
    return rows


def noise(n: int) -> list[dict]:
    pulse = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.2)
    rows = []
    for method, amplitudes in CASES:
        rng = np.random.default_rng(5)
        load, t = _load(), time.perf_counter()
        hits = sum(len(superres(rng.normal(size=N), pulse, FS, method=method, amplitudes=amplitudes)) > 0
                   for _ in range(n))
        rows.append({"method": method, "profiles": n, "with_an_echo": int(hits),
                     "time_per_profile_s": (time.perf_counter() - t) / n, "load": load})
    return rows


def _markdown(res: dict) -> str:
    out = [f"# Sparse stress figures ({res['date']}, {res['host']}, clsas {res['clsas']})", ""]
    if "stalls" in res:
        s = res["stalls"]
        out += ["## CBP-Polar's nlopt stops (K-echo profiles)", "",
                f"{s.get('profiles', 0)} profiles, {s.get('fits', 0)} fits: {s.get('fits stalled', 0)} fits and "
                f"{s.get('answers stalled', 0)} answers ended `stalled`; {s.get('succeeded', 0)} succeeded "
                f"({s['time_s']:.0f} s, load {s['load']:.1f}).", ""]
    if "edges" in res:
        out += ["## Two echoes in a real recording (37 dB)", "",
                "| taper | method | exactly two | more than two | s/profile | load |", "|---|---|---|---|---|---|"]
        out += [f"| {r['taper']} | {r['method']} | {r['exactly_two']}/{r['profiles']} | {r['more_than_two']} | "
                f"{r['time_per_profile_s']:.2f} | {r['load']:.1f} |" for r in res["edges"]]
        out.append("")
    if "noise" in res:
        out += ["## Pure noise", "", "| method | with an echo | s/profile | load |", "|---|---|---|---|"]
        out += [f"| {r['method']} | {r['with_an_echo']}/{r['profiles']} | {r['time_per_profile_s']:.3f} | "
                f"{r['load']:.1f} |" for r in res["noise"]]
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stalls", type=int, default=50, help="seeds per K-echo cell (0: skip)")
    ap.add_argument("--edges", type=int, default=20, help="profiles per chirp and method (0: skip)")
    ap.add_argument("--noise", type=int, default=200, help="pure-noise profiles per method (0: skip)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    ap.add_argument("--host", default=platform.node() or "host", help="name in the output files")
    args = ap.parse_args(argv)
    res = {"date": datetime.date.today().isoformat(), "host": args.host, "clsas": clsas.__version__,
           "cpus": os.cpu_count()}
    if args.stalls:
        res["stalls"] = stalls(args.stalls)
    if args.edges:
        res["edges"] = edges(args.edges)
    if args.noise:
        res["noise"] = noise(args.noise)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{res['date']}-stress-{res['host']}"
    stem.with_suffix(".json").write_text(json.dumps(res, indent=1))
    stem.with_suffix(".md").write_text(_markdown(res))
    print(_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
