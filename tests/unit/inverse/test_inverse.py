"""The forward projector (kernels/project.cl and its twin), the imaging operator and the model-based
methods of clsas.inverse."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import BACKENDS, needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.formation import bp_numpy
from clsas.inverse import ImagingOperator, compressed_pulse
from clsas.inverse import project_numpy as twin
from clsas.inverse.methods import INVERSE_OPTIONS, check_options


def _scene(rng, n_meas=7, n_lags=50):
    """A jittered bistatic geometry over a 6 x 3 x 5 grid, a speed of sound and t0 per measurement,
    a window that cuts the grid (voxels in and out of it)."""
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 6), np.linspace(-0.03, 0.03, 3), np.linspace(0.3, 0.5, 5))
    tx = np.c_[rng.uniform(-0.2, 0.2, (n_meas, 2)), rng.uniform(-0.01, 0.01, n_meas)]
    rx = tx + [0.03, 0.01, 0]
    c = rng.uniform(338, 348, n_meas)
    fs = 48e3
    path = np.linalg.norm([0, 0, 0.4] - tx, axis=1) + np.linalg.norm([0, 0, 0.4] - rx, axis=1)
    tau0 = path / c - (n_lags // 2) / fs + rng.uniform(-3, 3, n_meas) / fs
    return grid, tx, rx, c, tau0, 1 / fs


def _profiles(rng, n_meas=7, n_lags=50):
    grid, tx, rx, c, tau0, dtau = _scene(rng, n_meas, n_lags)
    data = rng.normal(size=(n_meas, n_lags)) + 1j * rng.normal(size=(n_meas, n_lags))
    return clsas.Profiles(data, tau0, dtau, 25e3, "matched", "numpy", tx, rx, c), grid


def test_twin_is_the_exact_adjoint_of_the_backprojection_twin(rng):
    grid, tx, rx, c, tau0, dtau = _scene(rng)
    pts = grid.points()
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    y = rng.normal(size=(7, 50)) + 1j * rng.normal(size=(7, 50))
    ax = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, pts)
    bty = bp_numpy.backproject(y, tau0, dtau, 25e3, tx, rx, c, pts)
    lhs, rhs = np.vdot(y, ax), np.vdot(bty, x)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)
    assert np.any(ax == 0) and np.any(ax != 0)  # lags no voxel reaches, and lags some do


def test_twin_puts_a_voxel_on_its_delay_with_the_conjugate_carrier():
    grid = clsas.VoxelGrid(np.array([0.0]), np.array([0.0]), np.array([0.5]))
    tx = rx = np.zeros((1, 3))
    c, fc, dtau = 343.0, 25e3, 1e-5
    tau = 1.0 / c
    k = 30.25
    tau0 = np.array([tau - k * dtau])
    p = twin.project(np.array([2.0 + 0j]), tau0, dtau, 64, fc, tx, rx, c, grid.points())[0]
    phase = np.exp(-2j * np.pi * fc * tau)
    np.testing.assert_allclose(p[30], 2 * 0.75 * phase, rtol=1e-9)
    np.testing.assert_allclose(p[31], 2 * 0.25 * phase, rtol=1e-9)
    assert np.count_nonzero(p) == 2


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("chunk, n_items", [(None, None), (3, 2), (7, 5)], ids=["default", "chunks3-items2",
                                                                              "chunk7-items5"])
def test_kernel_equals_twin(rng, vec, chunk, n_items):
    from clsas.inverse.project_opencl import ProjectPlan

    width_or_skip("project", vec)
    grid, tx, rx, c, tau0, dtau = _scene(rng)
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    plan = ProjectPlan(grid, 7, 50, vec=vec, chunk=chunk, n_items=n_items)
    got = plan(x, tau0, dtau, 25e3, tx, rx, c)
    want = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, grid.points())
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-4 * np.abs(want).max()
    again = plan(x, tau0, dtau, 25e3, tx, rx, c)  # the partial copies are overwritten, not added to
    np.testing.assert_array_equal(again, got)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_kernels_on_coarse_profiles_equal_twins_and_stay_adjoint(rng, vec):
    """Profiles of 1.3 carrier cycles per sample (both plans upsample them for the carrier):
    the projection equals its twin, and projection and backprojection pass the dot-product test."""
    from clsas.formation import bp_numpy
    from clsas.formation.bp_opencl import BackprojectPlan
    from clsas.inverse.project_opencl import ProjectPlan

    width_or_skip("project", vec)
    width_or_skip("backproject", vec)
    grid, tx, rx, c, tau0, _ = _scene(rng)
    dtau = 1.3 / 25e3
    x = rng.normal(size=grid.size) + 1j * rng.normal(size=grid.size)
    y = rng.normal(size=(7, 50)) + 1j * rng.normal(size=(7, 50))
    ax = ProjectPlan(grid, 7, 50, vec=vec, chunk=3, n_items=2)(x, tau0, dtau, 25e3, tx, rx, c)
    want = twin.project(x, tau0, dtau, 50, 25e3, tx, rx, c, grid.points())
    assert np.abs(ax - want).max() <= 1e-4 * np.abs(want).max()
    ahy = BackprojectPlan(grid, 7, 50, vec=vec, chunk=3)(y, tau0, dtau, 25e3, tx, rx, c)
    want_bp = bp_numpy.backproject(y, tau0, dtau, 25e3, tx, rx, c, grid.points())
    assert np.abs(ahy - want_bp).max() <= 1e-4 * np.abs(want_bp).max()
    lhs, rhs = np.vdot(y, ax), np.vdot(ahy, x)
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("with_pulse", [False, True], ids=["no-pulse", "pulse"])
def test_operator_passes_the_dot_product_test(rng, backend, with_pulse):
    prof, grid = _profiles(rng)
    pulse = (rng.normal(size=9) + 1j * rng.normal(size=9)) if with_pulse else None
    A = ImagingOperator(prof, grid, pulse=pulse, backend=backend)
    assert A.backend == backend and A.shape == (7 * 50, grid.size)
    x = rng.normal(size=A.shape[1]) + 1j * rng.normal(size=A.shape[1])
    y = rng.normal(size=A.shape[0]) + 1j * rng.normal(size=A.shape[0])
    lhs, rhs = np.vdot(y, A.matvec(x)), np.vdot(A.rmatvec(y), x)
    tol = 1e-12 if backend == "numpy" else 1e-5  # float64 twin; float32 kernels
    assert abs(lhs - rhs) <= tol * abs(lhs)
    # A.H is the adjoint as an operator (scipy's composition, e.g. in a masked model, goes through it)
    AH = A.H
    assert AH.shape == (A.shape[1], A.shape[0]) and AH.dtype == np.complex128
    np.testing.assert_allclose(AH @ y, A.rmatvec(y), rtol=0, atol=1e-12 * np.abs(A.rmatvec(y)).max())
    np.testing.assert_allclose(AH.H @ x, A.matvec(x), rtol=0, atol=1e-12 * np.abs(A.matvec(x)).max())
    # A^H without a pulse is the backprojection
    if not with_pulse:
        img = clsas.backproject(replace(prof, data=y.reshape(7, 50)), grid, backend=backend)
        np.testing.assert_allclose(A.rmatvec(y), img.values.ravel(), rtol=0, atol=2e-5 * np.abs(img.values).max())


def test_compressed_pulse_models_a_simulated_point_echo():
    """The operator's echo of one voxel (projector + compressed pulse) fits clsas.simulate's to 10 %."""
    data = small_dataset([[0.0, 0.0, 0.5]], nx=5, ny=5, width=0.3, height=0.3)
    grid = clsas.VoxelGrid(np.array([0.0]), np.array([0.0]), np.array([0.5]))
    prof = clsas.compress(data, backend="numpy", gate_s=(0.9 / 343, 1.1 / 343))
    pulse = compressed_pulse(data.waveform, data.fs_hz, prof.dtau_s, prof.fc_hz)
    assert len(pulse) % 2 == 1 and np.argmax(np.abs(pulse)) == len(pulse) // 2
    A = ImagingOperator(prof, grid, pulse=pulse, backend="numpy")
    m = A.matvec(np.ones(1)).reshape(prof.data.shape)
    alpha = np.vdot(m, prof.data) / np.vdot(m, m)
    assert abs(alpha.imag) < 1e-2 * abs(alpha.real) and alpha.real > 0  # same carrier convention
    assert np.linalg.norm(prof.data - alpha * m) < 0.1 * np.linalg.norm(prof.data)


def test_psf_deconvolution_undoes_a_known_blur(rng):
    from clsas.inverse.psf import wiener

    x = np.zeros((16, 1, 12), complex)
    x[5, 0, 4], x[9, 0, 7] = 1.0, 0.5j
    g = np.exp(-0.5 * ((np.arange(16)[:, None] - 8) ** 2 / 1.5 + (np.arange(12)[None] - 6) ** 2 / 1.0))
    psf = g[:, None, :] / g.max()
    kernel = np.roll(np.pad(psf, ((0, 16), (0, 0), (0, 12))), (-8, 0, -6), (0, 1, 2))
    spectrum = np.fft.fftn(x, (32, 1, 24), axes=(0, 1, 2)) * np.fft.fftn(kernel)
    blurred = np.fft.ifftn(spectrum)[:16, :, :12]
    sharp = wiener(blurred, psf, snr_db=120)
    assert np.abs(sharp - x).max() < 0.05 < np.abs(blurred - x).max()
    with pytest.raises(ValueError, match="psf shape"):
        wiener(blurred, psf[:3])


def test_operator_rejects_bad_input(rng):
    prof, grid = _profiles(rng)
    with pytest.raises(TypeError, match="profiles"):
        ImagingOperator(prof.data, grid)
    with pytest.raises(TypeError, match="grid"):
        ImagingOperator(prof, (1, 2, 3))
    with pytest.raises(ValueError, match="tx_positions"):
        ImagingOperator(replace(prof, tx_positions=None), grid)
    with pytest.raises(ValueError, match="pulse"):
        ImagingOperator(prof, grid, pulse=np.ones(4))
    with pytest.raises(ValueError, match="pulse"):
        ImagingOperator(prof, grid, pulse=np.array([1.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="c_mps"):
        ImagingOperator(replace(prof, c_mps=-1.0), grid)
    with pytest.raises(ValueError, match="lags"):
        ImagingOperator(replace(prof, data=prof.data[:, :1]), grid)


@pytest.mark.parametrize("options, error, match", [
    ({"bogus": 1}, ValueError, "unknown option"),
    ({"lam": -1.0}, ValueError, "lam"),
    ({"lam_tv": np.nan}, ValueError, "lam_tv"),
    ({"noise_std": -2}, ValueError, "noise_std"),
    ({"tv_ratio": -0.1}, ValueError, "tv_ratio"),
    ({"max_iter": 0}, ValueError, "max_iter"),
    ({"tol": 0}, ValueError, "tol"),
    ({"warm_start": "fbp"}, ValueError, "warm_start"),
    ({"pulse": "yes"}, TypeError, "pulse"),
    ({"tv_iter": 0}, ValueError, "tv_iter"),
    ({"n_draws": 0}, ValueError, "n_draws"),
    ({"delta": 1.5}, ValueError, "delta"),
    ({"seed": 1.5}, TypeError, "seed"),
    ({"psf_snr_db": np.inf}, ValueError, "psf_snr_db"),
    ("lam=1", TypeError, "inverse"),
], ids=lambda p: p if isinstance(p, str) else None)
def test_every_option_is_validated(options, error, match):
    with pytest.raises(error, match=match):
        check_options(options)


def test_defaults_are_complete():
    assert check_options(None).keys() == INVERSE_OPTIONS.keys()


def test_reconstruct_rejects_misused_inverse_options():
    data = small_dataset([[0.0, 0.0, 0.5]], nx=3, ny=3)
    grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (0, 0), (0.48, 0.52), 0.01)
    with pytest.raises(ValueError, match="inverse"):
        clsas.reconstruct(data, grid, method="bp", inverse={"lam": 1.0})
    with pytest.raises(ValueError, match="unknown option"):
        clsas.reconstruct(data, grid, method="l1", inverse={"lamb": 1.0})
    with pytest.raises(ValueError, match="formation"):
        clsas.reconstruct(data, grid, method="l1", formation="ffbp")
    with pytest.raises(ValueError, match="tiles"):
        clsas.reconstruct(data, grid, method="ls", tile_shape=(2, 1, 2))
    from clsas.pipeline.reconstruction import methods

    assert {"ls", "l1", "tv", "l1-tv"} <= set(methods())


@pytest.mark.parametrize("method", ["ls", "l1", "tv", "l1-tv", "psf"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_model_based_methods_put_a_point_in_its_voxel(method, backend):
    point = np.array([0.01, 0.0, 0.5])
    data = small_dataset([point], nx=9, ny=1, width=0.3, height=0.0, snr_db=20)
    grid = clsas.VoxelGrid.from_bounds((-0.04, 0.04), (0, 0), (0.47, 0.53), 0.005)
    seen = []
    image = clsas.reconstruct(data, grid, method=method, backend=backend, progress=lambda d, t: seen.append((d, t)))
    assert image.method == method and image.backend == backend
    top = image.peaks(1)[0].position_m
    assert np.linalg.norm(top - point) <= 0.0051
    info = image.provenance["inverse"]
    assert info["iterations"] >= 1 and seen
    if method != "psf":
        assert seen[-1][0] == info["iterations"]
    assert info["stopped"] in ("tolerance", "discrepancy", "max_iter", "direct")
    assert image.plan is not None and image.timings_s["total"] > 0


def test_offgrid_resolves_a_pair_at_half_the_cross_range_resolution():
    """Two reflectors 0.5 x the cross-range resolution apart (line aperture, 20 dB): the off-grid
    method finds both within 0.1 x the resolution; backprojection shows one peak."""
    from clsas.inverse.offgrid import reflector_peaks

    fs, R, D = 96e3, 0.6, 0.3
    res = 343.0 / 25e3 * R / (2 * D)
    pts = np.array([[-0.25 * res, 0, R], [0.25 * res, 0, R + 0.001]])
    chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    data = clsas.simulate(clsas.Scene(pts, np.array([0.8, 1.0])), clsas.raster_aperture(31, 1, D, 0.0), chirp, fs,
                          snr_db=20, seed=3)
    grid = clsas.VoxelGrid.from_bounds((-0.03, 0.03), (0, 0), (R - 0.02, R + 0.02), 0.002)
    image = clsas.reconstruct(data, grid, method="offgrid", backend="numpy", inverse={"max_reflectors": 4})
    found = reflector_peaks(image)
    strong = [p for p in found if p.magnitude > 0.3 * found[0].magnitude]
    assert len(strong) == 2
    for truth in pts:
        assert min(np.linalg.norm(p.position_m - truth) for p in strong) < 0.1 * res
    assert np.count_nonzero(image.values) == len(found)
    bp = clsas.reconstruct(data, grid, backend="numpy")
    peaks = bp.peaks(2, min_separation_m=0.3 * res)
    assert len(peaks) < 2 or peaks[1].magnitude < 0.5 * peaks[0].magnitude or \
        abs(peaks[1].position_m[0] - peaks[0].position_m[0]) > res  # no second peak at the pair
    with pytest.raises(ValueError, match="off-grid"):
        reflector_peaks(bp)
