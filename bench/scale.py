"""``python -m bench --scale``: volumes past memory and past one process (:mod:`clsas.pipeline.tiling`).

- peak RSS against grid size: each grid formed out of core (``reconstruct(out=..., max_memory=...)``)
  in a fresh child process, its peak resident memory (``VmHWM``) read there, and a sample of its
  tiles checked against an in-memory reconstruction of the same tiles;
- tiles/s and the tile size's effect (one process, the file in memory);
- strong scaling on a Dask ``LocalCluster`` of 1 and 2 single-threaded workers (each worker's CPU
  device a sub-device of one compute unit, by the library's device fission), the image checked
  against one in-memory call, and the overhead of 8 workers sharing the same cores.

The host's load average is recorded before and after each timed part: on a shared machine a
ratio measured under load says little. Benchmarks measure; nothing here asserts a timing.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import clsas
from clsas.physics.geometry import VoxelGrid
from clsas.types.profiles import Profiles

__all__ = ["QUICK_SCALE", "FULL_SCALE", "run_scale", "out_of_core_case", "strong_scaling", "tile_size_effect"]

log = logging.getLogger(__name__)

QUICK_SCALE = {
    "rss": {"voxels": (1e6, 1e7, 3e7), "n_meas": 4, "max_memory": 5e8, "sample": 3},
    "tiles": {"voxels": 4e6, "n_meas": 25, "planes": (None, 64, 16, 4, 1)},
    "scaling": {"pairs": 5e8, "n_meas": 50, "workers": (1, 2), "overhead_workers": 8, "n_tiles": 16},
}
FULL_SCALE = {
    "rss": {"voxels": (1e7, 1e8, 1e9), "n_meas": 4, "max_memory": 2e9, "sample": 4},
    "tiles": {"voxels": 2e7, "n_meas": 50, "planes": (None, 64, 16, 4, 1)},
    "scaling": {"pairs": 1.05e10, "n_meas": 400, "workers": (1, 2), "overhead_workers": 8, "n_tiles": 16},
}


def _grid(n_voxels: float) -> VoxelGrid:
    """A cube of about ``n_voxels`` at 2 mm, 0.5 m in front of the aperture."""
    side = max(2, int(round(float(n_voxels) ** (1 / 3))))
    ax = (np.arange(side) - side / 2) * 2e-3
    return VoxelGrid(ax, ax.copy(), 0.5 + np.arange(side) * 2e-3)


def _profiles(grid: VoxelGrid, n_meas: int, seed: int = 0) -> Profiles:
    from .throughput import backprojection_workload

    w = backprojection_workload(grid, n_meas, np.random.default_rng(seed))
    return Profiles.from_range_profiles(w["data"], tau0_s=w["tau0"], dtau_s=w["dtau"], tx_positions=w["tx"],
                                        rx_positions=w["rx"], c_mps=w["c"], fc_hz=w["fc"], baseband=True,
                                        method="bench")


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _autogroup() -> str | None:
    """Linux's scheduler autogroup (``/proc/sys/kernel/sched_autogroup_enabled`` and this process's
    group): where it is on, the CPU is shared fairly between sessions first, so on a busy host a
    session's workers share one session's part however many there are; None where unknown."""
    try:
        with open("/proc/sys/kernel/sched_autogroup_enabled") as f:
            on = f.read().strip() == "1"
        with open(f"/proc/{os.getpid()}/autogroup") as f:
            fields = f.read().split()
    except OSError:
        return None
    if not on:
        return "off"
    # The group file is empty in some containers (CI's among them): the setting is still known.
    return f"on ({fields[0]})" if fields else "on"


def _ooc_child(n_voxels: float, n_meas: int, max_memory: float, path: str, sample: int) -> dict:
    """In a fresh process: form the grid out of core, read the peak RSS, check a sample of tiles."""
    from clsas.pipeline.tiling import peak_rss_bytes, rss_bytes, tile_grid

    grid = _grid(n_voxels)
    prof = _profiles(grid, n_meas)
    rss0 = rss_bytes()
    t0 = time.perf_counter()
    image = clsas.reconstruct(prof, grid, out=path, max_memory=max_memory)
    seconds = time.perf_counter() - t0
    peak = peak_rss_bytes()
    tiles = image.provenance["tiles"]
    parts = tile_grid(grid, tuple(tiles["shape"]))
    picks = sorted({int(i) for i in np.linspace(0, len(parts) - 1, min(sample, len(parts))).round()})
    errors = []
    for i in picks:
        alone = clsas.reconstruct(prof, parts[i].grid).values
        got = image.values[parts[i].slices]
        errors.append(float(np.abs(got - alone).max() / max(np.abs(alone).max(), 1e-30)))
    size = Path(path).stat().st_size
    Path(path).unlink()
    return {"voxels": grid.size, "shape": list(grid.shape), "n_meas": n_meas, "pairs": float(grid.size) * n_meas,
            "max_memory_bytes": max_memory, "rss_before_bytes": rss0, "peak_rss_bytes": peak,
            "image_bytes_complex64": 8 * grid.size, "file_bytes": size, "time_s": seconds,
            "tiles": tiles["count"], "tile_shape": tiles["shape"], "tiles_per_s": tiles["count"] / seconds,
            "pairs_per_s": float(grid.size) * n_meas / seconds, "device": image.device,
            "checked_tiles": picks, "max_rel_diff_vs_in_memory": max(errors) if errors else None}


def out_of_core_case(n_voxels: float, n_meas: int, max_memory: float, workdir: str | Path, sample: int = 3) -> dict:
    """One grid formed out of core in a child process (so its peak RSS is its own); see :func:`_ooc_child`."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    path = str(Path(workdir) / f"ooc-{int(n_voxels)}.h5")
    load0 = _load()
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        row = ex.submit(_ooc_child, n_voxels, n_meas, max_memory, path, sample).result()
    return {**row, "load_before": load0, "load_after": _load()}


def tile_size_effect(n_voxels: float, n_meas: int, planes: tuple) -> list[dict]:
    """Run time of one grid formed in tiles of ``planes`` x-planes each (None: the whole grid), in memory."""
    grid = _grid(n_voxels)
    prof = _profiles(grid, n_meas)
    clsas.reconstruct(prof, grid)  # warm-up: kernel built, variants verified, memory touched
    rows = []
    for p in planes:
        shape = (grid.shape[0] if p is None else min(p, grid.shape[0]), *grid.shape[1:])
        load0 = _load()
        t0 = time.perf_counter()
        image = clsas.reconstruct(prof, grid, tile_shape=shape)
        seconds = time.perf_counter() - t0
        n = image.provenance["tiles"]["count"]
        rows.append({"tile_shape": list(shape), "tile_voxels": int(np.prod(shape)), "tiles": n, "time_s": seconds,
                     "tiles_per_s": n / seconds, "pairs_per_s": float(grid.size) * n_meas / seconds,
                     "load_before": load0, "load_after": _load()})
    return rows


def _warm(grid_axes, dask_worker=None) -> str:
    """On a worker: build the kernel once on the device its tiles will use (not counted in the timed run)."""
    from clsas.formation import form
    from clsas.pipeline.tiling.dask import worker_selection

    threads = None if dask_worker is None else dask_worker.state.nthreads
    selection, units = worker_selection("auto", None, threads=threads)
    grid = VoxelGrid(*grid_axes)
    image = form(_profiles(grid, 2), grid, "bp", backend=selection)
    return f"{image.device} ({units} CU)"


def cpu_bound_speedup(cpu_one: list[float], cpu_many: list[float], cores: int | None = None) -> float:
    """The speed-up an idle host would show, from CPU seconds: one worker's over the longer of the busiest
    worker's and all workers' shared over the host's ``cores`` (default ``os.cpu_count()``)."""
    cores = cores or os.cpu_count() or 1
    return sum(cpu_one) / max(max(cpu_many), sum(cpu_many) / cores, 1e-9)


def _cpu_s() -> float:
    """On a worker: CPU seconds of its process so far (user + system, its PoCL threads included)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _cluster_run(n_workers: int, prof, grid, tile_shape, ref) -> dict:
    import distributed

    # one core per worker: its OpenCL CPU device is a sub-device of 1 compute unit (clsas.pipeline.tiling.dask)
    env = {"OMP_NUM_THREADS": "1"}
    quiet = logging.getLogger("distributed")
    level = quiet.level
    quiet.setLevel(logging.WARNING)
    try:
        with distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                      dashboard_address=":0", silence_logs=logging.ERROR, env=env) as cluster, \
                distributed.Client(cluster) as client:
            small = (grid.x_m[:2], grid.y_m[:2], grid.z_m[:2])
            devices = sorted(set(client.run(_warm, small).values()))
            cpu0, here0 = client.run(_cpu_s), _cpu_s()
            load0 = _load()
            t0 = time.perf_counter()
            image = clsas.reconstruct(prof, grid, client=client, tile_shape=tile_shape)
            seconds = time.perf_counter() - t0
            cpu = [v - cpu0[k] for k, v in client.run(_cpu_s).items() if k in cpu0]
            here = _cpu_s() - here0
    finally:
        quiet.setLevel(level)
    err = float(np.abs(image.values - ref).max() / np.abs(ref).max())
    return {"workers": n_workers, "threads_per_worker": 1, "time_s": seconds,
            "tiles": image.provenance["tiles"]["count"], "pairs_per_s": float(grid.size) * prof.n_meas / seconds,
            "max_rel_diff_vs_single_process": err, "worker_devices": devices, "load_before": load0,
            "load_after": _load(), "worker_cpu_s": cpu, "cpu_share": sum(cpu) / seconds / n_workers,
            "client_cpu_s": here,
            "worker_compute_units": {d: v["compute_units"] for d, v in image.provenance["tiles"]["devices"].items()},
            "values": image.values}


def strong_scaling(pairs: float, n_meas: int, workers: tuple = (1, 2), overhead_workers: int = 8,
                   n_tiles: int = 16, status: Callable[[str], None] | None = None) -> dict:
    """The same bp on LocalClusters of ``workers`` single-threaded workers and of ``overhead_workers``."""
    say = status or (lambda s: log.info("%s", s))
    grid = _grid(pairs / n_meas)
    prof = _profiles(grid, n_meas)
    shape = (max(1, -(-grid.shape[0] // n_tiles)), *grid.shape[1:])
    say(f"scaling: single process, {grid.size:.3g} voxels x {n_meas} measurements")
    load0 = _load()
    t0 = time.perf_counter()
    ref = clsas.reconstruct(prof, grid).values
    single = {"time_s": time.perf_counter() - t0, "load_before": load0, "load_after": _load(),
              "note": "one process, no tiles, the PoCL device on every core"}
    rows = []
    for w in (*workers, overhead_workers):
        say(f"scaling: LocalCluster of {w} single-threaded worker(s)")
        rows.append(_cluster_run(w, prof, grid, shape, ref))
    base, first = rows[0]["time_s"], rows[0]["values"]
    for r in rows:
        r["speedup_vs_1_worker"] = base / r["time_s"]
        r["cpu_bound_speedup_vs_1_worker"] = cpu_bound_speedup(rows[0]["worker_cpu_s"], r["worker_cpu_s"])
        r["max_abs_diff_vs_1_worker"] = float(np.abs(r.pop("values") - first).max())
    return {"voxels": grid.size, "n_meas": n_meas, "pairs": float(grid.size) * n_meas, "tile_shape": list(shape),
            "single_process": single, "clusters": rows}


def run_scale(full: bool = False, out_dir: str | Path = "bench/results", *, parts: tuple = ("rss", "tiles", "scaling"),
              workdir: str | Path | None = None, status: Callable[[str], None] | None = None) -> dict:
    """Run the scale benchmark (quick or full) and write JSON and Markdown to ``out_dir``."""
    from .stats import jsonable

    say = status or (lambda s: log.info("%s", s))
    cfg = FULL_SCALE if full else QUICK_SCALE
    res: dict = {"kind": "scale", "full": full, "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                 "host": platform.node(), "cpus": os.cpu_count(), "load_start": _load(),
                 "sched_autogroup": _autogroup()}
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        if "rss" in parts:
            c = cfg["rss"]
            res["rss"] = []
            for n in c["voxels"]:
                say(f"out of core: {n:.3g} voxels, budget {c['max_memory'] / 1e9:.2g} GB")
                res["rss"].append(out_of_core_case(n, c["n_meas"], c["max_memory"], tmp, c["sample"]))
    if "tiles" in parts:
        say("tile size")
        res["tiles"] = tile_size_effect(cfg["tiles"]["voxels"], cfg["tiles"]["n_meas"], cfg["tiles"]["planes"])
    if "scaling" in parts:
        res["scaling"] = strong_scaling(**cfg["scaling"], status=say)
    res["load_end"] = _load()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{dt.date.today().isoformat()}-scale{'' if full else '-quick'}"
    if set(parts) != {"rss", "tiles", "scaling"}:
        stem += "-" + "-".join(parts)
    import json

    (out / f"{stem}.json").write_text(json.dumps(jsonable(res), indent=2))
    (out / f"{stem}.md").write_text(markdown(res))
    res["paths"] = {"json": str(out / f"{stem}.json"), "md": str(out / f"{stem}.md")}
    return res


def markdown(res: dict) -> str:
    """The report: one table per part, with the load average beside each timing."""
    lines = [f"# python -m bench --scale ({'full' if res['full'] else 'quick'}), {res['date']}", "",
             f"Host {res['host']}, {res['cpus']} CPUs; load average (1, 5, 15 min) at the start {res['load_start']}, "
             f"at the end {res['load_end']}; scheduler autogroup {res.get('sched_autogroup')} (on: the CPU is "
             "shared between sessions first, so on a busy host the workers of this run share one session's part).", ""]
    if res.get("rss"):
        lines += ["## Peak RSS against grid size (out of core, one process)", "",
                  "| voxels | pairs | budget | peak RSS | image (complex64) | tiles | tiles/s | pairs/s | "
                  "sampled tiles vs in-memory (max rel diff) | load before -> after |", "|" + "---|" * 10]
        for r in res["rss"]:
            lines.append(f"| {r['voxels']:.3g} | {r['pairs']:.3g} | {r['max_memory_bytes'] / 1e9:.2g} GB | "
                         f"{r['peak_rss_bytes'] / 1e9:.3g} GB | {r['image_bytes_complex64'] / 1e9:.3g} GB | "
                         f"{r['tiles']} | "
                         f"{r['tiles_per_s']:.3g} | {r['pairs_per_s']:.3g} | {r['max_rel_diff_vs_in_memory']:.2g} "
                         f"({len(r['checked_tiles'])} tiles) | {r['load_before'][0]} -> {r['load_after'][0]} |")
        lines.append("")
    if res.get("tiles"):
        lines += ["## Tile size (one process, in memory)", "",
                  "| tile | voxels/tile | tiles | time | tiles/s | pairs/s | load |", "|" + "---|" * 7]
        for r in res["tiles"]:
            lines.append(f"| {' x '.join(map(str, r['tile_shape']))} | {r['tile_voxels']:.3g} | {r['tiles']} | "
                         f"{r['time_s']:.2f} s | {r['tiles_per_s']:.3g} | {r['pairs_per_s']:.3g} | "
                         f"{r['load_before'][0]} -> {r['load_after'][0]} |")
        lines.append("")
    if res.get("scaling"):
        s = res["scaling"]
        sp = s["single_process"]
        lines += ["## Strong scaling on a LocalCluster (single-threaded workers)", "",
                  f"{s['voxels']:.3g} voxels x {s['n_meas']} measurements = {s['pairs']:.3g} pairs in tiles of "
                  f"{' x '.join(map(str, s['tile_shape']))}; one process without tiles: {sp['time_s']:.2f} s "
                  f"(load {sp['load_before'][0]} -> {sp['load_after'][0]}).", "",
                  "The CPU share is the workers' CPU seconds over (wall time x workers): 1 means each had a core to "
                  "itself. The CPU-bound speed-up is 1 worker's CPU seconds over the longer of the busiest worker's "
                  "and all workers' divided by the host's cores: the speed-up an idle host would show, estimated from "
                  "the CPU time the work took (not a wall-clock measurement; CPU time itself grows under load). "
                  "Client CPU: the client's process (with a LocalCluster, the scheduler too).", "",
                  "| workers | compute units per worker | time | pairs/s | speed-up vs 1 worker | CPU share | "
                  "CPU-bound speed-up | client CPU | image vs one process (max rel diff) | "
                  "vs 1 worker (max abs diff) | load |", "|" + "---|" * 11]
        for r in s["clusters"]:
            units = "/".join(str(u) for u in sorted(set(r.get("worker_compute_units", {}).values()))) or "?"
            lines.append(f"| {r['workers']} | {units} | {r['time_s']:.2f} s | {r['pairs_per_s']:.3g} | "
                         f"{r['speedup_vs_1_worker']:.2f}x | {r['cpu_share']:.2f} | "
                         f"{r['cpu_bound_speedup_vs_1_worker']:.2f}x | {r.get('client_cpu_s', float('nan')):.1f} s | "
                         f"{r['max_rel_diff_vs_single_process']:.2g} | "
                         f"{r['max_abs_diff_vs_1_worker']:.2g} | "
                         f"{r['load_before'][0]} -> {r['load_after'][0]} |")
        lines.append("")
    return "\n".join(lines)
