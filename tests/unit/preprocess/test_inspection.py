"""clsas.presenting.inspection: a look at a dataset before imaging it, with warnings where the geometry
and the data disagree (on clsas.synthetic.turntable_scan)."""

import numpy as np
import pytest

import clsas
from clsas import preprocess as pp
from clsas.presenting.inspection import draw_inspection, inspect_dataset
from clsas.synthesis.synthetic import turntable_scan


@pytest.fixture(scope="module")
def scan():
    return turntable_scan(36, temperature_c=(20.0, 20.0), snr_db=40)


GRID = clsas.VoxelGrid.from_bounds((-0.15, 0.15), (-0.15, 0.15), (0, 0), 0.005)


def test_a_consistent_dataset_gives_no_warning(scan, tmp_path):
    ds = pp.remove_delay(scan.dataset, scan.group_delay_s)
    ins = inspect_dataset(ds, GRID)
    assert ins.warnings == []
    assert np.nanmax(np.abs(ins.direct_measured_s - ins.direct_predicted_s)) < 2e-6
    assert ins.in_gate_fraction > 0.5 and ins.gate_s.shape == (ds.n_meas, 2)
    assert np.all(ins.gate_s[:, 0] < ins.gate_s[:, 1])
    assert ins.envelope_db.shape == ds.signals.shape and ins.envelope_db.max() == 0
    out = draw_inspection(ins, tmp_path / "look.png")
    assert out.stat().st_size > 10_000


def test_an_unknown_delay_and_a_delay_removed_twice_are_named(scan):
    (w,) = inspect_dataset(scan.dataset, GRID).warnings  # the hidden 62.33-sample delay
    assert "+62.33 samples" in w and "group delay or the speaker-microphone spacing" in w
    twice = pp.apply(scan.dataset, group_delay_s=scan.group_delay_s)
    twice = pp.remove_delay(twice, scan.group_delay_s)
    warnings = inspect_dataset(twice, GRID).warnings
    assert any("removed twice" in w for w in warnings), warnings


def test_a_grid_away_from_the_echoes_is_named(scan):
    ds = pp.remove_delay(scan.dataset, scan.group_delay_s)
    far = clsas.VoxelGrid.from_bounds((1.5, 1.8), (1.5, 1.8), (0, 0), 0.01)
    ins = inspect_dataset(ds, far)
    assert ins.in_gate_fraction < 0.2
    assert any("grid's delays" in w for w in ins.warnings)


def test_inputs_are_checked(scan):
    with pytest.raises(TypeError, match="ds"):
        inspect_dataset(scan.dataset.signals)
    with pytest.raises(TypeError, match="grid"):
        inspect_dataset(scan.dataset, grid=(0, 1))
    assert inspect_dataset(pp.remove_delay(scan.dataset, scan.group_delay_s)).gate_s is None


def test_cli_inspect(scan, tmp_path, capsys):
    from clsas.cli import main

    pp.remove_delay(scan.dataset, scan.group_delay_s).save(tmp_path / "ok.h5")
    scan.dataset.save(tmp_path / "late.h5")
    assert main(["inspect", str(tmp_path / "ok.h5"), "--grid=-0.15,0.15,-0.15,0.15,0,0"]) == 0
    out = capsys.readouterr().out
    assert "no disagreement" in out and (tmp_path / "ok-inspect.png").exists()
    assert main(["inspect", str(tmp_path / "late.h5"), "--png", str(tmp_path / "l.png"), "--strict"]) == 1
    assert "warning: the direct sound arrives" in capsys.readouterr().out


def test_drawing_leaves_the_callers_matplotlib_backend(scan, tmp_path):
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # a backend the drawing does not pick itself
    try:
        out = draw_inspection(inspect_dataset(scan.dataset, GRID), tmp_path / "look.png")
        assert matplotlib.get_backend() == "svg" and out.read_bytes()[:4] == b"\x89PNG"
    finally:
        matplotlib.use(before)
