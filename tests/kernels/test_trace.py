"""clsas.cl.Tracer: the launches and copies enqueued while it is entered, timed by their profiling
events; pyopencl and Plan.upload put back on exit."""

import numpy as np
import pytest
from conftest import needs_opencl


@pytest.fixture
def twice():
    """(queue, kernel doubling a float buffer in place) on the default OpenCL device."""
    import pyopencl

    from clsas import cl

    queue = cl.get_queue()
    prg = pyopencl.Program(queue.context, "__kernel void twice(__global float *x) { x[get_global_id(0)] *= 2.0f; }")
    return queue, prg.build().twice


@needs_opencl
def test_the_tracer_counts_a_launch_and_a_copy_by_their_events(twice):
    import pyopencl

    from clsas.cl import Tracer

    queue, knl = twice
    host = np.arange(4096, dtype=np.float32)
    buf = pyopencl.Buffer(queue.context, pyopencl.mem_flags.READ_WRITE, host.nbytes)
    with Tracer() as tr:
        pyopencl.enqueue_copy(queue, buf, host)
        knl(queue, host.shape, None, buf)
        out = np.empty_like(host)
        pyopencl.enqueue_copy(queue, out, buf)
    assert len(tr.kernels) == 1 and len(tr.copies) == 2
    kernel_s, transfer_s = tr.seconds()
    assert kernel_s > 0 and transfer_s > 0
    np.testing.assert_array_equal(out, 2 * host)


@needs_opencl
def test_a_queue_without_profiling_gives_no_times(twice):
    import pyopencl

    from clsas.cl import Tracer

    queue, knl = twice
    host = np.ones(256, dtype=np.float32)
    buf = pyopencl.Buffer(queue.context, pyopencl.mem_flags.READ_WRITE | pyopencl.mem_flags.COPY_HOST_PTR,
                          hostbuf=host)
    plain = pyopencl.CommandQueue(queue.context, queue.device)
    with Tracer() as tr:
        knl(plain, host.shape, None, buf)
        pyopencl.enqueue_copy(plain, host, buf)
    assert len(tr.kernels) == 1 and tr.seconds() == (None, None)


@needs_opencl
def test_the_tracer_times_plan_uploads_and_puts_everything_back_after_an_error():
    import pyopencl
    import pyopencl._cl as low

    from clsas.cl import Plan, Tracer, get_queue

    before = (pyopencl.enqueue_copy, low.enqueue_nd_range_kernel, Plan.upload)
    plan = Plan.__new__(Plan)  # upload needs only the queue's context and pyopencl
    plan.cl, plan.context = pyopencl, get_queue().context
    with pytest.raises(RuntimeError, match="inside"), Tracer() as tr:
        plan.upload(np.arange(1000.0), np.float32)
        raise RuntimeError("inside")
    assert tr.upload_s > 0 and tr.kernels == [] and tr.copies == []
    assert (pyopencl.enqueue_copy, low.enqueue_nd_range_kernel, Plan.upload) == before
