"""The configuration layer: scene and rig files are checked strictly, and every refusal names
the file, the table and the key."""

import subprocess
import sys

import numpy as np
import pytest

from clsas import rig
from clsas.cli import main
from clsas.io.config import ConfigError, suggestion
from clsas.synthesis.scenes import demo_configs, load_config, parse_config, stored_grid_and_truth

SCENE = """
[chirp]
f_start_hz = 20000.0
f_stop_hz = 30000.0
duration_s = 0.002
fs_hz = 96000.0
taper = 0.1

[aperture]
nx = 5
ny = 4
width_m = 0.4
height_m = 0.3

[air]
temperature_c = 20.0
humidity_pct = 50.0

[noise]
snr_db = 20.0
seed = 1

[[points]]
position_m = [0.02, -0.01, 0.6]
amplitude = 1.0

[[walls]]
point_m = [0.0, 0.0, 2.0]
normal = [0.0, 0.0, -1.0]

[grid]
x_m = [-0.1, 0.1]
y_m = [-0.1, 0.1]
z_m = [0.5, 0.7]
spacing_m = 0.05
"""


def _scene_error(tmp_path, old, new):
    path = tmp_path / "scene.toml"
    text = SCENE.replace(old, new)
    assert text != SCENE, f"{old!r} is not in the test scene"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert "\n" not in message
    return message


@pytest.mark.parametrize("old,new,expected", [
    ("nx = 5", "n_x = 5", "[aperture] unknown key 'n_x' (did you mean 'nx'?)"),
    ("snr_db = 20.0", "snr_bd = 0", "[noise] unknown key 'snr_bd' (did you mean 'snr_db'?)"),
    ("[noise]", "[nosie]", "unknown table 'nosie' (did you mean 'noise'?)"),
    ("[grid]", "[grdi]", "unknown table 'grdi' (did you mean 'grid'?)"),
    ("position_m = [0.02", "positon_m = [0.02", "[[points]] #1 unknown key 'positon_m' (did you mean 'position_m'?)"),
    ("normal = [0.0, 0.0, -1.0]", "", "[[walls]] #1 has no 'normal': walls[1].normal is required"),
    ("position_m = [0.02, -0.01, 0.6]", "", "[[points]] #1 has no 'position_m': points[1].position_m is required"),
    ("spacing_m = 0.05", "spacing = 0.05", "[grid] unknown key 'spacing' (did you mean 'spacing_m'?)"),
    ("[[points]]", "[[point]]", "unknown table 'point' (did you mean 'points'?)"),
])
def test_unknown_and_missing_keys_are_named(tmp_path, old, new, expected):
    assert expected in _scene_error(tmp_path, old, new)


@pytest.mark.parametrize("old,new,expected", [
    ("nx = 5", 'nx = "5"', "aperture.nx must be an integer, got '5'"),
    ("nx = 5", "nx = 5.0", "aperture.nx must be an integer, got 5.0"),
    ("width_m = 0.4", 'width_m = "wide"', "aperture.width_m must be a number, got 'wide'"),
    ("snr_db = 20.0", 'snr_db = "20"', "noise.snr_db must be a number, got '20'"),
    ("amplitude = 1.0", "amplitude = true", "points[1].amplitude must be a number, got true"),
    ("position_m = [0.02, -0.01, 0.6]", 'position_m = [0.02, "a", 0.6]', "points[1].position_m must be a list of 3"),
    ("position_m = [0.02, -0.01, 0.6]", "position_m = [0.02, 0.6]", "points[1].position_m must be a list of 3"),
    ("[[points]]", "[[points]]\nvisible = 1", "points[1].visible must be true or false, got 1"),
    ("[aperture]", '[aperture]\npattern = "zigzag"', "aperture.pattern must be one of 'serpentine', 'raster'"),
    ("[aperture]", "aperture = 3\n[apertures]", "unknown"),
])
def test_wrong_types_are_named(tmp_path, old, new, expected):
    assert expected in _scene_error(tmp_path, old, new)


@pytest.mark.parametrize("old,new,expected", [
    ("nx = 5", "nx = -3", "aperture.nx must be >= 1, got -3"),
    ("ny = 4", "ny = 0", "aperture.ny must be >= 1, got 0"),
    ("width_m = 0.4", "width_m = -0.4", "aperture.width_m must be >= 0, got -0.4"),
    ("seed = 1", "seed = -1", "noise.seed must be >= 0, got -1"),
    ("snr_db = 20.0", "snr_db = nan", "noise.snr_db must be finite, got nan"),
    ("humidity_pct = 50.0", "humidity_pct = 150.0", "air.humidity_pct must be <= 100, got 150.0"),
    ("taper = 0.1", "taper = 2", "chirp.taper must be <= 1, got 2"),
    ("duration_s = 0.002", "duration_s = 0", "chirp.duration_s must be > 0, got 0"),
    ("fs_hz = 96000.0", "fs_hz = 50000.0", "[chirp]"),  # the chirp's own check (Nyquist), with the table
    ("spacing_m = 0.05", "spacing_m = 0", "grid.spacing_m must be > 0, got 0"),
    ("z_m = [0.5, 0.7]", "z_m = [0.7, 0.5]", "grid.z_m must be [low, high], got [0.7, 0.5]"),
    ("normal = [0.0, 0.0, -1.0]", "normal = [0.0, 0.0, -1.0]\nreflectivity = 2",
     "walls[1].reflectivity must be <= 1, got 2"),
    ("normal = [0.0, 0.0, -1.0]", "normal = [0.0, 0.0, 0.0]", "[[walls]] #1 normal must be a non-zero vector"),
])
def test_out_of_range_values_are_named(tmp_path, old, new, expected):
    assert expected in _scene_error(tmp_path, old, new)


def test_a_scene_without_reflectors_says_what_to_add(tmp_path):
    text = SCENE.split("[[points]]")[0]
    with pytest.raises(ConfigError, match=r"scene\.toml: the scene has no reflector: add one \[\[points\]\]"):
        parse_config(text, "scene.toml")


def test_suggestion_only_when_close():
    assert suggestion("n_x", ("nx", "ny", "width_m")) == " (did you mean 'nx'?)"
    assert suggestion("colour", ("nx", "ny", "width_m")) == ""


def test_demo_and_sample_configurations_parse():
    for name, text in demo_configs(0.05).items():
        cfg = parse_config(text, name)
        assert cfg.grid is not None and len(cfg.scene.points_m) == 27 and cfg.snr_db == 20.0
    cfg = rig.parse_rig_config(rig.SAMPLE_RIG_TOML)
    assert cfg.n_stops == 216 and cfg.grid is not None and cfg.grid.shape == (101, 101, 81)
    assert cfg.simulate["latency_samples"] == 300 and len(cfg.simulate["points"]) == 1


def test_scene_values_are_read():
    cfg = parse_config(SCENE)
    assert cfg.aperture.n_meas == 20 and cfg.fs_hz == 96000.0 and cfg.seed == 1 and cfg.snr_db == 20.0
    assert cfg.chirp == {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 0.002, "taper": 0.1}
    assert len(cfg.scene.walls) == 1 and cfg.grid.shape == (5, 5, 5) and cfg.preprocess == {}


def test_preprocess_table_passes_through_scene_and_rig_files():
    table = '\n[preprocess]\ndc = true\nbandpass = [19000.0, 31000.0]\n'
    assert parse_config(SCENE + table).preprocess == {"dc": True, "bandpass": [19000.0, 31000.0]}
    assert rig.parse_rig_config(rig.SAMPLE_RIG_TOML + table).preprocess["dc"] is True
    with pytest.raises(ConfigError, match=r"\[preprocess\] unknown key 'bandpas' \(did you mean 'bandpass'\?\)"):
        parse_config(SCENE + "\n[preprocess]\nbandpas = [1.0, 2.0]\n")


@pytest.mark.parametrize("old,new,expected", [
    ("settle_s = 0.5", "setle_s = 0.5", "[scan] unknown key 'setle_s' (did you mean 'settle_s'?)"),
    ("repeats = 4", 'repeats = "4"', "recorder.repeats must be an integer, got '4'"),
    ("level = 0.5", "level = -0.5", "recorder.level must be > 0, got -0.5"),
    ("[audio]", "[adio]", "unknown table 'adio' (did you mean 'audio'?)"),
    ("home = true", 'home = "yes"', "scan.home must be true or false, got 'yes'"),
    ("mic_channels = [2]", "mic_channels = [0]", "audio.mic_channels must be a list of input channels"),
    ("noise_rms = 1e-4", "noise_rms = -1", "simulate.noise_rms must be >= 0, got -1"),
    ("position_m = [0.0, 0.0, 1.2]", "positon_m = [0.0, 0.0, 1.2]",
     "[simulate] points #1 unknown key 'positon_m' (did you mean 'position_m'?)"),
    ("spacing_m = 0.01", "spacing_m = -0.01", "grid.spacing_m must be > 0"),
    ("duration_s = 0.005", "duration_s = 0.005\nfs_hz = 96000", "[chirp] unknown key 'fs_hz'"),
])
def test_rig_refusals_name_file_table_and_key(tmp_path, old, new, expected):
    path = tmp_path / "rig.toml"
    text = rig.SAMPLE_RIG_TOML.replace(old, new, 1)
    assert text != rig.SAMPLE_RIG_TOML
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        rig.load_rig_config(path)
    assert str(info.value).startswith(f"{path}: ") and expected in str(info.value)


def test_a_rig_file_is_not_a_scene_and_a_scene_is_not_a_rig_file():
    with pytest.raises(ConfigError, match=r"rig\.toml is a rig configuration "
                       r"\(\[stage\], \[scan\], \[audio\], \[recorder\], \[simulate\]\)"
                       r", not a scene file: scan it with `clsas acquire"):
        parse_config(rig.SAMPLE_RIG_TOML, "rig.toml")
    with pytest.raises(ConfigError, match=r"scene\.toml is a scene configuration \(\[\[points\]\], \[\[walls\]\], "
                       r"\[noise\]\), not a rig file: simulate it with `clsas simulate"):
        rig.parse_rig_config(SCENE, "scene.toml")


def test_cli_refuses_bad_files_with_exit_2_and_one_line(tmp_path, capsys):
    scene, rig_file, out = tmp_path / "scene.toml", tmp_path / "rig.toml", tmp_path / "out.h5"
    scene.write_text(SCENE.replace("nx = 5", "n_x = 5"))
    assert main(["simulate", str(scene), str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{scene}: [aperture] unknown key 'n_x' (did you mean 'nx'?)" in err
    rig_file.write_text(rig.SAMPLE_RIG_TOML)
    assert main(["simulate", str(rig_file), str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is a rig configuration" in err and "clsas acquire" in err
    scene.write_text(SCENE)
    assert main(["acquire", str(scene), str(out), "--simulate", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is a scene configuration" in err and "clsas simulate" in err
    scene.write_text(SCENE.replace("position_m = [0.02", "positon_m = [0.02"))
    assert main(["simulate", str(scene), str(out), "-q"]) == 2
    assert "did you mean 'position_m'?" in capsys.readouterr().err
    assert not out.exists()


def test_stored_configurations_give_grid_and_truth():
    grid, truth = stored_grid_and_truth(SCENE)
    assert grid.shape == (5, 5, 5)
    np.testing.assert_allclose(truth[0], [0.02, -0.01, 0.6])
    grid, truth = stored_grid_and_truth(rig.SAMPLE_RIG_TOML)
    assert grid.shape == (101, 101, 81)
    np.testing.assert_allclose(truth, [[0.0, 0.0, 1.2]])
    assert stored_grid_and_truth("") == (None, None)
    assert stored_grid_and_truth("[recording]\nfs_hz = 96000.0\n") == (None, None)


def test_scenes_do_not_import_the_rig():
    code = "import sys, clsas.synthesis.scenes, clsas.io.config; print('clsas.rig' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_a_key_outside_its_table_is_told_where_it_belongs(tmp_path):
    message = _scene_error(tmp_path, "[chirp]", "nx = 5\n[chirp]")
    assert message.endswith("key 'nx' is outside any table: put it under [aperture]")
    with pytest.raises(ConfigError, match=r"rig\.toml: \[chirp\] unknown key 'fs_hz': a rig's sample rate is "
                       r"\[audio\] fs_hz"):
        rig.parse_rig_config(rig.SAMPLE_RIG_TOML.replace("taper = 0.1", "taper = 0.1\nfs_hz = 96000"), "rig.toml")


def test_files_of_another_kind_are_named(tmp_path):
    h5 = tmp_path / "scan.h5"
    h5.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    with pytest.raises(ConfigError, match=r"scan\.h5 is an HDF5 file .* not a scene file"):
        load_config(h5)
    with pytest.raises(ConfigError, match=r"scan\.h5 is an HDF5 file .* not a rig file"):
        rig.load_rig_config(h5)
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(tmp_path)
    with pytest.raises(ConfigError, match=r"import\.toml holds import settings .* `clsas import`"):
        parse_config("[recording]\nfs_hz = 96000.0\n", "import.toml")
    with pytest.raises(FileNotFoundError, match="no scene configuration"):
        load_config(tmp_path / "missing.toml")


def test_a_table_written_as_an_array_of_tables_is_named(tmp_path):
    message = _scene_error(tmp_path, "[aperture]", "[[aperture]]")
    assert message.endswith("[aperture] must be a table, got an array of tables ([[...]])")
    assert "scene.toml is not valid TOML: Expected ']'" in _scene_error(tmp_path, "[grid]", "[grid\n")


def test_a_stored_configuration_refused_today_costs_only_grid_or_truth(caplog):
    grid, truth = stored_grid_and_truth(SCENE.replace("nx = 5", "n_x = 5").replace("spacing_m = 0.05", "spacing = 1"))
    assert grid is None
    np.testing.assert_allclose(truth[0], [0.02, -0.01, 0.6])
    assert "no stored grid" in caplog.text


def test_stored_scene_of_scene_and_rig_files():
    from clsas.synthesis.scenes import stored_scene

    scene = stored_scene(SCENE)
    assert len(scene.points_m) == 1 and len(scene.walls) == 1
    wall = '\nwalls = [{ point_m = [0.0, 0.0, 2.0], normal = [0.0, 0.0, -1.0] }]\n'
    scene = stored_scene(rig.SAMPLE_RIG_TOML.replace("time_scale = 0.01", "time_scale = 0.01" + wall))
    assert len(scene.points_m) == 1 and len(scene.walls) == 1
    assert stored_scene("") is None and stored_scene("[recording]\nfs_hz = 1.0\n") is None
