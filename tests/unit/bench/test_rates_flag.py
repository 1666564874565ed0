"""``python -m bench --rates N``: the suite's entry to ``clsas bench`` (clsas.presenting.rates), which
prints the table and writes the run's report to ``--out``."""

from bench.__main__ import main


def test_the_rates_flag_prints_the_table_and_writes_its_report(tmp_path, capsys):
    assert main(["-q", "--rates", "8", "--devices", "numpy", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "kernel, pairs/s" in printed and "numpy (twins)" in printed and "wrote " in printed
    assert len(list(tmp_path.glob("*-rates-*.json"))) == 1 and len(list(tmp_path.glob("*-rates-*.md"))) == 1


def test_the_rates_flag_refuses_a_scan_too_small_naming_the_flag(capsys):
    assert main(["--rates", "4"]) == 2
    assert "--rates: N (stops per side)" in capsys.readouterr().err
