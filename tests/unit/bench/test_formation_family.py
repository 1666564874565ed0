"""The seeded request family of ``python -m bench --formation-family`` (no timing is asserted)."""

import numpy as np
import pytest

from bench import formation_family as ff


def test_requests_are_drawn_from_their_seed_and_bounded():
    ds, grid, p = ff.family_request(4)
    ds2, grid2, p2 = ff.family_request(4)
    assert p == p2 and grid.shape == grid2.shape
    assert np.array_equal(ds.signals, ds2.signals) and ds.n_meas == p["measurements"]
    kinds = set()
    for seed in range(30):
        d = ff.draw(seed, max_pairs=2e7)
        grid, p = d["grid"], d["params"]
        kinds.add(p["kind"])
        assert p["pairs"] <= 2e7 and p["voxels"] == grid.size
        lo, hi = p["band_hz"]
        assert 10e3 <= lo < hi <= 40e3
    assert kinds == set(ff.KINDS)  # planar, jittered and ring requests all occur


def test_tuning_and_held_out_seeds_are_disjoint():
    sets = [set(x) for x in ff.SEED_SETS.values()] + [set(range(500, 600))]  # the models' fit seeds
    assert sum(map(len, sets)) == len(set().union(*sets))
    assert len(ff.HELD_OUT_SEEDS) >= 30 and len(ff.HELD_OUT_2_SEEDS) >= 30


@pytest.mark.parametrize("bad", [-1, 1.5, True, "3"])
def test_the_seed_is_checked(bad):
    with pytest.raises(ValueError, match="seed"):
        ff.draw(bad)


def test_a_request_times_every_formation_and_auto(monkeypatch):
    from bench import crossover

    monkeypatch.setattr(crossover, "ROUNDS", (1, 1))
    jittered = next(s for s in range(40) if ff.draw(s)["params"]["kind"] == "jittered")
    row = ff.run_request(jittered, max_pairs=3e6)
    by = {r["formation"]: r for r in row["rows"]}
    assert "refused" in by["omega-k"]  # the stops are off the lattice
    assert by["bp"]["time_s"] > 0 and by["ffbp"]["error_all_db"] < 0
    a = row["auto"]
    assert a["chose"] in ("bp", "ffbp") and a["best"] in ("bp", "ffbp") and a["over_best"] > 0
    s = ff.summarise([row, {"seed": 99, "error": "ValueError: x"}])
    assert s["n"] == 1 and s["failed"] == 1 and 0 <= s["within"] <= 1
    md = ff.markdown([row], s, -30.0)
    assert f"| {jittered} | jittered" in md and "refused" in md


def test_summary_counts_auto_over_its_target():
    def row(seed, over, err):
        return {"seed": seed, "rows": [{"formation": "bp", "time_s": 0.02 * seed}],
                "auto": {"chose": "ffbp", "best": "bp", "over_best": over, "error_all_db": err,
                         "over_target": err > -30}}
    s = ff.summarise([row(1, 1.1, -35.0), row(2, 1.5, -28.0), row(3, 0.9, -40.0), row(4, 1.3, -31.0)])
    assert s["within"] == pytest.approx(0.5) and s["over_target"] == pytest.approx(0.25)
    assert s["worst_over_best"] == pytest.approx(1.5) and s["worst_seed"] == 2
    assert s["chose"] == {"ffbp": 4} and s["best"]["bp"] == 4
    assert s["n_large"] == 2 and s["within_large"] == pytest.approx(0.5)  # seeds 3 and 4: bp 60 and 80 ms


def test_the_cli_writes_the_family_report(tmp_path):
    from bench.__main__ import main

    assert main(["--formation-family", "--n-seeds", "1", "--out", str(tmp_path), "-q", "--no-plots"]) == 0
    md = next(tmp_path.glob("*-formation-family-tuning.md")).read_text()
    assert "tuning seeds 0-0" in md and "| 0 |" in md
