"""Sparse super-resolution: dictionaries, coherence, BPDN (fast against cvxpy), stability."""

import warnings

import numpy as np
import pytest

import clsas
from clsas.sparse import Atom, Dictionary, ShiftOperator, bpdn, bpdn_cvxpy, coherence, decaying_exponential

FS = 96e3
cp = pytest.importorskip("cvxpy", reason="cvxpy is an optional dependency (pip install 'clsas[sparse]')")


@pytest.fixture(scope="module")
def chirp():
    return clsas.lfm_chirp(20e3, 30e3, 1e-3, FS, taper=0.2)


def _noise(rng, n, cplx, scale):
    return scale * (rng.normal(size=n) + (1j * rng.normal(size=n) if cplx else 0))


@pytest.mark.parametrize("cplx", [False, True], ids=["real", "complex"])
@pytest.mark.parametrize("per_sample", [1, 3, 4])
def test_fft_operator_equals_the_dense_dictionary(rng, chirp, cplx, per_sample):
    at = Atom(chirp, FS, 300, complex=cplx)
    d = Dictionary(at, 1 / (per_sample * FS), tau0_s=0.2e-3, n_atoms=250)
    op = ShiftOperator(d)
    assert op.fft
    D = d.matrix()
    x, r = _noise(rng, d.k, cplx, 1.0), _noise(rng, 300, cplx, 1.0)
    np.testing.assert_allclose(op.forward(x), D @ x, atol=1e-10 * np.abs(D @ x).max())
    np.testing.assert_allclose(op.adjoint(r), D.conj().T @ r, atol=1e-10 * np.abs(D.conj().T @ r).max())


def test_sampled_atom_shifts_by_band_limited_interpolation(chirp):
    """A shift by a whole number of samples is the waveform moved; a fractional one is not rounded."""
    at = Atom(chirp, FS, 300)
    col = at.matrix([10 / FS])[:, 0]
    np.testing.assert_allclose(col[10 : 10 + len(chirp)], chirp, atol=1e-9)
    half = at.matrix([10.5 / FS])[:, 0]
    assert np.abs(half - col).max() > 0.1 and np.abs(half - at.matrix([11 / FS])[:, 0]).max() > 0.1
    # derivative: central difference of the shifted atom
    h = 1e-3 / FS
    num = (at.matrix([10 / FS + h]) - at.matrix([10 / FS - h]))[:, 0] / (2 * h)
    np.testing.assert_allclose(at.dmatrix([10 / FS])[:, 0], num, atol=1e-4 * np.abs(num).max())


def test_interpolation_error_falls_as_delta_squared_and_cubed(chirp):
    """Taylor (derivative atoms scaled by Delta/2) errs as Delta^2, polar as Delta^3 (tapered chirp)."""
    at = Atom(clsas.lfm_chirp(20e3, 30e3, 2e-3, FS, taper=0.2), FS, 400)
    taylor, polar = [], []
    deltas = np.array([1 / 2, 1 / 4, 1 / 8, 1 / 16]) / FS
    for dl in deltas:
        d = Dictionary(at, dl, tau0_s=1e-3, n_atoms=1)
        F, G = d.taylor()
        P = d.polar()
        et, ep = 0.0, 0.0
        for frac in np.linspace(-0.5, 0.5, 11):
            f = at.matrix([1e-3 + frac * dl])[:, 0]
            et = max(et, np.linalg.norm(f - F[:, 0] - 2 * frac * G[:, 0]) / at.norm)
            a = 2 * P.theta * frac
            model = P.C[:, 0] + P.r * np.cos(a) * P.U[:, 0] + P.r * np.sin(a) * P.V[:, 0]
            ep = max(ep, np.linalg.norm(f - model) / at.norm)
        taylor.append(et)
        polar.append(ep)
    slope_t = np.polyfit(np.log(deltas), np.log(taylor), 1)[0]
    slope_p = np.polyfit(np.log(deltas), np.log(polar), 1)[0]
    assert slope_t == pytest.approx(2.0, abs=0.15)
    assert slope_p == pytest.approx(3.0, abs=0.15)
    assert polar[0] < taylor[0] / 10


def test_coherence_rises_to_one_as_the_grid_shrinks(chirp):
    at = Atom(chirp, FS, 300)
    mus = [coherence(Dictionary(at, dl / FS, tau0_s=0.5e-3, n_atoms=20)) for dl in (4, 1, 0.25, 0.01)]
    assert all(a < b for a, b in zip(mus, mus[1:], strict=False))
    assert mus[-1] > 0.999
    with pytest.raises(ValueError, match="at least two atoms"):
        coherence(np.ones((5, 1)))


def _two_echoes(at, cplx, rng, snr_scale=0.02, amps=(1.0, 0.7), taus=(1.0e-3, 1.06e-3)):
    b = sum(a * at.matrix([t])[:, 0] for a, t in zip(amps, taus, strict=True))
    return b + _noise(rng, at.n, cplx, snr_scale)


@pytest.mark.parametrize("mode", ["positive", "real", "complex"])
def test_fast_bpdn_matches_cvxpy_objective(rng, chirp, mode):
    cplx = mode == "complex"
    at = Atom(chirp, FS, 200, complex=cplx)
    d = Dictionary(at, 1 / (2 * FS), tau0_s=0.6e-3, n_atoms=100)
    amps = (1.0, -0.6) if mode == "real" else (1.0, 0.7j) if cplx else (1.0, 0.7)
    b = _two_echoes(at, cplx, rng, amps=amps)
    fast = bpdn(d, b, lam_frac=0.1, amplitudes=mode)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = bpdn_cvxpy(d, b, lam=fast.lam, amplitudes=mode)
    assert fast.status == "optimal" and ref.status == "optimal"
    assert abs(fast.objective - ref.objective) <= 1e-6 * ref.objective
    assert fast.gap <= 1e-7 * fast.objective
    # the largest coefficient sits on the stronger echo
    assert abs(d.taus[np.argmax(np.abs(fast.x))] - 1.0e-3) < 1 / FS


@pytest.mark.parametrize("mode", ["positive", "real", "complex"])
def test_lambda_at_or_above_lam_max_gives_exactly_zero(rng, chirp, mode):
    at = Atom(chirp, FS, 200, complex=mode == "complex")
    d = Dictionary(at, 1 / FS, tau0_s=0.5e-3)
    b = _two_echoes(at, mode == "complex", rng)
    for frac in (1.0, 3.0):
        res = bpdn(d, b, lam_frac=frac, amplitudes=mode)
        assert res.status == "optimal" and not np.any(res.x)
    just_below = bpdn(d, b, lam_frac=0.999, amplitudes=mode)
    assert 0 < np.count_nonzero(just_below.x) <= 3
    if mode != "complex":  # lam -> 0: still finite, still certified (complex: see the slow test)
        tiny = bpdn(d, b, lam_frac=1e-4, amplitudes=mode)
        assert np.all(np.isfinite(tiny.x)) and tiny.status == "optimal"


@pytest.mark.parametrize("case", ["zeros", "noise", "dynamic-range", "edges", "opposite-sign"])
def test_bpdn_stability(rng, chirp, case):
    at = Atom(chirp, FS, 200)
    d = Dictionary(at, 1 / (2 * FS), tau0_s=0.0)
    mode = "positive"
    if case == "zeros":
        b = np.zeros(200)
    elif case == "noise":
        b = rng.normal(size=200)
    elif case == "dynamic-range":
        b = _two_echoes(at, False, rng, snr_scale=0.0, amps=(1e6, 1.0), taus=(0.5e-3, 1.2e-3))
    elif case == "edges":  # one echo cut by the window start, one running past its end
        b = _two_echoes(at, False, rng, snr_scale=1e-3, taus=(0.0, 200 / FS - 0.3e-3))
    else:
        mode = "real"
        b = _two_echoes(at, False, rng, snr_scale=1e-3, amps=(1.0, -1.0), taus=(1.0e-3, 1.02e-3))
    res = bpdn(d, b, lam_frac=0.05, amplitudes=mode)
    assert np.all(np.isfinite(res.x)) and np.isfinite(res.objective)
    assert res.status == "optimal", res
    if case == "zeros":
        assert not np.any(res.x) and res.objective == 0.0
    if case == "dynamic-range":
        k = np.argmax(np.abs(res.x))
        assert abs(d.taus[k] - 0.5e-3) < 1 / FS


def test_decaying_exponential_atom_and_bad_input(chirp):
    f = decaying_exponential(2000.0)
    assert f(np.array([-1.0, 0.0]))[0] == 0 and f(np.array([1 / 2000.0]))[0] == pytest.approx(np.exp(-1) / 2000)
    at = Atom(f, 10e3, 100)
    with pytest.raises(ValueError, match="delta_s"):
        Dictionary(at, 0.0)
    with pytest.raises(ValueError, match="alpha"):
        decaying_exponential(-1)
    with pytest.raises(ValueError, match="shape"):
        Atom(np.zeros(10), FS, 50)
    d = Dictionary(Atom(chirp, FS, 100), 1 / FS)
    with pytest.raises(ValueError, match="b has 99 samples"):
        bpdn(d, np.ones(99), lam_frac=0.1)
    with pytest.raises(ValueError, match="b contains 1 NaN"):
        bpdn(d, np.r_[np.nan, np.ones(99)], lam_frac=0.1)
    with pytest.raises(ValueError, match="exactly one of lam"):
        bpdn(d, np.ones(100))
    with pytest.raises(ValueError, match="complex"):
        bpdn(d, np.ones(100), lam_frac=0.1, amplitudes="complex")


# -- metrics, CRB, CBP ---------------------------------------------------------------------------
from clsas.sparse import (  # noqa: E402
    Echoes,
    cbp_polar,
    cbp_polar_refined,
    cbp_taylor,
    crb_delays,
    delay_error,
    superres,
)


def test_delay_error_matches_optimally_and_penalises_count_changes():
    truth = Echoes([1.0e-3, 2.0e-3], [1.0, 2.0])
    est = Echoes([2.0e-3 + 1e-6, 1.0e-3 - 2e-6], [2.0, 1.0])  # listed in the other order
    e = delay_error(est, truth, tol_s=5e-6)
    assert e.success and e.penalty == 0
    assert e.delay_term == pytest.approx((1e-6 * 2.0) ** 2 + (2e-6 * 1.0) ** 2)
    assert e.rmse_s == pytest.approx(np.sqrt((1e-12 + 4e-12) / 2))
    extra = Echoes([1.0e-3, 1.5e-3, 2.0e-3], [1.0, 0.5, 2.0])
    e2 = delay_error(extra, truth, tol_s=5e-6, window_s=4e-3)
    assert not e2.success and e2.penalty == pytest.approx((4e-3 * 0.5) ** 2)
    missing = delay_error(Echoes([], []), truth, window_s=4e-3)
    assert not missing.success and np.isnan(missing.rmse_s)
    assert delay_error(Echoes([], []), Echoes([], [])).success


def test_crb_matches_the_single_echo_formula_and_grows_as_echoes_close(chirp):
    """One real echo: var(tau) >= sigma^2 / (a^2 |f'|^2) (amplitude known to be decoupled at the
    peak of a symmetric atom only approximately, so compare within 5 %)."""
    at = Atom(chirp, FS, 300)
    sigma, a = 0.1, 2.0
    crb = crb_delays(at, [1e-3], [a], sigma)[0]
    simple = sigma**2 / (a**2 * np.sum(at.dmatrix([1e-3]) ** 2))
    assert crb == pytest.approx(simple, rel=0.05)
    atc = Atom(chirp, FS, 300, complex=True)
    far = crb_delays(atc, [1e-3, 2e-3], [1.0, 1.0j], sigma)
    near = crb_delays(atc, [1e-3, 1.0e-3 + 0.25 / 10e3], [1.0, 1.0j], sigma)
    assert np.all(near > 2 * far)


def _echo_signal(chirp, cplx, taus, amps, sigma, rng, n=300):
    at = Atom(chirp, FS, n, complex=cplx)
    return at, at.matrix(taus) @ np.asarray(amps) + _noise(rng, n, cplx, sigma)


def test_convex_cbps_place_an_off_grid_echo_between_grid_points(rng, chirp):
    tau = 1.0e-3 + 0.4 / FS
    at, b = _echo_signal(chirp, False, [tau], [1.0], 1e-3, rng)
    d = Dictionary(at, 1 / FS, tau0_s=0.5e-3, n_atoms=100)
    grid = bpdn(d, b, lam_frac=0.05)
    grid_tau = d.taus[np.argmax(grid.x)]
    for fn in (cbp_taylor, cbp_polar):
        e = fn(d, b, lam_frac=0.05)
        k = np.argmax(e.amplitudes)
        assert abs(e.delays_s[k] - tau) < abs(grid_tau - tau), fn.__name__
        assert abs(e.delays_s[k] - tau) < 0.1 / FS, fn.__name__
    with pytest.raises(ValueError, match="positive amplitudes"):
        cbp_polar(d, b, lam_frac=0.05, amplitudes="real")
    signed = cbp_taylor(d, b, lam_frac=0.05, amplitudes="real")  # the convex relaxation for signed echoes
    assert abs(signed.delays_s[np.argmax(np.abs(signed.amplitudes))] - tau) < 0.3 / FS


@pytest.mark.parametrize("mode", ["positive", "real", "complex"])
def test_refined_cbp_polar_resolves_two_close_echoes(rng, chirp, mode):
    """Two echoes 0.5/B apart (below the matched filter's resolution), off the grid."""
    cplx = mode == "complex"
    taus = [1.0e-3 + 0.3 / FS, 1.0e-3 + 0.3 / FS + 0.5 / 10e3]
    amps = {"positive": [1.0, 0.8], "real": [1.0, -0.8], "complex": [1.0, 0.8j]}[mode]
    at, b = _echo_signal(chirp, cplx, taus, amps, 1e-3, rng)
    d = Dictionary(at, 1 / FS, tau0_s=0.5e-3, n_atoms=100)
    e = cbp_polar_refined(d, b, lam_frac=0.02, amplitudes=mode)
    assert len(e) == 2, e
    np.testing.assert_allclose(e.delays_s, taus, atol=0.02 / FS)
    np.testing.assert_allclose(e.amplitudes, amps, atol=0.02)
    assert e.status and e.iterations > 0


@pytest.mark.parametrize("case", ["zeros", "noise", "dynamic-range"])
def test_refined_cbp_polar_stability(rng, chirp, case):
    at = Atom(chirp, FS, 300, complex=True)
    d = Dictionary(at, 1 / FS, tau0_s=0.0)
    if case == "zeros":
        b = np.zeros(300, complex)
    elif case == "noise":
        b = _noise(rng, 300, True, 1.0)
    else:
        b = at.matrix([1.0e-3, 2.0e-3]) @ np.array([1e6, 1.0])
    e = cbp_polar_refined(d, b, lam_frac=0.05)
    assert np.all(np.isfinite(e.delays_s)) and np.all(np.isfinite(e.amplitudes))
    if case == "zeros":
        assert len(e) == 0
    if case == "dynamic-range":
        assert abs(e.delays_s[np.argmax(np.abs(e.amplitudes))] - 1.0e-3) < 0.01 / FS


@pytest.mark.parametrize("method", ["bpdn", "cbp-polar"])
def test_superres_on_a_real_recording(rng, chirp, method):
    """A real recording of one echo with unknown phase: the analytic model finds it."""
    n = 300
    tau = 1.2e-3 + 0.25 / FS
    at = Atom(chirp, FS, n, complex=True)
    x = np.real(at.matrix([tau])[:, 0] * np.exp(0.9j)) + 1e-3 * rng.normal(size=n)
    e = superres(x, chirp, FS, method=method, delta_s=1 / FS)
    k = np.argmax(np.abs(e.amplitudes))
    assert abs(e.delays_s[k] - tau) < (1 / FS if method == "bpdn" else 0.05 / FS)
    with pytest.raises(ValueError, match="method"):
        superres(x, chirp, FS, method="music")


def test_fig4_example_reproduces_the_papers_ordering(tmp_path):
    """examples/fig4_1d_recovery.py runs, writes its figure and table, and CBP-Polar beats BPDN."""
    _run_example("fig4_1d_recovery.py", tmp_path)
    assert (tmp_path / "fig4.png").stat().st_size > 10_000
    rows = {line.split("|")[1].strip(): float(line.split("|")[4]) for line in
            (tmp_path / "fig4.md").read_text().splitlines() if line.startswith("| ") and "method" not in line}
    assert rows["CBP-Polar (refined)"] < rows["CBP-Polar (convex)"] < rows["CBP-Taylor"] < rows["BPDN"]


# -- fast atom evaluation, noise-level lam, the two-echo task -----------------------------------

@pytest.mark.parametrize("cplx", [False, True], ids=["real", "complex"])
def test_fast_table_evaluation_equals_the_exact_band_limited_shift(chirp, cplx):
    at = Atom(chirp, FS, 300, complex=cplx)
    taus = np.array([-0.4e-3, 0.0, 1.0e-3 + 0.37 / FS, 2.9e-3])
    A, Af = at.matrix(taus), at.matrix(taus, fast=True)
    D, Df = at.dmatrix(taus), at.dmatrix(taus, fast=True)
    assert np.abs(A - Af).max() < 1e-6 * np.abs(A).max()
    assert np.abs(D - Df).max() < 1e-6 * np.abs(D).max()


@pytest.mark.parametrize("cplx", [False, True], ids=["real", "complex"])
def test_noise_level_lam_keeps_echoes_and_drops_noise(rng, chirp, cplx):
    from clsas.sparse import lam_noise, noise_sigma

    at = Atom(chirp, FS, 600, complex=cplx)
    d = Dictionary(at, 1 / FS, tau0_s=0.0)
    sigma = 0.05
    noise = sigma * (rng.normal(size=600) + 1j * rng.normal(size=600)) / np.sqrt(2) if cplx else sigma * rng.normal(
        size=600)
    assert noise_sigma(noise) == pytest.approx(sigma, rel=0.15)
    mode = "complex" if cplx else "real"
    quiet = bpdn(d, noise + 1e-3 * at.matrix([2e-3])[:, 0], lam_noise(d, noise, mode), amplitudes=mode, tol=1e-4)
    assert np.count_nonzero(quiet.x) <= 2
    b = at.matrix([2e-3])[:, 0] + noise
    res = bpdn(d, b, lam_noise(d, b, mode), amplitudes=mode, tol=1e-4)
    k = np.argmax(np.abs(res.x))
    assert abs(d.taus[k] - 2e-3) <= 1 / FS


def test_two_echo_task_cbp_polar_resolves_what_the_matched_filter_cannot():
    """0.25/B apart at 10 dB: the refined CBP-Polar separates them, the matched filter never."""
    from bench.trials import TwoEchoTask, run_trial, summarise

    task = TwoEchoTask()
    rows = [run_trial(task, m, 0.25, 10, seed) for seed in range(5) for m in ("matched", "cbp-polar")]
    s = {r["method"]: r for r in summarise(rows)}
    assert s["matched"]["success_rate"] == 0
    assert s["cbp-polar"]["success_rate"] >= 0.8
    assert s["cbp-polar"]["rmse_over_crb"] < 2.0
    with pytest.raises(ValueError, match="method"):
        run_trial(task, "music", 0.25, 10, 0)


@pytest.mark.parametrize("case", ["sharp-onset", "hard-edged-chirp"])
def test_stiff_atoms_stay_finite(rng, case):
    """An atom with a near-step onset and a chirp with hard on/off edges: the Taylor/polar
    models are poor there (the physics notes), but nothing diverges and status is reported."""
    if case == "sharp-onset":
        f = decaying_exponential(400.0)  # peaks 2.5 ms after a step onset, on a 1 kHz grid
        at = Atom(f, 1000.0, 300)
        taus, delta = [0.1003, 0.1504], 1e-3
    else:
        at = Atom(clsas.lfm_chirp(20e3, 30e3, 1e-3, FS, taper=0.0), FS, 300)
        taus, delta = [1.0e-3 + 0.3 / FS, 1.5e-3], 1 / FS
    scale = 1 / np.abs(at.matrix([taus[0]])).max()  # peak 1
    b = at.matrix(taus) @ (scale * np.array([1.0, 0.6])) + 1e-3 * rng.normal(size=300)
    d = Dictionary(at, delta, tau0_s=0.0)
    for e in (cbp_taylor(d, b, lam_frac=0.05), cbp_polar_refined(d, b, lam_frac=0.05, amplitudes="positive")):
        assert np.all(np.isfinite(e.delays_s)) and np.all(np.isfinite(e.amplitudes)) and e.status
    g = bpdn(d, b, lam_frac=0.05)
    assert np.all(np.isfinite(g.x)) and g.iterations > 0
    assert np.min(np.abs(e.delays_s[:, None] - np.array(taus)[None, :]), axis=0).max() < 0.1 * delta


def test_complex_cbp_taylor_finds_an_echo_of_unknown_phase(rng, chirp):
    at = Atom(chirp, FS, 200, complex=True)
    tau = 0.8e-3 + 0.3 / FS
    b = at.matrix([tau])[:, 0] * np.exp(2.1j) + 1e-3 * (rng.normal(size=200) + 1j * rng.normal(size=200))
    e = cbp_taylor(Dictionary(at, 1 / FS, tau0_s=0.5e-3, n_atoms=60), b, lam_frac=0.05, amplitudes="complex")
    k = np.argmax(np.abs(e.amplitudes))
    assert abs(e.delays_s[k] - tau) < 0.3 / FS
    assert np.angle(e.amplitudes[k]) == pytest.approx(2.1, abs=0.2)


def _run_example(name, tmp_path, *extra):
    import runpy
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[3] / "examples" / name
    argv = sys.argv
    sys.argv = [str(script), "--out", str(tmp_path), *extra]
    try:  # an example ends normally on success (the gallery runs it too) and exits non-zero on failure
        runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv = argv


def test_fig6_example_writes_heat_maps(tmp_path):
    _run_example("fig6_heatmaps.py", tmp_path, "--quick")
    assert (tmp_path / "fig6.png").stat().st_size > 10_000
    best = {line.split("|")[1].strip(): float(line.split("|")[4]) for line in
            (tmp_path / "fig6.md").read_text().splitlines() if line.startswith("| ") and "method" not in line}
    assert best["CBP-Polar (refined)"] < best["CBP-Polar (convex)"] < best["BPDN"]
    assert best["CBP-Taylor"] < best["BPDN"]


def test_2d_example_matched_filter_one_blob_superres_two(tmp_path):
    """Reflectors 1 cm apart in range (below c/2B = 1.7 cm): the matched-filter image has no dip
    between them, the super-resolved ones a deep one."""
    _run_example("fig5_2d_superres.py", tmp_path, "--methods", "bp,bpdn,cbp-polar")
    dips = {line.split("|")[1].strip(): float(line.split("|")[2].split()[0]) for line in
            (tmp_path / "fig5.md").read_text().splitlines() if line.startswith("| ") and "method" not in line}
    assert dips["bp"] > -6
    assert dips["bpdn"] < -6 and dips["cbp-polar"] < -6
    assert (tmp_path / "fig5.png").stat().st_size > 10_000


@pytest.mark.parametrize("cplx", [False, True], ids=["real", "complex"])
def test_atom_correlate_equals_the_dictionary_product(cplx, rng):
    from bench.trials import TwoEchoTask

    task = TwoEchoTask(amplitudes="complex" if cplx else "positive")
    b, _, _ = task.draw(0.5, 20, 3)
    d = task.dictionary(0.25 / task.fs_hz)
    direct = d.matrix().conj().T @ b
    fast = task.atom.correlate(b)[int(round(d.tau0 * 4 * task.fs_hz)):][:len(d.taus)]
    if cplx:
        np.testing.assert_allclose(fast, direct, atol=1e-10 * np.abs(direct).max())
    else:  # the analytic signal of the real correlation: its real part is the correlation (the
        # analytic signal drops the Nyquist bin, where the chirp has no energy)
        np.testing.assert_allclose(fast.real, direct, atol=1e-7 * np.abs(direct).max())
    with pytest.raises(ValueError, match="b"):
        task.atom.correlate(b[:10])
