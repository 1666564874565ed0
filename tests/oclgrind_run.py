"""Run clsas kernels on the Oclgrind simulator (used by test_oclgrind.py in a subprocess).

Usage: python oclgrind_run.py [compress] [fft] [backproject] [vec=N ...]. Checks each result against its NumPy
twin; Oclgrind's own diagnostics (invalid or uninitialised access, data races) go to
stderr, which the test inspects.
"""

import sys

import numpy as np
import pyopencl as cl

import clsas
from clsas.compress import fft_layout
from clsas.compress import numpy as ctwin
from clsas.compress.opencl import FftMatchedPlan, FmcwPlan, MatchedFilterPlan
from clsas.imaging import numpy as btwin
from clsas.imaging.opencl import BackprojectPlan

FS = 96e3


def close(got, want, tol, name):
    err = np.abs(got - want).max() / np.abs(want).max()
    assert err < tol, f"{name}: {err:.3g} of the peak"


def check_compress(queue, rng, vec):
    wave = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.1)
    ref = np.conj(clsas.analytic(wave))
    sig = rng.normal(size=(3, 120))
    # matched filter: a lag window that runs past both edges of the recording
    lag0, n_lags = -10, 130
    rot = np.exp(-2j * np.pi * 0.26 * np.arange(n_lags))
    rot0 = np.exp(-2j * np.pi * rng.uniform(size=3))
    got = MatchedFilterPlan(3, 120, ref, lag0, n_lags, rot, rot0, queue=queue, vec=vec)(sig)
    close(got, ctwin.matched_filter(sig, ref, lag0, n_lags, rot, rot0), 1e-4, "matched_filter")
    got = MatchedFilterPlan(3, 120, ref, lag0, n_lags // 2, rot[::2], rot0, 2, queue=queue, vec=vec)(sig)
    close(got, ctwin.matched_filter(sig, ref, lag0, n_lags // 2, rot[::2], rot0, 2), 1e-4, "matched_filter, step 2")
    taus = 1e-4 + np.arange(21) / FS
    rvp = np.exp(1j * rng.uniform(size=21))
    fref = ref * np.hanning(len(ref))
    got = FmcwPlan(3, 120, fref, 10e3 / 0.4e-3, FS, taus, rvp, queue=queue, vec=vec)(sig)
    close(got, ctwin.fmcw_dechirp(sig, fref, 10e3 / 0.4e-3, FS, taus, rvp), 1e-3, "fmcw_dechirp")


def check_fft(queue, rng, vec):
    # FFT path: lag step 1 and 2 (decimated), rows in batches (scratch capped), more rows
    # than one work-item holds, the window past both edges of the recording
    wave = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.1)
    rows = rng.normal(size=(2 * vec + 3, 120))
    ref_a = clsas.analytic(wave)
    for step, lag0 in [(1, -10), (2, -10)]:
        n_lags = 130 // step
        rot = np.exp(-2j * np.pi * 0.26 * step * np.arange(n_lags))
        rot0 = np.exp(-2j * np.pi * rng.uniform(size=len(rows)))
        lay = fft_layout(ref_a, FS, 25e3, 0, 120, lag0, step, n_lags, rot)
        plan = FftMatchedPlan(len(rows), 120, lay, rot0, queue=queue, vec=vec, max_scratch_bytes=16 * lay.n_fft * vec)
        assert plan.items == 1 and len(rows) > vec
        if step == 1:
            want = ctwin.matched_filter(rows, np.conj(ref_a), lag0, n_lags, rot, rot0, step)
        else:  # the band-limited definition, term by term (the twin is band-limited only to -60 dB)
            n, nd = lay.n_fft, 1 << lay.log2_nd
            jj = np.where(np.arange(nd) < nd // 2, np.arange(nd), np.arange(nd) - nd)
            c = np.fft.ifft(np.fft.fft(rows, n)[:, (lay.bin0 + jj) % n] * lay.spec, axis=1) * nd
            want = rot0[:, None] * lay.post[None] * c[:, (lay.idx0 + np.arange(n_lags)) % nd]
        close(plan(rows), want, 1e-4, f"matched_fft, step {step}")


def check_backproject(queue, rng, vec):
    # 5 x 2 x 3 voxels (not a multiple of VEC), two chunks, voxels in and out of the window
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 5), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, 3))
    tx = np.c_[rng.uniform(-0.2, 0.2, (3, 2)), np.zeros(3)]
    rx = tx + [0.03, 0, 0]
    # profiles fall to zero at the window edges, as gated ones do (the gate has margins)
    prof = (rng.normal(size=(3, 40)) + 1j * rng.normal(size=(3, 40))) * np.hanning(40)
    tau0 = np.full(3, 2.0e-3)
    got = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2)(prof, tau0, 1 / FS, 25e3, tx, rx, 343.0)
    want = btwin.backproject(prof, tau0, 1 / FS, 25e3, tx, rx, 343.0, grid.points())
    close(got, want, 1e-4, "backproject")
    assert np.any(want == 0) and np.any(want != 0), "the scene must have voxels in and out of the window"


def main(kernels: set[str]) -> int:
    plats = [p for p in cl.get_platforms() if "Oclgrind" in p.name]
    if not plats:
        print("no Oclgrind platform", file=sys.stderr)
        return 3
    props = cl.command_queue_properties.PROFILING_ENABLE
    queue = cl.CommandQueue(cl.Context(plats[0].get_devices()), properties=props)
    rng = np.random.default_rng(0)
    vecs = [int(a[4:]) for a in kernels if a.startswith("vec=")] or [4, 16]
    for vec in vecs:
        if "compress" in kernels:
            check_compress(queue, rng, vec)
        if "fft" in kernels:
            check_fft(queue, rng, vec)
        if "backproject" in kernels:
            check_backproject(queue, rng, vec)
    print("oclgrind run ok")
    return 0


if __name__ == "__main__":
    sys.exit(main(set(sys.argv[1:]) or {"compress", "fft", "backproject"}))
