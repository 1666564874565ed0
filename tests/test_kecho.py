"""The K-echo benchmark task (issue 17's table): the references and the table's shape."""

import numpy as np

from clsas.bench.kecho import _task_for, bound_success, draw_k, k_markdown, k_sweep, k_table, ml_known_count
from clsas.sparse import ShiftOperator, lam_max, lam_noise


def test_bound_success_is_a_probability_that_grows_with_snr():
    task = _task_for(3, 2.0)
    p = []
    for snr in (-20.0, 0.0, 30.0):
        _, truth, sigma = draw_k(task, 3, 0.5, 2.0, snr, 0)
        p.append(bound_success(task, truth, sigma))
    assert 0.0 <= p[0] < p[1] < p[2] <= 1.0
    assert p[2] > 0.999


def test_known_count_ml_finds_five_echoes_with_a_weak_one_between():
    task = _task_for(5, 2.0)
    b, truth, _ = draw_k(task, 5, 0.1, 2.0, 30.0, 1)
    est = ml_known_count(task, b, 5)
    assert len(est) == 5
    np.testing.assert_allclose(np.sort(est.delays_s), truth.delays_s, atol=0.05 / task.bandwidth_hz)


def test_lam_noise_below_lam_max_when_echoes_cover_the_gate():
    # ten echoes 2/B apart fill the whole gate with chirps: the first noise estimate (median
    # correlation over the gate) is above lam_max; the residual's is not, so the echoes are kept
    task = _task_for(10, 2.0)
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
