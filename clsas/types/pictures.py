"""Pictures for papers: maximum-intensity projections and slices through the peak, in dB.

Presentation only: the compute functions never plot. Figures are made with
:class:`matplotlib.figure.Figure` and written through their own canvas, so nothing here selects
or changes the caller's matplotlib backend; with no ``path`` the figure comes from pyplot (in the
caller's backend) so that ``plt.show()`` shows it.

Layout
------
- A volume (every axis longer than 1): two blocks of orthogonal views, the maximum-intensity
  projections on the left and the slices through the brightest voxel on the right. In each block
  the front view (x-y) sits above the top view (x-z), which shares its x axis, and the side view
  (z-y) sits beside it, sharing y. Panel sizes are proportional to the grid's extents, so the
  figure's aspect follows the grid's.
- A plane (one axis of length 1): one panel of the plane.
- A line (two axes of length 1): the dB profile along it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from ..physics.geometry import Scene, VoxelGrid


class Image(Protocol):
    """What the pictures read of a :class:`clsas.Image` (named structurally, so that this module,
    which presents images, is not imported by the type it presents)."""

    values: np.ndarray
    grid: VoxelGrid
    method: str
    device: str
    provenance: dict

    def db(self, floor_db: float = -60.0) -> np.ndarray: ...

__all__ = ["plot_image", "plot_slices", "mip_png", "FORMATS"]

log = logging.getLogger(__name__)

FORMATS = (".png", ".svg", ".pdf")
_NAMES = ("x", "y", "z")
_LABELS = ("x (m)", "y (m)", "z, range (m)")
_MAX_WIDTH_IN = 12.0
_MAX_HEIGHT_IN = 9.0


def plot_image(
    image: Image,
    path: str | Path | None = None,
    *,
    truth_m: np.ndarray | None = None,
    scene: Scene | None = None,
    aperture=None,
    dynamic_range_db: float = 40.0,
    title: str | None = None,
    dpi: int = 150,
    cmap: str = "inferno",
) -> Figure:
    """Draw ``image`` in dB: projections and slices through its brightest voxel.

    Parameters
    ----------
    image : Image
        The reconstruction.
    path : str or Path, optional
        Where to write the picture; the suffix (.png, .svg or .pdf) picks the format.
    truth_m : (n, 3) array, optional
        True reflector (or mirror-image) positions, metres; only those inside the grid are drawn.
    scene : Scene, optional
        The simulated scene: its image sources become the truth (unless ``truth_m`` is given),
        its walls are drawn where they cross a panel, and its hidden reflectors are marked.
    aperture : Aperture, Dataset or (n, 3) array, optional
        The transducer positions (``tx_positions`` and ``rx_positions``, or the array); their
        footprint is drawn where it falls inside a panel.
    dynamic_range_db : float
        The colour scale's floor below the peak, dB (> 0).
    title : str, optional
        Figure title; default: method, formation, grid spacing and device.
    dpi : int
        Resolution of a PNG.
    cmap : str
        Matplotlib colour map.

    Returns
    -------
    matplotlib.figure.Figure
    """
    dr = float(dynamic_range_db)
    if not np.isfinite(dr) or dr <= 0:
        raise ValueError(f"dynamic_range_db must be a positive number of dB, got {dynamic_range_db!r}")
    if path is not None and Path(path).suffix.lower() not in FORMATS:
        raise ValueError(f"path must end in one of {', '.join(FORMATS)}, got {str(path)!r}")
    g = image.grid
    axes_m = (g.x_m, g.y_m, g.z_m)
    db = image.db(-dr)
    marks = _Marks.build(truth_m, scene, aperture, g)
    long = [i for i in range(3) if len(axes_m[i]) > 1]
    if title is None:
        title = _default_title(image)

    fig = _new_figure(path)
    if len(long) == 3:
        _volume(fig, db, axes_m, marks, dr, cmap)
    elif len(long) == 2:
        _plane(fig, db, axes_m, long, marks, dr, cmap)
    else:
        _line(fig, db, axes_m, long, dr)
    if title:
        fig.suptitle(_wrapped(title, fig, 10), fontsize=10)
    if path is not None:
        path = Path(path)
        fig.savefig(path, dpi=dpi)
        log.info("wrote %s", path)
    return fig


def plot_slices(
    image: Image,
    path: str | Path | None = None,
    *,
    axis: str = "z",
    n: int = 12,
    dynamic_range_db: float = 40.0,
    truth_m: np.ndarray | None = None,
    title: str | None = None,
    dpi: int = 150,
    cmap: str = "inferno",
) -> Figure:
    """A montage of ``n`` evenly spaced slices through the volume along ``axis``, in dB.

    Each slice is scaled to the volume's peak; truth within half a slice step is marked.

    Returns
    -------
    matplotlib.figure.Figure
    """
    if axis not in _NAMES:
        raise ValueError(f"axis must be one of 'x', 'y', 'z', got {axis!r}")
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if path is not None and Path(path).suffix.lower() not in FORMATS:
        raise ValueError(f"path must end in one of {', '.join(FORMATS)}, got {str(path)!r}")
    dr = float(dynamic_range_db)
    if not np.isfinite(dr) or dr <= 0:
        raise ValueError(f"dynamic_range_db must be a positive number of dB, got {dynamic_range_db!r}")
    g = image.grid
    axes_m = (g.x_m, g.y_m, g.z_m)
    k = _NAMES.index(axis)
    i, j = [d for d in range(3) if d != k]
    idx = np.unique(np.linspace(0, len(axes_m[k]) - 1, min(int(n), len(axes_m[k]))).round().astype(int))
    cols = int(np.ceil(np.sqrt(len(idx))))
    rows = int(np.ceil(len(idx) / cols))
    lu, lv = np.ptp(_extent(axes_m[i])), np.ptp(_extent(axes_m[j]))
    fig = _new_figure(path)
    fig.set_size_inches(*_size(cols * lu, rows * lv, 1.5, 0.8))
    db = np.moveaxis(image.db(-dr), (i, j, k), (0, 1, 2))
    step = float(np.ptp(axes_m[k])) / max(len(axes_m[k]) - 1, 1)
    marks = _Marks.build(truth_m, None, None, g)
    im = None
    for n_ax, ik in enumerate(idx):
        ax = fig.add_subplot(rows, cols, n_ax + 1)
        at = float(axes_m[k][ik])
        im = _panel(ax, db[:, :, ik].T, axes_m[i], axes_m[j], i, j, dr, cmap, f"{axis} = {at:.3f} m")
        marks.draw(ax, i, j, (k, at), step / 2 + 1e-12)
    fig.colorbar(im, ax=fig.axes, shrink=0.7, label="dB re peak")
    fig.suptitle(_default_title(image) if title is None else title, fontsize=10)
    if path is not None:
        fig.savefig(Path(path), dpi=dpi)
    return fig


def mip_png(image: Image, path: str | Path, truth_m: np.ndarray | None = None, title: str = "",
            dynamic_range_db: float = 30.0, **kwargs) -> Path:
    """Write the picture of :func:`plot_image` to ``path`` (kept for the CLI and examples)."""
    plot_image(image, path, truth_m=truth_m, title=title or None, dynamic_range_db=dynamic_range_db, **kwargs)
    return Path(path)


# ---------------------------------------------------------------------------------------------


def _new_figure(path) -> Figure:
    if path is None:
        import matplotlib.pyplot as plt

        return plt.figure(layout="constrained")
    from matplotlib.figure import Figure

    return Figure(layout="constrained")


def _wrapped(title: str, fig: Figure, fontsize: float) -> str:
    """``title`` broken into lines that fit the figure's width (a long one was clipped at its edges)."""
    import textwrap

    per_line = max(20, int(fig.get_figwidth() * 72 / (0.6 * fontsize)))
    return "\n".join(textwrap.wrap(title, per_line, break_long_words=False, break_on_hyphens=False)) or title


def _default_title(image: Image) -> str:
    formation = image.provenance.get("formation", "bp")
    sp = [f"{_NAMES[i]} {s * 1e3:.3g}" for i, (s, a) in
          enumerate(zip(image.grid.spacing(), (image.grid.x_m, image.grid.y_m, image.grid.z_m), strict=True))
          if len(a) > 1]
    src = image.provenance.get("source_path")
    comp = image.provenance.get("compression")
    parts = [f"method {image.method}", f"formation {formation}", f"compression {comp}" if comp else "",
             f"spacing {', '.join(sp)} mm" if sp else ""]
    head = f"{src}: " if src else ""
    return head + " | ".join(p for p in parts if p) + f" | {image.device}"


def _extent(a: np.ndarray) -> tuple[float, float]:
    d = a[1] - a[0] if len(a) > 1 else 0.01
    return float(a[0] - d / 2), float(a[-1] + d / 2)


def _size(width_m: float, height_m: float, extra_w_in: float, extra_h_in: float) -> tuple[float, float]:
    """Figure size in inches: panels with the grid's aspect plus fixed room for labels."""
    scale = min((_MAX_WIDTH_IN - extra_w_in) / width_m, (_MAX_HEIGHT_IN - extra_h_in) / height_m)
    return width_m * scale + extra_w_in, height_m * scale + extra_h_in


class _Marks:
    """What to draw over the image: truth, hidden reflectors, walls, the aperture's footprint."""

    def __init__(self, truth, hidden, walls, aperture, bounds):
        self.truth, self.hidden, self.walls, self.aperture, self.bounds = truth, hidden, walls, aperture, bounds

    @classmethod
    def build(cls, truth_m, scene, aperture, grid) -> _Marks:
        hidden = np.zeros((0, 3))
        walls = ()
        if scene is not None:
            if truth_m is None:
                truth_m = scene.image_sources()[0]
            hidden = np.asarray(scene.points_m)[~np.asarray(scene.visible, bool)]
            walls = tuple(scene.walls)
        truth = np.zeros((0, 3)) if truth_m is None else np.asarray(truth_m, float).reshape(-1, 3)
        ap = None
        if aperture is not None:
            if hasattr(aperture, "tx_positions"):
                ap = np.concatenate([np.asarray(aperture.tx_positions), np.asarray(aperture.rx_positions)])
            else:
                ap = np.asarray(aperture, float).reshape(-1, 3)
        bounds = np.array([_extent(a) for a in (grid.x_m, grid.y_m, grid.z_m)])
        return cls(truth, hidden, walls, ap, bounds)

    def inside(self, pts: np.ndarray, dims) -> np.ndarray:
        b = self.bounds
        return np.all([(pts[:, d] >= b[d, 0]) & (pts[:, d] <= b[d, 1]) for d in dims], axis=0)

    def draw(self, ax: Axes, i: int, j: int, fixed: tuple[int, float] | None, tol_m: float | None) -> None:
        """Draw on the panel of axes (i, j); ``fixed`` = (axis, position) of a slice or plane."""
        for pts, style, label in ((self.truth, dict(marker="+", color="c", ms=8, mew=1.3), "truth"),
                                  (self.hidden, dict(marker="x", color="lime", ms=7, mew=1.3), "hidden (true)")):
            if not len(pts):
                continue
            dims = [i, j] if fixed is None or tol_m is None else [i, j, fixed[0]]
            keep = self.inside(pts, dims)
            if fixed is not None and tol_m is not None:
                keep &= np.abs(pts[:, fixed[0]] - fixed[1]) <= tol_m
            if keep.any():
                ax.plot(pts[keep, i], pts[keep, j], ls="none", label=label, **style)
            elif label.startswith("hidden"):  # said in the legend, with no marker: none is drawn
                ax.plot([], [], ls="none", marker="", label=f"{label}: outside the grid, not drawn")
        if self.aperture is not None and len(self.aperture):
            ap = self.aperture
            if fixed is None or tol_m is None or bool(np.any(np.abs(ap[:, fixed[0]] - fixed[1]) <= tol_m)):
                _footprint(ax, self.aperture, i, j, self.bounds)
        k = 3 - i - j
        at = fixed[1] if fixed is not None else float(self.bounds[k].mean())
        for n, wall in enumerate(self.walls):
            _wall_line(ax, wall, i, j, k, at, self.bounds, "wall" if n == 0 else None)


def _footprint(ax: Axes, pts: np.ndarray, i: int, j: int, bounds: np.ndarray) -> None:
    """The aperture's bounding box in the panel, if it overlaps the panel."""
    lo, hi = pts[:, [i, j]].min(axis=0), pts[:, [i, j]].max(axis=0)
    if hi[0] < bounds[i, 0] or lo[0] > bounds[i, 1] or hi[1] < bounds[j, 0] or lo[1] > bounds[j, 1]:
        return
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1], fill=False, ec="0.8", ls="--",
                           lw=0.9, label="aperture", clip_on=True))


def _wall_line(ax: Axes, wall, i: int, j: int, k: int, at: float, bounds: np.ndarray, label) -> None:
    """Where the wall's plane crosses the panel (axes i, j at coordinate ``at`` on axis k)."""
    n, p = np.asarray(wall.normal), np.asarray(wall.point_m)
    rhs = float(n @ p) - n[k] * at
    if abs(n[j]) > abs(n[i]):
        u = np.array(bounds[i])
        v = (rhs - n[i] * u) / n[j]
    elif abs(n[i]) > 1e-12:
        v = np.array(bounds[j])
        u = (rhs - n[j] * v) / n[i]
    else:
        return  # the wall is parallel to the panel
    ax.plot(u, v, color="0.9", lw=1.2, ls="-.", label=label, clip_on=True)


def _panel(ax: Axes, img: np.ndarray, ha: np.ndarray, va: np.ndarray, i: int, j: int, dr: float, cmap: str,
           name: str, aspect: str = "equal"):
    ex = (*_extent(ha), *_extent(va))
    im = ax.imshow(img, origin="lower", extent=ex, aspect=aspect, cmap=cmap, vmin=-dr, vmax=0,
                   interpolation="nearest")
    ax.set_xlim(ex[0], ex[1])
    ax.set_ylim(ex[2], ex[3])
    ax.set_title(name, fontsize=9)
    ax.set_xlabel(_LABELS[i], fontsize=8)
    ax.set_ylabel(_LABELS[j], fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_autoscale_on(False)  # markers outside the grid never stretch the axes
    return im


def _volume(fig: Figure, db: np.ndarray, axes_m, marks: _Marks, dr: float, cmap: str) -> None:
    true = [float(np.ptp(_extent(a))) for a in axes_m]
    # a thin axis gets at least a quarter of the longest one (stretched: aspect no longer equal)
    lx, ly, lz = (max(t, 0.25 * max(true)) for t in true)
    aspect = "equal" if [lx, ly, lz] == true else "auto"
    peak = np.unravel_index(int(np.argmax(db)), db.shape)
    width, height = 2 * (lx + lz), ly + lz
    fig.set_size_inches(*_size(width, height, 3.5, 1.6))
    gs = fig.add_gridspec(2, 4, width_ratios=[lx, lz, lx, lz], height_ratios=[ly, lz])
    x, y, z = axes_m
    tol = 3 * max(float(np.ptp(a)) / max(len(a) - 1, 1) for a in axes_m)
    blocks = (
        ("projection", 0, (db.max(axis=2).T, db.max(axis=1).T, db.max(axis=0)), None),
        ("slice", 2, (db[:, :, peak[2]].T, db[:, peak[1], :].T, db[peak[0], :, :]), peak),
    )
    im = legend_ax = None
    for _kind, col, (xy, xz, zy), at in blocks:
        views = (
            (gs[0, col], xy, x, y, 0, 1, 2, "x-y"),
            (gs[1, col], xz, x, z, 0, 2, 1, "x-z"),
            (gs[0, col + 1], zy, z, y, 2, 1, 0, "z-y"),
        )
        for spec, img, ha, va, i, j, k, name in views:
            ax = fig.add_subplot(spec)
            where = f"MIP {name}" if at is None else f"{name} at {_NAMES[k]} = {axes_m[k][at[k]]:.3f} m"
            im = _panel(ax, img, ha, va, i, j, dr, cmap, where, aspect)
            marks.draw(ax, i, j, None if at is None else (k, float(axes_m[k][at[k]])), tol)
            if legend_ax is None:
                legend_ax = ax
    spare = fig.add_subplot(gs[1, 1])
    spare.axis("off")
    handles, labels = legend_ax.get_legend_handles_labels()
    if handles:
        spare.legend(handles, labels, loc="center", fontsize=7, facecolor="0.3", labelcolor="w")
    holder = fig.add_subplot(gs[1, 3])
    holder.axis("off")
    cax = holder.inset_axes((0.35, 0.05, 0.12, 0.9))
    fig.colorbar(im, cax=cax, label="dB re peak")


def _plane(fig: Figure, db: np.ndarray, axes_m, long: list[int], marks: _Marks, dr: float, cmap: str) -> None:
    i, j = long
    k = 3 - i - j
    lu, lv = np.ptp(_extent(axes_m[i])), np.ptp(_extent(axes_m[j]))
    fig.set_size_inches(*_size(lu, lv, 2.2, 1.2))
    ax = fig.add_subplot()
    img = np.moveaxis(db, (i, j, k), (0, 1, 2))[:, :, 0].T
    name = f"plane {_NAMES[k]} = {axes_m[k][0]:.3f} m ({_NAMES[i]}-{_NAMES[j]})"
    im = _panel(ax, img, axes_m[i], axes_m[j], i, j, dr, cmap, name)
    marks.draw(ax, i, j, (k, float(axes_m[k][0])), None)
    _legend(ax)
    fig.colorbar(im, ax=ax, shrink=0.8, label="dB re peak")


def _line(fig: Figure, db: np.ndarray, axes_m, long: list[int], dr: float) -> None:
    i = long[0] if long else 2
    fig.set_size_inches(6.0, 3.5)
    ax = fig.add_subplot()
    ax.plot(axes_m[i], db.reshape(-1), color="k", lw=1)
    ax.set(xlabel=_LABELS[i], ylabel="dB re peak", ylim=(-dr, 1))
    ax.grid(alpha=0.3)


def _legend(ax: Axes) -> None:
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, loc="lower right", fontsize=7, facecolor="0.3", labelcolor="w", framealpha=0.8)
