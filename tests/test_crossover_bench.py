"""The crossover table of ``clsas bench --formation`` and the calibration it stores (no timing is asserted)."""

import pytest

import clsas
from clsas.bench import crossover as cx
from clsas.formation import cost


def test_crossover_table_times_every_formation_and_auto(tmp_path, monkeypatch):
    monkeypatch.setenv("CLSAS_CACHE_DIR", str(tmp_path))
    res = cx.crossover((8,), store=True)
    (row,) = res["rows"]
    names = [r["formation"] for r in row["rows"]]
    assert names == ["bp", "omega-k", "ffbp", "auto"]
    auto = row["rows"][-1]
    assert auto["chose"] in cx.FORMS and auto["reason"]
    assert all(r["time_s"] > 0 for r in row["rows"])
    for r in row["rows"][1:3]:
        assert r["predicted_builtin_s"] > 0 and r["error_all_db"] < 0
    assert set(res["calibration"]) == {"bp", "omega-k", "ffbp"}
    assert cost.load_calibration(clsas.cl.select(None)) == pytest.approx(res["calibration"])
    md = "\n".join(cx.markdown(res))
    assert "| 8 | 64 |" in md and "Calibration" in md


def test_calibrate_takes_the_median_ratio():
    rows = [{"rows": [{"formation": "bp", "time_s": t, "predicted_builtin_s": 1.0}]} for t in (1.0, 2.0, 9.0)]
    assert cx.calibrate(rows) == {"bp": 2.0}
