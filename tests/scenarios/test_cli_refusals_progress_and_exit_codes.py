"""A user's first day: no silent downgrades, honest progress, guards before
work, one exit-code table, and the README's hurdles."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from clsas.cli import COMMANDS, build_parser, main
from clsas.cli.common import slow_job_notice, stage_bar, stage_label

SCENE = """
[chirp]
f_start_hz = 20000.0
f_stop_hz = 30000.0
duration_s = 0.002
fs_hz = 96000.0

[aperture]
nx = 5
ny = 4
width_m = 0.3
height_m = 0.2

[[points]]
position_m = [0.02, -0.01, 0.6]

[grid]
x_m = [-0.05, 0.05]
y_m = [-0.05, 0.05]
z_m = [0.55, 0.65]
spacing_m = 0.01
"""


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("first_day")
    (d / "scene.toml").write_text(SCENE)
    assert main(["simulate", str(d / "scene.toml"), str(d / "scan.h5"), "-q", "--backend", "numpy"]) == 0
    assert main(["reconstruct", str(d / "scan.h5"), "-q", "--backend", "numpy"]) == 0
    return d / "scan.h5"


# -- 6: -q and -v before the command ----------------------------------------------------------

@pytest.mark.parametrize("argv,quiet,verbose", [
    (["-q", "limits"], True, False), (["limits", "-q"], True, False), (["-v", "devices"], False, True),
    (["devices", "--verbose"], False, True), (["limits"], False, False), (["-q", "demo", "-v"], True, True),
])
def test_quiet_and_verbose_before_or_after_the_command(argv, quiet, verbose):
    args = build_parser().parse_args(argv)
    assert (args.quiet, args.verbose, args.debug) == (quiet, verbose, False)


def test_quiet_before_the_command_runs_it(capsys):
    assert main(["-q", "limits"]) == 0 and main(["-v", "limits", "--nx", "4"]) == 0
    assert "range resolution" in capsys.readouterr().out.lower()


# -- 7: one exit-code table, every command ------------------------------------------------------

def _bad_input(tmp: Path) -> dict[str, list[str]]:
    missing = str(tmp / "missing.h5")
    return {
        "demo": ["demo", "--out", str(tmp / "d"), "--spacing", "-0.01"],
        "simulate": ["simulate", str(tmp / "missing.toml"), str(tmp / "x.h5")],
        "reconstruct": ["reconstruct", missing],
        "autofocus": ["autofocus", missing, str(tmp / "x.h5")],
        "preprocess": ["preprocess", missing, str(tmp / "x.h5"), "--dc"],
        "limits": ["limits", "--f-start", "30000", "--f-stop", "20000"],
        "compare": ["compare", missing, missing],
        "devices": ["devices", "--opencl-only", "--variants", "--device", "7:3"],
        "acquire": ["acquire", str(tmp / "missing-rig.toml"), str(tmp / "x.h5")],
        "import": ["import", str(tmp / "no-such-folder"), str(tmp / "x.h5")],
        "inspect": ["inspect", missing],
        "export": ["export", missing, str(tmp / "x.npy")],
        "calibrate": ["calibrate", "--sides", "4"],
        "bench": ["bench", "--size", "4"],
    }


def test_every_command_exits_2_on_bad_input_with_one_line(tmp_path, capsys):
    cases = _bad_input(tmp_path)
    names = {sp.prog.split()[-1] for sp in build_parser()._subparsers._group_actions[0].choices.values()}
    assert names == set(cases) and len(COMMANDS) == len(cases)  # a new command needs its case here
    for name, argv in cases.items():
        assert main(argv) == 2, name
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "error" in err, (name, err)


@pytest.mark.parametrize("damage", ["truncated", "not-hdf5"])
def test_a_damaged_h5_exits_2_naming_the_file(scan, tmp_path, capsys, damage):
    bad = tmp_path / "bad.h5"
    data = scan.read_bytes()
    bad.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"not an HDF5 file at all" * 100)
    image = scan.with_name("scan-image.h5")
    for argv in (["reconstruct", str(bad)], ["preprocess", str(bad), str(tmp_path / "o.h5"), "--dc"],
                 ["autofocus", str(bad), str(tmp_path / "o.h5")], ["export", str(bad), str(tmp_path / "o.npy")],
                 ["compare", str(image), str(bad)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert str(bad) in err and "truncated or corrupt" in err and err.count("\n") == 1, err


# -- 2: no silent downgrades --------------------------------------------------------------------

@pytest.mark.parametrize("device,match", [("gpu", "must be P:D"), ("7:3", "no such OpenCL device")])
def test_a_device_that_does_not_exist_is_an_error_not_numpy(scan, tmp_path, capsys, device, match):
    out = tmp_path / "img.h5"
    assert main(["reconstruct", str(scan), "--device", device, "--out", str(out), "-q"]) == 2
    assert match in capsys.readouterr().err and not out.exists()
    assert main(["reconstruct", str(scan), "--device", "1:0", "--backend", "numpy", "--out", str(out)]) == 2


def test_devices_labels_the_simulator_and_auto_never_picks_it(capsys):
    from clsas import cl

    rows = cl.list_devices()
    if not any("oclgrind" in r.platform.lower() for r in rows):
        pytest.skip("no Oclgrind platform here")
    assert main(["devices", "--opencl-only"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "Oclgrind" in ln]
    assert lines and all("SIMULATOR" in ln and not ln.startswith("*") for ln in lines)


def test_a_sparse_method_without_its_solver_is_refused_before_any_work(scan, tmp_path, capsys, monkeypatch):
    import importlib.util

    import clsas

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "cvxpy" else real(name, *a))
    monkeypatch.setattr(clsas, "reconstruct", lambda *a, **k: pytest.fail("work started"))
    out = tmp_path / "img.h5"
    assert main(["reconstruct", str(scan), "--method", "cbp-taylor", "--out", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert "needs cvxpy (the sparse extra)" in err and "[sparse]'" in err and "pip install" in err
    assert not out.exists()


# -- 1: progress bars name their step; a long job says so ----------------------------------------

def test_progress_names_each_step_it_measures(scan, tmp_path, capsys):
    pytest.importorskip("scipy.optimize")
    assert main(["reconstruct", str(scan), "--method", "bpdn", "--backend", "numpy",
                 "--out", str(tmp_path / "i.h5")]) == 0
    err = capsys.readouterr().err
    assert "super-resolve (bpdn)" in err and "backproject" in err


@pytest.mark.parametrize("flags,stages", [
    (["--formation", "bp"], ("compress (matched)", "backproject")),
    (["--method", "bpdn"], ("super-resolve (bpdn)", "backproject")),
    ([], ("compress (matched)", "form (auto)")),
], ids=["bp", "sparse", "auto"])
def test_the_bar_names_the_stages_the_pipeline_announced(scan, tmp_path, capsys, monkeypatch, flags, stages):
    import clsas

    if "bpdn" in flags:
        pytest.importorskip("scipy.optimize")
    announced, reconstruct = [], clsas.reconstruct

    def spy(*a, progress, **kw):  # what the pipeline told the CLI's callback
        def told(report):
            announced.append(report.stages)
            progress(report)
        return reconstruct(*a, progress=told, **kw)

    monkeypatch.setattr(clsas, "reconstruct", spy)
    assert main(["reconstruct", str(scan), "--backend", "numpy", "--out", str(tmp_path / "i.h5"), *flags]) == 0
    assert set(announced) == {stages}
    err = capsys.readouterr().err
    for k, stage in enumerate(stages, 1):
        assert f"step {k} of {len(stages)}: {stage}" in err


def test_the_stage_bar_announces_each_stage_once_after_its_first_count():
    from clsas.types.progress import Progress

    stages, seen = ("super-resolve (cbp-taylor)", "backproject"), []
    with stage_bar(enabled=False, announce=lambda stage, *a: seen.append((stage, *a[1:]))) as cb:
        for stage in stages:
            cb(Progress(stage, 0, None, stages))
            for i in (1, 2, 3):
                cb(Progress(stage, i, 3, stages))
    assert seen == [("super-resolve (cbp-taylor)", 1, 3), ("backproject", 1, 3)]
    assert stage_label(Progress("backproject", 2, 3, stages)) == "step 2 of 2: backproject"


def test_a_job_over_a_minute_is_announced_with_the_faster_methods(capsys):
    notice = slow_job_notice("cbp-taylor")
    notice("super-resolve (cbp-taylor)", 352.0, 1, 216)
    err = capsys.readouterr().err
    assert "about 21 h 7 min for all of them" in err and "--method cbp-polar, --method bpdn, --method bp" in err
    notice("super-resolve (cbp-taylor)", 0.2, 1, 216)  # 43 s: said nothing
    notice("backproject", 100.0, 1, 216)
    assert capsys.readouterr().err == ""


# -- 5: guards for all the work before any of it --------------------------------------------------

def test_demo_checks_every_scene_memory_before_the_first_starts(tmp_path, monkeypatch, capsys):
    import clsas
    from clsas.formation import guard
    from clsas.synthesis.scenes import demo_configs, parse_config

    sizes = [parse_config(t).grid.size for t in demo_configs(0.01).values()]
    assert sizes[0] < sizes[1]  # front fits, corner does not
    per_voxel = guard.bytes_per_voxel("numpy")
    monkeypatch.setattr(guard, "available_memory_bytes", lambda: int(per_voxel * (sizes[0] + sizes[1]) / 2 / 0.8))
    monkeypatch.setattr(clsas, "simulate", lambda *a, **k: pytest.fail("work started before the guard"))
    assert main(["demo", "--out", str(tmp_path / "demo"), "--backend", "numpy", "-q"]) == 2
    err = capsys.readouterr().err
    assert f"= {sizes[1]:.3g} voxels" in err and "(at most 80% of it is used)" in err
    assert not (tmp_path / "demo").exists()


# -- 10: README hurdles ----------------------------------------------------------------------------

def test_submodules_work_after_a_plain_import():
    code = ("import clsas; assert callable(clsas.synthetic.turntable_scan); assert callable(clsas.io.import_folder); "
            "print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", out.stderr


def test_bandpass_outside_the_chirp_band_is_refused(scan, tmp_path, capsys):
    out = tmp_path / "p.h5"
    assert main(["preprocess", str(scan), str(out), "--bandpass", "40000,45000"]) == 2
    err = capsys.readouterr().err
    assert "outside the chirp's band 20000-30000 Hz" in err and not out.exists()
    assert main(["preprocess", str(scan), str(out), "--bandpass", "30000,20000"]) == 2
    assert main(["preprocess", str(scan), str(out), "--bandpass", "18000,32000", "-q"]) == 0


def test_limits_refuses_a_band_given_high_to_low(capsys):
    assert main(["limits", "--f-start", "30000", "--f-stop", "20000"]) == 2
    assert "above --f-stop" in capsys.readouterr().err


def _docs_text(root: Path) -> str:
    """The README and the guide's pages (where the README's sections live)."""
    return "\n".join(p.read_text() for p in [root / "README.md", *sorted((root / "docs" / "guide").glob("*.md"))])


def test_the_readme_scene_and_rig_files_are_shipped():
    from clsas import rig
    from clsas.synthesis.scenes import parse_config

    root = Path(__file__).resolve().parents[2]
    readme = _docs_text(root)
    block = readme.split("A scene file (this one is `examples/scene.toml`", 1)[1].split("```toml\n", 1)[1]
    block = block.split("```", 1)[0]
    shipped = (root / "examples" / "scene.toml").read_text()
    assert shipped.split("\n", 1)[1] == block  # the README's text, after one comment line
    assert parse_config(shipped).aperture.n_meas == 216
    assert (root / "examples" / "rig.toml").read_text() == rig.SAMPLE_RIG_TOML


def test_fig4_errors_in_the_readme_are_what_the_example_gives(tmp_path):
    """The README and examples/out/fig4.md quoted convex CBP-Polar at 6.8e-4 with
    two echoes; the example gives 0.0727 with three. The quoted figures must be the example's."""
    pytest.importorskip("cvxpy")
    pytest.importorskip("nlopt")
    import re

    root = Path(__file__).resolve().parents[2]
    res = subprocess.run([sys.executable, str(root / "examples" / "fig4_1d_recovery.py"), "--out", str(tmp_path)],
                         capture_output=True, text=True, cwd=tmp_path, env={**os.environ, "PYTHONPATH": _path(root)})
    assert res.returncode == 0, res.stderr

    def errors(md: str) -> dict[str, float]:
        return {row.split("|")[1].strip(): float(row.split("|")[4]) for row in md.splitlines()
                if row.startswith("| ") and not row.startswith("| method")}

    ran, shipped = errors((tmp_path / "fig4.md").read_text()), errors((root / "examples/out/fig4.md").read_text())
    assert ran.keys() == shipped.keys()
    for k in ran:
        assert ran[k] == pytest.approx(shipped[k], rel=0.05), k
    line = next(ln for ln in _docs_text(root).splitlines() if "examples/fig4_1d_recovery.py` |" in ln)
    quoted = dict(re.findall(r"(BPDN|CBP-T|convex CBP-P|refined CBP-P) ([\d.e-]+)", line))
    names = {"BPDN": "BPDN", "CBP-T": "CBP-Taylor", "convex CBP-P": "CBP-Polar (convex)",
             "refined CBP-P": "CBP-Polar (refined)"}
    for short, full in names.items():
        assert float(quoted[short]) == pytest.approx(ran[full], rel=0.1), short


def test_a_warning_repeated_word_for_word_is_said_once_per_command(monkeypatch, caplog):
    import logging

    from clsas.cli import limits

    def noisy(args):
        for _ in range(8):
            logging.getLogger("clsas.compression").warning("FMCW: the echoes overlap the chirp by 40%")
        logging.getLogger("clsas.compression").warning("another warning")
        return 0

    monkeypatch.setattr(limits, "cmd_limits", noisy)
    with caplog.at_level(logging.WARNING):
        assert main(["limits"]) == 0
        assert main(["limits"]) == 0  # once per command, not once per process
    texts = [r.getMessage() for r in caplog.records]
    assert texts.count("FMCW: the echoes overlap the chirp by 40%") == 2 and texts.count("another warning") == 2


def test_the_readme_bench_figures_are_the_results_file():
    """The figures the README quotes for the latest full run are the ones its results file holds."""
    import json
    import re

    root = Path(__file__).resolve().parents[2]
    readme = _docs_text(root)
    para = readme.split("Latest full run, with the C/OpenMP peer (", 1)[1].split("\n\n", 1)[0]
    stem = para.lstrip("[`").split(".*`", 1)[0]  # the guide links the results file: [`stem.*`](...)
    res = json.loads((root / (stem + ".json")).read_text())
    (demo, cube) = res["backprojection"][:2]
    flat = " ".join(para.split())
    m = re.search(r"backprojection ([\d.e+]+) pairs/s on the demo grid × 216 stops and ([\d.e+]+) on 64³", flat)
    assert float(m.group(1)) == pytest.approx(demo["opencl_kernel"]["rate_per_s"], rel=0.05)
    assert float(m.group(2)) == pytest.approx(cube["opencl_kernel"]["rate_per_s"], rel=0.05)
    m = re.search(r"\(([\d.]+)× and ([\d.]+)×\), (\d+)× the NumPy twin and (\d+)-(\d+)× the Numba peer", flat)
    assert float(m.group(1)) == pytest.approx(demo["ratios"]["opencl_kernel / c_openmp_peer"], abs=0.01)
    assert float(m.group(2)) == pytest.approx(cube["ratios"]["opencl_kernel / c_openmp_peer"], abs=0.01)
    assert int(m.group(3)) == round(demo["ratios"]["opencl_kernel / numpy_twin"])
    numba = sorted(r["ratios"]["opencl_kernel / numba_peer"] for r in (demo, cube))
    assert (int(m.group(4)), int(m.group(5))) == (round(numba[0]), round(numba[1]))
    comp = res["compression"]["ratios"]
    m = re.search(r"ran ([\d.]+)× scipy's `fftconvolve` \(kernel time; ([\d.]+)× in wall time", flat)
    assert float(m.group(1)) == pytest.approx(comp["opencl_fft_kernel / fftconvolve"], abs=0.05)
    assert float(m.group(2)) == pytest.approx(comp["opencl_fft_wall / fftconvolve"], abs=0.01)


def test_autofocus_reports_one_group_delay_with_one_sign(scan):
    """An error-free scan: the summary's group delay and the group-delay parameter line are one
    number with one sign where it was applied (they were printed with opposite signs: +2.36 us,
    then -2.4 us), and an estimate not applied is said to be so while the summary moves nothing."""
    import re

    import clsas
    from clsas.synthesis.scenes import stored_grid_and_truth

    ds = clsas.load(scan)
    grid, _ = stored_grid_and_truth(ds.config)
    _, rep = clsas.autofocus(ds, grid, methods=("delay",), backend="numpy", max_iter=5)
    text = rep.summary()
    summary = float(re.search(r"group delay ([-+][\d.]+) us", text).group(1))
    line = re.search(r"group_delay: ([-+][\d.e+-]+) \+- \S+ s \(([^;]+);", text)
    estimate_us, state = float(line.group(1)) * 1e6, line.group(2)
    if state == "applied":  # the summary states what was applied: the estimate, with its sign
        assert estimate_us == pytest.approx(summary, abs=0.051)
    else:  # an estimate not applied is reported as such, and the summary says nothing was moved
        assert summary == 0.0 and state in ("not determined", "determined, not applied")


def test_pictures_hold_no_marker_that_is_not_drawn_and_titles_fit(tmp_path):
    """The corner picture's legend showed the hidden reflector's marker, drawn nowhere (it is
    outside the grid); a plane image's long title was clipped at the figure's edges."""
    import numpy as np

    import clsas

    ds = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, 0.6], [0.5, 0.0, 0.6]]), visible=[True, False]),
                        clsas.raster_aperture(4, 3, 0.3, 0.2), clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3), 96e3)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.6, 0.6), 0.01)  # a plane
    image = clsas.reconstruct(ds, grid, backend="numpy")
    scene = clsas.Scene(np.array([[0.0, 0.0, 0.6], [0.5, 0.0, 0.6]]), visible=[True, False])
    fig = image.plot(None, scene=scene, title="a long title " * 25)
    renderer = fig.canvas.get_renderer()
    fig.draw(renderer)
    box = fig._suptitle.get_window_extent(renderer)
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1  # the whole title is inside the figure
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if hasattr(handle, "get_xdata") and handle.get_marker() not in ("", "None", None):
                assert len(handle.get_xdata()) > 0, f"legend entry {label!r} has a marker drawn nowhere"


def test_bench_help_and_readme_agree_on_how_long_the_sets_take():
    root = Path(__file__).resolve().parents[2]
    readme = _docs_text(root)
    quick = readme.split("python -m bench                     # the quick set, ", 1)[1].split(" on a", 1)[0]
    full = readme.split("python -m bench --full              # the full set, ", 1)[1].split(" on a", 1)[0]
    from bench.__main__ import build_parser as bench_parser

    sub = bench_parser()
    helps = " ".join(a.help or "" for a in sub._actions) + " " + (sub.description or "")
    assert f"the full set ({full} on a 2-core CPU" in helps and f"the quick set: {quick} on a 2-core CPU" in helps
    assert quick == "3 to 6 minutes" and full == "3 to 8 minutes"  # 345 s measured at load 5 (236 s CPU)


def test_a_convex_method_over_a_minute_is_announced_before_any_work(scan, capsys):
    """CBP-Taylor on the README's scene: about 350 s per recording, 21 h for the scan; said before
    the first recording starts, not after it ends."""
    import clsas
    from clsas.cli.common import announce_slow_method, estimated_sparse_s
    from clsas.synthesis.scenes import parse_config, stored_grid_and_truth

    root = Path(__file__).resolve().parents[2]
    cfg = parse_config((root / "examples" / "scene.toml").read_text())
    ds = clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=20, seed=0, chirp=cfg.chirp)
    est = estimated_sparse_s(ds, cfg.grid, "cbp-taylor")
    assert 10 * 3600 < est < 40 * 3600
    assert estimated_sparse_s(ds, cfg.grid, "cbp-polar") is None
    announce_slow_method(ds, cfg.grid, "cbp-taylor")
    err = capsys.readouterr().err
    assert "note: cbp-taylor solves a convex program per recording: roughly 2" in err and "--method bpdn" in err
    small = clsas.load(scan)
    announce_slow_method(small, stored_grid_and_truth(small.config)[0], "bpdn")  # timed on its first recording
    assert capsys.readouterr().err == ""


def test_a_pyopencl_ctx_that_names_no_device_is_an_error_too(scan, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PYOPENCL_CTX", "7:3")
    out = tmp_path / "img.h5"
    assert main(["reconstruct", str(scan), "--out", str(out), "-q"]) == 2
    assert "PYOPENCL_CTX=7:3: no such OpenCL device" in capsys.readouterr().err and not out.exists()
    assert main(["reconstruct", str(scan), "--out", str(out), "-q", "--backend", "numpy"]) == 0


def test_an_interrupted_scan_exits_3(tmp_path, monkeypatch, capsys):
    from clsas import rig

    def interrupted(*a, **k):
        raise rig.ScanInterrupted("interrupted at stop 3 of 12; 2 stops are saved in x.h5; resume with: ...", 2)

    monkeypatch.setattr(rig, "acquire", interrupted)
    conf = tmp_path / "rig.toml"
    conf.write_text(rig.SAMPLE_RIG_TOML)
    assert main(["acquire", str(conf), str(tmp_path / "x.h5"), "-q"]) == 3
    assert "2 stops are saved" in capsys.readouterr().err


def _path(root) -> str:
    """``root`` first on the import path, then what the caller had."""
    return os.pathsep.join(p for p in [str(root), os.environ.get("PYTHONPATH", "")] if p)
