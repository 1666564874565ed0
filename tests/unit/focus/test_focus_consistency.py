"""The data-consistency test: a least-squares target in the grid
explains a static scan to the noise, and leaves a scan with motion largely unexplained."""

import numpy as np
import pytest

import clsas
from clsas.focus.consistency import Consistency, data_consistency
from clsas.physics.scan_errors import HandMotion

FS = 96e3
POINTS = np.array([[0.02, -0.01, 0.6], [-0.03, 0.02, 0.62], [0.01, 0.025, 0.61]])
GRID = clsas.VoxelGrid.from_bounds((-0.05, 0.04), (-0.03, 0.045), (0.585, 0.635), 0.005)


def scan(motion_m=0.0, snr_db=30.0):
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ap = clsas.raster_aperture(8, 7, 0.24, 0.2)
    return clsas.simulate(clsas.Scene(POINTS), ap, w, FS, snr_db=snr_db, seed=3,
                          position_error=HandMotion(motion_m, seed=5))


@pytest.fixture(scope="module")
def fits():
    static, moved = scan(), scan(3e-3)
    c_static = data_consistency(static, GRID, max_iter=25, backend="numpy")
    c_moved = data_consistency(moved, GRID, max_iter=25, backend="numpy")
    tr = moved.truth
    at_truth = moved.replace(tx_positions=tr["tx_positions"], rx_positions=tr["rx_positions"])
    c_truth = data_consistency(at_truth, GRID, max_iter=25, floor_of=c_moved, backend="numpy")
    return c_static, c_moved, c_truth


def test_static_scan_is_explained_to_the_noise(fits):
    c, _, _ = fits
    assert isinstance(c, Consistency)
    assert c.iterations == 25 and len(c.history) == len(c.floor_history) == 26
    assert c.history[0] == pytest.approx(1.0)  # before the fit nothing is explained
    assert np.all(np.diff(c.history) <= 1e-12)  # CGLS never raises the residual
    assert c.residual < 0.1
    assert c.floor > 0 and c.noise_sigma > 0
    assert c.excess == pytest.approx(np.sqrt(max(c.residual ** 2 - c.floor ** 2, 0.0)))


def test_motion_leaves_the_data_unexplained_and_the_truth_explains_them(fits):
    static, moved, truth = fits
    # 3 mm of hand motion is about 1.4 rad of phase per stop at 25 kHz: no single target fits it
    assert moved.residual > 3 * static.residual
    assert moved.excess > 0.2
    # the same recordings at their true positions are explained as well as the static scan
    assert truth.residual < 1.5 * static.residual + 0.01
    assert truth.excess < 0.2 * moved.excess


def test_floor_of_reuses_the_noise_fit(fits):
    _, moved, truth = fits
    assert truth.noise_sigma == moved.noise_sigma
    assert truth.floor == pytest.approx(moved.floor * moved.scale / truth.scale)


def test_progress_names_each_fit():
    calls = []
    data_consistency(scan(), GRID, max_iter=2, backend="numpy", progress=lambda *a: calls.append(a))
    assert [c[0] for c in calls] == ["fit", "fit", "noise", "noise"]
    assert calls[-1][1:] == (2, 2)


@pytest.mark.parametrize("kwargs, match", [
    ({"max_iter": 0}, "max_iter"), ({"max_iter": 10_001}, "max_iter"), ({"max_iter": 2.5}, "max_iter"),
    ({"seed": -1}, "seed"), ({"seed": True}, "seed"), ({"floor_of": 3.0}, "floor_of"),
    ({"progress": 3}, "progress"),
])
def test_options_are_checked_by_name(kwargs, match):
    with pytest.raises((TypeError, ValueError), match=match):
        data_consistency(scan(), GRID, **kwargs)


def test_floor_of_must_match_the_iterations():
    c = Consistency(0.1, 0.01, 0.09, [1.0, 0.1], [0.02, 0.01], 1.0, 1.0, iterations=1, max_iter=1,
                    grid_shape=GRID.shape, n_meas=56)
    with pytest.raises(ValueError, match="floor_of was fitted with max_iter 1"):
        data_consistency(scan(), GRID, max_iter=2, floor_of=c)
    c.max_iter = 2
    with pytest.raises(ValueError, match="floor_of is of another grid"):
        data_consistency(scan(), clsas.VoxelGrid.from_bounds((-0.05, 0.04), (-0.03, 0.045), (0.585, 0.635), 0.01),
                         max_iter=2, floor_of=c)


def test_dataset_and_grid_types_are_checked():
    with pytest.raises(TypeError, match="dataset"):
        data_consistency(np.zeros((3, 3)), GRID)
    with pytest.raises(TypeError, match="grid"):
        data_consistency(scan(), "grid")


def test_cli_autofocus_prints_the_consistency_before_and_after(tmp_path, capsys):
    from clsas.cli import main

    scan(3e-3).save(tmp_path / "s.h5")
    args = ["autofocus", str(tmp_path / "s.h5"), str(tmp_path / "o.h5"), "--grid=-0.05,0.04,-0.03,0.045,0.585,0.635",
            "--spacing", "0.005", "--methods", "direct,points", "-q", "--backend", "numpy"]
    assert main([*args, "--consistency", "5"]) == 0
    text = capsys.readouterr().out
    assert "data consistency (5 iterations)" in text and "(ratio " in text
    # a negative count is refused before any focusing
    assert main([*args, "--consistency", "-1", "--overwrite"]) == 2
    assert "--consistency" in capsys.readouterr().err


def test_family_bench_summary_and_files(tmp_path):
    from bench import consistency_family as cf

    def row(seed, kind, rec, true, after, floor, peak):
        gap = rec ** 2 - true ** 2
        return {"seed": seed, "kind": kind, "nx": 13, "ny": 14, "pitch_over_speckle": 0.5, "residual_recorded": rec,
                "residual_true": true, "residual_after": after, "floor": floor, "determined": gap > floor ** 2,
                "removed": (rec ** 2 - after ** 2) / gap, "peak_before_db": -8.0, "peak_after_db": peak,
                "fit_time_s": 1.0}

    rows = [row(1, "plane", 0.7, 0.03, 0.05, 0.01, -0.2), row(2, "sphere", 0.7, 0.03, 0.7, 0.01, -8.0),
            row(3, "points", 0.06, 0.055, 0.06, 0.09, -7.0), {"seed": 4, "error": "ValueError: x"}]
    s = cf.summarise(rows)
    assert (s["n"], s["failed"], s["determined"], s["determined_within_1db"], s["undetermined_within_1db"]) == \
        (3, 1, 2, 1, 0)
    assert 0.4 < s["median_removed_determined"] < 0.6  # (1.0 + 0.0) / 2
    cf.write(rows, "test", tmp_path / "c")
    text = (tmp_path / "c.md").read_text()
    assert "determine the errors in 2" in text and "error: ValueError" in text
    assert (tmp_path / "c.png").stat().st_size > 0


def test_autofocus_reports_the_consistency_check():
    from clsas.focus import autofocus

    out, rep = autofocus(scan(3e-3), GRID, methods=("direct", "points"), consistency_iter=10, backend="numpy")
    assert rep.improved
    assert 0 < rep.check["excess_ratio"] < 0.9  # the points' correction explains most of what was unexplained
    assert rep.check["excess_after"] < rep.check["excess_before"]
    assert "data consistency (10 iterations)" in rep.notes[-1]
    assert any(s["step"] == "consistency" for s in rep.stages)
    assert "excess_ratio" in out.provenance[-1]["check"]


def test_gate_keeps_what_the_data_cannot_see_and_withdraws_what_they_contradict():
    from clsas.focus.final_consistency import consistency_gate
    from clsas.focus.report import AutofocusReport

    ds, sel = scan(3e-3), clsas.cl.select("numpy")
    rep = AutofocusReport()
    same = ds.replace(t0_s=ds.t0_s.copy())  # a "correction" that changes nothing: ratio 1, nothing to see
    assert consistency_gate(ds, same, GRID, rep, 5, sel)
    assert rep.check["excess_ratio"] == pytest.approx(1.0) and rep.check["consistency_passed"] is True
    assert "the data do not see the correction" in rep.notes[-1]
    # from the true positions to the stated ones: the data contradict that "correction"
    tr = ds.truth
    at_truth = ds.replace(tx_positions=tr["tx_positions"], rx_positions=tr["rx_positions"])
    rep = AutofocusReport()
    assert not consistency_gate(at_truth, ds, GRID, rep, 10, sel)
    assert rep.check["excess_ratio"] > 3 and rep.check["consistency_passed"] is False
    assert "the data contradict it" in rep.notes[-1]


@pytest.mark.parametrize("direct", [False, True])
def test_withdrawn_motion_keeps_only_the_direct_sounds_delay(monkeypatch, direct):
    import clsas.focus.final_check as final_check
    from clsas.focus import autofocus

    seen = []

    def refuse(base, out, *a):
        seen.append((base, out))
        return False

    monkeypatch.setattr(final_check, "consistency_gate", refuse)
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    # a scan where "points" applies a motion (with the direct sound at a third of its level, or none)
    ds = clsas.simulate(clsas.Scene(POINTS), clsas.raster_aperture(8, 7, 0.24, 0.2), w, FS, snr_db=30, seed=3,
                        position_error=HandMotion(3e-3, seed=5), group_delay_s=20e-6 if direct else 0.0,
                        direct_gain=0.3 if direct else None)
    ref_out, ref = autofocus(ds, GRID, methods=("direct", "points"), backend="numpy")
    assert ref.parameters["motion"].applied  # without the gate the motion is applied
    out, rep = autofocus(ds, GRID, methods=("direct", "points"), consistency_iter=3, backend="numpy")
    (base, judged), = seen
    assert base is not judged and not np.array_equal(judged.tx_positions, ds.tx_positions)  # a real motion judged
    assert not rep.parameters["motion"].applied
    assert np.array_equal(out.tx_positions, ds.tx_positions)  # no motion in what comes back
    assert "withdrawn" in rep.notes[-1]
    if direct:  # the delay the direct sound gives is physics, not focus: it stays
        assert rep.improved and rep.parameters["group_delay"].applied
        assert np.median(ds.t0_s - out.t0_s) == pytest.approx(20e-6, abs=1e-6)
        assert "the direct sound's delay alone is returned" in rep.notes[-1]
        assert out.provenance[-1]["step"] == "autofocus"
    else:
        assert out is ds and not rep.improved
        assert "the motion estimate is withdrawn; the input is returned unchanged" in rep.notes[-1]
        assert "data-consistency check withdrew the correction" in rep.summary()


def test_the_input_returned_still_gets_its_consistency():
    from clsas.focus import autofocus

    # too little motion for "points" to be determined: nothing applied, but the excess is reported
    ds = scan()
    out, rep = autofocus(ds, GRID, methods=("points",), consistency_iter=3, backend="numpy")
    assert out is ds and not rep.improved
    assert "excess_after" in rep.check and "excess_ratio" not in rep.check
    assert "no step found" in rep.notes[-1]


@pytest.mark.parametrize("bad", [-1, 10_001, 2.0, True])
def test_autofocus_checks_consistency_iter(bad):
    from clsas.focus import autofocus

    with pytest.raises(ValueError, match="consistency_iter"):
        autofocus(scan(), GRID, consistency_iter=bad)


def test_only_the_direct_delay_is_reported_not_judged():
    from clsas.focus import autofocus

    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.1)
    ds = clsas.simulate(clsas.Scene(POINTS), clsas.raster_aperture(8, 7, 0.24, 0.2), w, FS, snr_db=30, seed=3,
                        position_error=HandMotion(3e-3, seed=5), group_delay_s=20e-6, direct_gain=1.0)
    out, rep = autofocus(ds, GRID, methods=("direct",), consistency_iter=5, backend="numpy")
    # the delay is physics, not focus: kept, and the motion nobody looked for shows as excess
    assert rep.improved and np.median(ds.t0_s - out.t0_s) == pytest.approx(20e-6, abs=1e-6)
    assert "excess_ratio" not in rep.check and rep.check["excess_after"] > 0.2
    assert "no step found" in rep.notes[-1]


def test_a_fit_that_converges_early_can_still_lend_its_floor():
    # 8 voxels: CGLS converges long before 200 iterations; reusing its floor must not fail
    small = clsas.VoxelGrid.from_bounds((0.0, 0.005), (0.0, 0.005), (0.6, 0.605), 0.005)
    c = data_consistency(scan(), small, max_iter=200, backend="numpy")
    assert c.iterations < 200 and c.max_iter == 200
    again = data_consistency(scan(), small, max_iter=200, floor_of=c, backend="numpy")
    assert again.floor == pytest.approx(c.floor)
