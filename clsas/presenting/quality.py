"""Image quality: target-to-clutter ratio in a box, and the comparison of two images on one grid.

Boxes are ``((x0, x1), (y0, y1), (z0, z1))`` in metres; a voxel is in a box when its centre is
within the bounds on every axis (bounds included, to a millionth of a voxel). ``None`` in place
of an axis' bounds takes the whole axis, so a box on a plane grid need not name the plane.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import validate as v
from ..physics.geometry import VoxelGrid
from ..types.image import Image

__all__ = ["tcr_db", "compare", "Comparison", "PeakMatch"]

Box = Sequence[tuple[float, float] | None]


def _as_image(name: str, image: Image | str | Path) -> Image:
    """An Image, or one loaded from an image HDF5 file written by ``Image.save``."""
    if isinstance(image, Image):
        img = image
    elif isinstance(image, str | Path):
        path = Path(image)
        if not path.is_file():
            raise FileNotFoundError(f"{name}: no such image file: {path}")
        import h5py

        try:
            with h5py.File(path, "r") as f:
                missing = [k for k in ("values", "x_m", "y_m", "z_m") if k not in f]
        except OSError as exc:
            raise ValueError(f"{name}: {path} is not an HDF5 file ({exc})") from None
        if missing:
            raise ValueError(f"{name}: {path} is not a clsas image file (no {', '.join(missing)}; "
                             "a dataset file? image it first with `clsas reconstruct`)")
        img = Image.load(path)
    else:
        raise TypeError(f"{name} must be a clsas.Image or the path of an image file, got {type(image).__name__}")
    vals = np.asarray(img.values)
    if vals.shape != img.grid.shape:
        raise ValueError(f"{name}: values have shape {vals.shape} but the grid is {img.grid.shape}")
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{name} contains {int(np.sum(~np.isfinite(vals)))} NaN or Inf value(s)")
    return img


def box_mask(grid: VoxelGrid, box: Box, name: str = "box") -> np.ndarray:
    """Boolean (nx, ny, nz) mask of the voxels whose centres lie in ``box``.

    Parameters
    ----------
    grid : VoxelGrid
    box : ((x0, x1), (y0, y1), (z0, z1)), metres; ``None`` for an axis takes all of it.
    name : str
        The parameter name used in error messages.
    """
    if isinstance(box, np.ndarray):
        box = list(box)
    if isinstance(box, str | bytes) or not isinstance(box, Sequence) or len(box) != 3:
        raise ValueError(f"{name} must be ((x0, x1), (y0, y1), (z0, z1)) in metres, got {box!r}")
    axes = (grid.x_m, grid.y_m, grid.z_m)
    sel = []
    for label, ax, b, d in zip("xyz", axes, box, grid.spacing(), strict=True):
        if b is None:
            sel.append(np.ones(len(ax), bool))
            continue
        lo, hi = v.array(f"{name} ({label} bounds)", b, shape=(2,))
        if hi < lo:
            raise ValueError(f"{name} has inverted {label} bounds ({lo:g}, {hi:g})")
        tol = 1e-6 * d
        sel.append((ax >= lo - tol) & (ax <= hi + tol))
    mask = sel[0][:, None, None] & sel[1][None, :, None] & sel[2][None, None, :]
    if not mask.any():
        b = grid.bounds()
        raise ValueError(f"{name} {_fmt_box(box)} contains no voxel of the grid, which spans "
                         f"x [{b[0, 0]:g}, {b[0, 1]:g}], y [{b[1, 0]:g}, {b[1, 1]:g}], z [{b[2, 0]:g}, {b[2, 1]:g}] m")
    return mask


def _fmt_box(box: Box) -> str:
    return "(" + ", ".join("all" if b is None else f"[{float(b[0]):g}, {float(b[1]):g}]" for b in box) + ")"


def tcr_db(image: Image | str | Path, target_box: Box, clutter_box: Box | None = None) -> float:
    """Target-to-clutter ratio: the peak in ``target_box`` over the RMS clutter, in dB.

    ``TCR = 20 log10( max |v| over the target box / sqrt(mean |v|^2 over the clutter) )``, the
    peak-to-RMS-clutter ratio (a peak-to-peak-clutter ratio would follow the single strongest
    sidelobe; the RMS follows the clutter floor). The clutter is every voxel outside the target
    box, or, with ``clutter_box``, every voxel in ``clutter_box`` that is not in the target box
    (so a clutter box around the target measures the clutter in a ring about it).

    Parameters
    ----------
    image : Image, or the path of an image HDF5 file
        Complex values (nx, ny, nz) on a grid.
    target_box, clutter_box : ((x0, x1), (y0, y1), (z0, z1))
        Metres; see the module notes.

    Returns
    -------
    float
        dB; ``inf`` when the clutter is exactly zero, ``-inf`` when the target box is.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> image = clsas.reconstruct(data, grid)
    >>> tcr = clsas.tcr_db(image, ((-0.03, 0.03), (-0.03, 0.03), (0.97, 1.03)))   # dB
    """
    img = _as_image("image", image)
    target = box_mask(img.grid, target_box, "target_box")
    clutter = ~target if clutter_box is None else box_mask(img.grid, clutter_box, "clutter_box") & ~target
    if not clutter.any():
        raise ValueError("no clutter voxel is left: the target box covers "
                         + ("the whole grid" if clutter_box is None else "all of clutter_box"))
    mag = np.abs(np.asarray(img.values, dtype=np.complex128))
    peak = float(mag[target].max())
    rms = float(np.sqrt(np.mean(mag[clutter] ** 2)))
    if rms == 0:
        if peak == 0:
            raise ValueError("the image is zero in the target box and in the clutter: no ratio")
        return float("inf")
    return float("-inf") if peak == 0 else float(20 * np.log10(peak / rms))


@dataclass(frozen=True)
class PeakMatch:
    """One of image a's strongest peaks and the peak of image b matched to it.

    Positions (3,) in metres; ``offset_m = position_b_m - position_a_m``; levels in dB relative
    to each image's maximum.
    """

    position_a_m: np.ndarray
    position_b_m: np.ndarray
    offset_m: np.ndarray
    level_a_db: float
    level_b_db: float

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.offset_m))


@dataclass(frozen=True)
class Comparison:
    """The comparison of two images on the same grid (see :func:`compare`).

    Attributes
    ----------
    correlation : float
        ``|<a, b>| / (||a|| ||b||)`` of the complex values, in [0, 1]: 1 when b is a times a
        complex constant (a global phase or gain does not count).
    magnitude_correlation : float
        Pearson correlation of ``|a|`` and ``|b|`` over the voxels, in [-1, 1]; NaN when one of
        them is constant.
    peak_a_m, peak_b_m : (3,) array
        Centre of each image's brightest voxel, metres.
    peak_offset_m : (3,) array
        ``peak_b_m - peak_a_m``, metres.
    peak_ratio_db : float
        ``20 log10(max |b| / max |a|)``.
    matches : list of PeakMatch
        a's ``k`` strongest peaks, each matched to one of b's ``k`` strongest (the assignment
        that minimises the total distance), in a's order.
    tcr_a_db, tcr_b_db : float or None
        Target-to-clutter ratios (:func:`tcr_db`) when a target box was given.
    grid : VoxelGrid
    target_box, clutter_box : the boxes used, or None.
    """

    correlation: float
    magnitude_correlation: float
    peak_a_m: np.ndarray
    peak_b_m: np.ndarray
    peak_offset_m: np.ndarray
    peak_ratio_db: float
    matches: list[PeakMatch] = field(default_factory=list)
    tcr_a_db: float | None = None
    tcr_b_db: float | None = None
    grid: VoxelGrid | None = None
    target_box: Box | None = None
    clutter_box: Box | None = None

    def report(self, names: tuple[str, str] = ("a", "b")) -> str:
        """A readable multi-line summary (positions in metres, offsets in millimetres)."""
        a, b = names

        def pos(p: np.ndarray) -> str:
            return "(" + ", ".join(f"{x:+.4f}" for x in p) + ") m"

        def off(d: np.ndarray) -> str:
            return "(" + ", ".join(f"{1e3 * x:+.1f}" for x in d) + f") mm, |d| = {1e3 * np.linalg.norm(d):.1f} mm"

        lines = []
        if self.grid is not None:
            g, bd = self.grid, self.grid.bounds()
            lines.append(f"grid: {' x '.join(map(str, g.shape))} voxels, x [{bd[0, 0]:+.3f}, {bd[0, 1]:+.3f}], "
                         f"y [{bd[1, 0]:+.3f}, {bd[1, 1]:+.3f}], z [{bd[2, 0]:+.3f}, {bd[2, 1]:+.3f}] m")
        lines += [
            f"complex correlation |<a,b>|/(|a||b|): {self.correlation:.4f}",
            f"magnitude correlation (Pearson, |a| vs |b|): {self.magnitude_correlation:.4f}",
            f"peak of {a}: {pos(self.peak_a_m)}",
            f"peak of {b}: {pos(self.peak_b_m)}  ({self.peak_ratio_db:+.2f} dB relative to {a})",
            f"peak offset {b} - {a}: {off(self.peak_offset_m)}",
        ]
        if self.matches:
            lines.append(f"{len(self.matches)} strongest peak(s) of {a} matched to {b}'s:")
            for i, m in enumerate(self.matches, 1):
                lines.append(f"  {i}. {a} {pos(m.position_a_m)} {m.level_a_db:+.1f} dB | {b} {pos(m.position_b_m)} "
                             f"{m.level_b_db:+.1f} dB | offset {off(m.offset_m)}")
        if self.tcr_a_db is not None and self.tcr_b_db is not None:
            where = "outside it" if self.clutter_box is None else f"in clutter box {_fmt_box(self.clutter_box)}"
            lines.append(f"target-to-clutter ratio (peak in box {_fmt_box(self.target_box)} / RMS {where}): "
                         f"{a} {self.tcr_a_db:.2f} dB, {b} {self.tcr_b_db:.2f} dB, "
                         f"{b} - {a} {self.tcr_b_db - self.tcr_a_db:+.2f} dB")
        return "\n".join(lines)


def same_grid(a: VoxelGrid, b: VoxelGrid) -> bool:
    """Whether two grids have the same shape and voxel centres (to 1/1000 of a voxel)."""
    if a.shape != b.shape:
        return False
    for ax_a, ax_b, d in zip((a.x_m, a.y_m, a.z_m), (b.x_m, b.y_m, b.z_m), a.spacing(), strict=True):
        tol = 1e-3 * d if len(ax_a) > 1 else 1e-9
        if np.max(np.abs(ax_a - ax_b)) > tol:
            return False
    return True


def _describe(g: VoxelGrid) -> str:
    b = g.bounds()
    return (f"{'x'.join(map(str, g.shape))} over x [{b[0, 0]:g}, {b[0, 1]:g}], y [{b[1, 0]:g}, {b[1, 1]:g}], "
            f"z [{b[2, 0]:g}, {b[2, 1]:g}] m")


def compare(a: Image | str | Path, b: Image | str | Path, *, target_box: Box | None = None,
            clutter_box: Box | None = None, peaks: int = 3, min_separation_m: float | None = None) -> Comparison:
    """Compare two images on the same grid: correlation, peak offsets, target-to-clutter ratios.

    Parameters
    ----------
    a, b : Image, or paths of image HDF5 files
        Complex values on the same grid (same shape and voxel centres).
    target_box, clutter_box : ((x0, x1), (y0, y1), (z0, z1)), optional
        Metres; with a target box the TCR of each image is reported (:func:`tcr_db`).
    peaks : int
        How many of the strongest peaks of each image to match (>= 1).
    min_separation_m : float, optional
        Peaks closer than this to a stronger one are not counted (``Image.peaks``); default
        two voxels (the largest spacing of the grid's non-flat axes).

    Returns
    -------
    Comparison
        ``.report()`` gives a readable summary.

    Raises
    ------
    ValueError
        When the grids differ, an image holds NaN or Inf, or a box holds no voxel.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> a = clsas.reconstruct(data, grid)
    >>> b = clsas.reconstruct(data, grid, formation="omega-k")
    >>> text = clsas.compare(a, b, target_box=((-0.03, 0.03), (-0.03, 0.03), (0.97, 1.03))).report()
    """
    ia, ib = _images_on_one_grid(a, b)
    k = v.positive_int("peaks", peaks)
    sep = _peak_separation(ia.grid, min_separation_m)
    va, vb = _nonzero_values(ia, ib)
    corr, mcorr = _correlations(va, vb)
    ma, mb = np.abs(va), np.abs(vb)
    pts = ia.grid.points()
    pa, pb = pts[int(np.argmax(ma))], pts[int(np.argmax(mb))]
    matches = _match_peaks(ia, ib, k, sep)
    tcr_a, tcr_b = _tcrs(ia, ib, target_box, clutter_box)
    return Comparison(
        correlation=min(corr, 1.0), magnitude_correlation=mcorr, peak_a_m=pa, peak_b_m=pb,
        peak_offset_m=pb - pa, peak_ratio_db=float(20 * np.log10(mb.max() / ma.max())), matches=matches,
        tcr_a_db=tcr_a, tcr_b_db=tcr_b, grid=ia.grid, target_box=target_box, clutter_box=clutter_box,
    )


def _images_on_one_grid(a: Image | str | Path, b: Image | str | Path) -> tuple[Image, Image]:
    """:func:`compare`'s two images (read where they are paths), refused unless on the same grid."""
    ia, ib = _as_image("a", a), _as_image("b", b)
    if not same_grid(ia.grid, ib.grid):
        raise ValueError(f"a and b must be on the same grid: a is {_describe(ia.grid)}, b is "
                         f"{_describe(ib.grid)} (reconstruct both on one VoxelGrid)")
    return ia, ib


def _peak_separation(g: VoxelGrid, min_separation_m: float | None) -> float:
    """The distance within which a weaker peak is not counted, m: ``min_separation_m``, or by
    default two voxels (the largest spacing of the grid's non-flat axes)."""
    if min_separation_m is not None:
        return v.non_negative("min_separation_m", min_separation_m)
    flat = [d for d, n in zip(g.spacing(), g.shape, strict=True) if n > 1]
    return 2.0 * max(flat) if flat else 0.0


def _nonzero_values(ia: Image, ib: Image) -> tuple[np.ndarray, np.ndarray]:
    """Both images' values as flat complex arrays, refused where one is zero everywhere."""
    va = np.asarray(ia.values, np.complex128).ravel()
    vb = np.asarray(ib.values, np.complex128).ravel()
    na, nb = np.linalg.norm(va), np.linalg.norm(vb)
    if na == 0 or nb == 0:
        raise ValueError(f"{'a' if na == 0 else 'b'} is zero everywhere: nothing to compare")
    return va, vb


def _correlations(va: np.ndarray, vb: np.ndarray) -> tuple[float, float]:
    """The normalised complex correlation ``|<a, b>| / (|a| |b|)`` of two non-zero value arrays, and
    the Pearson correlation of their magnitudes (NaN where one magnitude is constant)."""
    corr = float(abs(np.vdot(va, vb)) / (np.linalg.norm(va) * np.linalg.norm(vb)))
    ma, mb = np.abs(va), np.abs(vb)
    da, db = ma - ma.mean(), mb - mb.mean()
    den = np.linalg.norm(da) * np.linalg.norm(db)
    return corr, float(da @ db / den) if den > 0 else float("nan")


def _tcrs(ia: Image, ib: Image, target_box: Box | None, clutter_box: Box | None) -> tuple[float | None, float | None]:
    """Each image's target-to-clutter ratio, dB, where a target box is given (None, None otherwise)."""
    if target_box is not None:
        return tcr_db(ia, target_box, clutter_box), tcr_db(ib, target_box, clutter_box)
    if clutter_box is not None:
        raise ValueError("clutter_box needs a target_box")
    return None, None


def _match_peaks(a: Image, b: Image, k: int, sep: float) -> list[PeakMatch]:
    """a's k strongest peaks matched one to one to b's (least total distance)."""
    from scipy.optimize import linear_sum_assignment

    qa, qb = a.peaks(k, min_separation_m=sep), b.peaks(k, min_separation_m=sep)
    if not qa or not qb:
        return []
    xa = np.array([p.position_m for p in qa])
    xb = np.array([p.position_m for p in qb])
    rows, cols = linear_sum_assignment(np.linalg.norm(xa[:, None] - xb[None], axis=2))
    top_a, top_b = qa[0].magnitude, qb[0].magnitude
    out = []
    for i, j in sorted(zip(rows, cols, strict=True)):
        out.append(PeakMatch(xa[i], xb[j], xb[j] - xa[i], float(20 * np.log10(qa[i].magnitude / top_a)),
                             float(20 * np.log10(qb[j].magnitude / top_b))))
    return out
