"""Pictures: files written for volumes and planes, sizes that follow the grid, no backend change."""

import numpy as np
import pytest

import clsas
from clsas.physics.geometry import Scene, Wall
from clsas.types.image import Image

pytest.importorskip("matplotlib")


def _blob(grid: clsas.VoxelGrid, centre=(0.0, 0.0, 1.5), width_m=0.05) -> Image:
    p = grid.points() - np.asarray(centre)
    vals = np.exp(-np.sum(p**2, axis=1) / (2 * width_m**2)).reshape(grid.shape).astype(complex)
    return Image(vals + 1e-3, grid, method="bp")


VOLUME = clsas.VoxelGrid.from_bounds((-0.4, 0.4), (-0.2, 0.2), (1.3, 1.7), 0.02)
PLANE_WIDE = clsas.VoxelGrid.plane("z", at_m=1.5, u_m=(-0.6, 0.6), v_m=(-0.15, 0.15), spacing_m=0.02)
PLANE_TALL = clsas.VoxelGrid.plane("y", at_m=0.0, u_m=(-0.15, 0.15), v_m=(1.0, 2.2), spacing_m=0.02)


@pytest.mark.parametrize("suffix", [".png", ".svg", ".pdf"])
@pytest.mark.parametrize("grid", [VOLUME, PLANE_WIDE], ids=["volume", "plane"])
def test_pictures_are_written(tmp_path, grid, suffix):
    image = _blob(grid)
    path = tmp_path / f"img{suffix}"
    fig = image.plot(path, truth_m=np.array([[0.0, 0.0, 1.5]]), dynamic_range_db=30)
    assert path.exists() and path.stat().st_size > 1000
    head = path.read_bytes()[:8]
    assert {".png": b"\x89PNG", ".pdf": b"%PDF", ".svg": b"<?xml"}[suffix] in head
    assert fig.axes


def test_figure_size_follows_the_grid(tmp_path):
    wide = _blob(PLANE_WIDE).plot(tmp_path / "w.png").get_size_inches()
    tall = _blob(PLANE_TALL, centre=(0.0, 0.0, 1.5)).plot(tmp_path / "t.png").get_size_inches()
    assert wide[0] > 1.5 * wide[1]
    assert tall[1] > 1.5 * tall[0]
    # a plane gets one image panel (plus its colour bar), a volume six projections and slices
    assert len(_blob(PLANE_WIDE).plot(tmp_path / "p.png").axes) == 2
    images = [ax for ax in _blob(VOLUME).plot(tmp_path / "v.png").axes if ax.images]
    assert len(images) == 6
    # volumes too: tall in y gives a taller figure than wide in x; a thin axis is not a sliver
    tall_v = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.6, 0.6), (1.4, 1.6), 0.02)
    w_in, h_in = _blob(tall_v).plot(tmp_path / "tv.png").get_size_inches()
    assert h_in / w_in > _volume_ratio(tmp_path)
    thin = clsas.VoxelGrid.from_bounds((-0.5, 0.5), (-0.5, 0.5), (1.49, 1.51), 0.01)
    fig = _blob(thin).plot(tmp_path / "thin.png")
    top = fig.axes[1].get_window_extent()
    assert top.height > 0.1 * fig.bbox.height


def _volume_ratio(tmp_path) -> float:
    w_in, h_in = _blob(VOLUME).plot(tmp_path / "v2.png").get_size_inches()
    return h_in / w_in


def test_backend_is_left_alone(tmp_path):
    import matplotlib

    before = matplotlib.get_backend()
    _blob(VOLUME).plot(tmp_path / "a.png")
    clsas.plots.mip_png(_blob(VOLUME), tmp_path / "b.png", None, "t")
    assert matplotlib.get_backend() == before


def test_markers_outside_the_grid_do_not_stretch_the_axes(tmp_path):
    image = _blob(VOLUME)
    wall = Wall((0.0, 0.0, 2.0), (0.7071, 0.0, -0.7071))
    scene = Scene(np.array([[0.0, 0.0, 1.5], [3.0, 0.0, 5.0]]), visible=np.array([True, False]), walls=(wall,))
    ap = clsas.raster_aperture(4, 3, 1.0, 1.0)
    fig = image.plot(tmp_path / "m.png", scene=scene, aperture=ap, truth_m=np.array([[0.0, 0.0, 1.5], [9, 9, 9]]))
    front = fig.axes[0]
    assert front.get_xlim() == pytest.approx((-0.41, 0.41))
    assert front.get_ylim() == pytest.approx((-0.21, 0.21))
    labels = {t for ax in fig.axes for t in ax.get_legend_handles_labels()[1]}
    assert {"truth", "aperture", "wall"} <= labels


def test_title_names_method_formation_and_spacing(tmp_path):
    fig = _blob(VOLUME).plot(tmp_path / "t.png")
    title = fig._suptitle.get_text()
    assert "bp" in title and "formation" in title and "20 mm" in title


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(ValueError, match="dynamic_range_db"):
        _blob(VOLUME).plot(tmp_path / "a.png", dynamic_range_db=-3)
    with pytest.raises(ValueError, match=r"\.png"):
        _blob(VOLUME).plot(tmp_path / "a.gif")


def test_slice_montage_and_figure_without_path(tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt

    before = matplotlib.get_backend()
    fig = clsas.plots.plot_slices(_blob(VOLUME), tmp_path / "s.png", axis="z", n=6)
    assert (tmp_path / "s.png").stat().st_size > 1000
    assert len([ax for ax in fig.axes if ax.images]) == 6
    fig = _blob(PLANE_WIDE).plot()  # no file: a pyplot figure in the caller's backend
    assert plt.fignum_exists(fig.number)
    plt.close(fig)
    assert matplotlib.get_backend() == before
