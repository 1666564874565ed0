"""Every entry of every registry through the same checks, generated from the registries.

A new formation, compression, sparse method or importer is one module and one line; the cases
below are generated from :data:`clsas.formation.FORMATIONS`, :data:`clsas.compression.COMPRESSIONS`,
:data:`clsas.sparse.SPARSE_METHODS` and :data:`clsas.io.IMPORTERS` when the tests are collected, so
it is tested here without a test file of its own:

- formations: an image of the grid's shape, finite, its peak at the reflector (within two
  voxels); an unknown option refused before any work, naming it and the known ones; where an
  OpenCL device builds kernels, the device's image equals the NumPy twin's within the formation's
  own tolerance against bp;
- compressions: profiles of one row per recording, finite, the echo's delay where it is; the
  kernel equal to the twin;
- sparse methods: echoes inside the gate, finite, the strongest at the echo's delay within a
  sample;
- importers: a folder in no format is not detected, and reading a missing path raises an error
  naming it.

``test_a_new_module_becomes_cases_of_this_file`` shows it: toy modules (tests/unit/registry/test_registry.py's),
each imported before collection as a user's module would be, become cases of this file that the
checks judge; ``test_a_new_entry_is_covered_by_the_same_checks`` runs the checks on them in process.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import OPENCL_MISSING, ROOT, small_dataset
from test_registry import TOY_FORMATION, TOY_IMPORTER, TOY_SPARSE, toys  # noqa: F401 - the toy entries' fixture

import clsas
import clsas.io
from clsas.compression import COMPRESSIONS
from clsas.formation import FORMATIONS, form
from clsas.sparse import SPARSE_METHODS

POINT = (0.01, -0.01, 0.5)


@pytest.fixture(scope="module")
def scan():
    # an 8 ms chirp: the echo (3 ms) within half of it, where FMCW dechirping sees it too
    ds = small_dataset([POINT], nx=9, ny=9, width=0.24, height=0.24, snr_db=40, duration_s=8e-3)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.45, 0.55), 0.01)
    return ds, grid, clsas.compress(ds, backend="numpy")


def _delay(ds, m: int) -> float:
    """The point's two-way delay at measurement ``m``, s."""
    path = np.linalg.norm(np.subtract(POINT, ds.tx_positions[m])) + \
        np.linalg.norm(np.subtract(POINT, ds.rx_positions[m]))
    return float(path / np.atleast_1d(ds.c_mps)[0])


def check_formation(name: str, scan) -> None:
    ds, grid, prof = scan
    image = form(prof, grid, name, backend="numpy")
    assert image.values.shape == grid.shape, name
    assert np.isfinite(image.values).all(), name
    peak = np.array(image.peaks(1)[0].position_m)
    assert np.linalg.norm(peak - POINT) <= 2 * 0.01 * np.sqrt(3), (name, peak)
    with pytest.raises(ValueError, match="no_such_option") as err:
        form(prof, grid, name, backend="numpy", no_such_option=1)
    assert name in str(err.value)
    if OPENCL_MISSING is None:
        dev = form(clsas.compress(ds, backend="opencl"), grid, name, backend="opencl")
        twin = image.values
        kept = dev.provenance["formation"]
        if kept != image.provenance["formation"]:  # auto chose another formation on the device: that one's twin
            twin = form(prof, grid, kept, backend="numpy", **dev.provenance.get("formation_options", {})).values
        err_db = 20 * np.log10(np.linalg.norm(dev.values - twin) / np.linalg.norm(twin))
        assert err_db < -40, (name, err_db)


def check_compression(name: str, scan) -> None:
    ds, _, _ = scan
    prof = clsas.compress(ds, method=name, backend="numpy")
    assert prof.data.shape[0] == ds.n_meas and np.isfinite(prof.data).all(), name
    m = 0
    want = _delay(ds, m)
    got = prof.tau0_s[m] + prof.dtau_s * int(np.argmax(np.abs(prof.data[m])))
    assert abs(got - want) <= 2 * prof.dtau_s + 2 / ds.fs_hz, (name, got, want)
    if OPENCL_MISSING is None:
        dev = clsas.compress(ds, method=name, backend="opencl")
        assert np.abs(dev.data - prof.data).max() <= 2e-4 * np.abs(prof.data).max(), name


def check_sparse(name: str, scan) -> None:
    from clsas.sparse import superres

    ds, _, _ = scan
    m = 0
    want = _delay(ds, m)
    i0 = int((want - 5e-4) * ds.fs_hz)  # a window of 3 ms from half a millisecond before the echo
    window = ds.signals[m][i0:i0 + int(3e-3 * ds.fs_hz)]
    try:
        echoes = superres(window, ds.waveform, ds.fs_hz, method=name, tau0_s=0.0, max_echoes=3)
    except ValueError as exc:  # a method for positive amplitudes only says so; then it gets those
        assert "positive amplitudes" in str(exc), exc
        echoes = superres(window, ds.waveform, ds.fs_hz, method=name, tau0_s=0.0, max_echoes=3, amplitudes="positive")
    delays = np.asarray(echoes.delays_s)
    assert len(delays) >= 1 and np.isfinite(delays).all(), name
    assert ((delays >= -1 / ds.fs_hz) & (delays <= window.size / ds.fs_hz)).all(), (name, delays)
    strongest = delays[int(np.argmax(np.abs(echoes.amplitudes)))]
    assert abs(strongest - (want - i0 / ds.fs_hz)) <= 1 / ds.fs_hz, (name, strongest, want - i0 / ds.fs_hz)


def check_importer(name: str, tmp_path) -> None:
    importer = clsas.io.IMPORTERS[name]
    empty = tmp_path / f"nothing-{name}"
    empty.mkdir()
    assert not importer.detect(empty), name
    missing = tmp_path / f"missing-{name}"
    with pytest.raises((FileNotFoundError, ValueError), match=missing.name):
        importer.read(missing)


@pytest.mark.parametrize("name", FORMATIONS.names())
def test_every_formation(name, scan):
    check_formation(name, scan)


@pytest.mark.parametrize("name", COMPRESSIONS.names())
def test_every_compression(name, scan):
    check_compression(name, scan)


@pytest.mark.parametrize("name", SPARSE_METHODS.names())
def test_every_sparse_method(name, scan):
    pytest.importorskip("cvxpy")
    pytest.importorskip("nlopt")
    check_sparse(name, scan)


@pytest.mark.parametrize("name", clsas.io.IMPORTERS.names())
def test_every_importer(name, tmp_path):
    check_importer(name, tmp_path)


def test_a_new_entry_is_covered_by_the_same_checks(toys, scan, tmp_path):  # noqa: F811 - the imported fixture
    """The toy formation and importer of tests/unit/registry/test_registry.py, each registered by importing one
    module, are in the registries the cases above are generated from, and the same checks judge
    them: the toy formation's flat image has no peak at the reflector and it takes any option; the
    toy importer reads a missing path without an error. A well-behaved importer registered the
    same way passes."""
    from pathlib import Path

    from clsas.io import Importer

    assert {"toy-formation"} <= set(FORMATIONS.names()) and {"toy-format"} <= set(clsas.io.IMPORTERS.names())
    with pytest.raises(AssertionError):
        check_formation("toy-formation", scan)
    with pytest.raises(pytest.fail.Exception, match="DID NOT RAISE"):
        check_importer("toy-format", tmp_path)

    def read(source, *, background=None):
        if not Path(source, "good.txt").is_file():
            raise FileNotFoundError(f"no good.txt in {source}")
        return None

    clsas.io.IMPORTERS.register("good-toy", Importer(read=read, detect=lambda p: Path(p, "good.txt").is_file()))
    try:
        check_importer("good-toy", tmp_path)
    finally:
        clsas.io.IMPORTERS.unregister("good-toy")


# a well-behaved formation in one module: bp under another name
TOY_BP = '''
from clsas.formation import FORMATIONS, form

@FORMATIONS.register("toy-bp")
def toy_bp(profiles, grid, *, backend=None, device=None, progress=None, force=False):
    """bp under another name."""
    return form(profiles, grid, "bp", backend=backend, device=device, progress=progress, force=force)
'''


def test_a_new_module_becomes_cases_of_this_file(tmp_path):
    """Four modules that each register one entry, imported before collection (``-p``, as an
    installed plugin or a module of clsas would be), are cases of this file with no test file of
    their own: the well-behaved formation passes, the three toys (a flat image, an echo in the
    wrong place, an importer that reads a missing path) fail the checks."""
    modules = {"toy_formation": TOY_FORMATION, "toy_sparse": TOY_SPARSE, "toy_importer": TOY_IMPORTER,
               "toy_bp": TOY_BP}
    for name, text in modules.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(text))
    plugins = [arg for name in modules for arg in ("-p", name)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]),
           "CLSAS_BACKEND": "numpy"}
    run = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *plugins, "-q", "-rA",
                          "-k", "toy and every", str(Path(__file__).relative_to(ROOT))],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    outcomes = {line.split("::", 1)[1].split("[", 1)[1].split("]", 1)[0]: line.split()[0]
                for line in run.stdout.splitlines() if line.startswith(("PASSED", "FAILED", "ERROR")) and "::" in line}
    want = {"toy-formation": "FAILED", "toy-format": "FAILED", "toy-bp": "PASSED", "toy-sparse": "FAILED"}
    if not _installed("cvxpy", "nlopt"):  # the sparse cases skip without them
        del want["toy-sparse"]
    assert outcomes == want, run.stdout[-3000:] + run.stderr[-2000:]


def _installed(*names: str) -> bool:
    import importlib.util

    return all(importlib.util.find_spec(n) is not None for n in names)
