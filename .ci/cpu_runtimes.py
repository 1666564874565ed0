"""Print one line per OpenCL CPU runtime here that builds and runs kernels: ``P:D<TAB>description``.

CI runs the kernel tests once per line (``PYOPENCL_CTX=P:D pytest -m opencl``). Runtimes that build
no kernel on this CPU are named on stderr with the compiler's words; the exit status is 1 when
fewer than ``--at-least`` runtimes build.
"""

import argparse
import sys

from clsas import cl


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--at-least", type=int, default=2)
    args = ap.parse_args()
    good = []
    for row in cl.list_devices():
        if row.kind != "CPU" or "oclgrind" in row.platform.lower():
            continue
        name = f"{row.device} on {row.platform} ({row.platform_version})"
        if row.builds:
            good.append(row.index)
            print(f"{row.index}\t{name}")
        else:
            print(f"not tested: {name}: {row.reason}. Fix: {row.fix}", file=sys.stderr)
    if len(good) < args.at_least:
        print(f"only {len(good)} OpenCL CPU runtime(s) build kernels here; CI needs {args.at_least}",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
