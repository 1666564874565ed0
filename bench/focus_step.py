"""One autofocus step with its metric on the device against the same step with the metric on the host.

    python -m bench.focus_step [--side 48] [--measurements 256] [--repeats 5]

An autofocus step (:meth:`clsas.focus.engine.FocusEngine.evaluate`: the image, the focus metric,
its weight per voxel and the gradient sums) on ``side``³ voxels of a planar scan of
``measurements`` stops (``bench.resident``'s scene), on the device ``PYOPENCL_CTX`` names. The
two ways alternate in each repeat: the metric and weight from the image bp left on the device
(kernels/focus_metric.cl, the weight written into the gradient kernel's buffers), and the metric
computed on the host from the image read back, the weight written back to the device. It prints
the medians of the step's wall time, their ratio, the metrics' difference and the load average.
"""

from __future__ import annotations

import argparse
import os
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.focus_step", description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=48)
    ap.add_argument("--measurements", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)

    import numpy as np

    from bench import throughput as tp
    from bench.resident import _scan
    from clsas.focus.engine import FocusEngine

    ds = _scan(args.measurements)
    grid = tp.cube_grid(args.side)
    on_device = FocusEngine(ds, grid, backend="opencl")
    on_host = FocusEngine(ds, grid, backend="opencl", metric_on_device=False)
    shift = np.zeros(ds.n_meas)
    walls = {"device": [], "host": []}
    metrics = {}
    for r in range(args.repeats + 1):  # the first round builds and warms up
        for name, eng in (("device", on_device), ("host", on_host)):
            t0 = time.perf_counter()
            m, _, _ = eng.evaluate(shift, ds.c_per_meas)
            if r:
                walls[name].append(time.perf_counter() - t0)
            metrics[name] = m
    assert on_device.n_device_metrics == args.repeats + 1 and on_host.n_device_metrics == 0
    dev, host = (float(np.median(walls[k])) for k in ("device", "host"))
    print(f"device {os.environ.get('PYOPENCL_CTX', '(default)')}: {on_device.device}")
    print(f"{args.side}^3 voxels x {ds.n_meas} measurements, medians of {args.repeats}, "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"step, metric on the device: {dev * 1e3:.1f} ms; on the host: {host * 1e3:.1f} ms; "
          f"host / device {host / dev:.2f}")
    print(f"metric: {metrics['device']:.9f} (device) {metrics['host']:.9f} (host)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
