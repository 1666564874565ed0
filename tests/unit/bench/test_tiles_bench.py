"""``python -m bench --scale`` on tiny sizes: it runs and writes its report (no timing is asserted)."""

import json

import pytest

from bench import scale

TINY = {
    "rss": {"voxels": (2e4, 6e4), "n_meas": 3, "max_memory": 4e8, "sample": 2},
    "tiles": {"voxels": 3e4, "n_meas": 4, "planes": (None, 8)},
    "scaling": {"pairs": 2e5, "n_meas": 4, "workers": (1, 2), "overhead_workers": 3, "n_tiles": 4},
}


def test_scale_bench_writes_its_report(tmp_path, monkeypatch):
    monkeypatch.setitem(scale.QUICK_SCALE, "rss", TINY["rss"])
    monkeypatch.setitem(scale.QUICK_SCALE, "tiles", TINY["tiles"])
    res = scale.run_scale(out_dir=tmp_path, parts=("rss", "tiles"), workdir=tmp_path)
    data = json.loads((tmp_path / res["paths"]["json"].split("/")[-1]).read_text())
    assert [r["voxels"] for r in data["rss"]] == [27 * 27 * 27, 39 * 39 * 39]
    assert all(r["max_rel_diff_vs_in_memory"] == 0 and r["peak_rss_bytes"] > 0 for r in data["rss"])
    assert [r["tiles"] for r in data["tiles"]] == [1, 4]
    assert "Peak RSS against grid size" in (tmp_path / res["paths"]["md"].split("/")[-1]).read_text()


@pytest.mark.slow
def test_scale_bench_scaling_part(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setitem(scale.QUICK_SCALE, "scaling", TINY["scaling"])
    res = scale.run_scale(out_dir=tmp_path, parts=("scaling",))
    rows = res["scaling"]["clusters"]
    assert [r["workers"] for r in rows] == [1, 2, 3]
    assert all(r["max_rel_diff_vs_single_process"] < 1e-4 and r["max_abs_diff_vs_1_worker"] == 0 for r in rows)
    # each single-threaded worker formed its tiles on one compute unit (None: no OpenCL, the NumPy twin)
    assert all(set(r["worker_compute_units"].values()) <= {1, None} and r["worker_compute_units"] for r in rows)


def test_scale_flag_alone_or_with_a_number(monkeypatch, tmp_path):
    from bench.__main__ import main

    calls = []
    monkeypatch.setattr(scale, "run_scale", lambda **kw: calls.append(kw) or {"paths": {}})
    assert main(["--scale", "--scale-parts", "tiles", "--out", str(tmp_path), "-q"]) == 0
    assert calls == [{"full": False, "out_dir": str(tmp_path), "parts": ("tiles",), "status": calls[0]["status"]}]
    assert main(["--scale", "--formation", "bp"]) == 2  # with --formation it takes a number


@pytest.mark.parametrize("enabled, group, expected", [("1\n", "/autogroup-7 nice 0\n", "on (/autogroup-7)"),
                                                      ("1\n", "", "on"), ("0\n", "", "off")])
def test_autogroup_reads_what_the_kernel_gives(monkeypatch, enabled, group, expected):
    """CI's containers leave /proc/<pid>/autogroup empty: the report still says what it knows."""
    import builtins
    import io

    real_open = builtins.open

    def fake_open(path, *args, **kwargs):
        if str(path).endswith("sched_autogroup_enabled"):
            return io.StringIO(enabled)
        if str(path).endswith("/autogroup"):
            return io.StringIO(group)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", fake_open)
    assert scale._autogroup() == expected
