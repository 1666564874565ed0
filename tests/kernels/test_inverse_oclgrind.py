"""kernels/project.cl (project, project_sum) runs clean under Oclgrind: no invalid or uninitialised
access, no data race (the pattern of tests/kernels/test_oclgrind.py; this file is also the child script)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

DIAGNOSTICS = ("Invalid read", "Invalid write", "Uninitialized", "data race", "Data race", "Invalid access")


def _oclgrind_available() -> str | None:
    try:
        import pyopencl as cl

        names = [p.name for p in cl.get_platforms()]
    except Exception as exc:  # noqa: BLE001 - no ICD loader or no platform
        return f"no OpenCL platform ({exc})"
    return None if any("Oclgrind" in n for n in names) else "Oclgrind not installed (pip install 'pyopencl[oclgrind]')"


# one check and one width per process (Oclgrind's uninitialised-value plugin keeps state between
# programs built in one process); every width for invalid accesses and races
CHECKS = [pytest.param({"OCLGRIND_DATA_RACES": "1"}, ["4", "8", "16"], id="memcheck+races-vec4-8-16")] + [
    pytest.param({"OCLGRIND_UNINITIALIZED": "1"}, [str(vec)], id=f"uninitialized-vec{vec}") for vec in (4, 8)
]


@pytest.mark.oclgrind
@pytest.mark.slow
@pytest.mark.skipif(_oclgrind_available() is not None, reason=str(_oclgrind_available()))
@pytest.mark.parametrize("checks, vecs", CHECKS)
def test_projector_runs_clean_under_oclgrind(checks, vecs):
    env = dict(os.environ, **checks)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    res = subprocess.run([sys.executable, __file__, *vecs], capture_output=True, text=True, env=env, timeout=900)
    report = res.stderr
    assert res.returncode == 0, f"project.cl failed under Oclgrind:\n{res.stdout}\n{report[-4000:]}"
    assert "oclgrind run ok" in res.stdout
    found = [d for d in DIAGNOSTICS if d in report]
    assert not found, f"Oclgrind reported {found}:\n{report[-4000:]}"


def _main(vecs: list[int]) -> int:
    """The child: the plan's selftest (5 x 2 x 3 voxels, not a multiple of VEC; voxels in and out of
    the window; two chunks; two slabs per measurement) on the Oclgrind device, at each width."""
    import pyopencl as cl

    from clsas.inverse.project_opencl import ProjectPlan

    plats = [p for p in cl.get_platforms() if "Oclgrind" in p.name]
    if not plats:
        print("no Oclgrind platform", file=sys.stderr)
        return 3
    queue = cl.CommandQueue(cl.Context(plats[0].get_devices()),
                            properties=cl.command_queue_properties.PROFILING_ENABLE)
    for vec in vecs:
        err = ProjectPlan.selftest(queue, vec)
        assert err < 1e-4, f"project VEC={vec}: {err:.3g} of the peak"
    print("oclgrind run ok")
    return 0


if __name__ == "__main__":
    sys.exit(_main([int(a) for a in sys.argv[1:]] or [4, 8, 16]))
