"""``reconstruct``'s progress reports name their stage: every stage it runs is announced in the
first record and reported in that order; a ``(done, total)`` callback is called as before."""

from __future__ import annotations

import numpy as np
import pytest

import clsas
from clsas.types.progress import Progress, Reporter, takes_record


@pytest.fixture(scope="module")
def scan():
    fs = 96_000.0
    waveform = clsas.lfm_chirp(20e3, 30e3, 0.002, fs, taper=0.1)
    ds = clsas.simulate(clsas.Scene(np.array([[0.02, -0.01, 0.6]])), clsas.raster_aperture(5, 4, 0.3, 0.2),
                        waveform, fs)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.55, 0.65), 0.01)
    return ds, grid


def _records(ds, grid, **kw) -> tuple[list[Progress], clsas.Image]:
    seen: list[Progress] = []
    image = clsas.reconstruct(ds, grid, backend="numpy", progress=seen.append, **kw)
    return seen, image


def _assert_every_stage_in_order(seen: list[Progress]) -> None:
    """Each announced stage reported, in the announced order, each starting with its announcement."""
    stages = seen[0].stages
    assert all(r.stages == stages for r in seen)
    order = [r.stage for i, r in enumerate(seen) if i == 0 or r.stage != seen[i - 1].stage]
    assert order == list(stages)  # every stage, once each, in order
    for i, r in enumerate(seen):
        if i == 0 or r.stage != seen[i - 1].stage:
            assert (r.done, r.total) == (0, None)  # a stage is announced when it starts
        else:
            assert isinstance(r.done, int) and isinstance(r.total, int) and 0 <= r.done <= r.total
        assert r.step == stages.index(r.stage) + 1


@pytest.mark.parametrize("kw,stages", [
    ({"formation": "bp"}, ("compress (matched)", "backproject")),
    ({"formation": "omega-k"}, ("compress (matched)", "form (omega-k)")),
    ({}, ("compress (matched)", "form (auto)")),
    ({"method": "ls"}, ("compress (matched)", "solve (ls)")),
], ids=["bp", "omega-k", "auto", "model-ls"])
def test_a_callback_receives_every_announced_stage_in_order(scan, kw, stages):
    seen, _ = _records(*scan, **kw)
    assert seen[0].stages == stages and seen[0].stage == stages[0]
    _assert_every_stage_in_order(seen)


def test_a_sparse_method_with_auto_announces_the_backprojection_auto_takes_by_rule(scan):
    pytest.importorskip("scipy.optimize")
    seen, image = _records(*scan, method="bpdn")
    assert seen[0].stages == ("super-resolve (bpdn)", "backproject")
    _assert_every_stage_in_order(seen)
    assert image.provenance["formation"] == "bp"  # what the stage's name says formed it


def test_profiles_and_tiles_name_their_one_formation_stage(scan, tmp_path):
    ds, grid = scan
    prof = clsas.compress(ds, backend="numpy")
    seen, _ = _records(prof, grid, formation="bp")
    assert seen[0].stages == ("backproject",)
    _assert_every_stage_in_order(seen)
    seen, _ = _records(ds, grid, out=tmp_path / "tiles.h5", tile_shape=(5, 11, 11))
    assert seen[0].stages == ("compress (matched)", "backproject in tiles")  # auto forms tiles by bp
    _assert_every_stage_in_order(seen)
    assert seen[-1].done == seen[-1].total >= 2  # tiles counted


def test_a_done_total_callback_receives_the_counts_alone(scan):
    ds, grid = scan
    calls = []
    clsas.reconstruct(ds, grid, backend="numpy", formation="bp",
                      progress=lambda done, total: calls.append((done, total)))
    assert calls == [(m, ds.n_meas) for m in range(1, ds.n_meas + 1)]  # backprojection's counts, as before


@pytest.mark.parametrize("callback,record", [
    (lambda report: None, True), ([].append, True), (lambda report, *, verbose=False: None, True),
    (lambda done, total: None, False), (lambda *args: None, False), (lambda report, extra=None: None, False),
    (print, False),
], ids=["one", "bound-builtin", "one-and-keyword", "two", "varargs", "one-and-default", "print"])
def test_the_call_shape_is_read_once_from_the_signature(callback, record):
    assert takes_record(callback) is record


def test_a_progress_that_is_not_callable_is_refused_before_any_work(scan):
    with pytest.raises(TypeError, match="progress must be callable"):
        clsas.reconstruct(*scan, backend="numpy", progress=3)


def test_a_reporter_refuses_a_stage_it_was_not_told():
    with pytest.raises(ValueError, match="not one of this call's stages"):
        Reporter(lambda report: None, ("compress (matched)",)).start("backproject")
