"""Transducer beams in the model-based operator: the forward projector weights each
voxel-measurement pair as beam-weighted backprojection does, so it stays the exact adjoint; the kernel's
-DBEAM variant against its twin, the operator's A^H against clsas.backproject, the methods' default
choice, validation by name, and Oclgrind on the BEAM build of kernels/project.cl."""

import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from conftest import BACKENDS, ROOT, TESTS, needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.formation import bp_numpy
from clsas.inverse import ImagingOperator
from clsas.inverse import project_numpy as twin
from clsas.inverse.methods import check_options
from clsas.physics.beam import Beams, Cone, Piston, beam_weights, gate_level

MODES = ["weighted", "limited"]


def _scene(rng, n_meas=7, n_lags=50):
    """A jittered bistatic geometry over a 6 x 3 x 5 grid (a window that cuts it), a speed of sound and
    t0 per measurement, and beams: a piston speaker and a cone microphone, boresights tilted per
    measurement so that some pairs are in and some out of the beams."""
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 6), np.linspace(-0.03, 0.03, 3), np.linspace(0.3, 0.5, 5))
    tx = np.c_[rng.uniform(-0.2, 0.2, (n_meas, 2)), rng.uniform(-0.01, 0.01, n_meas)]
    rx = tx + [0.03, 0.01, 0]
    c = rng.uniform(338, 348, n_meas)
    fs = 48e3
    path = np.linalg.norm([0, 0, 0.4] - tx, axis=1) + np.linalg.norm([0, 0, 0.4] - rx, axis=1)
    tau0 = path / c - (n_lags // 2) / fs + rng.uniform(-3, 3, n_meas) / fs
    tilt = np.c_[rng.uniform(-0.3, 0.3, (n_meas, 2)), np.ones(n_meas)]
    beams = Beams(Piston(0.04), Cone(20.0), tilt, (0.0, 0.0, 1.0), n_meas)
    return grid, tx, rx, c, tau0, 1 / fs, beams


def _profiles(rng, n_meas=7, n_lags=50):
    grid, tx, rx, c, tau0, dtau, beams = _scene(rng, n_meas, n_lags)
    data = rng.normal(size=(n_meas, n_lags)) + 1j * rng.normal(size=(n_meas, n_lags))
    prof = clsas.Profiles(data, tau0, dtau, 25e3, "matched", "numpy", tx, rx, c)
    return replace(prof, beams=beams), grid


def _weights(rng, mode):
    grid, tx, rx, c, tau0, dtau, beams = _scene(rng)
    return grid, tx, rx, c, tau0, dtau, beam_weights(beams, mode, 25e3, c, -12.0)


@pytest.mark.parametrize("mode", MODES)
def test_weighted_twin_is_the_exact_adjoint_of_the_weighted_backprojection_twin(rng, mode):
    grid, tx, rx, c, tau0, dtau, w = _weights(rng, mode)
    pts = grid.points()
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    y = rng.normal(size=(7, 50)) + 1j * rng.normal(size=(7, 50))
    ax = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, pts, beam=w)
    bty = bp_numpy.backproject(y, tau0, dtau, 25e3, tx, rx, c, pts, beam=w)
    lhs, rhs = np.vdot(y, ax), np.vdot(bty, x)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    # the weight acts: the projection differs from the omnidirectional one, and is no larger
    omni = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, pts)
    assert np.abs(ax - omni).max() > 0.05 * np.abs(omni).max()
    # the weight is the one of the pair: one voxel, one measurement, its pair_weights times the omni profile
    e = np.zeros(grid.size, complex)
    e[17] = 1.0
    one = twin.project(e, tau0, dtau, 50, 25e3, tx, rx, c, pts, beam=w)
    bare = twin.project(e, tau0, dtau, 50, 25e3, tx, rx, c, pts)
    from clsas.physics.beam import pair_weights

    for m in range(7):
        pw = pair_weights(w.luts, tx[m], rx[m], w.tx_dir[m], w.rx_dir[m], pts[17:18], w.gate)[0]
        np.testing.assert_allclose(one[m], pw * bare[m], rtol=0, atol=1e-14)


@needs_opencl
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_weighted_kernel_equals_its_twin(rng, vec, mode):
    from clsas import cl
    from clsas.inverse.project_opencl import ProjectPlan, beam_selftest

    width_or_skip("project", vec)
    assert beam_selftest(cl.get_queue(), vec, mode) < 1e-4
    grid, tx, rx, c, tau0, dtau, w = _weights(rng, mode)
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    plan = ProjectPlan(grid, 7, 50, vec=vec, chunk=3, n_items=2, beam_lut=w.luts.shape[1])
    got = plan(x, tau0, dtau, 25e3, tx, rx, c, beam=w)
    want = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, grid.points(), beam=w)
    assert np.abs(got - want).max() <= 1e-4 * np.abs(want).max()
    with pytest.raises(ValueError, match="beam"):
        plan(x, tau0, dtau, 25e3, tx, rx, c)  # a BEAM plan needs the weights


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("with_pulse", [False, True], ids=["no-pulse", "pulse"])
def test_beam_operator_passes_the_dot_product_test(rng, backend, mode, with_pulse):
    prof, grid = _profiles(rng)
    pulse = (rng.normal(size=9) + 1j * rng.normal(size=9)) if with_pulse else None
    A = ImagingOperator(prof, grid, pulse=pulse, backend=backend, beam=mode)
    assert A.backend == backend and A.weights is not None
    assert (A.weights.gate is None) == (mode == "weighted")
    x = rng.normal(size=A.shape[1]) + 1j * rng.normal(size=A.shape[1])
    y = rng.normal(size=A.shape[0]) + 1j * rng.normal(size=A.shape[0])
    lhs, rhs = np.vdot(y, A.matvec(x)), np.vdot(A.rmatvec(y), x)
    tol = 1e-12 if backend == "numpy" else 1e-5  # float64 twins; float32 kernels
    assert abs(lhs - rhs) <= tol * abs(lhs)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", [None, *MODES], ids=["default", *MODES])
def test_rmatvec_is_the_beam_weighted_backprojection(rng, backend, mode):
    prof, grid = _profiles(rng)
    A = ImagingOperator(prof, grid, backend=backend, beam=mode)
    y = rng.normal(size=A.shape[0]) + 1j * rng.normal(size=A.shape[0])
    img = clsas.backproject(replace(prof, data=y.reshape(7, 50)), grid, backend=backend, beam=mode)
    np.testing.assert_allclose(A.rmatvec(y), img.values.ravel(), rtol=0, atol=2e-5 * np.abs(img.values).max())
    omni = clsas.backproject(replace(prof, data=y.reshape(7, 50)), grid, backend=backend, beam="none")
    assert np.abs(img.values - omni.values).max() > 0.05 * np.abs(omni.values).max()  # the beams act


def test_operator_takes_bps_default_beam(rng):
    prof, grid = _profiles(rng)
    limited = ImagingOperator(prof, grid, backend="numpy")
    assert limited.weights is not None and limited.weights.gate == pytest.approx(gate_level(-12.0))
    six = ImagingOperator(prof, grid, backend="numpy", beam_floor_db=-6.0)
    assert six.weights.gate == pytest.approx(gate_level(-6.0))
    assert ImagingOperator(prof, grid, backend="numpy", beam="none").weights is None
    assert ImagingOperator(replace(prof, beams=None), grid, backend="numpy").weights is None
    omni = Beams("omni", "omni", (0, 0, 1), (0, 0, 1), 7)
    assert ImagingOperator(prof, grid, backend="numpy", beams=omni).weights is None


def test_beam_options_are_validated_by_name(rng):
    prof, grid = _profiles(rng)
    with pytest.raises(ValueError, match="beam"):
        ImagingOperator(prof, grid, backend="numpy", beam="gated")
    with pytest.raises(ValueError, match="beam_floor_db"):
        ImagingOperator(prof, grid, backend="numpy", beam_floor_db=float("nan"))
    with pytest.raises(TypeError, match="beams"):
        ImagingOperator(prof, grid, backend="numpy", beams="cone")
    with pytest.raises(ValueError, match="beams must have 7 boresights"):
        ImagingOperator(prof, grid, backend="numpy", beams=prof.beams.subset(slice(0, 3)))
    with pytest.raises(ValueError, match=r"inverse\['beam'\]"):
        check_options({"beam": "gated"})
    with pytest.raises(ValueError, match=r"inverse\['beam_floor_db'\]"):
        check_options({"beam_floor_db": float("inf")})
    assert check_options({"beam": "weighted"})["beam"] == "weighted"
    assert check_options(None)["beam"] is None


def test_model_based_methods_use_the_choice_bp_would(monkeypatch):
    """reconstruct(method=...) builds its operator with the dataset's beams: beam-limited by default
    (as bp), weighted or none when the inverse options say so."""
    from clsas.inverse import methods

    made = []

    class Spy(ImagingOperator):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(methods, "ImagingOperator", Spy)
    ds = small_dataset([[0.0, 0.0, 0.5]], nx=3, ny=3, width=0.1, height=0.1)
    ds = replace(ds, beams=Beams(Cone(30.0), Cone(30.0), (0, 0, 1), (0, 0, 1), ds.n_meas))
    grid = clsas.VoxelGrid(np.linspace(-0.05, 0.05, 3), np.array([0.0]), np.linspace(0.48, 0.52, 3))
    gates = []
    for inverse in (None, {"beam": "weighted"}, {"beam": "none"}):
        made.clear()
        clsas.reconstruct(ds, grid, method="psf", backend="numpy", inverse=inverse)
        assert made, "the method built no ImagingOperator"
        w = made[-1].weights
        gates.append("none" if w is None else ("weighted" if w.gate is None else w.gate))
    assert gates[0] == pytest.approx(gate_level(-12.0)) and gates[1:] == ["weighted", "none"]


def test_offgrid_point_model_carries_the_same_pair_weights(rng):
    """The off-grid method's continuous point model weights each measurement's echo by the operator's
    beam weight of that pair (the ADCG fit and the grid operator see the same beams)."""
    from clsas.inverse.offgrid import PointModel
    from clsas.physics.beam import pair_weights

    prof, grid = _profiles(rng)
    wave = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    pos = np.array([[0.02, 0.0, 0.41]])
    cols = {}
    for mode in ("none", "weighted"):
        A = ImagingOperator(prof, grid, backend="numpy", beam=mode)
        cols[mode] = PointModel(A, wave, 96e3).columns(pos)[:, 0].reshape(7, 50)
    w = A.weights
    pw = [pair_weights(w.luts, A.tx[m], A.rx[m], w.tx_dir[m], w.rx_dir[m], pos, None)[0] for m in range(7)]
    assert np.ptp(pw) > 0.1  # the measurements see the point at different weights
    np.testing.assert_allclose(cols["weighted"], np.array(pw)[:, None] * cols["none"], rtol=1e-12, atol=1e-15)


@pytest.mark.oclgrind
@pytest.mark.slow
def test_beam_projector_runs_clean_under_oclgrind():
    from conftest import OCLGRIND_DIAGNOSTICS as DIAGNOSTICS
    from conftest import oclgrind_missing as _oclgrind_available

    why = _oclgrind_available()
    if why is not None:
        pytest.skip(why)
    for checks in ({"OCLGRIND_DATA_RACES": "1"}, {"OCLGRIND_UNINITIALIZED": "1"}):
        for vec in (4, 8):
            env = dict(os.environ, **checks)
            paths = [str(ROOT), str(TESTS)]  # the child imports clsas and conftest.py
            env["PYTHONPATH"] = os.pathsep.join([*paths, *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])])
            res = subprocess.run([sys.executable, __file__, str(vec)], capture_output=True, text=True, env=env,
                                 timeout=600)
            assert res.returncode == 0 and "oclgrind run ok" in res.stdout, f"{res.stdout}\n{res.stderr[-4000:]}"
            found = [d for d in DIAGNOSTICS if d in res.stderr]
            assert not found, f"Oclgrind reported {found} ({checks}, VEC={vec}):\n{res.stderr[-4000:]}"


def _main(vec: int) -> int:
    """The child: the BEAM build of project.cl (weighted and limited) on the Oclgrind device."""
    import pyopencl as cl

    from clsas.inverse.project_opencl import beam_selftest

    plats = [p for p in cl.get_platforms() if "Oclgrind" in p.name]
    if not plats:
        print("no Oclgrind platform", file=sys.stderr)
        return 3
    queue = cl.CommandQueue(cl.Context(plats[0].get_devices()),
                            properties=cl.command_queue_properties.PROFILING_ENABLE)
    for mode in MODES:
        err = beam_selftest(queue, vec, mode)
        assert err < 1e-4, f"project beam {mode} VEC={vec}: {err:.3g} of the peak"
    print("oclgrind run ok")
    return 0


if __name__ == "__main__":
    sys.exit(_main(int(sys.argv[1]) if len(sys.argv) > 1 else 4))
