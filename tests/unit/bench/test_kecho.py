"""The K-echo benchmark task: the references and the table's shape."""

import numpy as np

from bench.kecho import bound_success, draw_k, k_markdown, k_sweep, k_table, ml_known_count, task_for
from clsas.sparse import ShiftOperator, lam_max, lam_noise


def test_bound_success_is_a_probability_that_grows_with_snr():
    task = task_for(3, 2.0)
    p = []
    for snr in (-20.0, 0.0, 30.0):
        _, truth, sigma = draw_k(task, 3, 0.5, 2.0, snr, 0)
        p.append(bound_success(task, truth, sigma))
    assert 0.0 <= p[0] < p[1] < p[2] <= 1.0
    assert p[2] > 0.999


def test_known_count_ml_finds_five_echoes_with_a_weak_one_between():
    task = task_for(5, 2.0)
    b, truth, _ = draw_k(task, 5, 0.1, 2.0, 30.0, 1)
    est = ml_known_count(task, b, 5)
    assert len(est) == 5
    np.testing.assert_allclose(np.sort(est.delays_s), truth.delays_s, atol=0.05 / task.bandwidth_hz)


def test_lam_noise_below_lam_max_when_echoes_cover_the_gate():
    # ten echoes 2/B apart fill the whole gate with chirps: the first noise estimate (median
    # correlation over the gate) is above lam_max; the residual's is not, so the echoes are kept
    task = task_for(10, 2.0)
    b, _, _ = draw_k(task, 10, 1.0, 2.0, 10.0, 0)
    d = task.dictionary()
    assert lam_noise(d, b, "complex") < 0.1 * lam_max(ShiftOperator(d), b, "complex")


def test_k_table_has_a_row_per_cell_and_method():
    rows = k_sweep((2,), (1.0, 0.1), 1, snr_db=30.0)
    table = k_table(rows)
    assert [(c["k"], c["ratio"], c["method"]) for c in table] == [
        (2, 1.0, "cbp-polar"), (2, 1.0, "bpdn"), (2, 1.0, "bpdn-detect"), (2, 1.0, "mlk"),
        (2, 0.1, "cbp-polar"), (2, 0.1, "bpdn"), (2, 0.1, "bpdn-detect"), (2, 0.1, "mlk")]
    assert all(c["ml_success"] == 1.0 and c["bound_success"] > 0.99 for c in table)
    assert len(k_markdown(table)) == 2 + len(table)


def test_detection_success_matches_the_fitted_likelihood_ratio_on_noise_draws():
    """The order test's pass rate at an echo's true delay (amplitude and delay fitted, noise
    known): measured on 200 draws, it is the formula's noncentral chi-square (3 degrees of freedom)."""
    from bench.kecho import detection_success
    from clsas.sparse.varpro import VarPro

    task = task_for(1, 2.0)
    threshold, n, hits = 18.1, 200, 0
    lo, hi = task.gate_s
    for seed in range(n):
        b, truth, sigma = draw_k(task, 1, 1.0, 2.0, -12.0, seed)
        _, _, rss, _ = VarPro(task.atom, b, "complex").fit(truth.delays_s.copy(), lo, hi)
        hits += (np.vdot(b, b).real - rss) / (sigma**2 / 2) > threshold
    p = detection_success(task, truth, sigma, threshold)
    assert 0.6 < p < 0.95  # the level where the test is sensitive
    assert abs(hits / n - p) < 3 * np.sqrt(p * (1 - p) / n)  # measured 0.813 against 0.813 on 300
    # with ten echoes the weak ones' evidence is what the strong ones leave: lower, never above one
    _, truth10, sigma10 = draw_k(task_for(10, 2.0), 10, 0.1, 2.0, 10.0, 0)
    p10 = detection_success(task_for(10, 2.0), truth10, sigma10, threshold)
    assert 0.8 < p10 < 0.95
    assert detection_success(task_for(10, 2.0), truth10, sigma10, 0.0) == 1.0
