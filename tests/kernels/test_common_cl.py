"""kernels/common.cl helpers: sincos_2pi and RINT against NumPy on PoCL."""

import numpy as np
import pytest
from conftest import needs_opencl, width_or_skip

SRC = """
__kernel void probe(__global const float *c, __global const float *w,
                    __global float *s, __global float *k, __global float *r)
{
    const int i = get_global_id(0) * VEC;
    lanes_f in, os, ok, orr;
    lanes_f wv;
    for (int l = 0; l < VEC; ++l) { in.s[l] = c[i + l]; wv.s[l] = w[i + l]; }
    floatV cv;
    os.v = sincos_2pi(in.v, &cv);
    ok.v = cv;
    orr.v = RINT(wv.v);
    for (int l = 0; l < VEC; ++l) { s[i + l] = os.s[l]; k[i + l] = ok.s[l]; r[i + l] = orr.s[l]; }
}
"""


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_sincos_2pi_and_rint(vec):
    import pyopencl as cl

    width_or_skip("backproject", vec)  # never build a width the device layer rejected
    from clsas import cl as ccl

    q = ccl.get_queue()
    prog = cl.Program(q.context, ccl.kernel_source("common.cl") + SRC).build(options=[f"-DVEC={vec}"])
    c = np.linspace(-0.5, 0.5, 4096, dtype=np.float32)
    w = (np.arange(len(c), dtype=np.float32) - 2048) * np.float32(0.25)  # exact ties at x.5
    s, k, r = (np.empty_like(c) for _ in range(3))
    mf = cl.mem_flags
    d_c = cl.Buffer(q.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=c)
    d_w = cl.Buffer(q.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=w)
    outs = [cl.Buffer(q.context, mf.WRITE_ONLY, c.nbytes) for _ in range(3)]
    cl.Kernel(prog, "probe")(q, (len(c) // vec,), None, d_c, d_w, *outs)
    for host, dev in zip((s, k, r), outs, strict=True):
        cl.enqueue_copy(q, host, dev)
    assert np.abs(s - np.sin(2 * np.pi * c.astype(float))).max() < 1e-6
    assert np.abs(k - np.cos(2 * np.pi * c.astype(float))).max() < 1e-6
    np.testing.assert_array_equal(r, np.rint(w))  # round half to even
