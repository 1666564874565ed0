"""Image quality: target-to-clutter ratio, comparison of two images, `clsas compare`."""

import numpy as np
import pytest
from conftest import small_dataset

import clsas
from clsas.cli import main
from clsas.presenting.quality import box_mask, compare, same_grid, tcr_db
from clsas.types.image import Image

SP = 0.01


def _grid(nx=12, ny=10, nz=8, x0=-0.05):
    return clsas.VoxelGrid(x0 + SP * np.arange(nx), -0.04 + SP * np.arange(ny), 0.5 + SP * np.arange(nz))


def _clutter(rng, grid, level):
    phase = np.exp(2j * np.pi * rng.random(grid.shape))
    return level * phase


def _blobs(grid, centres, amps, width=0.012):
    pts = grid.points()
    v = np.zeros(len(pts), complex)
    for c, a in zip(centres, amps, strict=True):
        v += a * np.exp(-np.sum((pts - c) ** 2, axis=1) / (2 * width**2)) * np.exp(1j * a)
    return v.reshape(grid.shape)


def test_tcr_is_peak_over_rms_clutter(rng):
    g = _grid()
    values = _clutter(rng, g, 0.1)  # |v| = 0.1 everywhere: RMS 0.1
    values[3, 4, 2] = 10.0 * np.exp(0.7j)
    box = ((-0.03, -0.01), (-0.01, 0.01), (0.51, 0.53))  # 3 x 3 x 3 voxels about the target
    assert box_mask(g, box).sum() == 27
    img = Image(values, g)
    assert tcr_db(img, box) == pytest.approx(20 * np.log10(10.0 / 0.1))
    # a clutter box around the target: its voxels at 0.5, the target box left out of it
    ring = ((-0.05, 0.01), (-0.04, 0.03), (0.5, 0.56))
    in_ring = box_mask(g, ring) & ~box_mask(g, box)
    values[in_ring] *= 5.0
    assert tcr_db(Image(values, g), box, ring) == pytest.approx(20 * np.log10(10.0 / 0.5))
    # clutter of two levels: RMS = sqrt((1 + 9) / 2) when half the outside voxels are each
    two = np.where(np.arange(g.size).reshape(g.shape) % 2 == 0, 1.0, 3.0) * np.exp(1j * rng.random(g.shape))
    cube = ((-0.03, -0.02), (-0.01, 0.0), (0.51, 0.52))  # 2 x 2 x 2 voxels: as many of each level left out
    two[2, 3, 1] = 20.0
    assert tcr_db(Image(two, g), cube) == pytest.approx(20 * np.log10(20.0 / np.sqrt(5.0)))


def test_boxes_on_a_plane_grid_and_their_errors():
    g = clsas.VoxelGrid.plane("z", at_m=0.1, u_m=(-0.1, 0.1), v_m=(-0.1, 0.1), spacing_m=SP)
    values = np.full(g.shape, 0.01, complex)
    values[g.index_of([0.02, 0.0, 0.1])] = 1.0
    img = Image(values, g)
    assert tcr_db(img, ((0.0, 0.04), (-0.02, 0.02), None)) == pytest.approx(40.0)
    assert tcr_db(img, ((0.0, 0.04), (-0.02, 0.02), (0.1, 0.1))) == pytest.approx(40.0)  # bounds included
    with pytest.raises(ValueError, match="target_box .* contains no voxel"):
        tcr_db(img, ((0.5, 0.6), None, None))
    with pytest.raises(ValueError, match="inverted x bounds"):
        tcr_db(img, ((0.1, 0.0), None, None))
    with pytest.raises(ValueError, match="no clutter voxel"):
        tcr_db(img, (None, None, None))
    with pytest.raises(ValueError, match=r"target_box must be \(\(x0, x1\)"):
        tcr_db(img, (0.0, 0.1))
    with pytest.raises(ValueError, match="NaN"):
        tcr_db(img, ((0.0, np.nan), None, None))
    bad = values.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="image contains 1 NaN"):
        tcr_db(Image(bad, g), ((0.0, 0.04), None, None))


def test_compare_with_itself_and_a_scaled_copy():
    g = _grid()
    centres = [[0.0, 0.0, 0.53], [0.03, 0.02, 0.55]]
    a = Image(_blobs(g, centres, [1.0, 0.5]), g)
    res = compare(a, a, target_box=((-0.01, 0.01), (-0.01, 0.01), (0.52, 0.54)), peaks=2)
    assert res.correlation == pytest.approx(1.0) and res.magnitude_correlation == pytest.approx(1.0)
    np.testing.assert_allclose(res.peak_offset_m, 0.0)
    np.testing.assert_allclose(res.peak_a_m, centres[0])
    assert len(res.matches) == 2
    for m, c in zip(res.matches, centres, strict=True):
        np.testing.assert_allclose(m.position_a_m, c, atol=1e-12)
        assert m.distance_m == 0.0
    assert res.tcr_a_db == res.tcr_b_db and res.tcr_a_db > 0
    b = Image(-0.5j * a.values, g)  # a global gain and phase is no difference in shape
    res = compare(a, b)
    assert res.correlation == pytest.approx(1.0) and res.peak_ratio_db == pytest.approx(20 * np.log10(0.5))
    assert res.tcr_a_db is None


def test_compare_finds_the_shift():
    g = _grid()
    centres = np.array([[0.0, 0.0, 0.53], [0.03, 0.02, 0.55], [-0.03, 0.03, 0.52]])
    shift = np.array([0.02, -0.01, 0.01])
    a = Image(_blobs(g, centres, [1.0, 0.6, 0.3]), g)
    b = Image(_blobs(g, centres + shift, [1.0, 0.6, 0.3]), g)
    res = compare(a, b, peaks=3)
    np.testing.assert_allclose(res.peak_offset_m, shift, atol=1e-12)
    assert len(res.matches) == 3
    for m in res.matches:
        np.testing.assert_allclose(m.offset_m, shift, atol=1e-12)
    assert res.correlation < 0.5
    text = res.report()
    assert "+20.0, -10.0, +10.0" in text and "3 strongest peak(s)" in text


def test_compare_refuses_different_grids():
    g = _grid()
    a = Image(_blobs(g, [[0.0, 0.0, 0.53]], [1.0]), g)
    moved = _grid(x0=-0.045)
    with pytest.raises(ValueError, match="same grid"):
        compare(a, Image(a.values, moved))
    smaller = _grid(nx=11)
    with pytest.raises(ValueError, match="same grid: a is 12x10x8"):
        compare(a, Image(a.values[:11], smaller))
    assert same_grid(g, _grid(x0=-0.05 + 1e-7)) and not same_grid(g, moved)
    with pytest.raises(TypeError, match="clsas.Image"):
        compare(a, a.values)
    with pytest.raises(ValueError, match="peaks"):
        compare(a, a, peaks=0)
    with pytest.raises(ValueError, match="clutter_box needs a target_box"):
        compare(a, a, clutter_box=(None, None, None))


def test_compare_two_reconstructions_from_files(tmp_path):
    grid = clsas.VoxelGrid.from_bounds((-0.06, 0.06), (-0.06, 0.06), (0.6, 0.6), 0.01)
    target = [0.02, -0.01, 0.6]
    clean = clsas.reconstruct(small_dataset([target]), grid, backend="numpy")
    noisy = clsas.reconstruct(small_dataset([target], snr_db=0.0), grid, backend="numpy")
    pa, pb = clean.save(tmp_path / "clean.h5"), noisy.save(tmp_path / "noisy.h5")
    box = ((0.0, 0.04), (-0.03, 0.01), None)
    res = compare(pa, pb, target_box=box)
    assert 0.8 < res.correlation < 1.0
    np.testing.assert_allclose(res.peak_a_m, target, atol=1e-12)
    np.testing.assert_allclose(res.peak_offset_m, 0.0, atol=1e-12)
    assert res.tcr_a_db > res.tcr_b_db
    small_dataset([target], nx=3, ny=1).save(tmp_path / "scan.h5")
    with pytest.raises(ValueError, match="not a clsas image file"):
        compare(pa, tmp_path / "scan.h5")
    with pytest.raises(FileNotFoundError, match="b: no such image file"):
        compare(pa, tmp_path / "missing.h5")


def test_cli_compare(tmp_path, capsys):
    g = _grid()
    centres = np.array([[0.0, 0.0, 0.53], [0.03, 0.02, 0.55]])
    a = Image(_blobs(g, centres, [1.0, 0.5]), g).save(tmp_path / "a.h5")
    b = Image(_blobs(g, centres + [0.01, 0, 0], [1.0, 0.5]), g).save(tmp_path / "b.h5")
    assert main(["compare", str(a), str(b), "--box=-0.01,0.01,-0.01,0.01,0.52,0.54", "--peaks", "2"]) == 0
    out = capsys.readouterr().out
    assert "complex correlation" in out and "target-to-clutter ratio" in out
    assert "peak offset b - a: (+10.0, +0.0, +0.0) mm" in out
    assert main(["compare", str(a), str(b), "--box", "1,2,3"]) == 2
    assert "--box must be six numbers" in capsys.readouterr().err
    other = Image(np.ones((3, 3, 1), complex), clsas.VoxelGrid.plane(at_m=0, u_m=(0, 0.02), v_m=(0, 0.02),
                                                                        spacing_m=SP)).save(tmp_path / "c.h5")
    assert main(["compare", str(a), str(other)]) == 2
    assert "same grid" in capsys.readouterr().err
    assert main(["compare", str(a), str(tmp_path / "none.h5")]) == 2
