"""The crossover table of ``python -m bench --formation`` and the calibration it stores (no timing is asserted)."""

import pytest

import clsas
from bench import crossover as cx
from clsas.formation.auto import load_calibration


def test_crossover_table_times_every_formation_and_auto(tmp_path, monkeypatch):
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    res = cx.crossover((8,), store=True)
    (row,) = res["rows"]
    names = [r["formation"] for r in row["rows"]]
    assert names == ["bp", "omega-k", "ffbp", "auto"]
    auto = row["rows"][-1]
    assert auto["chose"] in cx.FORMS and auto["reason"]
    assert all(r["time_s"] > 0 for r in row["rows"])
    for r in row["rows"][1:3]:
        assert r["predicted_builtin_s"] > 0 and r["error_all_db"] < 0
    assert set(res["calibration"]) == {"bp", "omega-k", "ffbp"}
    assert load_calibration(clsas.cl.select(None)) == pytest.approx(res["calibration"])
    md = "\n".join(cx.markdown(res))
    assert "| 8 | 64 |" in md and "Calibration" in md


def test_calibrate_takes_the_median_ratio():
    rows = [{"rows": [{"formation": "bp", "time_s": t, "predicted_builtin_s": 1.0}]} for t in (1.0, 2.0, 9.0)]
    assert cx.calibrate(rows) == {"bp": 2.0}


def test_roofline_ceilings_of_the_bp_kernel():
    from bench import throughput as tp

    info = {"compute_units": 2, "clock_mhz": 2000, "vector_width_float": 8}
    cb = tp.compute_bound(info, bandwidth_bps=16e9)
    assert cb["pairs_per_s"] == pytest.approx(2 * 2e9 * 8 * 2 / tp.FLOPS_PER_PAIR)
    assert cb["memory_pairs_per_s"] == pytest.approx(1e9)
    assert cb["ridge_flops_per_byte"] == pytest.approx(cb["peak_flops"] / 16e9)
    assert "memory_pairs_per_s" not in tp.compute_bound(info)


def test_lanes_per_unit_of_cpus_and_gpus():
    """The arithmetic ceiling counts a GPU's lanes per compute unit where its vendor reports them, and
    claims none where OpenCL does not say (a GPU's preferred vector width is 1: not its lanes)."""
    pytest.importorskip("pyopencl")
    import pyopencl as cl

    from bench import throughput as tp

    class Dev:
        def __init__(self, kind, **attrs):
            self.type = kind
            self.preferred_vector_width_float = 1
            self.__dict__.update(attrs)

    cpu = Dev(cl.device_type.CPU, preferred_vector_width_float=8)
    assert tp.lanes_per_unit(cpu)[0] == 8
    nv = Dev(cl.device_type.GPU, compute_capability_major_nv=9, compute_capability_minor_nv=0)
    assert tp.lanes_per_unit(nv) == (128, "FP32 lanes per SM of compute capability 9.0")
    assert tp.lanes_per_unit(Dev(cl.device_type.GPU, compute_capability_major_nv=8,
                                 compute_capability_minor_nv=0))[0] == 64
    amd = Dev(cl.device_type.GPU, simd_per_compute_unit_amd=4, simd_width_amd=16, simd_instruction_width_amd=1)
    assert tp.lanes_per_unit(amd)[0] == 64
    lanes, why = tp.lanes_per_unit(Dev(cl.device_type.GPU))
    assert lanes is None and "not reported" in why
    info = {"compute_units": 132, "clock_mhz": 1980, "vector_width_float": 1}
    assert tp.compute_bound({**info, "lanes_per_unit": None}) is None
    mem_only = tp.compute_bound({**info, "lanes_per_unit": None, "lanes_from": "not reported"}, bandwidth_bps=4e12)
    assert mem_only["pairs_per_s"] is None and mem_only["memory_pairs_per_s"] == pytest.approx(4e12 / 16)
    assert tp.lanes_per_unit(Dev(cl.device_type.GPU, compute_capability_major_nv=3,
                                 compute_capability_minor_nv=5))[0] == 192
    lanes, why = tp.lanes_per_unit(Dev(cl.device_type.GPU, compute_capability_major_nv=4,
                                       compute_capability_minor_nv=0))
    assert lanes is None and "4.0" in why
    # the report: the memory ceiling alone, and why there is no arithmetic one
    from bench import report

    row = {"workload": "w", "pairs": 1e6, "opencl_kernel": {"rate_per_s": 1e11}}
    md = "\n".join(report._md_backprojection({"backprojection": [row], "compute_bound": mem_only,
                                               "device": {"lanes_per_unit": None, "lanes_from": "not reported"}}))
    assert "No arithmetic ceiling of the device is given: not reported." in md
    assert "Roofline of the bp kernel: memory ceiling 2.5e+11 pairs/s" in md
    h200 = tp.compute_bound({**info, "lanes_per_unit": 128, "lanes_from": "x"})
    assert h200["peak_flops"] == pytest.approx(132 * 1.98e9 * 128 * 2)


def test_results_name_the_commit_they_ran():
    """A stored result names its code: the checkout's commit (``+dirty`` where tracked files
    differ), or None outside a git checkout."""
    import re
    import shutil

    from bench import package_versions
    from bench.stats import source_commit

    got = source_commit()
    if shutil.which("git") is None or got is None:
        pytest.skip("not a git checkout, or no git")
    assert re.fullmatch(r"[0-9a-f]{7,40}(\+dirty)?", got)
    assert package_versions()["clsas_commit"] == got


def test_bp_throughput_script_writes_its_table(tmp_path):
    """``bench/bp_throughput.py`` (the bp part alone, for a GPU): a tiny run writes JSON and Markdown
    naming the device and the commit; without an OpenCL device it says so and returns 1."""
    import json

    from bench import bp_throughput as mod
    with pytest.raises(SystemExit):
        mod.main(["--sides", "1"])
    rc = mod.main(["--sides", "4", "--measurements", "3", "--repeats", "1", "--out", str(tmp_path)])
    from bench import throughput as tp

    if tp.opencl_device_info() is None:
        assert rc == 1
        return
    assert rc == 0
    res = json.loads(next(tmp_path.glob("*-bp-*.json")).read_text())
    assert res["rows"][0]["voxels"] == 64 and "opencl_kernel" in res["rows"][0]
    md = next(tmp_path.glob("*-bp-*.md")).read_text()
    assert "| 4^3 voxels x 3 measurements |" in md and "Script: `bench/bp_throughput.py`" in md


def test_clsas_calibrate_measures_and_keeps_autos_factors(tmp_path, monkeypatch, capsys):
    """``clsas calibrate`` (the library's, not the benchmark's): each formation's measured over
    predicted time on this device, kept where formation='auto' reads it; --dry-run keeps nothing."""
    from clsas.cli import main
    from clsas.formation.auto import calibrate as calibration

    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    assert main(["calibrate", "--sides", "8", "--dry-run", "-q"]) == 0
    out = capsys.readouterr().out
    assert "not kept" in out and not any(tmp_path.rglob("formation_cost/*.json"))
    res = calibration.calibrate_auto((8,), status=lambda s: None)
    assert set(res["factors"]) == set(calibration.FORMS) and all(f > 0 for f in res["factors"].values())
    assert load_calibration(clsas.cl.select(None)) == pytest.approx(res["factors"])
    with pytest.raises(ValueError, match="sides"):
        calibration.calibrate_auto((4,))
    assert main(["calibrate", "--sides", "4"]) == 2
