import numpy as np
import pytest
from conftest import SCENE_TOML as SCENE

import clsas
from clsas.cli import main


def test_simulate_then_reconstruct(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    data = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(data), "-q", "--backend", "numpy"]) == 0
    assert main(["reconstruct", str(data), "-q", "--png", "--backend", "numpy"]) == 0
    out = capsys.readouterr().out
    assert "peak (+0.020, -0.010, 0.600) m" in out
    image = clsas.Image.load(tmp_path / "scan-image.h5")
    assert image.values.shape == (21, 21, 21)
    assert (tmp_path / "scan-image.png").stat().st_size > 1000


def test_reconstruct_verbose_prints_the_plan(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    data = tmp_path / "scan.h5"
    main(["simulate", str(scene), str(data), "-q"])
    assert main(["reconstruct", str(data), "-q", "--verbose", "--grid=-0.1,0.1,0,0,0.5,0.7",
                 "--backend", "numpy"]) == 0
    out = capsys.readouterr().out
    assert "2-D" in out and "skipped" in out


def test_limits_warns_about_the_paper_rig(capsys):
    assert main(["limits"]) == 0
    out = capsys.readouterr().out
    assert "1.72 cm" in out and "grating lobes" in out


def test_devices_runs(capsys):
    assert main(["devices"]) == 0


def test_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace("fs_hz = 96000.0", "fs_hz = 50000.0"))
    assert main(["simulate", str(bad), str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Nyquist" in err
    assert main(["reconstruct", str(tmp_path / "missing.h5")]) == 2


@pytest.mark.slow
def test_demo_writes_datasets_images_and_pictures(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--spacing", "0.03", "-q"]) == 0
    for name in ("front", "corner"):
        for suffix in (".h5", "-image.h5", ".png"):
            assert (tmp_path / f"{name}{suffix}").exists()
    out = capsys.readouterr().out
    assert out.count("from the nearest true (image) reflector") == 2
    assert np.all(np.isfinite(clsas.Image.load(tmp_path / "corner-image.h5").values))


@pytest.mark.parametrize("command", ["simulate", "preprocess", "reconstruct", "export", "inspect", "autofocus"])
def test_a_command_never_replaces_a_file_unasked(tmp_path, capsys, command):
    """Every command that writes refuses an existing output before any work, naming the file and
    --overwrite; with --overwrite it replaces it."""
    from conftest import small_dataset

    from clsas.cli import main

    ds = small_dataset([[0.0, 0.0, 0.5]], nx=5, ny=4)
    scan = ds.save(tmp_path / "scan.h5")
    grid = "--grid=-0.05,0.05,-0.04,0.04,0.45,0.55"
    image = tmp_path / "scan-image.h5"
    assert main(["reconstruct", str(scan), grid, "--spacing", "0.02", "--backend", "numpy", "-q"]) == 0
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    target = {"simulate": tmp_path / "sim.h5", "preprocess": tmp_path / "pre.h5", "reconstruct": image,
              "export": tmp_path / "x.npy", "inspect": tmp_path / "look.png",
              "autofocus": tmp_path / "af.h5"}[command]
    argv = {"simulate": ["simulate", str(scene), str(target), "-q", "--backend", "numpy"],
            "preprocess": ["preprocess", str(scan), str(target), "--dc"],
            "reconstruct": ["reconstruct", str(scan), grid, "--spacing", "0.02", "--backend", "numpy", "-q"],
            "export": ["export", str(image), str(target)],
            "inspect": ["inspect", str(scan), grid, "--png", str(target)],
            "autofocus": ["autofocus", str(scan), str(target), grid, "--spacing", "0.02", "--backend", "numpy",
                          "-q"]}[command]
    target.write_bytes(b"precious")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert str(target) in err and "--overwrite" in err
    assert target.read_bytes() == b"precious"
    assert main([*argv, "--overwrite"]) == 0
    assert target.read_bytes() != b"precious"
