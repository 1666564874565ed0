"""Run the backprojection and FFBP leaf kernels' beam variants (-DBEAM, kernels/beam.cl) on
Oclgrind, weighted and limited, at the VEC given on the command line (used by
test_beam_formation.py in a subprocess; Oclgrind's diagnostics go to stderr)."""

import sys

import pyopencl as cl

from clsas.formation.bp_opencl import beam_selftest
from clsas.formation.ffbp_opencl import leaf_beam_selftest


def main(vec: int) -> int:
    plats = [p for p in cl.get_platforms() if "Oclgrind" in p.name]
    if not plats:
        print("no Oclgrind platform", file=sys.stderr)
        return 3
    props = cl.command_queue_properties.PROFILING_ENABLE
    queue = cl.CommandQueue(cl.Context(plats[0].get_devices()), properties=props)
    for mode in ("weighted", "limited"):
        err = beam_selftest(queue, vec, mode)
        assert err < 2e-4, f"beam {mode}: {err:.3g} of the peak"
        err = leaf_beam_selftest(queue, vec, mode)
        assert err < 2e-4, f"ffbp_leaf beam {mode}: {err:.3g} of the peak"
    print("oclgrind run ok")
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 4))
