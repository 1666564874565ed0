"""Every code block of the README and of the guide's pages is run by a test, or listed here as not
run with the reason.

A block is known by the ``##`` heading it sits under (the README's sections moved into
``docs/guide/*.md`` with their headings), its language and its place among that heading's blocks
in its file; a new block fails ``test_every_block_is_run_or_excused`` until it is given a runner
here (or a reason not to run it), so a snippet cannot drift from the code unnoticed. A guide
page's own setup blocks, above its first ``##`` heading, are run by ``tests/docs/test_docs.py``.
"""

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

import clsas

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs" / "guide").glob("*.md"))]

# the fast-formation page's headings of its ω-k and FFBP snippets
OMEGA_K, FFBP = "ω-k: `formation=\"omega-k\"`", "FFBP: `formation=\"ffbp\"`"
# the own-data page's headings of its AirSAS pipeline and of its preprocessing steps
AIRSAS, PREPROCESS = "The AirSAS scans, start to end", "Preprocessing"
# the benchmarks page's rates table
RATES = "Kernel and wall rates on every device"

# (heading, language, n-th block under it) -> where it is run
RUN_ELSEWHERE = {
    **{(heading, "python", 0): "tests/docs/test_docs.py (the own-data page in order, on the scan.h5 of its setup "
                               "block; its outputs compared)"
       for heading in ("Look before imaging", PREPROCESS, "Image and compare", "Importing")},
    ("Volumes past memory and past one machine", "python", 0):
        "tests/docs/test_docs.py (the large-volumes page, after its setup block)",
    ("Apodization: `formation_options={\"beam\": ...}`", "python", 0): "tests/docs/test_docs.py (the beams page)",
    ("Super-resolution (sparse recovery)", "python", 0):
        "tests/docs/test_docs.py (the super-resolution page, after its setup block; its output compared)",
    ("A measured-looking scan to try things on", "bash", 0):
        "tests/docs/test_docs.py::test_example_prints_what_the_page_shows (the turntable example, its output "
        "against the page's)",
    ("Super-resolution (sparse recovery)", "bash", 0):
        "tests/docs/test_docs.py::test_example_prints_what_the_page_shows (the fig4 example, its output against "
        "the page's)",
    **{(heading, "python", 0): "tests/docs/test_docs.py (the autofocus page in order; its outputs compared)"
       for heading in ("A hand-held scan", "Run it and read the report", "When an estimate is applied",
                       "A last check that trusts no image: data consistency")},
    ("`formation=\"auto\"`: what it chooses and what it prints", "python", 0):
        "tests/docs/test_docs.py (the fast-formation page, after its setup block; its output compared)",
    ("Python API in ten lines", "python", 0):
        "tests/scenarios/test_first_use_guards_and_light_import.py::test_the_readme_python_api_in_ten_lines_runs_as_written",
}
RUN_HERE = {
    (AIRSAS, "python", 0): "test_your_own_data_python",
    (AIRSAS, "bash", 0): "test_your_own_data_command_line",
    (PREPROCESS, "toml", 0): "test_your_own_data_preprocess_table",
    ("Command line", "toml", 0): "test_command_line_scene_file",
    ("Beam models and boresights", "toml", 0): "test_beams_table",
    (OMEGA_K, "python", 0): "test_fragments_on_a_small_scan",
    (FFBP, "python", 0): "test_fragments_on_a_small_scan",
    ("Extending clsas: one module and one line", "python", 0): "test_extending_registers_a_formation",
    ("On the command line", "bash", 0): "test_autofocus_command_line",
    (RATES, "bash", 0): "test_rates_command_prints_what_the_page_shows",
}
NOT_RUN = {
    ("The two commands", "bash", 0): "installs the package into a new virtual environment and runs the whole "
                                     "test suite (what CI does)",
    ("Which formation when", "bash", 0): "a synopsis with [optional] parts, not a command line",
    ("Building and running a rig", "bash", 0): "runs a scan against the GRBL and audio emulators (about a "
                                               "minute); tests/hw/test_rig.py runs the same commands",
    ("Building and running a rig", "", 0): "a wiring diagram, not code",
    ("Building and running a rig", "toml", 0): "not yet run: a rig file excerpt (test_rig.py checks rig files)",
    ("How it is organised", "", 0): "a map of the source tree, not code",
    ("Benchmarks", "bash", 0): "runs the benchmark suite (minutes)",
    ("Volumes past memory and past one machine", "", 0): "command lines on a scan.h5 and a Dask scheduler of the "
                                                         "reader's; tests/unit/tiling/test_tiles.py runs --out and "
                                                         "--max-memory",
    ("Documentation", "bash", 0): "builds the documentation site (CI does it, with warnings as errors)",
}


def blocks() -> list[tuple[tuple[str, str, int], str]]:
    """((heading, language, index under the heading in its file), code) of every fenced block under a
    ``##`` or ``###`` heading (a block that is in the README and again in a guide page counts once;
    an ``output`` block is what the block before it prints, which ``tests/docs/test_docs.py`` checks)."""
    out: dict = {}
    for page in PAGES:
        heading, seen = "", {}
        lines = page.read_text().splitlines()
        i = 0
        while i < len(lines):
            line = lines[i]
            m = re.match(r"^#{2,3} (.*)", line)
            if m:
                heading = m.group(1).strip()
            elif line.startswith("```"):
                lang = line[3:].strip().split()[0] if line[3:].strip() else ""
                j = i + 1
                while not lines[j].startswith("```"):
                    j += 1
                if lang != "output" and (heading or page == README):  # an output block belongs to the block before
                    key = (heading, lang, seen.get((heading, lang), 0))
                    out.setdefault(key, "\n".join(lines[i + 1: j]))
                    seen[(heading, lang)] = key[2] + 1
                i = j
            i += 1
    return list(out.items())


def block(heading: str, lang: str, index: int = 0) -> str:
    return dict(blocks())[(heading, lang, index)]


def test_every_block_is_run_or_excused():
    known = set(RUN_ELSEWHERE) | set(RUN_HERE) | set(NOT_RUN)
    found = [k for k, _ in blocks()]
    assert not [k for k in found if k not in known], "README blocks with no runner and no reason"
    assert not [k for k in known if k not in found], "runners or reasons for blocks the README no longer has"
    for name in set(RUN_HERE.values()):
        assert callable(globals().get(name)), name


@pytest.fixture
def airsas_folders(tmp_path, monkeypatch):
    """The folder names of the README's AirSAS example, in the published layout."""
    from airsas_kit import write_scan

    write_scan(tmp_path / "small_features_cutout_20k")
    write_scan(tmp_path / "bg_20k", target=None)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CLSAS_BACKEND", "numpy")
    return tmp_path


def test_your_own_data_python(airsas_folders):
    from airsas_kit import TARGET

    env: dict = {}
    exec(compile(block(AIRSAS, "python"), "own-data.md (AirSAS)", "exec"), env)  # noqa: S102
    image = env["image"]
    found = np.array([p.position_m for p in image.peaks(3, min_separation_m=0.015)])
    for t in TARGET:
        assert np.min(np.linalg.norm(found - t, axis=1)) < 0.006
    assert clsas.tcr_db(image, ((-0.07, 0.07), (-0.11, 0.11), None)) > 15
    assert [p["step"] for p in env["ds"].provenance][-3:] == ["background", "common", "blank_direct"]


def test_your_own_data_python_prints_what_the_page_shows(monkeypatch, capsys):
    """The AirSAS block on the public scans prints the figure the page shows. Set
    ``CLSAS_AIRSAS_DATA`` to a copy of ``airsas_deconv_pipeline/airsas_data`` of
    github.com/awreed/CSAS_Deconvolution_INR (the folders ``small_features_cutout_20k`` and
    ``bg_20k``); without it the test skips (the download stays outside the repository)."""
    import os

    from doc_output import compare
    from test_docs import code_blocks

    data = os.environ.get("CLSAS_AIRSAS_DATA", "")
    if not data or not (Path(data) / "small_features_cutout_20k").is_dir():
        pytest.skip("CLSAS_AIRSAS_DATA does not name the AirSAS data folder (small_features_cutout_20k, bg_20k)")
    code = block(AIRSAS, "python")
    shown = next(out for _, lang, _, c, out in code_blocks(ROOT / "docs" / "guide" / "own-data.md")
                 if lang == "python" and c.rstrip("\n") == code.rstrip("\n"))
    monkeypatch.chdir(data)
    exec(compile(code, "own-data.md (AirSAS)", "exec"), {})  # noqa: S102
    why = compare(shown.text, capsys.readouterr().out, shown.rtol)
    assert why is None, why


def test_your_own_data_command_line(airsas_folders, capsys):
    from clsas.cli import main

    for line in block(AIRSAS, "bash").splitlines():
        argv = shlex.split(line.split("#")[0])
        assert argv[0] == "clsas"
        assert main(argv[1:]) == 0, line
    assert (airsas_folders / "clean.h5").exists()
    assert list(airsas_folders.glob("*.png"))
    steps = [p["step"] for p in clsas.load(airsas_folders / "clean.h5").provenance]
    assert steps[-3:] == ["background", "common", "blank_direct"]


def test_your_own_data_preprocess_table(tmp_path):
    from clsas import preprocess as pp
    from clsas.synthesis.synthetic import turntable_scan

    scan = turntable_scan(12, snr_db=40)
    scan.background.save(tmp_path / "empty.h5")
    (tmp_path / "steps.toml").write_text(block(PREPROCESS, "toml"))
    import tomllib

    from clsas.io.config import preprocess_table

    cfg = tomllib.loads((tmp_path / "steps.toml").read_text())
    table = preprocess_table(cfg, str(tmp_path / "steps.toml"))
    table["background"] = str(tmp_path / table["background"])
    out = pp.from_table(scan.dataset, table)
    assert [p["step"] for p in out.provenance][1:] == ["speed_of_sound", "group_delay", "dc", "bandpass",
                                                      "direct_clock", "background", "common", "blank_direct"]


def test_command_line_scene_file(tmp_path):
    from clsas.synthesis.scenes import load_config

    (tmp_path / "scene.toml").write_text(block("Command line", "toml"))
    cfg = load_config(tmp_path / "scene.toml")
    # each table of the block reached the scan it describes
    assert (cfg.fs_hz, cfg.chirp["duration_s"], cfg.snr_db, cfg.waveform.shape) == (96000.0, 0.005, 20.0, (480,))
    assert cfg.aperture.tx_positions.shape == (18 * 12, 3)
    np.testing.assert_array_equal(cfg.scene.points_m, [[0.0, 0.0, 1.5]])
    assert [w.reflectivity for w in cfg.scene.walls] == [0.9] and cfg.grid.shape == (101, 101, 61)


def test_beams_table(tmp_path):
    """The beams page's [beams] table, in the command-line page's scene file."""
    from clsas.synthesis.scenes import load_config

    text = block("Command line", "toml") + "\n" + block("Beam models and boresights", "toml")
    (tmp_path / "scene.toml").write_text(text)
    cfg = load_config(tmp_path / "scene.toml")
    assert cfg.beams.specs()["speaker"] == {"model": "piston", "diameter_m": 0.006}
    assert np.allclose(cfg.beams.tx_boresight, [0, 0, 1])


def test_fragments_on_a_small_scan():
    """The formation fragments, with ``dataset`` and ``grid`` a small planar scan."""
    fs = 96e3
    chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    dataset = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, 0.6]])), clsas.raster_aperture(36, 36, 0.1, 0.1),
                             chirp, fs, n_samples=900, snr_db=30)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.55, 0.65), 0.01)
    for heading in (OMEGA_K, FFBP):
        env = {"clsas": clsas, "dataset": dataset, "grid": grid}
        exec(compile(block(heading, "python"), f"fast-formation.md ({heading})", "exec"), env)  # noqa: S102
        assert env["image"].values.shape == grid.shape


@pytest.mark.slow
def test_autofocus_command_line(tmp_path, monkeypatch):
    """The autofocus page's command lines on its own scan (its setup block), saved as scan.h5."""
    from clsas.cli import main

    env: dict = {}
    exec(compile(block("A hand-held scan", "python"), "autofocus.md (setup)", "exec"), env)  # noqa: S102
    monkeypatch.chdir(tmp_path)
    env["ds"].save("scan.h5")
    for line in block("On the command line", "bash").splitlines():
        argv = shlex.split(line.split("#")[0])
        assert argv[0] == "clsas"
        assert main(argv[1:]) == 0, line
    assert (tmp_path / "fixed.h5").exists() and (tmp_path / "before_after.png").exists()
    assert (tmp_path / "fixed.png").exists()
    steps = [p["step"] for p in clsas.load(tmp_path / "fixed.h5").provenance]
    assert steps[-1] == "autofocus"


def test_rates_command_prints_what_the_page_shows(tmp_path, capsys):
    """The benchmarks page's rates command, on the smallest scan (8 x 8 stops) and on the NumPy twins
    only (the page's output block leaves the sizes, timings and devices as ``...``), prints what the
    page shows."""
    from doc_output import compare
    from test_docs import code_blocks

    from bench.__main__ import main

    code = block(RATES, "bash")
    shown = next(out for _, lang, _, c, out in code_blocks(ROOT / "docs" / "guide" / "benchmarks.md")
                 if lang == "bash" and c.rstrip("\n") == code.rstrip("\n"))
    argv = shlex.split(code.split("#")[0])
    assert argv[:3] == ["python", "-m", "bench"] and "--rates" in argv
    assert main([*argv[3:], "--rates", "8", "--devices", "numpy", "--out", str(tmp_path)]) == 0
    why = compare(shown.text, capsys.readouterr().out, shown.rtol)
    assert why is None, why


def test_extending_registers_a_formation():
    from clsas.formation import FORMATIONS

    env: dict = {}
    code = block("Extending clsas: one module and one line", "python")
    exec(compile(code, "README.md (Extending clsas)", "exec"), env)  # noqa: S102
    try:
        ds = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, 0.5]])), clsas.raster_aperture(3, 3, 0.1, 0.1),
                            clsas.lfm_chirp(20e3, 30e3, 1e-3, 96e3), 96e3, n_samples=600)
        grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (0.5, 0.5), 0.01)
        image = clsas.reconstruct(ds, grid, formation="sum-of-magnitudes", backend="numpy")
        assert np.allclose(image.values, image.values.flat[0]) and abs(image.values.flat[0]) > 0
    finally:
        FORMATIONS.unregister("sum-of-magnitudes")
