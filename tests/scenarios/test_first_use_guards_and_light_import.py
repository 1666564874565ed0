"""A user's first hour: guards before work, a light import, a CLI that agrees with the README."""

import subprocess
import sys

import numpy as np
import pytest
from conftest import small_dataset

import clsas
from clsas.cli import main
from clsas.formation import guard


def test_import_clsas_is_light():
    code = ("import sys, clsas; heavy = ['scipy.signal', 'scipy.stats', 'scipy.optimize', 'cvxpy', 'nlopt', "
            "'pyopencl', 'matplotlib', 'h5py', 'serial', 'sounddevice']; "
            "print(' '.join(m for m in heavy if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"import clsas pulled in {out}"


def test_contract_names_at_the_top_level_are_lazy():
    code = ("import sys, clsas; assert 'clsas.sparse' not in sys.modules; f = clsas.superres; "
            "assert callable(f) and callable(clsas.delay_error) and callable(clsas.coherence); "
            "assert 'cvxpy' not in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "ok"
    assert {"superres", "delay_error", "coherence"} <= set(dir(clsas)) and "superres" in clsas.__all__
    with pytest.raises(AttributeError, match="no attribute 'superress'"):
        clsas.superress  # noqa: B018


@pytest.mark.parametrize("n", [2, 3, 11, 480, 481])
@pytest.mark.parametrize("fraction", [0.1, 0.5, 1.0])
def test_own_tukey_and_hilbert_equal_scipy(n, fraction):
    import scipy.signal

    from clsas.physics.signals import tukey_taper

    assert np.allclose(tukey_taper(n, fraction), scipy.signal.windows.tukey(n, fraction))
    x = np.random.default_rng(n).normal(size=(3, n))
    assert np.allclose(clsas.analytic(x), scipy.signal.hilbert(x))
    assert np.allclose(clsas.analytic(x.T, axis=0), scipy.signal.hilbert(x.T, axis=0))


def test_a_mistyped_spacing_is_refused_before_any_allocation():
    with pytest.raises(ValueError, match=r"spacing_m=1e-09 gives 1e\+09 voxels along x.*1e-06 m or more"):
        clsas.VoxelGrid.from_bounds((0, 1), (0, 1), (0, 1), 1e-9)


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_a_grid_that_does_not_fit_is_refused_with_the_numbers(monkeypatch, backend):
    ds = small_dataset([[0.0, 0.0, 0.6]], nx=3, ny=3)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.5, 0.7), 0.01)  # 9261 voxels
    monkeypatch.setattr(guard, "available_memory_bytes", lambda: 100_000)  # 100 kB "free"

    def no_work(*a, **k):
        raise AssertionError("work started before the guard")

    monkeypatch.setattr(clsas.pipeline.reconstruction, "compress", no_work)
    with pytest.raises(ValueError, match=r"21 x 21 x 21 = 9.26e\+03 voxels needs about .* a spacing of .* m or more"):
        clsas.reconstruct(ds, grid, backend=backend)
    monkeypatch.undo()
    monkeypatch.setattr(guard, "available_memory_bytes", lambda: 100_000)
    image = clsas.reconstruct(ds, grid, backend=backend, force=True)  # forced: it goes on
    assert image.values.shape == grid.shape


def test_the_suggested_spacing_fits(monkeypatch):
    grid = clsas.VoxelGrid.from_bounds((-0.5, 0.5), (-0.5, 0.5), (1.0, 2.0), 0.002)
    monkeypatch.setattr(guard, "available_memory_bytes", lambda: 2 * 10**9)
    with pytest.raises(ValueError) as err:
        guard.check_grid(grid, "numpy")
    spacing = float(str(err.value).split("a spacing of ")[1].split(" m")[0])
    coarser = clsas.VoxelGrid.from_bounds((-0.5, 0.5), (-0.5, 0.5), (1.0, 2.0), spacing)
    guard.check_grid(coarser, "numpy")  # no error


def test_cli_refuses_a_huge_grid_with_exit_2(tmp_path, capsys):
    ds = small_dataset([[0.0, 0.0, 0.6]], nx=3, ny=3)
    ds.save(tmp_path / "scan.h5")
    rc = main(["reconstruct", str(tmp_path / "scan.h5"), "--grid=-1,1,-1,1,0,2", "--spacing", "0.0001", "-q",
               "--backend", "numpy"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "voxels" in err and "--force" in err


def test_fmcw_refuses_echoes_that_arrive_after_the_chirp():
    # the README's scene: a 5 ms chirp, reflectors 1.5 m away (echoes after 8.7 ms)
    fs = 96e3
    chirp = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 5e-3}
    ds = clsas.simulate(clsas.Scene([[0.0, 0.0, 1.5]]), clsas.raster_aperture(2, 2, 0.1, 0.1),
                        clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1), fs, chirp=chirp)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (0, 0), (1.4, 1.6), 0.01)
    with pytest.raises(ValueError, match=r"fmcw.*after the 5 ms chirp has ended.*compression='matched'"):
        clsas.reconstruct(ds, grid, compression="fmcw", backend="numpy")


def test_fmcw_warns_when_echoes_overlap_less_than_half_the_chirp(caplog):
    fs = 96e3
    chirp = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 10e-3}
    ds = clsas.simulate(clsas.Scene([[0.0, 0.0, 1.0]]), clsas.raster_aperture(2, 2, 0.1, 0.1),
                        clsas.lfm_chirp(20e3, 30e3, 10e-3, fs), fs, chirp=chirp)
    clsas.compress(ds, method="fmcw", gate_s=(4e-3, 7e-3), backend="numpy")
    assert "overlap less than half the chirp" in caplog.text


@pytest.mark.parametrize("argv", [["limits", "--debug"], ["--debug", "limits"], ["limits", "-q", "-v"],
                                  ["devices", "--opencl-only", "-q"], ["compare", "--help"]],
                         ids=["debug-after", "debug-before", "quiet-verbose", "devices-quiet", "help"])
def test_every_command_takes_the_common_flags(argv, capsys):
    try:
        assert main(argv) == 0
    except SystemExit as exc:  # --help
        assert exc.code == 0


def test_debug_after_the_command_shows_the_traceback(tmp_path):
    with pytest.raises(FileNotFoundError):
        main(["reconstruct", str(tmp_path / "missing.h5"), "--debug"])
    assert main(["reconstruct", str(tmp_path / "missing.h5")]) == 2


def test_limits_reads_a_scene_file(tmp_path, capsys):
    f = tmp_path / "scene.toml"
    f.write_text("[chirp]\nf_start_hz = 20000.0\nf_stop_hz = 40000.0\n[aperture]\nnx = 40\nny = 30\n"
                 "width_m = 0.5\nheight_m = 0.4\n[[points]]\nposition_m = [0.0, 0.0, 0.6]\n")
    assert main(["limits", str(f), "--nx", "50"]) == 0
    out = capsys.readouterr().out
    assert "B = 20000 Hz" in out and "nx=50" in out and "range=0.6" in out
    assert main(["limits", str(tmp_path / "nothere.toml")]) == 2


def test_grating_lobes_of_an_undersampled_aperture_are_flagged():
    from clsas.compression import center_frequency
    from clsas.formation.lobes import grating_lobe_notes

    fs = 96e3
    w = clsas.lfm_chirp(24e3, 26e3, 2e-3, fs, taper=0.1)  # narrow band: sharp lobes
    ds = clsas.simulate(clsas.Scene([[0.0, 0.0, 1.0]]), clsas.raster_aperture(9, 1, 0.6, 0.0), w, fs)
    grid = clsas.VoxelGrid.from_bounds((-0.4, 0.4), (0, 0), (0.95, 1.05), 0.005)
    peaks = clsas.reconstruct(ds, grid, backend="numpy").peaks(5, min_separation_m=0.03)
    notes = grating_lobe_notes(peaks, ds.tx_positions, ds.rx_positions, center_frequency(w, fs), ds.c_mps)
    assert notes[0] == "" and all(n == "possibly a grating lobe of peak 1" for n in notes[1:])
    fine = clsas.raster_aperture(9, 1, 0.02, 0.0)  # 2.5 mm < lambda / 4: no lobes to flag
    assert grating_lobe_notes(peaks, fine.tx_positions, fine.rx_positions, 25e3, 343.0) == [""] * 5


def test_a_partial_scan_is_flagged_when_imaged(tmp_path, capsys):
    import h5py

    ds = small_dataset([[0.0, 0.0, 0.6]], nx=3, ny=3)
    path = ds.save(tmp_path / "scan.h5")
    with h5py.File(path, "a") as f:  # as `clsas acquire` leaves a scan it did not finish
        f.attrs["complete"] = False
        f.attrs["n_stops_planned"] = 12
        f.create_dataset("stop_index", data=np.arange(9, dtype=np.int32))
    assert main(["reconstruct", str(path), "--grid=-0.1,0.1,-0.1,0.1,0.5,0.7", "-q", "--backend", "numpy"]) == 0
    out = capsys.readouterr()
    assert "partial scan: 9 of 12 stops" in out.err and "--resume" in out.err
    assert "imaged from a partial scan" in out.out


def test_install_hints_fit_a_source_checkout():
    from clsas.validate import install_hint

    hint = install_hint("rig")
    assert hint.startswith("pip install -e '") and hint.endswith("[rig]'")  # tests run from the checkout


def test_the_readme_python_api_in_ten_lines_runs_as_written(tmp_path, monkeypatch):
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    section = text.split("## Python API in ten lines", 1)[1]
    code = section.split("```python", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    env: dict = {}
    exec(compile(code, "README.md (Python API in ten lines)", "exec"), env)  # noqa: S102 - our own README
    peaks = env["image"].peaks(2, min_separation_m=0.05)
    truth = np.array([[0.1, 0.05, 1.2], [-0.2, 0.1, 1.5]])
    for p in peaks:
        assert np.min(np.linalg.norm(truth - p.position_m, axis=1)) < 0.015
    assert (tmp_path / "scan.h5").exists() and (tmp_path / "image.h5").exists()


def test_delay_error_refuses_a_signal_without_its_atom():
    from clsas.sparse import Echoes

    truth = Echoes([1e-3], [1.0])
    with pytest.raises(ValueError, match="signal was given without atom"):
        clsas.delay_error(truth, truth, np.zeros(10))
