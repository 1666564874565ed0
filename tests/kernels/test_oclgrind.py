"""Every kernel (compress.cl: matched_filter, fmcw_dechirp; backproject.cl, plain, -DLOCAL_PROFILES, -DHALF_PROFILES,
-DRANGE_EXPANSION;
autofocus.cl; stolt.cl; ffbp.cl: ffbp_leaf, ffbp_merge; records.cl, with backproject.cl's complex image
after it) runs clean under Oclgrind."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import OCLGRIND_DIAGNOSTICS as DIAGNOSTICS
from conftest import oclgrind_missing as _oclgrind_available

# The uninitialised-value plugin of Oclgrind keeps state between programs built in one process
# (a second program gets false reports), so it checks one kernel file and one VEC per process.
# It segfaults (inside itself) on backproject.cl at VEC=16, whose gather builds float16 vectors
# from float8 swizzles; that width is still checked for invalid accesses and data races by the
# first run, and VEC 4 and 8 (the same code with narrower vectors) for uninitialised values.
# ffbp.cl's leaf kernel has backproject.cl's vector gather (the merge kernel is scalar): the
# same widths, 4 and 8, are checked for uninitialised values. stolt.cl's direct sum (stolt_depths)
# is checked for them at VEC=4 only: at 8 and 16 Oclgrind reports every value of one lane (3 at 8,
# 11 at 16) of the copy from its vector sums to the output, whose values equal the twin's there
# (the selftest passes under Oclgrind); the same copy read as floats, or its other lane loops
# unrolled, gave reports at every width or crashed Oclgrind. Its invalid accesses and races are
# checked at every width. records.cl (with the resident path: backproject.cl writing the complex
# image after it) is checked for uninitialised values at VEC 4 and 8, backproject.cl's widths, as is
# backproject.cl's -DLOCAL_PROFILES variant (records staged in local memory, barriers: the race check
# covers them at every width), -DHALF_PROFILES and -DRANGE_EXPANSION variants (the latter's
# -DROWS_ALIGNED build in a process of its own; its builds with 2 or 4 runs per work-item crash the
# plugin, so it checks one run per work-item there; the race check covers every run); for each, a
# plan of several groups runs before the selftest (in the other order the plugin reports the second
# plan's accumulators, whose values equal the twin's; either alone is clean).
WIDTHS = ("vec=4", "vec=8", "vec=16")
CHECKS = [
    pytest.param({"OCLGRIND_DATA_RACES": "1"},
                 ["compress", "fft", "backproject", "backproject_local", "backproject_half", "backproject_expansion",
                  "backproject_expansion_aligned", "gradient", "metric", "stolt", "stolt_depths", "ffbp", "records",
                  *WIDTHS],
                 id="memcheck+races-all"),
] + [
    pytest.param({"OCLGRIND_UNINITIALIZED": "1"}, [kernels, f"vec={vec}"], id=f"uninitialized-{kernels}-vec{vec}")
    for kernels, vecs in [("compress", (4, 8, 16)), ("fft", (4, 8, 16)), ("backproject", (4, 8)),
                           ("backproject_local", (4, 8)), ("backproject_half", (4, 8)),
                           ("backproject_expansion", (4, 8)), ("backproject_expansion_aligned", (4, 8)),
                           ("gradient", (4, 8)),
                           ("metric", (4, 16)), ("stolt", (4, 16)),
                           ("stolt_depths", (4,)), ("ffbp", (4, 8)), ("records", (4, 8))]
    for vec in vecs
]


@pytest.mark.oclgrind
@pytest.mark.skipif(_oclgrind_available() is not None, reason=str(_oclgrind_available()))
@pytest.mark.parametrize("checks, kernels", CHECKS)
def test_kernels_run_clean_under_oclgrind(checks, kernels):
    env = dict(os.environ, **checks)
    root = str(Path(__file__).resolve().parents[2])  # this tree's clsas, not an installed one
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    script = Path(__file__).with_name("oclgrind_run.py")
    res = subprocess.run([sys.executable, str(script), *kernels], capture_output=True, text=True, env=env, timeout=600)
    report = res.stderr
    assert res.returncode == 0, f"kernels failed under Oclgrind:\n{res.stdout}\n{report[-4000:]}"
    assert "oclgrind run ok" in res.stdout
    found = [d for d in DIAGNOSTICS if d in report]
    assert not found, f"Oclgrind reported {found}:\n{report[-4000:]}"
