"""``python -m bench.overlap`` on a tiny grid, one device: it runs and writes its report (no timing is
asserted)."""

import json

from conftest import needs_opencl

from bench import overlap


@needs_opencl
def test_overlap_bench_writes_its_report(tmp_path):
    from clsas import cl

    device = next(r.index for r in cl.list_devices() if r.selected)
    assert overlap.main(["--side", "8", "--measurements", "16", "--tile-x", "3", "--repeats", "1",
                         "--devices", device, "--out", str(tmp_path)]) == 0
    (js,) = tmp_path.glob("*-overlap-*.json")
    (row,) = json.loads(js.read_text())["rows"]
    assert "error" not in row, row
    med = row["median_s"]
    assert set(med) == {*overlap.VARIANTS, "whole grid"} and row["tiles"] == 3
    assert all(wall > 0 for wall, *_ in med.values()) and med["memory, overlapped"][1] > 0
    assert "sequential / overlapped wall" in js.with_suffix(".md").read_text()


@needs_opencl
def test_overlap_bench_on_a_dask_cluster(tmp_path):
    """``--dask-workers 2``: the tiles also formed on a local cluster, with and without overlap inside
    each task's run of tiles (the child checks that the tiles' provenance says which)."""
    import pytest

    from clsas import cl

    pytest.importorskip("distributed")
    device = next(r.index for r in cl.list_devices() if r.selected)
    assert overlap.main(["--side", "8", "--measurements", "16", "--tile-x", "1", "--repeats", "1",
                         "--dask-workers", "2", "--devices", device, "--out", str(tmp_path)]) == 0
    (js,) = tmp_path.glob("*-overlap-*.json")
    (row,) = json.loads(js.read_text())["rows"]
    assert "error" not in row, row
    med = row["median_s"]
    assert set(med) == {*overlap.VARIANTS, *overlap.DASK_VARIANTS, "whole grid"} and row["tiles"] == 8
    assert all(med[v][0] > 0 for v in overlap.DASK_VARIANTS)
    assert "Dask: a local cluster of 2" in js.with_suffix(".md").read_text()
