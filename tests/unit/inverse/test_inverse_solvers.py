"""The solvers of clsas.inverse lower their objectives as their theory says, on small problems; the
noise-level weight leaves pure noise without a reflector."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import small_dataset
from scipy.sparse.linalg import aslinearoperator

import clsas
from clsas.inverse import solvers


@pytest.fixture
def problem(rng):
    M = rng.normal(size=(80, 48)) + 1j * rng.normal(size=(80, 48))
    x = np.zeros(48, complex)
    x[[5, 30]] = [3.0, -2j]
    b = M @ x + 0.05 * (rng.normal(size=80) + 1j * rng.normal(size=80))
    return aslinearoperator(M), M, b


def test_cgls_reaches_least_squares_with_a_falling_residual(problem):
    A, M, b = problem
    res = solvers.cgls(A, b, max_iter=200, tol=1e-10)
    np.testing.assert_allclose(res.x, np.linalg.lstsq(M, b, rcond=None)[0], atol=1e-8)
    assert np.all(np.diff(res.objective) <= 1e-12 * res.objective[0])  # CGLS: ||r|| never rises
    assert res.stopped == "tolerance" and res.n_forward == res.iterations + 1


def test_cgls_stops_at_the_discrepancy(problem):
    A, M, b = problem
    target = 0.5 * np.linalg.norm(b)
    res = solvers.cgls(A, b, max_iter=200, residual_norm=target)
    assert res.stopped == "discrepancy" and np.sqrt(2 * res.objective[-1]) <= target
    assert np.sqrt(2 * res.objective[-2]) > target  # the first iterate that reaches it


def test_fista_l1_meets_the_optimality_conditions(problem):
    """Monotone objective; at the end the KKT conditions of the complex lasso hold: A^H r = lam x/|x| on
    the support and |A^H r| <= lam off it."""
    A, M, b = problem
    lam = 5.0
    res = solvers.fista(A, b, lam_l1=lam, max_iter=3000, tol=1e-10)
    assert np.all(np.diff(res.objective) <= 0)
    g = M.conj().T @ (b - M @ res.x)
    on = np.abs(res.x) > 1e-6
    assert set(np.flatnonzero(on)) == {5, 30}
    np.testing.assert_allclose(g[on], lam * res.x[on] / np.abs(res.x[on]), rtol=1e-4)
    assert np.all(np.abs(g[~on]) <= lam * (1 + 1e-6))
    # the rate: F(x_k) - F* <= 2 L ||x0 - x*||^2 / (k + 1)^2 (Beck and Teboulle, theorem 4.4)
    L = 1.02 * np.linalg.norm(M, 2) ** 2
    f_star = res.objective[-1]
    bound = [2 * L * np.linalg.norm(res.x) ** 2 / (k + 1) ** 2 for k in range(1, len(res.objective))]
    assert all(f - f_star <= bd + 1e-9 for f, bd in zip(res.objective[1:], bound, strict=False))


def test_tv_prox_is_the_minimiser(rng):
    """The prox of TV at u is no worse than any perturbation of it (a convex problem: a local check is
    a global one)."""
    u = rng.normal(size=(6, 1, 5))
    w = 0.4
    p = solvers.tv_prox(u, w, n_iter=500)

    def f(z):
        return 0.5 * np.sum((z - u) ** 2) + w * solvers.tv(z)

    for _ in range(50):
        assert f(p) <= f(p + 1e-3 * rng.normal(size=u.shape)) + 1e-9
    assert solvers.tv(p) < solvers.tv(u)
    np.testing.assert_allclose(solvers.tv_prox(np.full((4, 4), 2.0), 1.0), 2.0)  # a constant is kept


@pytest.mark.parametrize("lam_l1, lam_tv", [(0.0, 0.5), (1.0, 1.0)], ids=["tv", "l1-tv"])
def test_fista_with_tv_lowers_its_objective(rng, lam_l1, lam_tv):
    """Monotone, and it ends below the objective of the truth and of the least-squares solution (an
    under-determined problem: 30 equations, 40 unknowns)."""
    M = rng.normal(size=(30, 40)) + 1j * rng.normal(size=(30, 40))
    x = np.zeros((5, 8))
    x[1:4, 2:6] = 1.0  # a flat patch: what TV likes
    b = M @ x.ravel() + 0.1 * rng.normal(size=30)

    def f(z):
        r = M @ z - b
        return 0.5 * np.vdot(r, r).real + lam_l1 * np.abs(z).sum() + lam_tv * solvers.tv(np.abs(z).reshape(5, 8))

    res = solvers.fista(aslinearoperator(M), b, lam_l1=lam_l1, lam_tv=lam_tv, shape=(5, 8), max_iter=300, tol=1e-8)
    assert np.all(np.diff(res.objective) <= 0)
    assert res.objective[-1] == pytest.approx(f(res.x))
    assert res.objective[-1] < min(f(x.ravel()), f(np.linalg.lstsq(M, b, rcond=None)[0]))


def test_solvers_reject_bad_input(problem):
    A, M, b = problem
    with pytest.raises(TypeError, match="LinearOperator"):
        solvers.cgls(M, b)
    with pytest.raises(ValueError, match="b must have"):
        solvers.cgls(A, b[:-1])
    with pytest.raises(ValueError, match="finite"):
        solvers.fista(A, np.full_like(b, np.nan))
    with pytest.raises(ValueError, match="x0"):
        solvers.fista(A, b, np.ones(3))
    with pytest.raises(ValueError, match="lam_l1"):
        solvers.fista(A, b, lam_l1=-1)
    with pytest.raises(ValueError, match="shape"):
        solvers.fista(A, b, lam_tv=1, shape=(7, 7))
    with pytest.raises(ValueError, match="max_iter"):
        solvers.cgls(A, b, max_iter=0)
    with pytest.raises(ValueError, match="residual_norm"):
        solvers.cgls(A, b, residual_norm=-1)


@pytest.mark.slow
def test_noise_level_weight_puts_no_reflector_on_pure_noise():
    """Pure noise recordings (20 seeds), weight from the noise-level rule: the L1 image is empty in
    at least 95 % of draws."""
    base = small_dataset([[0.0, 0.0, 0.5]], nx=7, ny=1, width=0.3, height=0.0)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (0, 0), (0.45, 0.55), 0.005)
    empty = 0
    for seed in range(20):
        noise = np.random.default_rng(seed).normal(size=base.signals.shape)
        image = clsas.reconstruct(replace(base, signals=noise), grid, method="l1", backend="numpy",
                                  inverse={"seed": seed, "max_iter": 20})
        empty += int(np.all(image.values == 0))
    assert empty >= 19, f"{empty} of 20 noise draws gave an empty image"


def test_noise_level_weight_keeps_a_clear_reflector():
    data = small_dataset([[0.0, 0.0, 0.5]], nx=7, ny=1, width=0.3, height=0.0, snr_db=10)
    grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (0, 0), (0.45, 0.55), 0.005)
    image = clsas.reconstruct(data, grid, method="l1", backend="numpy")
    assert np.count_nonzero(image.values) >= 1
    assert np.linalg.norm(image.peaks(1)[0].position_m - [0, 0, 0.5]) <= 0.0051
