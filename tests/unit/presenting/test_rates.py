"""``clsas bench`` (clsas.presenting.rates) on a small scan: the table's columns, finite shares that sum
to 1 and positive rates, on the NumPy twins and on the OpenCL device tests run on (no timing is
asserted); its refusals name the parameter."""

import json
import math

import pytest
from conftest import needs_opencl

from clsas.cli import main
from clsas.presenting import rates

SIDE = 8  # the smallest scan the calibration case makes


def _opencl_index() -> str:
    """The ``P:D`` of the device ``backend="auto"`` takes (the one the kernel tests run on)."""
    from clsas import cl

    q = cl.get_queue()
    for d in rates.devices():
        if d["device"] == q.device.name and d["index"] != "numpy":
            return d["index"]
    pytest.skip(f"the default device {q.device.name} is not among the devices the rates table lists")


def _check_rows(res: dict, index: str) -> None:
    rows = [r for r in res["rows"] if r["index"] == index]
    assert [r["step"] for r in rows] == list(rates.STEPS)
    for r in rows:
        assert r["wall_rate"] > 0 and r["kernel_rate"] > 0, r
        assert rates.finite_shares(r), r
        assert math.isclose(sum(r["shares"].values()), 1.0, abs_tol=0.02), r
        assert r["kernel_s"] > 0 and r["transfer_s"] >= 0 and len(r["runs"]) == res["repeats"]


def test_rates_on_the_numpy_twins_have_every_column_and_shares_that_sum_to_one():
    lines_seen: list[str] = []
    res = rates.measure_rates(SIDE, devices=["numpy"], repeats=1, status=lines_seen.append)
    _check_rows(res, "numpy")
    assert all(r["transfer_s"] == 0 for r in res["rows"])  # the twins move nothing to a device
    assert res["pairs"] == res["measurements"] * math.prod(res["grid"]) and res["measurements"] == SIDE * SIDE
    lines = rates.table(res)
    assert lines[0].startswith(f"rates on {SIDE} x {SIDE} stops")
    assert lines[1].split() == " ".join(rates.COLUMNS).split()
    assert len(lines) == 2 + len(rates.STEPS)
    # a progress line per step, naming the device and the step
    assert [s for s in lines_seen if "step" in s] == [f"numpy (twins): step {i} of 4: {step}"
                                                     for i, step in enumerate(rates.STEPS, 1)]


@needs_opencl
def test_rates_on_an_opencl_device_see_its_kernels_and_copies():
    import pyopencl as cl
    import pyopencl._cl as _cl

    from clsas.cl import Plan

    index = _opencl_index()
    before = (cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload)
    res = rates.measure_rates(SIDE, devices=[index], repeats=2)
    assert (cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload) == before  # the tracer put them back
    _check_rows(res, index)
    # bp's kernels and the image read back are seen by their events; the whole reconstruct launches more
    by_step = {r["step"]: r for r in res["rows"]}
    assert by_step["bp"]["transfer_s"] > 0
    assert by_step["reconstruct"]["kernel_s"] > by_step["bp"]["kernel_s"] * 0.5


@pytest.mark.parametrize("kwargs, match", [
    ({"size": 4}, "size: stops per side"), ({"size": 8.0}, "size: stops per side"), ({"size": True}, "size"),
    ({"repeats": 0}, "repeats"), ({"steps": ("bp", "sar")}, r"steps: unknown \['sar'\]"), ({"steps": ()}, "steps"),
    ({"devices": ["9:9"]}, r"devices: \['9:9'\] not among"), ({"devices": "numpy"}, "devices: must be a non-empty"),
], ids=["size-small", "size-float", "size-bool", "repeats", "steps-unknown", "steps-empty", "devices-unknown",
        "devices-str"])
def test_rates_refuse_a_bad_request_naming_the_parameter(kwargs, match):
    with pytest.raises(ValueError, match=match):
        rates.measure_rates(**kwargs)


def test_a_row_without_profiling_times_shows_its_wall_rate_only():
    row = {"device": "0:0 X", "index": "0:0", "step": "bp",
           **rates._row([{"wall_s": 0.5, "kernel_s": None, "transfer_s": None}], 1000)}
    res = {"side": 8, "grid": [8, 8, 41], "pairs": 1000, "repeats": 1, "load_before": [1.0], "load_after": [1.0],
           "rows": [row]}
    assert row["wall_rate"] == 2000 and row["kernel_rate"] is None and not rates.finite_shares(row)
    # kernel rate, wall rate, host, transfers, kernels
    assert rates.table(res)[2].split()[-5:] == ["-", "2e+03", "-", "-", "-"]


def test_the_bench_command_prints_the_table_and_writes_its_report(tmp_path, capsys):
    out = tmp_path / "runs"
    assert main(["bench", "--size", str(SIDE), "--devices", "numpy", "--repeats", "1", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "kernel, pairs/s" in captured.out and "numpy (twins)" in captured.out
    assert "[bench] numpy (twins): step 4 of 4: reconstruct" in captured.err  # the progress, on stderr
    (report,) = out.glob("*-rates-*.json")
    assert len(list(out.glob("*-rates-*.md"))) == 1 and f"wrote {report.with_suffix('')}.json" in captured.out
    saved = json.loads(report.read_text())
    assert saved["side"] == SIDE and [r["step"] for r in saved["rows"]] == list(rates.STEPS)


@pytest.mark.parametrize("argv, flag", [
    (["--size", "4"], "--size"), (["--repeats", "0"], "--repeats"), (["--devices", "9:9"], "--devices"),
])
def test_the_bench_command_refuses_bad_flags_with_exit_2(argv, flag, capsys):
    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"clsas bench: error: {flag}") and err.count("\n") == 1, err


def test_the_bench_command_refuses_an_out_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["bench", "--size", str(SIDE), "--devices", "numpy", "--out", str(f)]) == 2
    assert "--out" in capsys.readouterr().err
