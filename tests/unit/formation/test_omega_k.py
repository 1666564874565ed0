"""ω-k (wavenumber-domain) formation: against backprojection, its refusals, its Stolt kernel."""

import dataclasses

import numpy as np
import pytest
from conftest import BACKENDS, OPENCL_MISSING, TOL, needs_opencl, width_or_skip

import clsas
from clsas.formation import error_to_signal_db, form
from clsas.formation.planar import NotPlanarUniform, planar_aperture, well_sampled_cone
from clsas.formation.stolt_numpy import spread

FS = 96e3
F_TOP = 30e3
# stated accuracy of ω-k against bp inside the well-sampled cone on these small scans (the
# measured figure is about -45 dB; the dense benchmark's is in the README)
STATED_DB = -35.0


def _scan(points, n=24, pitch=0.004, pattern="serpentine", temperature_c=None, duration_s=2e-3, **ap_kw):
    w = clsas.lfm_chirp(20e3, F_TOP, duration_s, FS, taper=0.1)
    ap = clsas.raster_aperture(n, n, pitch * (n - 1), pitch * (n - 1), pattern=pattern, **ap_kw)
    return clsas.simulate(clsas.Scene(np.asarray(points, float)), ap, w, FS, temperature_c=temperature_c,
                          chirp={"f_start_hz": 20e3, "f_stop_hz": F_TOP, "duration_s": duration_s})


GRID = clsas.VoxelGrid.from_bounds((-0.024, 0.024), (-0.024, 0.024), (0.23, 0.274), 0.004)
TARGETS = [[0.008, -0.004, 0.25], [-0.012, 0.012, 0.262]]


def _profiles(ds, grid):
    """Compressed over the grid's gate (on OpenCL where there is a device: the NumPy twin of
    compression is slow, and it is not what is tested here)."""
    return clsas.compress(ds, gate_s=clsas.types.rangegate.plan_reconstruction(ds, grid, []).gate_s)


@pytest.fixture(scope="module")
def scan():
    ds = _scan(TARGETS)
    prof = _profiles(ds, GRID)
    return ds, prof, clsas.backproject(prof, GRID, backend="numpy")


def _cone(ds, grid):
    return well_sampled_cone(ds.tx_positions, ds.rx_positions, grid, F_TOP, float(np.mean(ds.c_mps)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_target_lands_in_its_voxel(backend):
    target = [0.008, -0.004, 0.25]
    ds = _scan([target], n=16)
    img = clsas.reconstruct(ds, GRID, backend=backend, formation="omega-k")
    assert img.provenance["formation"] == "omega-k"
    assert img.peaks(1)[0].index == GRID.index_of(np.array(target))


@pytest.mark.parametrize("backend", BACKENDS)
def test_omega_k_equals_bp_inside_the_cone(scan, backend):
    ds, prof, ref = scan
    cone = _cone(ds, GRID)
    assert cone.all()  # a lambda/2.9 lattice at 0.23-0.27 m: every voxel is well sampled
    img = form(prof, GRID, "omega-k", backend=backend)
    assert error_to_signal_db(img, ref, cone) < STATED_DB
    # amplitude and phase, not only the shape: the peak voxel agrees to a few percent
    i = ref.peaks(1)[0].index
    assert abs(img.values[i] / ref.values[i] - 1) < 0.03


def test_the_bistatic_compensation_matters(scan):
    ds, prof, ref = scan
    with_it = error_to_signal_db(form(prof, GRID, "omega-k", backend="numpy"), ref)
    midpoint = error_to_signal_db(form(prof, GRID, "omega-k", backend="numpy", bistatic=False), ref)
    one_term = error_to_signal_db(form(prof, GRID, "omega-k", backend="numpy", phase_tol=10.0), ref)
    # 4 cm baseline at 0.25 m: d^2/4R = 1.6 mm of path, 0.9 rad at 30 kHz
    assert midpoint > -15.0
    assert with_it < STATED_DB
    assert with_it < one_term - 5 < midpoint - 10


def test_visiting_order_does_not_matter():
    prof_s = _profiles(_scan(TARGETS, n=12), GRID)
    prof_r = _profiles(_scan(TARGETS, n=12, pattern="raster"), GRID)
    perm = np.random.default_rng(0).permutation(prof_r.n_meas)
    shuffled = clsas.Profiles(prof_r.data[perm], prof_r.tau0_s[perm], prof_r.dtau_s, prof_r.fc_hz, "matched",
                              "numpy", prof_r.tx_positions[perm], prof_r.rx_positions[perm], prof_r.c_mps)
    a = form(prof_s, GRID, "omega-k", backend="numpy").values
    b = form(prof_r, GRID, "omega-k", backend="numpy").values
    c = form(shuffled, GRID, "omega-k", backend="numpy").values
    assert error_to_signal_db(b, a) < -60 and error_to_signal_db(c, a) < -60


def test_two_microphones_and_air_that_changes():
    # two offset groups (a lattice each, summed) and one speed of sound per measurement
    n = 16
    temps = np.linspace(18.0, 24.0, 2 * n * n)
    ds = _scan(TARGETS[:1], n=n, rx_offsets_m=[[0.02, 0.0, 0.0], [0.0, 0.03, 0.0]], temperature_c=temps)
    assert np.ptp(ds.c_mps) > 3
    grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (0.238, 0.262), 0.004)
    prof = _profiles(ds, grid)
    ref = clsas.backproject(prof, grid, backend="numpy")
    img = form(prof, grid, "omega-k", backend="numpy")
    assert img.provenance["omega_k"]["groups"] == 2
    assert error_to_signal_db(img, ref, _cone(ds, grid)) < STATED_DB
    # one mean c instead would be far off: the per-measurement speeds are used
    prof = dataclasses.replace(prof, c_mps=float(np.mean(ds.c_mps)))  # Profiles are immutable once built
    assert error_to_signal_db(form(prof, grid, "omega-k", backend="numpy"), ref) > -20


def test_range_profiles_from_elsewhere_and_fmcw(scan):
    ds, _, _ = scan
    # analytic profiles at the recording's rate, as an outside deconvolution would give them
    gate = clsas.types.rangegate.plan_reconstruction(ds, GRID, []).gate_s
    prof = clsas.compress(ds, gate_s=gate, lag_step=1)
    ext = clsas.Profiles.from_range_profiles(prof.carrier(), tau0_s=prof.tau0_s, dtau_s=prof.dtau_s,
                                             tx_positions=ds.tx_positions, rx_positions=ds.rx_positions,
                                             c_mps=ds.c_mps, fc_hz=prof.fc_hz)
    ref = clsas.backproject(ext, GRID, backend="numpy")
    img = clsas.reconstruct(ext, GRID, backend="numpy", formation="omega-k")
    assert error_to_signal_db(img, ref) < STATED_DB
    target = np.array(TARGETS[0])
    long = _scan([target], n=12, duration_s=10e-3)  # echoes while the chirp plays: fmcw's case
    fm = clsas.reconstruct(long, GRID, compression="fmcw", formation="omega-k")
    assert fm.peaks(1)[0].index == GRID.index_of(target)


@pytest.mark.slow
def test_upsample_forms_the_aliased_angles_too():
    # 12 mm stops (about lambda at 30 kHz): the cone is small and bp has grating lobes about
    # lambda R / 2d = 0.12-0.18 m off the target; upsample="auto" forms every angle (a line
    # through the target and its lobes keeps this fast)
    ds = _scan([[0.008, 0.0, 0.25]], n=12, pitch=0.012)
    grid = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (0.0, 0.0), (0.25, 0.25), 0.005)
    prof = _profiles(ds, grid)
    ref = clsas.backproject(prof, grid, backend="numpy")
    assert not _cone(ds, grid).any()
    plain = form(prof, grid, "omega-k", backend="numpy")
    full = form(prof, grid, "omega-k", backend="numpy", upsample="auto")
    assert error_to_signal_db(plain, ref) > -20  # bp's grating lobes are not formed...
    assert error_to_signal_db(full, ref) < -30  # ...unless asked for
    assert full.provenance["omega_k"]["lattices"][0]["upsample"] > 1


@pytest.mark.parametrize("case", ["circle", "jitter", "missing", "tilted", "crossing", "line"])
def test_apertures_that_are_not_planar_uniform_are_refused(case):
    prof = _profiles(_scan(TARGETS[:1], n=8), GRID)
    tx, rx = prof.tx_positions.copy(), prof.rx_positions.copy()
    keep = np.arange(prof.n_meas)
    grid = GRID
    if case == "circle":
        ap = clsas.circular_aperture(64, 0.5)
        tx, rx, keep = ap.tx_positions, ap.rx_positions, keep[:64]
        grid = clsas.VoxelGrid.from_bounds((-0.05, 0.05), (-0.05, 0.05), (0.0, 0.0), 0.01)
    elif case == "jitter":
        tx[:, :2] += np.random.default_rng(1).normal(0, 1e-3, (len(tx), 2))
        rx[:, :2] = tx[:, :2] + [0.04, 0.0]
    elif case == "missing":
        keep = keep[1:]
    elif case == "tilted":
        tx[:, 2] += 0.1 * tx[:, 0]
        rx[:, 2] += 0.1 * rx[:, 0]
    elif case == "crossing":
        grid = clsas.VoxelGrid.from_bounds((-0.02, 0.02), (-0.02, 0.02), (-0.1, 0.1), 0.02)
    elif case == "line":
        tx[:, 1] = rx[:, 1] = 0.0
        keep = keep[:8]
    bad = clsas.Profiles(prof.data[keep], prof.tau0_s[keep], prof.dtau_s, prof.fc_hz, "matched", "numpy",
                         tx[: len(keep)] if case == "circle" else tx[keep], rx[: len(keep)] if case == "circle"
                         else rx[keep], prof.c_mps)
    with pytest.raises(ValueError, match="planar, uniform") as err:
        form(bad, grid, "omega-k", backend="numpy")
    assert "ffbp" in str(err.value) and "'bp'" in str(err.value)
    assert isinstance(err.value, NotPlanarUniform)


def test_lattice_and_cone():
    ds = _scan(TARGETS[:1], n=6, pattern="raster")
    ap = planar_aperture(ds.tx_positions, ds.rx_positions, GRID, 1e-4)
    (g,) = ap.groups
    assert ap.axis == 2 and g.shape == (6, 6) and np.allclose(g.spacing_uv, 0.004)
    assert np.allclose(g.baseline_uvw, [-0.04, 0, 0])
    # the paper's 18 x 12 stops over 1 m: nothing is well sampled at 1.5 m
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, FS)
    paper = clsas.raster_aperture(18, 12, 1.0, 1.0)
    grid = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (-0.2, 0.2), (1.4, 1.6), 0.05)
    assert not well_sampled_cone(paper.tx_positions, paper.rx_positions, grid, 30e3, 343.0).any()
    # a lambda/4 lattice samples every angle
    fine = clsas.raster_aperture(10, 10, 0.025, 0.025)
    assert well_sampled_cone(fine.tx_positions, fine.rx_positions, grid, 30e3, 343.0).all()
    del w
    with pytest.raises(ValueError, match="f_max_hz"):
        well_sampled_cone(fine.tx_positions, fine.rx_positions, grid, float("nan"), 343.0)
    with pytest.raises(ValueError, match="rx"):
        well_sampled_cone(fine.tx_positions, fine.rx_positions[:3], grid, 30e3, 343.0)


def test_options_and_inputs_are_checked(scan):
    ds, prof, _ = scan
    for opts, err, match in [
        ({"zero_pad": 2}, ValueError, "unknown option"),
        ({"window": "kaiser"}, ValueError, "window"),
        ({"upsample": 0}, ValueError, "upsample"),
        ({"upsample": 1.5}, TypeError, "upsample"),
        ({"taper": 1.0}, ValueError, "taper"),
        ({"pad": 0.5}, ValueError, "pad"),
        ({"pad_time": float("nan")}, ValueError, "pad_time"),
        ({"phase_tol": -1}, ValueError, "phase_tol"),
        ({"kernel_width": 40}, ValueError, "kernel_width"),
        ({"bistatic": "yes"}, TypeError, "bistatic"),
    ]:
        with pytest.raises(err, match=match):
            form(prof, GRID, "omega-k", backend="numpy", **opts)
    nan = clsas.Profiles(prof.data.copy(), prof.tau0_s, prof.dtau_s, prof.fc_hz, "matched", "numpy",
                         prof.tx_positions, prof.rx_positions, prof.c_mps)
    nan.data[3, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        form(nan, GRID, "omega-k", backend="numpy")
    with pytest.raises(TypeError, match="Profiles"):
        form(prof.data, GRID, "omega-k")
    with pytest.raises(ValueError, match="formation_options"):
        clsas.reconstruct(prof, GRID, backend="numpy", formation="omega-k", formation_options={"depth": 3})


@needs_opencl
def test_stolt_kernel_equals_its_twin():
    from clsas import cl
    from clsas.formation.stolt_opencl import StoltPlan

    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    plan = StoltPlan(queue=cl.get_queue())
    want = spread(spec, k, ku, kv, p)
    got = plan(spec, k, ku, kv, p)
    assert np.any(want != 0) and np.any(np.all(want == 0, axis=(0, 2)))  # kept and dropped columns
    assert np.abs(got - want).max() / np.abs(want).max() < TOL["stolt"]
    # a second, larger call reuses the plan (buffers grow)
    spec2 = np.tile(spec, (3, 1))
    got2 = plan(spec2, k, np.tile(ku, 3), np.tile(kv, 3), p)
    assert np.abs(got2[:, : len(ku)] - want).max() / np.abs(want).max() < TOL["stolt"]


@needs_opencl
@pytest.mark.parametrize("cells", [6, 4], ids=lambda w: f"kernel{w}")
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_stolt_kernel_equals_its_twin_at_every_width(vec, cells):
    # the kernel's columns are its vector lanes: every width the device accepts, with a ragged
    # last work-item (37 columns), evanescent and windowed samples and folded positions; the
    # spreading kernel at 6 cells and at omega-k's default 4
    from clsas import cl
    from clsas.formation.stolt_opencl import StoltPlan

    width_or_skip("stolt_spread", vec)
    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    p = dataclasses.replace(p, width=cells)
    got = StoltPlan(queue=cl.get_queue(), vec=vec)(spec, k, ku, kv, p)
    want = spread(spec, k, ku, kv, p)
    assert np.abs(got - want).max() / np.abs(want).max() < TOL["stolt"]


def test_cli_reconstruct_with_a_formation(tmp_path, capsys):
    from clsas.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text(
        "[chirp]\nf_start_hz = 20000.0\nf_stop_hz = 30000.0\nduration_s = 0.002\nfs_hz = 96000.0\ntaper = 0.1\n"
        "[aperture]\nnx = 16\nny = 16\nwidth_m = 0.06\nheight_m = 0.06\n"
        "[[points]]\nposition_m = [0.008, -0.004, 0.25]\namplitude = 1.0\n"
        "[grid]\nx_m = [-0.024, 0.024]\ny_m = [-0.024, 0.024]\nz_m = [0.234, 0.266]\nspacing_m = 0.004\n")
    scan = tmp_path / "scan.h5"
    assert main(["simulate", str(scene), str(scan), "-q"]) == 0
    out = tmp_path / "img.h5"
    assert main(["reconstruct", str(scan), "--formation", "omega-k", "--formation-option", "pad_time=2",
                 "--formation-option", "window=hann", "--out", str(out), "-q"]) == 0
    assert "peak (+0.008, -0.004, 0.250)" in capsys.readouterr().out
    from clsas.types.image import Image

    assert Image.load(out).provenance["formation"] == "omega-k"
    assert main(["reconstruct", str(scan), "--formation", "omega-k", "--formation-option", "bogus=1", "-q"]) == 2
    assert "unknown option" in capsys.readouterr().err


@pytest.mark.parametrize("frame", ["normal-x", "behind"])
def test_any_plane_normal_and_either_side(frame):
    # the same scan in a frame where the aperture's normal is x, or with the scene behind it (-z)
    ds = _scan(TARGETS, n=12)
    prof = _profiles(ds, GRID)
    if frame == "normal-x":
        perm = [2, 0, 1]  # new (x, y, z) = old (z, x, y)
        tx, rx = prof.tx_positions[:, perm], prof.rx_positions[:, perm]
        grid = clsas.VoxelGrid(GRID.z_m, GRID.x_m, GRID.y_m)
    else:
        flip = np.array([1.0, 1.0, -1.0])
        tx, rx = prof.tx_positions * flip, prof.rx_positions * flip
        grid = clsas.VoxelGrid(GRID.x_m, GRID.y_m, -GRID.z_m[::-1])
    moved = clsas.Profiles(prof.data, prof.tau0_s, prof.dtau_s, prof.fc_hz, "matched", "numpy", tx, rx, prof.c_mps)
    ref = clsas.backproject(moved, grid, backend="numpy")
    img = form(moved, grid, "omega-k", backend="numpy")
    assert error_to_signal_db(img, ref) < STATED_DB


@pytest.mark.slow
def test_formation_benchmark_writes_its_table(tmp_path):
    import json

    from bench import run_formation

    res = run_formation(out_dir=tmp_path, scale=0.1, cases=("dense", "circular"), sides=(6, 8), plots=False)
    js = json.loads(next(tmp_path.glob("*-formation-*-quick.json")).read_text())
    dense, circ = js["cases"]
    rows = {r["formation"]: r for r in dense["rows"]}
    assert rows["bp"]["time_s"] > 0 and rows["omega-k"]["error_cone_db"] < -30
    assert dense["cone_fraction"] > 0.5
    wk = {r["formation"]: r for r in circ["rows"]}["omega-k"]
    assert "ffbp" in wk["refused"] and circ["cone_fraction"] is None
    assert set(js["scaling"]) >= {"bp", "omega-k"}
    md = next(tmp_path.glob("*-formation-*-quick.md")).read_text()
    assert "| dense | omega-k |" in md and "refused" in md
    assert res["paths"]["json"].endswith(".json")


def test_stolt_interpolation_equals_the_direct_sum():
    # spreading + FFT + de-apodisation against the non-uniform DFT it stands for, term by term
    from clsas.formation.stolt_numpy import columns_to_depths, stolt_strengths
    from clsas.formation.stolt_opencl import StoltPlan

    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    n_z = p.n_cells // 2
    got = columns_to_depths(spread(spec, k, ku, kv, p), n_z, p)
    c0, alpha, _, valid = stolt_strengths(spec, k, ku, kv, p)
    kz = np.sign(k) * np.sqrt(np.maximum(k[None, :] ** 2 - (ku**2 + kv**2)[:, None], 0))  # k < 0: kz < 0
    ell = np.arange(n_z) - n_z // 2
    phase = np.exp(1j * kz[:, :, None] * ell[None, None, :] * p.dz_m)  # (cols, f, z)
    for term in range(p.n_terms):
        want = np.einsum("cf,cfz->cz", np.where(valid, c0 * alpha**term, 0), phase)
        assert np.abs(got[term] - want).max() < 1e-4 * np.abs(want).max()


@pytest.mark.parametrize("n_z", [1, 6, 11, 12], ids=lambda n: f"nz{n}")
def test_terms_to_depths_is_the_weighted_sum_of_columns_to_depths(n_z):
    # omega-k's fused step: the terms weighted per depth and summed, in the cells' precision
    from clsas.formation.stolt_numpy import columns_to_depths, terms_to_depths
    from clsas.formation.stolt_opencl import StoltPlan

    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    cells = spread(spec, k, ku, kv, p)
    rng = np.random.default_rng(5)
    factors = rng.normal(size=(p.n_terms, n_z)) + 1j * rng.normal(size=(p.n_terms, n_z))
    want = np.einsum("pcz,pz->cz", columns_to_depths(cells, n_z, p), factors)
    got = terms_to_depths(cells.copy(), n_z, p, factors)
    assert got.dtype == cells.dtype
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()
    got32 = terms_to_depths(cells.astype(np.complex64), n_z, p, factors)
    assert got32.dtype == np.complex64 and np.abs(got32 - want).max() < 1e-5 * np.abs(want).max()
    # overwrite=True (omega-k's own call: the IFFT works in the cells) gives the same values
    np.testing.assert_array_equal(terms_to_depths(cells.astype(np.complex64), n_z, p, factors, overwrite=True),
                                  got32)


@pytest.mark.parametrize("dtype", [np.complex64, np.complex128], ids=["c64", "c128"])
def test_dft_axis_direct_product_equals_the_chirp_z(monkeypatch, dtype):
    # small axes take the DFT matrix's product, large ones the chirp-z: the same values
    from clsas.formation import omega_k_transforms as tr

    rng = np.random.default_rng(11)
    a = (rng.normal(size=(37, 5, 3)) + 1j * rng.normal(size=(37, 5, 3))).astype(dtype)
    k = 2 * np.pi * np.fft.fftfreq(37, 0.004)  # FFT order, as omega-k passes it
    x = np.linspace(-0.03, 0.05, 11)
    want = np.einsum("iq,q...->i...", np.exp(1j * np.outer(x, k)), a.astype(np.complex128))
    tol = 1e-5 if dtype == np.complex64 else 1e-10
    for direct_max in (0, 1 << 30):
        monkeypatch.setattr(tr, "DIRECT_MAX", direct_max)
        got = tr.dft_axis(a, k, x, 1)
        assert got.dtype == dtype and np.abs(got - want).max() < tol * np.abs(want).max()


def test_planar_aperture_is_remembered_by_content_and_shared_read_only():
    # auto sizes omega-k and omega-k then forms the image: one analysis serves both
    from clsas.formation.planar import NotPlanarUniform, planar_aperture

    ap = clsas.raster_aperture(6, 5, 0.05, 0.04)
    tx, rx = ap.tx_positions.copy(), ap.rx_positions.copy()
    grid = clsas.VoxelGrid(np.linspace(-0.02, 0.02, 5), np.linspace(-0.02, 0.02, 4), np.linspace(0.3, 0.4, 3))
    first = planar_aperture(tx, rx, grid, 1e-4)
    assert planar_aperture(tx.copy(), rx.copy(), grid, 1e-4) is first
    assert all(not g.index.flags.writeable and not g.iu.flags.writeable for g in first.groups)
    moved = tx.copy()
    moved[:, 0] *= 2  # another lattice spacing: analysed anew
    rx2 = rx.copy()
    rx2[:, 0] *= 2
    assert planar_aperture(moved, rx2, grid, 1e-4).groups[0].spacing_uv != first.groups[0].spacing_uv
    bad = tx.copy()
    bad[3, 0] += 3e-3  # a stop moved: refused, and refused again from memory with the same words
    for _ in range(2):
        with pytest.raises(NotPlanarUniform, match="do not fill a 6 x 5 lattice"):
            planar_aperture(bad, rx, grid, 1e-4)


def test_terms_to_depths_leaves_its_cells_and_refuses_more_depths_than_cells():
    from clsas.formation.stolt_numpy import terms_to_depths
    from clsas.formation.stolt_opencl import StoltPlan

    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    cells = spread(spec, k, ku, kv, p)
    kept = cells.copy()
    terms_to_depths(cells, 5, p, np.ones((p.n_terms, 5)))
    np.testing.assert_array_equal(cells, kept)
    with pytest.raises(ValueError, match="n_z must be between 1 and the cells per column"):
        terms_to_depths(cells, p.n_cells + 1, p, np.ones((p.n_terms, p.n_cells + 1)))


def test_columns_in_several_chunks_give_the_same_image_and_report_progress():
    # omega-k's Stolt step in chunks of 7 columns against one chunk: the same image; progress
    # counts up to every column
    ds = _scan(TARGETS, n=12)
    prof = _profiles(ds, GRID)
    one = form(prof, GRID, "omega-k", backend="numpy")
    seen = []
    many = form(prof, GRID, "omega-k", backend="numpy", chunk=7,
                progress=lambda done, total: seen.append((done, total)))
    assert np.abs(many.values - one.values).max() <= 1e-5 * np.abs(one.values).max()
    done = [d for d, _ in seen]
    assert len(seen) > 2 and done == sorted(done) and done[-1] == seen[-1][1]
    assert max(b - a for a, b in zip([0, *done[:-1]], done, strict=True)) <= 7


# -- the direct sum at the depths (stolt_depths) ----------------------------------------------
def _depth_factors(p, n_z, seed=7):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(p.n_terms, n_z)) + 1j * rng.normal(size=(p.n_terms, n_z))


@pytest.mark.parametrize("n_z", [1, 7, 40], ids=lambda n: f"nz{n}")
def test_direct_sum_equals_the_spread_path(n_z):
    # the twin of stolt_depths against spread + FFT + de-apodisation + terms (which approximate the
    # same sum; a wide kernel makes that approximation tight)
    from clsas.formation.stolt_numpy import direct, terms_to_depths
    from clsas.formation.stolt_opencl import StoltPlan

    spec, k, ku, kv, p = StoltPlan.selftest_inputs()
    p = dataclasses.replace(p, n_cells=max(2 * n_z, 24), width=10)
    fac = _depth_factors(p, n_z)
    want = terms_to_depths(spread(spec, k, ku, kv, p), n_z, p, fac)
    got = direct(spec, k, ku, kv, p, n_z, fac)
    assert np.abs(got - want).max() < 1e-7 * np.abs(want).max()
    with pytest.raises(ValueError, match="factors"):
        direct(spec, k, ku, kv, p, n_z + 1, fac)


def test_direct_sum_of_one_plane_wave_analytic():
    # one column at normal incidence (ku = kv = 0: kz = k), one frequency, no baseline: the sum is
    # d 2 pi / k (1 + i / (k zref)) exp(i k z) at each depth z = zc + (l - n_z // 2) dz
    from clsas import cl
    from clsas.formation.stolt_numpy import StoltParams, direct
    from clsas.formation.stolt_opencl import StoltDepthsPlan

    kk, d, n_z = 900.0, 0.3 - 0.2j, 45
    p = StoltParams(dz_m=0.005, zc_m=0.8, zref_m=0.75, baseline_uv=(0.0, 0.0), n_cells=96, width=4, n_terms=1,
                    s1=0.5, s2=0.6)
    z = p.zc_m + (np.arange(n_z) - n_z // 2) * p.dz_m
    want = d * 2 * np.pi / kk * (1 + 1j / (kk * p.zref_m)) * np.exp(1j * kk * z)
    args = (np.array([[d]]), np.array([kk]), np.zeros(1), np.zeros(1), p, n_z, np.ones((1, n_z)))
    np.testing.assert_allclose(direct(*args)[0], want, rtol=1e-12)
    if OPENCL_MISSING is None:
        got = StoltDepthsPlan(queue=cl.get_queue())(*args)[0]
        assert np.abs(got - want).max() < 2e-5 * np.abs(want).max()


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
def test_stolt_depths_kernel_equals_its_twin_at_every_width(vec):
    # VEC columns per work-item with a ragged last one (37 columns), evanescent and windowed
    # samples, negative frequencies, three terms; 40 depths (two runs of rotations, the second
    # partial) and 5 (one short run); a second, larger call reuses the plan
    from clsas import cl
    from clsas.formation.stolt_numpy import direct
    from clsas.formation.stolt_opencl import StoltDepthsPlan

    width_or_skip("stolt_depths", vec)
    spec, k, ku, kv, p = StoltDepthsPlan.selftest_inputs()
    plan = StoltDepthsPlan(queue=cl.get_queue(), vec=vec)
    for n_z in (40, 5):
        fac = _depth_factors(p, n_z)
        want = direct(spec, k, ku, kv, p, n_z, fac)
        assert np.any(want != 0) and np.any(np.all(want == 0, axis=1))  # kept and dropped columns
        got = plan(spec, k, ku, kv, p, n_z, fac)
        assert got.dtype == np.complex64
        assert np.abs(got - want).max() / np.abs(want).max() < TOL["stolt"]
    got2 = plan(np.tile(spec, (3, 1)), k, np.tile(ku, 3), np.tile(kv, 3), p, 5, fac)
    assert np.abs(got2[: len(ku)] - want).max() / np.abs(want).max() < TOL["stolt"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_omega_k_direct_and_spread_depths_agree(backend):
    # the two ways to the depths give one image (to the spread's own error, about 1e-3), "auto"
    # names the one it took, and the option is checked by name
    prof, grid = _depths_case()
    imgs = {d: form(prof, grid, "omega-k", backend=backend, depths=d) for d in ("direct", "spread", "auto")}
    peak = np.abs(imgs["direct"].values).max()
    assert np.abs(imgs["direct"].values - imgs["spread"].values).max() < 5e-3 * peak
    took = imgs["auto"].provenance["omega_k"]["depths"]
    assert took == ("direct" if backend == "opencl" else "spread")
    assert imgs["direct"].provenance["omega_k"]["depths"] == "direct"
    with pytest.raises(ValueError, match="depths"):
        form(prof, grid, "omega-k", backend=backend, depths="fft")


def _depths_case():
    ap = clsas.raster_aperture(12, 12, 0.0616, 0.0616)
    w = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.1)
    ds = clsas.simulate(clsas.Scene(np.array([[0.005, -0.004, 0.64], [-0.01, 0.006, 0.68]])), ap, w, 96e3,
                        snr_db=40, seed=1, chirp={"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 2e-3})
    grid = clsas.VoxelGrid(np.linspace(-0.02, 0.02, 9), np.linspace(-0.02, 0.02, 9), np.linspace(0.6, 0.72, 25))
    return clsas.compress(ds, backend="numpy"), grid
