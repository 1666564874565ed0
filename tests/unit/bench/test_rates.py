"""``python -m bench --rates`` on a small scan: the table's columns, finite shares that sum to 1
and positive rates, on the NumPy twins and on the OpenCL device tests run on (no timing is asserted)."""

import math

import pytest
from conftest import needs_opencl

from bench import rates

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
    res = rates.run_rates(SIDE, indices=["numpy"], repeats=1)
    _check_rows(res, "numpy")
    assert all(r["transfer_s"] == 0 for r in res["rows"])  # the twins move nothing to a device
    lines = rates.table(res)
    assert lines[0].startswith(f"rates on {SIDE} x {SIDE} stops")
    assert lines[1].split() == " ".join(rates.COLUMNS).split()
    assert len(lines) == 2 + len(rates.STEPS)


@needs_opencl
def test_rates_on_an_opencl_device_see_its_kernels_and_copies():
    import pyopencl as cl
    import pyopencl._cl as _cl

    from clsas.cl import Plan

    index = _opencl_index()
    before = (cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload)
    res = rates.run_rates(SIDE, indices=[index], repeats=2)
    assert (cl.enqueue_copy, _cl.enqueue_nd_range_kernel, Plan.upload) == before  # the tracer put them back
    _check_rows(res, index)
    # bp's kernels and the image read back are seen by their events; the whole reconstruct launches more
    by_step = {r["step"]: r for r in res["rows"]}
    assert by_step["bp"]["transfer_s"] > 0
    assert by_step["reconstruct"]["kernel_s"] > by_step["bp"]["kernel_s"] * 0.5


def test_the_tracer_counts_a_launch_and_a_copy_by_their_events():
    pytest.importorskip("pyopencl")
    from clsas import cl
    from clsas.cl import OpenCLUnavailable

    try:
        queue = cl.get_queue()
    except OpenCLUnavailable as exc:
        pytest.skip(f"no OpenCL device: {exc}")
    import numpy as np
    import pyopencl

    prg = pyopencl.Program(queue.context, "__kernel void twice(__global float *x) { x[get_global_id(0)] *= 2.0f; }")
    knl = prg.build().twice
    host = np.arange(4096, dtype=np.float32)
    buf = pyopencl.Buffer(queue.context, pyopencl.mem_flags.READ_WRITE, host.nbytes)
    with rates.Tracer() as tr:
        pyopencl.enqueue_copy(queue, buf, host)
        knl(queue, host.shape, None, buf)
        out = np.empty_like(host)
        pyopencl.enqueue_copy(queue, out, buf)
    assert len(tr.kernels) == 1 and len(tr.copies) == 2
    kernel_s, transfer_s = tr.seconds()
    assert kernel_s > 0 and transfer_s > 0
    np.testing.assert_array_equal(out, 2 * host)
    # a queue without profiling gives no kernel or transfer times (the table then shows "-")
    plain = pyopencl.CommandQueue(queue.context, queue.device)
    with rates.Tracer() as tr:
        knl(plain, host.shape, None, buf)
        pyopencl.enqueue_copy(plain, out, buf)
    assert tr.seconds() == (None, None)


def test_rates_refuse_a_scan_too_small_and_an_unknown_device():
    with pytest.raises(ValueError, match="--rates: N"):
        rates.run_rates(4)
    with pytest.raises(ValueError, match="--devices"):
        rates.run_rates(SIDE, indices=["9:9"])


def test_the_rates_flag_prints_the_table_and_writes_its_report(tmp_path, capsys):
    from bench.__main__ import main

    assert main(["-q", "--rates", str(SIDE), "--devices", "numpy", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "kernel, pairs/s" in printed and "numpy (twins)" in printed
    assert len(list(tmp_path.glob("*-rates-*.json"))) == 1 and len(list(tmp_path.glob("*-rates-*.md"))) == 1


def test_a_row_without_profiling_times_shows_its_wall_rate_only():
    row = {"device": "0:0 X", "index": "0:0", "step": "bp",
           **rates._row([{"wall_s": 0.5, "kernel_s": None, "transfer_s": None}], 1000)}
    res = {"side": 8, "grid": [8, 8, 41], "pairs": 1000, "repeats": 1, "load_before": [1.0], "load_after": [1.0],
           "rows": [row]}
    assert row["wall_rate"] == 2000 and row["kernel_rate"] is None and not rates.finite_shares(row)
    # kernel rate, wall rate, host, transfers, kernels
    assert rates.table(res)[2].split()[-5:] == ["-", "2e+03", "-", "-", "-"]
