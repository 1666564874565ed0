"""The benchmark suite: a smoke run of the quick set (no timing is asserted), the Dask sweep
against the serial sweep, and a tiled volume against one call."""

import json

import numpy as np
import pytest

import clsas
from bench import accuracy, distributed, stats
from bench.trials import TwoEchoTask, grid_sweep, sweep

pytest.importorskip("distributed", reason="the Dask tests need dask.distributed (pip install 'clsas[bench]')")


def test_fit_exponent_recovers_a_power_law(rng):
    x = np.logspace(2, 5, 7)
    assert stats.fit_exponent(x, 3e-9 * x**1.5) == pytest.approx(1.5, abs=1e-12)
    # +-2 % timing noise over three decades moves the slope by far less than the half-power it measures
    assert stats.fit_exponent(x, 3e-9 * x**1.5 * rng.uniform(0.98, 1.02, x.size)) == pytest.approx(1.5, abs=0.01)
    with pytest.raises(ValueError, match="two distinct positive sizes"):
        stats.fit_exponent([10, 10], [1.0, 2.0])
    with pytest.raises(ValueError, match="repeats"):
        stats.timed(lambda: None, 0)


def test_pareto_front_keeps_only_undominated_points():
    pts = [(1.0, 0.5), (2.0, 0.6), (3.0, 0.1), (0.5, 0.9), (4.0, 0.1)]
    assert accuracy.pareto_front(pts) == [(0.5, 0.9), (1.0, 0.5), (3.0, 0.1)]


def test_tiles_cover_the_grid_once():
    g = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.05, 0.05), (1.0, 1.1), 0.01)
    parts = distributed.tiles(g, 4)
    assert np.concatenate([sub.x_m for _, sub in parts]).tolist() == g.x_m.tolist()
    with pytest.raises(ValueError, match="n_tiles"):
        distributed.tiles(g, 0)


@pytest.fixture(scope="module")
def client():
    with distributed.dask_client(None, n_workers=2) as c:
        yield c


def _strip(rows):
    return [{k: v for k, v in r.items() if k != "time_s"} for r in rows]


def test_dask_sweep_equals_serial_sweep(client):
    task = TwoEchoTask()
    args = (("matched", "bpdn", "cbp-polar"), (0.25, 1.0), (10.0, 30.0), 2)
    serial = sweep(task, *args)
    on_dask = distributed.sweep_dask(client, task, *args)
    assert len(client.scheduler_info()["workers"]) == 2
    a, b = _strip(serial), _strip(on_dask)
    assert len(a) == len(b) == 24
    _assert_same_rows(a, b)
    grid_args = (("bpdn", "cbp-polar"), (0.05, 0.1), (0.01,))
    _assert_same_rows(_strip(grid_sweep(*grid_args)), _strip(distributed.grid_sweep_dask(client, *grid_args)))


def _assert_same_rows(a, b):
    """Equal rows: every count and flag exactly, floats to 1e-4 relative. Dask workers run BLAS with
    one thread (its nanny sets OMP_NUM_THREADS=1); on some CPUs a threaded BLAS sums in another
    order (seen on an AMD EPYC: 1e-14 in one product, 4e-6 after BPDN's thousands of iterations)."""
    assert len(a) == len(b)
    for ra, rb in zip(a, b, strict=True):
        assert ra.keys() == rb.keys()
        for k in ra:
            x, y = ra[k], rb[k]
            if isinstance(x, float) and isinstance(y, float):
                assert (np.isnan(x) and np.isnan(y)) or np.isclose(x, y, rtol=1e-4, atol=0), (k, ra, rb)
            else:
                assert x == y, (k, ra, rb)


def test_tiled_volume_equals_one_call(client):
    from conftest import small_dataset

    ds = small_dataset([[0.02, -0.01, 0.5]])
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.08, 0.08), (0.42, 0.58), 0.01)
    prof = clsas.compress(ds, backend="numpy", gate_s=(0.0, 1.2 / ds.c_mps))
    one = clsas.backproject(prof, grid).values
    tiled, devices = distributed.backproject_tiled(client, prof, grid, 3)
    assert len(devices) == 3
    assert np.abs(tiled - one).max() <= 1e-5 * np.abs(one).max()  # float32 tolerance


@pytest.mark.slow
def test_quick_bench_writes_json_report_and_plot(tmp_path, capsys, monkeypatch):
    """The whole quick suite's path through the CLI, its heaviest parts shrunk (the quick set itself
    runs autofocus on the demo mannequin and every K-echo cell: minutes, a benchmark's time)."""
    import bench
    from bench import formation
    from bench.__main__ import main

    monkeypatch.setitem(bench.QUICK, "autofocus", None)
    monkeypatch.setitem(bench.QUICK, "k_echo", {"ks": (2,), "ratios": (1.0,), "trials": 1})
    monkeypatch.setattr(formation, "QUICK", {"cases": ("demo", "circular"), "scale": 0.25, "sides": (8, 12)})
    assert main(["--out", str(tmp_path), "-q"]) == 0
    out = capsys.readouterr().out
    js = sorted(tmp_path.glob("*-quick.json"))
    assert len(js) == 1 and "wrote" in out
    res = json.loads(js[0].read_text())
    assert res["mode"] == "quick" and res["versions"]["clsas"] == clsas.__version__
    for part in ("backprojection", "compression", "scaling", "plan_saving", "two_echo", "delta_lambda", "formation"):
        assert part in res, part
    bp = res["backprojection"][0]
    assert bp["numpy_twin"]["rate_per_s"] > 0 and bp["numpy_twin"]["repeats"] >= 1
    assert set(res["two_echo"]["per_method"]) == {"matched", "fmcw", "bpdn", "cbp-polar", "ml2"}
    assert {r["method"] for r in res["delta_lambda"]["rows"]} == {"bpdn", "cbp-taylor", "cbp-polar-socp", "cbp-polar"}
    md = js[0].with_suffix(".md").read_text()
    assert "## Backprojection" in md and "## Error against run time" in md
    assert js[0].with_suffix(".png").stat().st_size > 10_000


def test_bench_names_what_to_install_before_any_work(monkeypatch, tmp_path):
    import importlib.util

    import bench

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "nlopt" else real(name, *a))
    with pytest.raises(ImportError, match=r"needs nlopt .*pip install 'clsas\[bench\]'"):
        bench.run(out_dir=tmp_path)
    assert not any(tmp_path.iterdir())


def test_c_openmp_peer_equals_the_twin(rng):
    """The compiled peer of `python -m bench` computes the same image (float32) as the NumPy twin."""
    from bench import cpeer, throughput
    from clsas.formation import bp_numpy as twin

    fn, why = cpeer.load()
    if fn is None:
        pytest.skip(f"C/OpenMP peer unavailable: {why}")
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.05, 0.05), (1.0, 1.1), 0.013)  # 119 voxels: a partial block
    wl = throughput.backprojection_workload(grid, 30, rng)
    got = cpeer.backproject(wl, grid.points())
    want = twin.backproject(wl["data"].astype(np.complex128), wl["tau0"], wl["dtau"], wl["fc"], wl["tx"], wl["rx"],
                            wl["c"], grid.points())
    assert np.abs(got - want).max() < 2e-4 * np.abs(want).max()
