"""kernels/records.cl (the carrier records bp reads, made on the device) against its twin
(clsas.formation.bp_numpy.carrier_records) and analytically; the resident path (compression ->
records -> bp on device buffers, the image read once as complex64) against the step-by-step one;
FFBP's leaves from the compression's rows (records made on the device in tree order)."""

import numpy as np
import pytest
from conftest import TOL, needs_opencl, small_dataset, width_or_skip

import clsas
from clsas.formation.bp_numpy import carrier_records, upsample, upsample_factor

FS = 96e3
FC = 25e3


def _profiles(rng, n_meas, n_data):
    return (rng.normal(size=(n_meas, n_data)) + 1j * rng.normal(size=(n_meas, n_data))).astype(np.complex64)


@pytest.mark.parametrize("up", [1, 2, 3, 5])
def test_twin_upsamples_then_rotates(rng, up):
    """The twin's records are the upsampled profile's samples j and j + 1 times the carrier at the
    middle of record j (the definition in records.cl), the last record's second sample zero."""
    n_meas, n_lags = 4, 30
    dtau = up * 0.5 / FC  # fc dtau = 0.5 up: upsample_factor gives up (1 for up = 1)
    assert upsample_factor(FC, dtau) == up
    data = _profiles(rng, n_meas, n_lags - 3)
    tau0 = rng.uniform(1e-3, 2e-3, n_meas)
    pairs, fine, phi = carrier_records(data, n_lags, tau0, dtau, FC)
    padded = np.zeros((n_meas, n_lags), complex)
    padded[:, : data.shape[1]] = data
    fine_prof = upsample(padded, up) if up > 1 else padded
    j = np.arange(fine_prof.shape[1])
    rot = np.exp(2j * np.pi * FC * (tau0[:, None] + (j + 0.5) * fine))
    assert fine == pytest.approx(dtau / up) and phi == pytest.approx(2 * np.pi * FC * dtau / up)
    np.testing.assert_allclose(pairs[:, :, 0], fine_prof * rot, atol=2e-5 * np.abs(data).max())
    np.testing.assert_allclose(pairs[:, :-1, 1], fine_prof[:, 1:] * rot[:, :-1], atol=2e-5 * np.abs(data).max())
    assert np.all(pairs[:, -1, 1] == 0)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("up", [1, 2, 4, 7], ids=lambda u: f"up{u}")
def test_records_kernel_equals_twin_at_every_width(rng, vec, up):
    """Rows shorter than the window (zero-padded), a row stride wider than the data (as the
    direct matched filter leaves them), records not a multiple of VEC."""
    from clsas import cl
    from clsas.formation.bp_opencl import RecordsPlan

    width_or_skip("carrier_records", vec)
    n_meas, n_lags, n_data, stride = 2 * vec + 3, 53, 47, 56
    dtau = up * 0.55 / FC
    assert upsample_factor(FC, dtau) == up
    data = _profiles(rng, n_meas, n_data)
    tau0 = rng.uniform(1e-3, 9e-3, n_meas)
    want, w_fine, w_phi = carrier_records(data, n_lags, tau0, dtau, FC)
    plan = RecordsPlan(n_meas, n_lags, up, queue=cl.get_queue(), vec=vec)
    assert plan.vec == vec and plan.n_rec == want.shape[1] and plan.n_rec % vec
    wide = np.zeros((n_meas, stride), np.complex64)
    wide[:, :n_data] = data
    d_prof = plan.upload(wide, np.complex64)
    plan.begin()
    _, fine, phi = plan.enqueue(d_prof, stride, n_data, tau0, dtau, FC)
    got = plan.read(plan.d_pairs, want.shape, np.complex64)
    assert (fine, phi) == pytest.approx((w_fine, w_phi))
    assert np.abs(got - want).max() / np.abs(want).max() < 1e-6
    got2, *_ = plan(data, tau0, dtau, FC)  # the host-profile call: the same records
    assert np.abs(got2 - want).max() / np.abs(want).max() < 1e-6


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_records_kernel_with_a_row_map_equals_twin_on_the_rows_reordered(rng, vec):
    """Built with ROW_MAP, record row m is the twin's record of profile row row_of[m] (FFBP's tree
    order), with tau0 given in the records' order; a map that is not a permutation is refused."""
    from clsas import cl
    from clsas.formation.bp_opencl import RecordsPlan

    width_or_skip("carrier_records", vec)
    n_meas, n_lags, n_data, stride, up = 2 * vec + 3, 41, 37, 44, 3
    dtau = up * 0.55 / FC
    data = _profiles(rng, n_meas, n_data)
    tau0 = rng.uniform(1e-3, 9e-3, n_meas)
    order = rng.permutation(n_meas)
    want, *_ = carrier_records(data[order], n_lags, tau0[order], dtau, FC)
    plan = RecordsPlan(n_meas, n_lags, up, queue=cl.get_queue(), vec=vec, row_map=True)
    wide = np.zeros((n_meas, stride), np.complex64)
    wide[:, :n_data] = data
    d_prof = plan.upload(wide, np.complex64)
    plan.begin()
    plan.enqueue(d_prof, stride, n_data, tau0[order], dtau, FC, row_of=order)
    got = plan.read(plan.d_pairs, want.shape, np.complex64)
    assert np.abs(got - want).max() / np.abs(want).max() < 1e-6
    with pytest.raises(ValueError, match="row_of must be a permutation"):
        plan.enqueue(d_prof, stride, n_data, tau0, dtau, FC, row_of=np.zeros(n_meas, int))
    with pytest.raises(ValueError, match="without row_map"):
        RecordsPlan(n_meas, n_lags, up, queue=cl.get_queue()).enqueue(d_prof, stride, n_data, tau0, dtau, FC,
                                                                        row_of=order)


@needs_opencl
def test_ffbp_forms_its_leaves_from_the_rows_compression_left_on_the_device(monkeypatch):
    """FFBP on OpenCL takes the compression's rows on the device (no records made on the host) and
    forms the image the host-records path forms; profiles without rows take the host path."""
    import dataclasses

    from clsas.formation import ffbp_opencl

    ds = small_dataset([[0.02, -0.03, 0.6], [-0.05, 0.04, 0.7]], nx=12, ny=10)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.55, 0.75), 0.01)
    prof = clsas.compress(ds, backend="opencl")
    assert prof.on_device is not None
    host = clsas.formation.form(dataclasses.replace(prof, on_device=None), grid, "ffbp", backend="opencl")
    assert "ffbp_records_kernel" not in host.timings_s

    def no_host_records(*args, **kwargs):
        raise AssertionError("records made on the host")

    monkeypatch.setattr(ffbp_opencl, "carrier_records", no_host_records)
    resident = clsas.formation.form(prof, grid, "ffbp", backend="opencl")
    assert resident.timings_s["ffbp_records_kernel"] > 0
    ref = np.abs(host.values).max()
    assert np.abs(resident.values - host.values).max() / ref < 1e-6


@needs_opencl
def test_records_kernel_analytic():
    """A constant profile upsampled stays constant, a ramp stays a ramp; the records' phase is
    the carrier at the middle of each record, 2 pi fc (tau0 + (j + 1/2) dtau / up)."""
    from clsas.formation.bp_opencl import RecordsPlan

    n_lags, up = 20, 4
    dtau = 2.1 / FC  # fc dtau = 2.1: 4 x
    assert upsample_factor(FC, dtau) == up
    tau0 = np.array([1.234e-3, 5.678e-3])
    data = np.stack([np.ones(n_lags), np.arange(n_lags)]).astype(np.complex64)
    pairs, fine, _ = RecordsPlan(2, n_lags, up)(data, tau0, dtau, FC)
    n_rec = (n_lags - 1) * up + 1
    j = np.arange(n_rec)
    carrier = np.exp(2j * np.pi * FC * (tau0[:, None] + (j + 0.5) * dtau / up))
    level = np.stack([np.ones(n_rec), j / up])  # the constant, and the ramp at the fine samples
    np.testing.assert_allclose(pairs[:, :, 0], level * carrier, atol=2e-5 * n_lags)
    np.testing.assert_allclose(pairs[:, :-1, 1], (level[:, 1:]) * carrier[:, :-1], atol=2e-5 * n_lags)
    assert np.all(pairs[:, -1, 1] == 0) and fine == pytest.approx(dtau / up)


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_complex_image_equals_two_planes(vec):
    """bp's image written as one complex array (-DCOMPLEX_IMAGE) equals the two planes joined,
    over several chunks, to the last bit."""
    from clsas import cl
    from clsas.formation.bp_opencl import BackprojectPlan, selftest_scene

    width_or_skip("backproject", vec)
    grid, prof, tau0, fs, tx, rx, c, _ = selftest_scene()
    args = (prof, tau0, 1 / fs, FC, tx, rx, c)
    q = cl.get_queue()
    planes = BackprojectPlan(grid, 3, 40, queue=q, vec=vec, chunk=2)(*args)
    joined = BackprojectPlan(grid, 3, 40, queue=q, vec=vec, chunk=2, complex_image=True)(*args)
    assert joined.dtype == np.complex64 and np.array_equal(planes, joined)


def _scan():
    ds = small_dataset([[0.02, -0.03, 0.6], [-0.05, 0.04, 0.7]], nx=7, ny=6)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.55, 0.75), 0.01)
    return ds, grid


@needs_opencl
@pytest.mark.parametrize("algorithm", ["fft", "direct"])
@pytest.mark.parametrize("lag_step", [1, 4], ids=lambda d: f"step{d}")
def test_resident_equals_step_by_step_per_step(algorithm, lag_step):
    """Each step of the resident path against the step-by-step one on a small scene: the profiles
    it leaves on the device are those read back; the records made from them on the device are
    the host's; the image formed from them equals the step-by-step image (bp's tolerance)."""
    from clsas.formation.bp import Backprojector
    from clsas.formation.bp_opencl import BackprojectPlan, RecordsPlan

    ds, grid = _scan()
    prof = clsas.compress(ds, backend="opencl", algorithm=algorithm, lag_step=lag_step)
    rows = prof.on_device
    assert rows is not None and rows.n_cols == prof.n_lags and not prof.data.flags.writeable
    back = np.empty((rows.n_rows, rows.stride), np.complex64)
    import pyopencl as pcl

    pcl.enqueue_copy(rows.queue, back, rows.buffer)
    assert np.array_equal(back[:, : rows.n_cols], prof.data)  # step 1: compression's output, on the device
    plan = BackprojectPlan(grid, prof.n_meas, prof.n_lags, queue=rows.queue, complex_image=True)
    assert rows.valid(plan.queue, prof.data)
    records = RecordsPlan(prof.n_meas, prof.n_lags, upsample_factor(prof.fc_hz, prof.dtau_s), queue=rows.queue)
    resident = plan.from_device(rows, records, prof.tau0_s, prof.dtau_s, prof.fc_hz, prof.tx_positions,
                                prof.rx_positions, prof.c_mps)
    want_rec, *_ = carrier_records(prof.data, prof.n_lags, prof.tau0_s, prof.dtau_s, prof.fc_hz)
    got_rec = records.read(records.d_pairs, want_rec.shape, np.complex64)
    assert np.abs(got_rec - want_rec).max() / np.abs(want_rec).max() < 1e-6  # step 2: the records
    step = Backprojector(grid, backend="opencl", resident=False)(prof).values.ravel()
    assert np.abs(resident - step).max() / np.abs(step).max() < TOL["backproject"]  # step 3: the image
    image = Backprojector(grid, backend="opencl")(prof)  # the default takes the resident path
    assert np.abs(image.values.ravel() - step).max() / np.abs(step).max() < TOL["backproject"]


@needs_opencl
def test_reconstruct_takes_the_resident_path_and_equals_step_by_step():
    """``reconstruct`` with bp on OpenCL forms from the profiles compression left on the device
    (its provenance says the records were made from the compression's rows); its image equals
    the step-by-step one (and the NumPy twin's within bp's tolerance)."""
    from clsas.formation.bp import Backprojector

    ds, grid = _scan()
    image = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    assert image.provenance["bp"]["records"] == "rows", "reconstruct did not take the resident path"
    prof = clsas.compress(ds, backend="opencl", gate_s=image.plan.gate_s)
    step = Backprojector(grid, backend="opencl", resident=False)(prof).values
    twin = clsas.reconstruct(ds, grid, backend="numpy", formation="bp").values
    for want in (step, twin):
        assert np.abs(image.values - want).max() / np.abs(want).max() < TOL["backproject"]


@needs_opencl
def test_stale_rows_are_not_read():
    """Profiles whose device rows were overwritten by a later call of the same plan, whose data
    was replaced, or which were pickled, go the host way (and still give the right image)."""
    import pickle
    from dataclasses import replace

    from clsas.compression.compress_opencl import MatchedFilterPlan

    ds, grid = _scan()
    prof = clsas.compress(ds, backend="opencl", algorithm="direct")
    rows = prof.on_device
    from clsas import cl

    q = cl.get_queue()
    assert rows.valid(q, prof.data)
    assert not rows.valid(q, prof.data.copy())  # another array
    assert not replace(prof, data=prof.data.copy()).on_device.valid(q, prof.data.copy())
    assert not pickle.loads(pickle.dumps(rows)).valid(q, prof.data)
    plan = MatchedFilterPlan(2, 50, np.ones(4), 0, 10, np.ones(10), np.ones(2), queue=q)
    rows2 = plan.enqueue(np.zeros((2, 50)))
    assert rows2.valid(q) and rows2.valid(q, rows2.host)
    rows3 = plan.enqueue(np.zeros((2, 50)))  # the same plan again: its buffer holds the new rows
    assert not rows2.valid(q, rows2.host) and not rows2.valid(q) and rows3.valid(q, rows3.host)
    writable = rows3.host.copy()
    assert not rows3.valid(q, writable)  # a copy, even of the same values, is not the rows' array


@needs_opencl
def test_plans_are_reused_across_calls_with_the_same_shapes():
    """A second compression and bp of the same shapes reuse the first call's plans (no new
    buffers, no new uploads) and still apply what changed between the calls: a compression with
    another t0 equals its twin, not the first call's profiles."""
    from clsas import cl
    from clsas.formation.bp import Backprojector

    ds, grid = _scan()
    cl.release_reused()
    first = clsas.compress(ds, backend="opencl", algorithm="fft")
    shifted = clsas.Dataset(ds.signals, ds.tx_positions, ds.rx_positions, ds.fs_hz, ds.waveform,
                            t0_s=np.asarray(ds.t0_s) + 3e-5, c_mps=ds.c_mps)
    second = clsas.compress(shifted, backend="opencl", algorithm="fft")
    assert first.on_device.buffer is second.on_device.buffer  # the same plan's output buffer
    assert not first.on_device.valid(second.on_device.queue, first.data)  # overwritten by the second call
    want = clsas.compress(shifted, backend="numpy")
    assert np.abs(second.data - want.data).max() / np.abs(want.data).max() < TOL["compress_fft"]
    a = Backprojector(grid, backend="opencl")
    b = Backprojector(grid, backend="opencl")
    img_a, img_b = a(second), b(second)
    assert a._plan is b._plan and np.array_equal(img_a.values, img_b.values)
    step = Backprojector(grid, backend="opencl", resident=False)
    step(second)
    assert step._plan is not a._plan  # the step-by-step path keeps a plan of its own kind
    assert cl.release_reused() >= 2


@needs_opencl
def test_resident_default_reads_one_complex_image_and_leaves_it_on_the_device():
    """The default (resident) Backprojector builds bp with -DCOMPLEX_IMAGE and reads the image
    back once as complex64; the image it returns also names its device buffer
    (``image.on_device``), which holds the values until the plan's next call; the step-by-step
    path builds without it, reads two planes and leaves nothing."""
    import pyopencl as pcl

    from clsas import cl
    from clsas.formation.bp import Backprojector

    ds, grid = _scan()
    prof = clsas.compress(ds, backend="opencl")
    bp = Backprojector(grid, backend="opencl")
    image = bp(prof)
    plan = bp._plan
    assert plan.complex_image and plan.defines().get("COMPLEX_IMAGE") == 1 and plan.image_buffers == 1
    assert image.values.dtype == np.complex64 and image.timings_s["image_read"] > 0
    rows = image.on_device
    q = cl.get_queue()
    assert rows is not None and rows.valid(q, image.values) and (rows.n_rows, rows.n_cols) == (1, grid.size)
    back = np.empty(rows.stride, np.complex64)
    pcl.enqueue_copy(rows.queue, back, rows.buffer)
    assert np.array_equal(back[: grid.size], image.values.ravel())  # the device copy is the image
    assert not image.values.flags.writeable
    Backprojector(grid, backend="opencl")(prof)  # the same plan again: its buffer holds the new image
    assert not rows.valid(q, image.values)
    step = Backprojector(grid, backend="opencl", resident=False)
    old = step(prof)
    assert not step._plan.complex_image and "COMPLEX_IMAGE" not in step._plan.defines()
    assert old.on_device is None and np.abs(old.values - image.values).max() <= TOL["backproject"] * np.abs(
        old.values).max()


def _count_reads(monkeypatch) -> list:
    """Every read of device rows back to the host (clsas.cl.DeviceRows), recorded from here on."""
    from clsas.cl.plan import DeviceRows

    reads, read = [], DeviceRows._read

    def counted(rows):
        reads.append((rows.n_rows, rows.n_cols))
        return read(rows)

    monkeypatch.setattr(DeviceRows, "_read", counted)
    return reads


@needs_opencl
@pytest.mark.parametrize("algorithm", ["fft", "direct"])
def test_compress_then_bp_reads_no_profile_back_and_forms_the_same_image(monkeypatch, algorithm):
    """Compression on OpenCL leaves its profiles on the device and bp reads them there: neither
    ``compress``, ``Backprojector`` nor ``reconstruct`` reads them back. The image is bit-identical
    to the one formed from the rows once their host copy was read (the path before the rows were
    read lazily), and to the one formed from that host copy uploaded; asking for ``data`` reads
    the rows once, and equals the NumPy twin's profiles."""
    from dataclasses import replace

    from clsas.formation.bp import Backprojector

    ds, grid = _scan()
    reads = _count_reads(monkeypatch)
    prof = clsas.compress(ds, backend="opencl", algorithm=algorithm)
    image = Backprojector(grid, backend="opencl")(prof)
    assert image.provenance["bp"]["records"] == "rows" and prof.timings_s["compress_kernel"] > 0
    assert reads == [] and not prof.on_device.is_read, "the profiles were read back"
    whole = clsas.reconstruct(ds, grid, backend="opencl", formation="bp")
    assert whole.provenance["bp"]["records"] == "rows" and reads == []

    data = prof.data
    assert reads == [(prof.n_meas, prof.n_lags)] and prof.data is data is prof.on_device.host  # read once
    read_first = Backprojector(grid, backend="opencl")(prof)
    uploaded = Backprojector(grid, backend="opencl")(replace(prof, data=data.copy()))
    assert read_first.provenance["bp"]["records"] == "rows" and uploaded.provenance["bp"]["records"] == "uploaded"
    assert np.array_equal(image.values, read_first.values) and np.array_equal(image.values, uploaded.values)
    assert len(reads) == 1
    twin = clsas.compress(ds, backend="numpy", algorithm=algorithm)
    assert np.abs(prof.data - twin.data).max() / np.abs(twin.data).max() < TOL["compress_fft"]


@needs_opencl
def test_a_plan_reads_the_rows_it_lent_before_overwriting_them(monkeypatch):
    """Profiles whose rows a later call of the same (reused) plan overwrites keep their data: the
    plan reads the rows still held and unread first, so each keeps its own profiles (not the later
    call's), never offers the overwritten rows, and pickles with its data; rows nobody holds any
    more are not read."""
    import pickle

    ds, grid = _scan()
    shifted = clsas.Dataset(ds.signals, ds.tx_positions, ds.rx_positions, ds.fs_hz, ds.waveform,
                            t0_s=np.asarray(ds.t0_s) + 3e-5, c_mps=ds.c_mps)
    reads = _count_reads(monkeypatch)
    first = clsas.compress(ds, backend="opencl", algorithm="direct")
    clsas.compress(shifted, backend="opencl", algorithm="direct")  # dropped at once: nothing holds its rows
    assert first.on_device.is_read and len(reads) == 1 and first.device_rows() is None
    second = clsas.compress(shifted, backend="opencl", algorithm="direct")
    assert len(reads) == 1 and second.on_device.buffer is first.on_device.buffer and second.device_rows() is not None
    for prof, data in ((first, ds), (second, shifted)):
        want = clsas.compress(data, backend="numpy", algorithm="direct").data
        assert np.abs(prof.data - want).max() / np.abs(want).max() < TOL["compress_fft"]
    third = clsas.compress(ds, backend="opencl", algorithm="direct")
    back = pickle.loads(pickle.dumps(third))  # another process: the data travels, the rows do not
    assert np.array_equal(back.data, third.data) and back.device_rows() is None
    image = clsas.Backprojector(grid, backend="opencl")(first)  # from its host copy, uploaded
    assert image.provenance["bp"]["records"] == "uploaded"
