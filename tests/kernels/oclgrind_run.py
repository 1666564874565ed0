"""Run clsas kernels on the Oclgrind simulator (used by test_oclgrind.py in a subprocess).

Usage: python oclgrind_run.py [compress] [fft] [backproject] [backproject_local] [backproject_half]
[backproject_expansion] [backproject_expansion_aligned] [gradient]
[metric] [stolt] [stolt_depths] [ffbp] [records] [vec=N ...]. Checks each
result against its NumPy twin; Oclgrind's own diagnostics (invalid or uninitialised access, data races) go to
stderr, which the test inspects.
"""

import os
import sys

import numpy as np
import pyopencl as cl

import clsas
from clsas.cl import Shape
from clsas.compression import fft_layout
from clsas.compression.compress_opencl import FftMatchedPlan, FmcwPlan, MatchedFilterPlan
from clsas.focus.gradient_opencl import FocusGradientPlan
from clsas.focus.metric_opencl import FocusMomentsPlan, FocusWeightPlan
from clsas.formation.bp_numpy import backproject as bp_twin
from clsas.formation.bp_numpy import backproject_range_expansion as bp_range_expansion
from clsas.formation.bp_numpy import carrier_records
from clsas.formation.bp_opencl import BackprojectPlan, RecordsPlan, selftest_scene, upsample_factor
from clsas.formation.ffbp_opencl import FfbpLeafPlan, FfbpMergePlan
from clsas.formation.stolt_opencl import StoltDepthsPlan, StoltPlan

FS = 96e3


def close(got, want, tol, name):
    err = np.abs(got - want).max() / np.abs(want).max()
    assert err < tol, f"{name}: {err:.3g} of the peak"


def check_compress(queue, rng, vec):
    # the plans' own selftests (what the device layer's probe runs): matched filter with a lag
    # window past both edges of the recording at lag steps 1 and 2, FMCW at gated delays
    assert MatchedFilterPlan.selftest(queue, vec) < 1e-4, "matched_filter"
    assert FmcwPlan.selftest(queue, vec) < 1e-3, "fmcw_dechirp"


def check_fft(queue, rng, vec):
    # lag step 1 against the direct twin, rows in batches: the plan's selftest
    assert FftMatchedPlan.selftest(queue, vec) < 1e-4, "matched_fft, step 1"
    # lag step 2 (decimated), one work-item per batch, more rows than one work-item holds, the
    # window past both edges of the recording, against the band-limited definition term by
    # term (the twin is band-limited only to -60 dB)
    wave = clsas.lfm_chirp(20e3, 30e3, 0.4e-3, FS, taper=0.1)
    rows = rng.normal(size=(2 * vec + 3, 120))
    ref_a = clsas.analytic(wave)
    step, lag0, n_lags = 2, -10, 65
    rot = np.exp(-2j * np.pi * 0.26 * step * np.arange(n_lags))
    rot0 = np.exp(-2j * np.pi * rng.uniform(size=len(rows)))
    lay = fft_layout(ref_a, FS, 25e3, 0, 120, lag0, step, n_lags, rot)
    plan = FftMatchedPlan(len(rows), 120, lay, rot0, queue=queue, vec=vec, max_scratch_bytes=16 * lay.n_fft * vec)
    assert plan.items == 1 and len(rows) > vec
    n, nd = lay.n_fft, 1 << lay.log2_nd
    jj = np.where(np.arange(nd) < nd // 2, np.arange(nd), np.arange(nd) - nd)
    c = np.fft.ifft(np.fft.fft(rows, n)[:, (lay.bin0 + jj) % n] * lay.spec, axis=1) * nd
    want = rot0[:, None] * lay.post[None] * c[:, (lay.idx0 + np.arange(n_lags)) % nd]
    close(plan(rows), want, 1e-4, f"matched_fft, step {step}")


def check_backproject(queue, rng, vec):
    # the plan's selftest: 5 x 2 x 3 voxels (not a multiple of VEC), two chunks, voxels in and
    # out of the window (it raises if the scene has not both)
    assert BackprojectPlan.selftest(queue, vec) < 1e-4, "backproject"


def check_backproject_local(queue, rng, vec):
    # -DLOCAL_PROFILES (records staged in local memory per work-group, two barriers per
    # measurement): 5 x 3 x 7 voxels in groups of 2 work-items (several groups, the last one part
    # padding) over two chunks against the twin, then the selftest in groups of 4. (In the other
    # order the uninitialised-value plugin reports the accumulators of the second plan's groups
    # inside the window, whose values equal the twin's; either plan alone is clean.)
    _, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 5), np.linspace(0.0, 0.05, 3), np.linspace(0.2, 0.6, 7))
    plan = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, shape=Shape(2, "local_profiles"))
    got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c)
    close(got, bp_twin(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid.points()), 1e-4, "backproject local, 15 groups")
    assert BackprojectPlan.selftest(queue, vec, Shape(4, "local_profiles")) < 1e-4, "backproject local, selftest"


def check_backproject_half(queue, rng, vec):
    # -DHALF_PROFILES (records stored as half, read with vload_half4): Oclgrind does not report
    # cl_khr_fp16, but vload_half is core OpenCL, so this checking process lifts the plan's
    # extension gate; 5 x 3 x 7 voxels in groups of 2 over two chunks, then the selftest (in that
    # order, as for the local variant)
    BackprojectPlan.NEEDS_EXTENSION = {}
    _, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 5), np.linspace(0.0, 0.05, 3), np.linspace(0.2, 0.6, 7))
    plan = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, shape=Shape(2, "half_profiles"))
    got = plan(prof * 1e6, tau0, 1 / fs, 25e3, tx, rx, c)
    close(got, bp_twin(prof * 1e6, tau0, 1 / fs, 25e3, tx, rx, c, grid.points()), 1e-3, "backproject half")
    assert BackprojectPlan.selftest(queue, vec, Shape(None, "half_profiles")) < 1e-3, "backproject half, selftest"


def check_backproject_expansion(queue, rng, vec, nzs=(37,)):
    # -DRANGE_EXPANSION (the distances expanded along z per run of voxels): 3 x 2 x 37 voxels
    # (work-items in one z row, expanded, and across a row's end, exact) in groups of 2 over two
    # chunks against its twin at each run (8 and 4, those up to VEC), then the selftest (the shortest
    # run); check_backproject_expansion_aligned: on 3 x 2 x 32 voxels instead (rows aligned to every
    # width: -DROWS_ALIGNED). Oclgrind's uninitialised-value plugin crashes (a segfault inside
    # Oclgrind) on the builds with 2 or 4 runs per work-item (float2 / float4 of the runs spread over
    # the lanes), so under it only the run of VEC voxels is checked (VEC 4 and 8: one run per work-item).
    _, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    single = bool(os.environ.get("OCLGRIND_UNINITIALIZED"))
    runs = [min(vec, 8)] if single else [r for r in (8, 4) if r <= vec]  # 16: beyond 0.99 of the peak here
    for nz in nzs:
        grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 3), np.array([0.0, 0.05]), np.linspace(0.2, 0.6, nz))
        for run in runs:
            plan = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, shape=Shape(2, "range_expansion"),
                                   max_error=0.99)
            plan.expansion_runs, plan.expansion_limit = (run,), 0.99  # the arithmetic, at errors above -50 dB
            got = plan(prof, tau0, 1 / fs, 25e3, tx, rx, c)
            assert plan.last_expansion_run == run, (plan.last_variant, plan.last_expansion_run, run)
            want = bp_range_expansion(prof, tau0, 1 / fs, 25e3, tx, rx, c, grid, run, vec)
            close(got, want, 1e-4, f"backproject range expansion, nz {nz}, run {run}")
    if nzs == (37,) and not (single and vec > 4):  # the selftest's run: 4
        assert BackprojectPlan.selftest(queue, vec, Shape(None, "range_expansion")) < 1e-4, "bp expansion selftest"


def check_backproject_expansion_aligned(queue, rng, vec):
    check_backproject_expansion(queue, rng, vec, (32,))


def check_records(queue, rng, vec):
    # the resident path: profiles in a device buffer with a row stride wider than the data, the
    # carrier records made there (not upsampled, then 4 x), bp on them over two chunks writing the
    # complex image (-DCOMPLEX_IMAGE); then the records plan's selftest. backproject.cl is built
    # first: the uninitialised-value plugin reports false uses in some programs built after another
    grid, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    plan = BackprojectPlan(grid, 3, 40, queue=queue, vec=vec, chunk=2, complex_image=True)
    wide = np.zeros((3, 43), np.complex64)
    wide[:, :37] = prof[:, :37]
    d_prof = plan.upload(wide, np.complex64)

    class Rows:
        buffer, n_rows, n_cols, stride = d_prof, 3, 37, 43

    for dtau in (1 / fs, 8 / fs):
        records = RecordsPlan(3, 40, upsample_factor(25e3, dtau), queue=queue, vec=vec)
        got = plan.from_device(Rows, records, tau0, dtau, 25e3, tx, rx, c)
        want = bp_twin(wide[:, :40], tau0, dtau, 25e3, tx, rx, c, grid.points())  # zero-padded to the plan's 40
        close(got, want, 1e-4, f"resident bp, dtau {dtau * fs:g} samples")
    assert RecordsPlan.selftest(queue, vec) < 1e-4, "carrier_records"
    # the row-map build (FFBP's tree order): rows read through row_of, in another order
    order = np.array([2, 0, 1])
    mapped = RecordsPlan(3, 40, upsample_factor(25e3, 8 / fs), queue=queue, vec=vec, row_map=True)
    mapped.begin()
    mapped.enqueue(d_prof, 43, 37, tau0[order], 8 / fs, 25e3, row_of=order)
    want_rec, *_ = carrier_records(wide[order, :37], 40, tau0[order], 8 / fs, 25e3)
    close(mapped.read(mapped.d_pairs, want_rec.shape, np.complex64), want_rec, 1e-5, "carrier_records, row map")


def check_gradient(queue, rng, vec):
    # the plan's selftest: 5 x 2 x 3 voxels, two chunks of measurements, two work-items per
    # measurement over three blocks, voxels in and out of the window
    assert FocusGradientPlan.selftest(queue, vec) < 1e-4, "focus_gradient"


def check_metric(queue, rng, vec):
    # the plans' selftests: voxels not a multiple of VEC, more blocks than work-items, a zero
    # voxel, padding after the voxels (written as zeros), both metrics' weights
    assert FocusMomentsPlan.selftest(queue, vec) < 1e-5, "focus_moments"
    assert FocusWeightPlan.selftest(queue, vec) < 1e-5, "focus_weight"


def check_stolt(queue, rng, vec):
    # the plan's selftest: columns with evanescent, windowed and kept samples, three terms,
    # positions that fold around the kz axis, VEC columns per work-item with a ragged last one
    assert StoltPlan.selftest(queue, vec) < 2e-4, "stolt_spread"


def check_stolt_depths(queue, rng, vec):
    # the direct sum's selftest: the same columns at 40 depths (two runs of rotations, the second
    # partial), three terms, a ragged last work-item
    assert StoltDepthsPlan.selftest(queue, vec) < 2e-4, "stolt_depths"


def check_ffbp(queue, rng, vec):
    # the plans' selftests: leaves of a depth-2 tree over 20 jittered bistatic pairs (samples in
    # and out of the profile windows, padding and directions outside the unit disc), a merge of
    # 16 leaves into 4 parents (stencils shifted at the grids' edges) and the 4 parents onto a
    # 5 x 4 x 3 grid (not a multiple of the block)
    assert FfbpLeafPlan.selftest(queue, vec) < 1e-4, "ffbp_leaf"
    assert FfbpMergePlan.selftest(queue, vec) < 1e-4, "ffbp_merge"


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
        if "backproject_local" in kernels:
            check_backproject_local(queue, rng, vec)
        if "backproject_half" in kernels:
            check_backproject_half(queue, rng, vec)
        if "backproject_expansion" in kernels:
            check_backproject_expansion(queue, rng, vec)
        if "backproject_expansion_aligned" in kernels:
            check_backproject_expansion_aligned(queue, rng, vec)
        if "gradient" in kernels:
            check_gradient(queue, rng, vec)
        if "metric" in kernels:
            check_metric(queue, rng, vec)
        if "stolt" in kernels:
            check_stolt(queue, rng, vec)
        if "stolt_depths" in kernels:
            check_stolt_depths(queue, rng, vec)
        if "ffbp" in kernels:
            check_ffbp(queue, rng, vec)
        if "records" in kernels:
            check_records(queue, rng, vec)
    print("oclgrind run ok")
    return 0


if __name__ == "__main__":
    sys.exit(main(set(sys.argv[1:]) or {"compress", "fft", "backproject", "backproject_local", "backproject_half",
                                        "backproject_expansion", "backproject_expansion_aligned", "gradient",
                                        "metric", "stolt", "stolt_depths", "ffbp", "records"}))
