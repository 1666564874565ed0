"""``python -m bench.focus_step`` runs both ways of an autofocus step and prints them (no timing is asserted)."""

from conftest import needs_opencl


@needs_opencl
def test_focus_step_bench_prints_both_ways(capsys):
    from bench import focus_step

    assert focus_step.main(["--side", "8", "--measurements", "16", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "metric on the device" in out and "on the host" in out and "host / device" in out
