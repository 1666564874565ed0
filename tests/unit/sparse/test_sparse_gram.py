"""The working-set solver of complex BPDN (:mod:`clsas.sparse.gram`): FISTA with a Newton polish
on the support, against the conic reference and against FISTA alone (iteration counts, never
times)."""

import numpy as np
import pytest

import clsas
from clsas.sparse.atoms import Atom
from clsas.sparse.gram import as_pairs, atom_magnitudes, fista_gram, newton_polish

FS = 96e3


def _problem(seed=0, k=40, n=300):
    """A coherent working set: ``k`` complex atoms half a sample apart around three echoes."""
    rng = np.random.default_rng(seed)
    chirp = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.2)
    at = Atom(chirp, FS, n, complex=True)
    taus = (100 + 0.5 * np.arange(k)) / FS
    D = at.matrix(taus)
    truth = at.matrix(np.array([104.3, 110.8, 118.2]) / FS) @ np.array([1.0, 0.6j, -0.4])
    b = truth + 0.05 * (rng.normal(size=n) + 1j * rng.normal(size=n))
    G, c = D.conj().T @ D, D.conj().T @ b
    lam = 0.1 * 2 * np.abs(c).max()
    return G, c, float(np.vdot(b, b).real), lam


def _objective(G, c, bb, lam, x, amplitudes="complex"):
    return float(bb + np.vdot(x, G @ x).real - 2 * np.vdot(c, x).real + lam * atom_magnitudes(x, amplitudes).sum())


def _kkt(G, c, lam, x):
    """Largest violation of the optimality conditions: on the support ``c - G x = lam/2 x/|x|``,
    off it ``|c - G x| <= lam/2``; relative to lam/2."""
    g = c - G @ x
    on = np.abs(x) > 0
    v_on = np.abs(g[on] - lam / 2 * x[on] / np.abs(x[on])).max(initial=0.0)
    v_off = np.maximum(np.abs(g[~on]) - lam / 2, 0).max(initial=0.0)
    return max(v_on, v_off) / (lam / 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_polished_fista_matches_the_conic_reference_in_far_fewer_steps(seed):
    cp = pytest.importorskip("cvxpy", reason="cvxpy is an optional dependency (pip install 'clsas[sparse]')")
    G, c, bb, lam = _problem(seed)
    x0 = np.zeros(len(c), complex)
    x, it = fista_gram(G, c, bb, lam, "complex", x0, 1e-9, 200_000)
    # FISTA alone does not certify 1e-9 in 200,000 steps on these (measured); 20,000 suffice to show it
    x_plain, it_plain = fista_gram(G, c, bb, lam, "complex", x0, 1e-9, 20_000, polish=False)
    # the reference: the same quadratic through a Cholesky factor of G
    L = np.linalg.cholesky(G + 1e-12 * np.trace(G).real / len(c) * np.eye(len(c)))
    z = cp.Variable(len(c), complex=True)
    w = np.linalg.solve(L, c)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(L.conj().T @ z - w) + lam * cp.sum(cp.abs(z))))
    prob.solve(solver="CLARABEL")
    f_ref = _objective(G, c, bb, lam, np.asarray(z.value))
    f = _objective(G, c, bb, lam, x)
    assert f <= f_ref * (1 + 1e-6)
    assert _kkt(G, c, lam, x) < 1e-3
    assert _objective(G, c, bb, lam, x_plain) >= f * (1 - 1e-9)
    assert it <= 500 and it * 10 <= it_plain, (it, it_plain)


def test_newton_polish_never_raises_the_objective_and_reaches_optimality_on_the_right_support():
    G, c, bb, lam = _problem(3)
    x_opt, _ = fista_gram(G, c, bb, lam, "complex", np.zeros(len(c), complex), 1e-10, 20_000)
    rng = np.random.default_rng(4)
    for _ in range(20):  # arbitrary points: never uphill
        x = np.where(rng.uniform(size=len(c)) < 0.3, rng.normal(size=len(c)) + 1j * rng.normal(size=len(c)), 0)
        xp = newton_polish(G, c, lam, x, "complex")
        assert _objective(G, c, bb, lam, xp) <= _objective(G, c, bb, lam, x) * (1 + 1e-12)
    # from the optimum's support with wrong values: optimal to the KKT conditions' precision
    on = np.abs(x_opt) > 0
    start = np.where(on, x_opt * 1.5 + 0.1 * np.abs(x_opt).max(), 0)
    xp = newton_polish(G, c, lam, start, "complex")
    assert _kkt(G, c, lam, xp) < 1e-6
    np.testing.assert_allclose(xp, x_opt, atol=1e-5 * np.abs(x_opt).max())


def test_pairs_layout_is_the_complex_problem():
    G, c, bb, lam = _problem(5)
    G2, c2, _ = as_pairs(G, c, np.zeros(len(c), complex))
    k = len(c)
    x, _ = fista_gram(G, c, bb, lam, "complex", np.zeros(k, complex), 1e-10, 200_000)
    u, _ = fista_gram(G2, c2, bb, lam, "pairs", np.zeros(2 * k), 1e-10, 200_000)
    assert _objective(G2, c2, bb, lam, u, "pairs") == pytest.approx(_objective(G, c, bb, lam, x), rel=1e-8)
    np.testing.assert_allclose(u[:k] + 1j * u[k:], x, atol=1e-4 * np.abs(x).max())


def test_newton_polish_refuses_other_amplitude_models():
    G, c, _, lam = _problem(0, k=5)
    with pytest.raises(ValueError, match="amplitudes"):
        newton_polish(G.real, c.real, lam, np.ones(5), "positive")
