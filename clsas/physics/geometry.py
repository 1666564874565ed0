"""Apertures (the type, raster scans), voxel grids, scenes with point reflectors and mirror walls.

Frames
------
All positions are in the scene frame, metres. The raster aperture's rig faces +z (z is range, y
is up). Circular and helical apertures turn about a vertical axis: z is up and the rotation axis
is the line through ``center_m`` parallel to z; the rig looks horizontally towards that axis.

Transducer offsets are given in the rig's local frame, the same right-handed frame in every
aperture: local y is up, local z points where the rig looks, local x = y x z is horizontal. For
the raster aperture the local frame is the scene frame; on a circle at azimuth phi (measured
counterclockwise seen from +z, from the +x axis) local z = (-cos phi, -sin phi, 0) points to the
axis, local y = (0, 0, 1) and local x = (sin phi, -cos phi, 0) is tangential, pointing clockwise
seen from above. An offset ``(-0.02, 0, 0)`` thus means "2 cm along -x" on the raster and "2 cm
along the counterclockwise tangent" on a circle: the same side of the rig in both.

Several microphones per ping: an aperture with k microphones per stop has k measurements per
stop, stop-major (measurement ``i * k + j`` is microphone j at stop i); ``tx_positions`` and
``stage_positions`` repeat for each microphone.

Circular, helical and CSV apertures are built in :mod:`clsas.physics.apertures`.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import validate as v
from .sound import speed_of_sound

__all__ = ["Aperture", "raster_aperture", "VoxelGrid", "Wall", "Scene", "TX_OFFSET_M", "RX_OFFSET_M",
           "BISTATIC_COLUMNS", "STAGE_COLUMNS", "mic_offsets", "aperture_from_stops"]

# the default speaker and microphone offsets from the rig's reference point, metres, rig frame
TX_OFFSET_M = (-0.02, 0.0, 0.0)
RX_OFFSET_M = (0.02, 0.0, 0.0)
# the columns of an aperture CSV table (see clsas.physics.apertures.aperture_from_csv)
BISTATIC_COLUMNS = ("tx_x", "tx_y", "tx_z", "rx_x", "rx_y", "rx_z")
STAGE_COLUMNS = ("x", "y", "z")


@dataclass(frozen=True)
class Aperture:
    """Speaker and microphone positions, one bistatic pair per measurement.

    Attributes
    ----------
    tx_positions, rx_positions : numpy.ndarray
        (n_meas, 3) float64, metres.
    stage_positions : numpy.ndarray
        (n_meas, 3) rig reference point (the carriage) in the order the stops are visited,
        metres; repeated for each microphone of a stop.
    mics_per_stop : int
        Microphones recorded per ping (k): measurements ``i * k .. i * k + k - 1`` are stop i.

    Examples
    --------
    Apertures are made by :func:`clsas.raster_aperture`, :func:`clsas.circular_aperture`,
    :func:`clsas.helical_aperture` or :func:`clsas.aperture_from_csv`:

    >>> import clsas
    >>> aperture = clsas.raster_aperture(3, 2, 0.1, 0.1)
    >>> aperture.tx_positions.shape, aperture.rx_positions.shape, aperture.mics_per_stop
    ((6, 3), (6, 3), 1)
    """

    tx_positions: np.ndarray
    rx_positions: np.ndarray
    stage_positions: np.ndarray
    mics_per_stop: int = 1

    def __post_init__(self) -> None:
        tx = v.array("tx_positions", self.tx_positions, shape=(None, 3))
        rx = v.array("rx_positions", self.rx_positions, shape=(len(tx), 3))
        st = v.array("stage_positions", self.stage_positions, shape=(len(tx), 3))
        k = v.positive_int("mics_per_stop", self.mics_per_stop)
        if len(tx) % k:
            raise ValueError(f"mics_per_stop={k} does not divide the {len(tx)} measurements")
        object.__setattr__(self, "tx_positions", tx)
        object.__setattr__(self, "rx_positions", rx)
        object.__setattr__(self, "stage_positions", st)
        object.__setattr__(self, "mics_per_stop", k)

    def __len__(self) -> int:
        return len(self.tx_positions)

    @property
    def n_meas(self) -> int:
        return len(self.tx_positions)

    @property
    def n_stops(self) -> int:
        """Pings (stops): ``n_meas // mics_per_stop``."""
        return len(self.tx_positions) // self.mics_per_stop

    def to_csv(self, path: str | Path) -> Path:
        """Write one row per measurement: ``tx_x..rx_z`` and the stage ``x, y, z``, metres.

        :func:`aperture_from_csv` reads it back (with ``mics_per_stop`` = 1).
        """
        path = Path(path)
        table = np.hstack([self.tx_positions, self.rx_positions, self.stage_positions])
        with path.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(BISTATIC_COLUMNS + STAGE_COLUMNS)
            w.writerows([[repr(float(x)) for x in row] for row in table])
        return path


def mic_offsets(rx_offset_m: tuple[float, float, float] | None,
                rx_offsets_m: np.ndarray | None) -> np.ndarray:
    """(k, 3) microphone offsets from ``rx_offset_m`` (one) or ``rx_offsets_m`` (several)."""
    if rx_offsets_m is None:
        return v.array("rx_offset_m", RX_OFFSET_M if rx_offset_m is None else rx_offset_m, shape=(3,))[None]
    if rx_offset_m is not None:
        raise ValueError("give rx_offset_m (one microphone) or rx_offsets_m (several), not both")
    return v.array("rx_offsets_m", rx_offsets_m, shape=(None, 3))


def aperture_from_stops(stage: np.ndarray, tx: np.ndarray, rx: np.ndarray) -> Aperture:
    """Aperture from stops: ``stage``, ``tx`` (n, 3) and ``rx`` (n, k, 3), stop-major."""
    k = rx.shape[1]
    return Aperture(np.repeat(tx, k, axis=0), rx.reshape(-1, 3), np.repeat(stage, k, axis=0), k)


def raster_aperture(
    nx: int,
    ny: int,
    width_m: float,
    height_m: float,
    *,
    center_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    tx_offset_m: tuple[float, float, float] = TX_OFFSET_M,
    rx_offset_m: tuple[float, float, float] | None = None,
    pattern: str = "serpentine",
    rx_offsets_m: np.ndarray | None = None,
) -> Aperture:
    """Stops on an ``nx`` x ``ny`` grid in the plane ``z = center_m[2]`` facing +z.

    Parameters
    ----------
    nx, ny : int
        Number of columns (along x) and rows (along y).
    width_m, height_m : float
        Extent covered by the stops along x and y (first to last stop).
    center_m : tuple of float
        Centre of the scan, metres.
    tx_offset_m, rx_offset_m : tuple of float
        Speaker and microphone offsets from the carriage, metres (the rig's local frame is the
        scene frame here). ``rx_offset_m`` defaults to ``(0.02, 0, 0)``.
    pattern : {"serpentine", "raster"}
        Visiting order: serpentine reverses every other row (shorter moves); raster always
        runs along +x.
    rx_offsets_m : (k, 3) array, optional
        Several microphones per ping, replacing ``rx_offset_m``: k measurements per stop.

    Examples
    --------
    >>> import clsas
    >>> aperture = clsas.raster_aperture(18, 12, 1.0, 1.0)   # the paper's 216 stops over 1 m x 1 m
    >>> aperture.tx_positions.shape
    (216, 3)
    """
    nx = v.positive_int("nx", nx)
    ny = v.positive_int("ny", ny)
    w = v.non_negative("width_m", width_m)
    h = v.non_negative("height_m", height_m)
    v.choice("pattern", pattern, ("serpentine", "raster"))
    c = v.array("center_m", center_m, shape=(3,))
    txo = v.array("tx_offset_m", tx_offset_m, shape=(3,))
    rxo = mic_offsets(rx_offset_m, rx_offsets_m)
    xs = np.linspace(-w / 2, w / 2, nx) if nx > 1 else np.zeros(1)
    ys = np.linspace(-h / 2, h / 2, ny) if ny > 1 else np.zeros(1)
    stops = []
    for j, y in enumerate(ys):
        row = xs[::-1] if (pattern == "serpentine" and j % 2) else xs
        stops += [(x, y, 0.0) for x in row]
    stage = np.asarray(stops) + c
    return aperture_from_stops(stage, stage + txo, stage[:, None, :] + rxo[None])


# no machine images more than this many voxels along one axis; refusing here keeps a mistyped
# spacing from allocating gigabytes of axis before the memory guard can speak
MAX_AXIS_POINTS = 1_000_000


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid of voxel centres; axes in metres, values indexed ``[ix, iy, iz]``.

    Parameters
    ----------
    x_m, y_m, z_m : numpy.ndarray
        (n,) voxel centres along each axis, metres, increasing and evenly spaced. A single value
        makes the grid flat along that axis (a plane).

    Examples
    --------
    >>> import clsas
    >>> grid = clsas.VoxelGrid.from_bounds((-0.4, 0.4), (-0.3, 0.3), (1.0, 1.7), 0.01)
    >>> grid.shape
    (81, 61, 71)
    >>> plane = clsas.VoxelGrid.plane("z", at_m=0.0, u_m=(-0.15, 0.15), v_m=(-0.15, 0.15), spacing_m=0.01)
    >>> plane.shape
    (31, 31, 1)
    """

    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray

    def __post_init__(self) -> None:
        for name in ("x_m", "y_m", "z_m"):
            ax = v.array(name, getattr(self, name), ndim=1)
            if len(ax) > 1:
                d = np.diff(ax)
                if np.any(d <= 0):
                    raise ValueError(f"{name} must be strictly increasing (an inverted grid?)")
                if not np.allclose(d, d[0], rtol=1e-6, atol=1e-12):
                    raise ValueError(f"{name} must be evenly spaced")
            object.__setattr__(self, name, ax)

    @classmethod
    def from_bounds(
        cls,
        x_m: tuple[float, float],
        y_m: tuple[float, float],
        z_m: tuple[float, float],
        spacing_m: float | tuple[float, float, float],
    ) -> VoxelGrid:
        """Grid covering ``[lo, hi]`` on each axis with the given spacing.

        An axis with ``lo == hi`` is a single plane: a 2-D grid costs a plane, not a volume.
        """
        sp = np.broadcast_to(np.asarray(spacing_m, dtype=float), (3,))
        axes = []
        for name, b, d in zip(("x_m", "y_m", "z_m"), (x_m, y_m, z_m), sp, strict=True):
            lo, hi = v.array(name, b, shape=(2,))
            d = v.positive("spacing_m", d)
            if hi < lo:
                raise ValueError(f"{name} bounds are inverted: ({lo:g}, {hi:g})")
            n = np.floor((hi - lo) / d + 1e-9) + 1
            if n > MAX_AXIS_POINTS:
                raise ValueError(
                    f"spacing_m={d:g} gives {n:.3g} voxels along {name[0]} ({lo:g} to {hi:g} m); at most "
                    f"{MAX_AXIS_POINTS:.0e} per axis: use a spacing of {(hi - lo) / MAX_AXIS_POINTS:.3g} m or more"
                )
            axes.append(lo + d * np.arange(int(n)))
        return cls(*axes)

    @classmethod
    def plane(
        cls,
        axis: str = "z",
        *,
        at_m: float,
        u_m: tuple[float, float],
        v_m: tuple[float, float],
        spacing_m: float | tuple[float, float],
    ) -> VoxelGrid:
        """A 2-D grid: the plane ``axis = at_m``, one voxel thick.

        ``axis="z"`` is a horizontal plane (z is up for circular apertures: turntable users image
        the plane through the target), ``"x"`` or ``"y"`` a vertical one. The in-plane axes
        (u, v) are the other two in order: (x, y) for ``"z"``, (x, z) for ``"y"``, (y, z) for ``"x"``.

        Parameters
        ----------
        axis : {"x", "y", "z"}
            The axis normal to the plane.
        at_m : float
            Position of the plane on that axis, metres.
        u_m, v_m : (lo, hi) tuple of float
            Extent along the in-plane axes, metres (voxel centres from lo, up to hi).
        spacing_m : float or (du, dv)
            Voxel spacing in the plane, metres.

        Returns
        -------
        VoxelGrid
            Shape with a 1 on ``axis``, e.g. ``(nu, nv, 1)`` for ``axis="z"``.
        """
        v.choice("axis", axis, ("x", "y", "z"))
        at = v.finite("at_m", at_m)
        bounds = {}
        for name, b in (("u_m", u_m), ("v_m", v_m)):
            lo, hi = v.array(name, b, shape=(2,))
            if hi < lo:
                raise ValueError(f"{name} bounds are inverted: ({lo:g}, {hi:g})")
            bounds[name] = (lo, hi)
        sp = v.array("spacing_m", np.broadcast_to(np.asarray(spacing_m, dtype=float), (2,)), shape=(2,))
        for d in sp:
            v.positive("spacing_m", d)
        inplane = [a for a in "xyz" if a != axis]
        box = {inplane[0]: bounds["u_m"], inplane[1]: bounds["v_m"], axis: (at, at)}
        step = {inplane[0]: sp[0], inplane[1]: sp[1], axis: 1.0}
        return cls.from_bounds(box["x"], box["y"], box["z"], tuple(step[a] for a in "xyz"))

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.x_m), len(self.y_m), len(self.z_m))

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def spacing(self) -> tuple[float, float, float]:
        """Spacing along each axis (1.0 for a single-plane axis), metres."""
        return tuple(float(a[1] - a[0]) if len(a) > 1 else 1.0 for a in (self.x_m, self.y_m, self.z_m))

    def bounds(self) -> np.ndarray:
        """(3, 2) array of the first and last voxel centre on each axis."""
        return np.array([[a[0], a[-1]] for a in (self.x_m, self.y_m, self.z_m)])

    def points(self) -> np.ndarray:
        """(size, 3) voxel centres in C order (z fastest)."""
        X, Y, Z = np.meshgrid(self.x_m, self.y_m, self.z_m, indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def index_of(self, point_m: np.ndarray) -> tuple[int, int, int]:
        """Index of the voxel nearest to ``point_m``."""
        p = v.array("point_m", point_m, shape=(3,))
        return tuple(int(np.argmin(np.abs(a - c))) for a, c in zip((self.x_m, self.y_m, self.z_m), p, strict=True))


@dataclass(frozen=True)
class Wall:
    """An infinite plane that reflects sound specularly.

    ``point_m`` lies on the plane; ``normal`` points into the half-space the rig is in;
    ``reflectivity`` is the pressure reflection coefficient.

    Parameters
    ----------
    point_m : tuple of float
        A point on the plane, metres.
    normal : tuple of float
        The plane's normal (normalised here), pointing towards the rig.
    reflectivity : float
        Pressure reflection coefficient, 0 to 1.

    Examples
    --------
    A mannequin around a corner, heard only through the wall's mirror image:

    >>> import numpy as np
    >>> import clsas
    >>> wall = clsas.Wall(point_m=(0.0, 0.0, 2.0), normal=(0.7071, 0.0, -0.7071))
    >>> scene = clsas.Scene(np.array([[0.8, 0.0, 1.6]]), visible=np.array([False]), walls=(wall,))
    """

    point_m: tuple[float, float, float]
    normal: tuple[float, float, float]
    reflectivity: float = 0.9

    def __post_init__(self) -> None:
        p = v.array("point_m", self.point_m, shape=(3,))
        n = v.array("normal", self.normal, shape=(3,))
        norm = np.linalg.norm(n)
        if norm == 0:
            raise ValueError("normal must be a non-zero vector")
        r = v.finite("reflectivity", self.reflectivity)
        if not -1 <= r <= 1:
            raise ValueError(f"reflectivity must be in [-1, 1], got {r:g}")
        object.__setattr__(self, "point_m", p)
        object.__setattr__(self, "normal", n / norm)

    def mirror(self, points_m: np.ndarray) -> np.ndarray:
        """Mirror image of (n, 3) points across the plane."""
        d = (np.asarray(points_m) - self.point_m) @ self.normal
        return points_m - 2 * d[:, None] * self.normal


@dataclass(frozen=True)
class Scene:
    """Point reflectors, mirror walls and air.

    Attributes
    ----------
    points_m : (k, 3) reflector positions, metres.
    amplitudes : (k,) reflection amplitudes (pressure ratio at 1 m).
    visible : (k,) whether the rig sees a reflector directly (False: around a corner, heard
        only through a wall's mirror image).
    walls : mirror walls; each adds a first-order image of every reflector (both legs by the
        wall, amplitude times reflectivity squared) and, if ``wall_echo``, the wall's own echo.
    temperature_c, humidity_pct : the air, degrees Celsius and percent relative humidity; they
        give the speed of sound (``c_mps``, :func:`clsas.speed_of_sound`, humid air) and the
        absorption, and the simulated dataset carries both.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> scene = clsas.Scene(np.array([[0.1, 0.05, 1.2], [-0.2, 0.1, 1.5]]), amplitudes=np.array([1.0, 0.5]),
    ...                     temperature_c=25.0)
    >>> scene.points_m.shape
    (2, 3)
    """

    points_m: np.ndarray
    amplitudes: np.ndarray | None = None
    visible: np.ndarray | None = None
    walls: tuple[Wall, ...] = ()
    temperature_c: float = 20.0
    humidity_pct: float = 50.0
    wall_echo: bool = False

    def __post_init__(self) -> None:
        p = v.array("points_m", self.points_m, shape=(None, 3))
        a = np.ones(len(p)) if self.amplitudes is None else v.array(
            "amplitudes", self.amplitudes, shape=(len(p),)
        )
        vis = np.ones(len(p), bool) if self.visible is None else np.asarray(self.visible, bool)
        if vis.shape != (len(p),):
            raise ValueError(f"visible must have shape ({len(p)},), got {vis.shape}")
        object.__setattr__(self, "points_m", p)
        object.__setattr__(self, "amplitudes", a)
        object.__setattr__(self, "visible", vis)
        object.__setattr__(self, "walls", tuple(self.walls))
        speed_of_sound(self.temperature_c, self.humidity_pct)  # validates the temperature and humidity

    @property
    def c_mps(self) -> float:
        """The speed of sound in the scene's air (its temperature and humidity), m/s."""
        return speed_of_sound(self.temperature_c, self.humidity_pct)

    def image_sources(self) -> tuple[np.ndarray, np.ndarray]:
        """Every reflector the rig hears: direct ones and first-order mirror images.

        Returns ``(points (n, 3), amplitudes (n,))``.
        """
        pts = [self.points_m[self.visible]]
        amps = [self.amplitudes[self.visible]]
        for wall in self.walls:
            pts.append(wall.mirror(self.points_m))
            amps.append(self.amplitudes * wall.reflectivity**2)
        return np.concatenate(pts), np.concatenate(amps)
