"""One registry pattern: a toy formation, sparse method and importer, each one module that
registers itself, are found by ``reconstruct``, ``clsas import`` and the command line's choices."""

from __future__ import annotations

import importlib
import sys
import textwrap

import numpy as np
import pytest

import clsas
import clsas.io
from clsas.cli import build_parser, main
from clsas.registry import Registry

TOY_FORMATION = '''
import numpy as np
from clsas.formation import FORMATIONS
from clsas.types.image import Image

@FORMATIONS.register("toy-formation")
def form(profiles, grid, *, backend=None, device=None, progress=None, force=False, **options):
    """Every voxel the sum of the profiles' magnitudes (a toy, not an image)."""
    value = float(np.abs(profiles.data).sum())
    return Image(np.full(grid.shape, value, complex), grid, "bp", "numpy", "toy", {"toy": 0.0})
'''

TOY_SPARSE = '''
import numpy as np
from clsas.sparse import SPARSE_METHODS, Echoes

def toy(dictionary, b, lam, lam_frac, amplitudes, *, max_echoes=None):
    """One echo at the centre of the dictionary's delays, of amplitude 1."""
    d = dictionary.taus
    return Echoes([float(d[len(d) // 2])], [1.0 + 0j], "toy-sparse", "optimal", 1, 0.0, {})

SPARSE_METHODS.register("toy-sparse", toy)
'''

TOY_IMPORTER = '''
from pathlib import Path
import numpy as np
import clsas
import clsas.io
from clsas.io import IMPORTERS, Importer

def read(source, *, background=None):
    wave = clsas.lfm_chirp(20e3, 30e3, 1e-3, 96e3)
    tx = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    return clsas.Dataset(np.zeros((2, 256)), tx, tx, 96e3, wave, temperature_c=20.0)

IMPORTERS.register("toy-format", Importer(read=read, detect=lambda p: Path(p, "toy.txt").is_file(),
                                          summary="a toy layout"))
'''


@pytest.fixture
def toys(tmp_path, monkeypatch):
    """The three toy modules, imported (so registered); unregistered afterwards."""
    for name, text in (("toy_formation", TOY_FORMATION), ("toy_sparse", TOY_SPARSE), ("toy_importer", TOY_IMPORTER)):
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    import clsas.io
    from clsas.formation import FORMATIONS
    from clsas.sparse import SPARSE_METHODS

    for name in ("toy_formation", "toy_sparse", "toy_importer"):
        importlib.import_module(name)
    yield tmp_path
    FORMATIONS.unregister("toy-formation")
    SPARSE_METHODS.unregister("toy-sparse")
    clsas.io.IMPORTERS.unregister("toy-format")
    for name in ("toy_formation", "toy_sparse", "toy_importer"):
        sys.modules.pop(name, None)


def _scan():
    scene = clsas.Scene(np.array([[0.0, 0.0, 0.6]]))
    ap = clsas.raster_aperture(4, 4, 0.2, 0.2)
    wave = clsas.lfm_chirp(20e3, 30e3, 1e-3, 96e3, taper=0.2)
    return clsas.simulate(scene, ap, wave, 96e3, seed=1)


def test_toys_are_found_by_reconstruct_import_and_the_cli(toys, tmp_path, capsys):
    ds = _scan()
    grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (0.58, 0.62), 0.02)
    image = clsas.reconstruct(ds, grid, formation="toy-formation", backend="numpy")
    assert image.device == "toy" and image.provenance["formation"] == "toy-formation"
    assert np.all(image.values == image.values.flat[0]) and image.values.flat[0] != 0

    image = clsas.reconstruct(ds, grid, method="toy-sparse", backend="numpy", sparse={"max_echoes": 2})
    assert [e.method for e in image.echoes] == ["toy-sparse"] * ds.n_meas

    src = tmp_path / "scan"
    src.mkdir()
    (src / "toy.txt").write_text("")
    assert clsas.io.detect_format(src) == "toy-format"
    assert main(["import", str(src), str(tmp_path / "toy.h5")]) == 0
    assert "(toy-format)" in capsys.readouterr().out
    assert clsas.load(tmp_path / "toy.h5").n_meas == 2

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    choices = {a.dest: a.choices for a in sub["reconstruct"]._actions}
    assert "toy-formation" in choices["formation"] and "toy-sparse" in choices["method"]
    assert "toy-format" in {a.dest: a.choices for a in sub["import"]._actions}["format"]


def test_the_registries_hold_the_built_in_algorithms():
    import clsas.io
    from clsas.compression import COMPRESSIONS
    from clsas.formation import FORMATIONS
    from clsas.inverse import MODEL_METHODS
    from clsas.pipeline.reconstruction import methods
    from clsas.sparse import SPARSE_METHODS

    assert set(FORMATIONS) == {"auto", "bp", "omega-k", "ffbp"}
    assert {"bpdn", "cbp-taylor", "cbp-polar"} <= set(SPARSE_METHODS)
    assert set(COMPRESSIONS) == {"matched", "fmcw"}
    assert set(clsas.io.IMPORTERS) >= {"airsas", "folder"}
    assert {"ls", "l1", "tv", "l1-tv", "l1-psf", "psf", "offgrid"} <= set(MODEL_METHODS)
    assert methods()[0] == "bp" and set(methods()[1:]) == set(SPARSE_METHODS) | set(MODEL_METHODS)


def test_a_registry_refuses_a_taken_name_and_names_the_parameter():
    reg: Registry = Registry("widget", "widget")
    reg.register("a", 1)
    with pytest.raises(ValueError, match="widget 'a' is already registered"):
        reg.register("a", 2)
    reg.register("a", 2, replace=True)
    assert reg.choose("a") == 2
    with pytest.raises(ValueError, match=r"widget must be one of \('a',\), got 'b'"):
        reg.choose("b")
    with pytest.raises(ValueError, match="compression must be one of"):
        reg.check("b", "compression")
    with pytest.raises(ValueError, match="non-empty string"):
        reg.register(" a", 3)


def test_unknown_names_are_refused_by_name_before_any_work():
    ds = _scan()
    grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (0.58, 0.62), 0.02)
    with pytest.raises(ValueError, match=r"formation must be one of \('auto', 'bp'"):
        clsas.reconstruct(ds, grid, formation="nope")
    with pytest.raises(ValueError, match="method must be one of"):
        clsas.reconstruct(ds, grid, method="nope")
    with pytest.raises(ValueError, match="compression must be one of"):
        clsas.reconstruct(ds, grid, compression="nope")
    with pytest.raises(ValueError, match="format must be one of"):
        clsas.io.import_scan(".", format="nope")
