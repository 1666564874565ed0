"""The measures of bench.superres_image on images whose answer is known."""

import numpy as np

import clsas
from bench.superres_image import edge_width_mm, resolved, tcr_db


def _image(values, grid):
    return clsas.Image(values.astype(complex), grid)


def test_resolved_needs_two_peaks_near_the_two_reflectors_with_a_dip():
    x = np.linspace(-0.02, 0.02, 41)
    grid = clsas.VoxelGrid(x, np.array([0.0]), np.array([0.5]))
    truth = np.array([[-0.005, 0, 0.5], [0.005, 0, 0.5]])
    two = np.exp(-0.5 * ((x + 0.005) / 0.002) ** 2) + np.exp(-0.5 * ((x - 0.005) / 0.002) ** 2)
    ok, err = resolved(_image(two[:, None, None], grid), "bp", truth, res=0.02)
    assert ok and err < 0.05
    one = np.exp(-0.5 * (x / 0.006) ** 2)
    assert not resolved(_image(one[:, None, None], grid), "bp", truth, res=0.02)[0]
    shallow = two + 0.9 * np.exp(-0.5 * (x / 0.002) ** 2)  # the peaks are there, the dip is not
    assert not resolved(_image(shallow[:, None, None], grid), "bp", truth, res=0.02)[0]


def test_edge_width_and_tcr_of_a_drawn_rectangle():
    step = 0.0015
    x = np.arange(-0.12, 0.12 + 1e-9, step)
    y = np.arange(-0.16, 0.16 + 1e-9, step)
    sigma = 0.002  # edges as Gaussian lines: -6 dB full width 2 sqrt(2 ln 2) sigma
    mag = np.zeros((len(x), len(y)))
    for xe in (-0.045, 0.045):
        mag += np.exp(-0.5 * ((x[:, None] - xe) / sigma) ** 2) * (np.abs(y) < 0.11)[None]
    width, cuts = edge_width_mm(mag, x, y)
    assert abs(width - 2 * np.sqrt(2 * np.log(2)) * sigma * 1e3) < 0.3 and cuts > 100
    clutter = mag + 0.01
    assert abs(tcr_db(clutter, x, y) - 20 * np.log10(1.01 / 0.01)) < 0.1  # peak 1.01 over clutter 0.01


def test_cli_takes_the_benchmark_and_the_methods(monkeypatch, tmp_path):
    """``python -m bench --superres-image`` reaches run_superres_image with its arguments (stubbed: the real
    run takes minutes); ``clsas reconstruct --method`` offers the model-based methods."""
    from bench.__main__ import main as bench_main
    from clsas.cli import build_parser

    seen = {}

    def fake(out, **kw):
        seen.update(out=out, **kw)
        return {"pairs": [], "airsas": [], "paths": {}}

    monkeypatch.setattr("bench.superres_image.run_superres_image", fake)
    assert bench_main(["--superres-image", "--n-seeds", "3", "--out", str(tmp_path), "-q"]) == 0
    assert seen["n_trials"] == seen["noise_draws"] == 3 and seen["airsas_root"] is None and seen["out"] == str(tmp_path)
    args = build_parser().parse_args(["reconstruct", "x.h5", "--method", "offgrid"])
    assert args.method == "offgrid"
