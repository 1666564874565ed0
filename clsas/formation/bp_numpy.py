"""NumPy twins of kernels/backproject.cl (float64, written to be read) and of kernels/records.cl (the
carrier records backproject.cl reads, complex64 as the kernel makes them)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..physics.beam import BeamWeights, pair_weights
from ..physics.geometry import VoxelGrid


def backproject(
    data: np.ndarray,
    tau0_s: np.ndarray,
    dtau_s: float,
    fc_hz: float,
    tx_positions: np.ndarray,
    rx_positions: np.ndarray,
    c_mps: float | np.ndarray,
    points_m: np.ndarray,
    progress: Callable[[int, int], None] | None = None,
    beam: BeamWeights | None = None,
) -> np.ndarray:
    """Sum over measurements of the linearly interpolated profile times the carrier.

    Parameters
    ----------
    data : (n_meas, n_lags) complex baseband profiles; sample ``k`` of row ``m`` is delay
        ``tau0_s[m] + k dtau_s``.
    c_mps : float or (n_meas,) array
        Speed of sound, m/s; an array gives each measurement its own.
    points_m : (n_vox, 3) voxel centres, m.
    beam : clsas.physics.beam.BeamWeights, optional
        Weight (or gate) each pair by the two-way beam (:func:`clsas.physics.beam.pair_weights`);
        None: every pair counts fully (omnidirectional).

    Returns
    -------
    (n_vox,) complex128 image values.
    """
    return _form(data, tau0_s, dtau_s, fc_hz, tx_positions, rx_positions, c_mps, points_m,
                 lambda m: exact_path(points_m, tx_positions[m], rx_positions[m]), progress, beam)


def exact_path(points_m: np.ndarray, tx: np.ndarray, rx: np.ndarray) -> np.ndarray:
    """(n_vox,) bistatic path |v - tx| + |v - rx| of every voxel centre, m."""
    return np.linalg.norm(points_m - tx, axis=1) + np.linalg.norm(points_m - rx, axis=1)


def _form(data, tau0_s, dtau_s, fc_hz, tx_positions, rx_positions, c_mps, points_m,
          path_of: Callable[[int], np.ndarray], progress, beam) -> np.ndarray:
    """The image of :func:`backproject` with the path of measurement m given by ``path_of(m)``."""
    n_meas, n_lags = data.shape
    out = np.zeros(len(points_m), dtype=np.complex128)
    c = np.broadcast_to(np.asarray(c_mps, float), (n_meas,))
    for m in range(n_meas):
        tau = path_of(m) / c[m]
        idx = (tau - tau0_s[m]) / dtau_s
        inside = (idx >= 0) & (idx <= n_lags - 1)  # no wrap-around, no clamping to the edge
        i0 = np.clip(np.floor(idx), 0, n_lags - 2).astype(np.int64)
        w = idx - i0
        value = (1 - w) * data[m, i0] + w * data[m, i0 + 1]
        if beam is not None:
            value = value * pair_weights(beam.luts, tx_positions[m], rx_positions[m], beam.tx_dir[m],
                                         beam.rx_dir[m], points_m, beam.gate)
        out += np.where(inside, value * np.exp(2j * np.pi * fc_hz * tau), 0)
        if progress is not None:
            progress(m + 1, n_meas)
    return out


def backproject_range_expansion(
    data: np.ndarray,
    tau0_s: np.ndarray,
    dtau_s: float,
    fc_hz: float,
    tx_positions: np.ndarray,
    rx_positions: np.ndarray,
    c_mps: float | np.ndarray,
    grid: VoxelGrid,
    run: int,
    vec: int,
    progress: Callable[[int, int], None] | None = None,
    beam: BeamWeights | None = None,
) -> np.ndarray:
    """:func:`backproject` on ``grid`` with the paths of kernels/backproject.cl's
    -DRANGE_EXPANSION=run build at VEC=vec (:func:`range_expanded_path`): the variant's
    arithmetic in float64. Returns (n_vox,) complex128 values in the grid's C order."""
    layout = expansion_layout(grid, run, vec)
    return _form(data, tau0_s, dtau_s, fc_hz, tx_positions, rx_positions, c_mps, layout["points"],
                 lambda m: range_expanded_path(layout, tx_positions[m], rx_positions[m]), progress, beam)


def expansion_layout(grid: VoxelGrid, run: int, vec: int) -> dict:
    """Where the -DRANGE_EXPANSION=run build at VEC=vec expands: work-item i owns the ``vec``
    consecutive voxels ``i vec .. i vec + vec - 1`` of the flattened grid (C order, z fastest).
    Those of a work-item whose voxels lie in one z row (``along``, (n_vox,) bool) are expanded
    in runs of ``run`` consecutive voxels (``run`` divides ``vec``), each around the point midway
    between the run's first and last voxel (``ref``, (n_vox, 3), m), ``s`` voxel steps from it
    (``s`` = its place in the run - (run - 1) / 2); the others are exact. Also the voxel centres
    (``points``) and the z spacing ``dz`` (m)."""
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    for name, n in (("run", run), ("vec", vec)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"{name} must be a positive int (voxels), got {n!r}")
    if vec % run:
        raise ValueError(f"run must divide vec, got run={run}, vec={vec}")
    nz = grid.shape[2]
    v = np.arange(grid.size)
    along = (v - v % vec) % nz + vec <= nz  # the work-item's voxels in one z row
    first = v - v % run  # the run's first voxel
    points = grid.points()
    dz = grid.spacing()[2]
    half = 0.5 * (run - 1)
    ref = points[first].copy()
    ref[:, 2] += half * dz
    return {"points": points, "along": along, "s": (v - first) - half, "ref": ref, "dz": dz}


def range_expanded_path(layout: dict, tx: np.ndarray, rx: np.ndarray) -> np.ndarray:
    """(n_vox,) bistatic path of every voxel as the -DRANGE_EXPANSION build computes it (float64):
    where the work-item's voxels lie along z (``layout`` from :func:`expansion_layout`), each
    distance d(s) = |ref + s dz e_z - p| by its second-order Taylor expansion in s at the
    reference, d0 + s g + s^2 h with a = ref - p, d0 = |a|, g = a_z dz / d0,
    h = (dz^2 - g^2) / (2 d0); elsewhere exact."""
    path = exact_path(layout["points"], tx, rx)
    along = layout["along"]
    s, ref, dz = layout["s"][along], layout["ref"][along], layout["dz"]
    expanded = np.zeros(len(ref))
    for p in (tx, rx):
        a = ref - p
        d0 = np.linalg.norm(a, axis=1)
        g = a[:, 2] * dz / d0
        h = (dz * dz - g * g) / (2 * d0)
        expanded += d0 + s * (g + s * h)
    path[along] = expanded
    return path


def expansion_path_error(grid: VoxelGrid, tx_positions: np.ndarray, rx_positions: np.ndarray,
                         run: int) -> np.ndarray:
    """(n_meas,) the largest path error of the -DRANGE_EXPANSION build per measurement, m.

    The Lagrange remainder of each distance's second-order expansion along z is
    |D3(xi)| |s|^3 / 6, with the third derivative D3 = -3 rho^2 zeta dz^3 / r^5 (zeta = z - p_z,
    rho the distance across z, r = |v - p|) somewhere between the reference and the voxel, and
    |s| <= (run - 1) / 2; rho^2 |zeta| / r^5 is taken at its largest over the box of
    (|zeta|, rho) that the grid's voxels span from the transducer; tx's and rx's are added.
    Any work-item of ``run`` or more voxels (a multiple of ``run``) is within it: those not in one
    z row are exact. 0 where no run fits in a z row; inf where a transducer lies in the grid's
    box."""
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    if isinstance(run, bool) or not isinstance(run, (int, np.integer)) or run < 1:
        raise ValueError(f"run must be a positive int (voxels per expansion), got {run!r}")
    tx = np.asarray(tx_positions, float).reshape(-1, 3)
    rx = np.asarray(rx_positions, float).reshape(-1, 3)
    if run == 1 or grid.shape[2] < run:
        return np.zeros(len(tx))
    half_run = 0.5 * (run - 1) * grid.spacing()[2]
    b = grid.bounds()
    return 0.5 * half_run ** 3 * (_largest_cubic_rate(b, tx) + _largest_cubic_rate(b, rx))


def _largest_cubic_rate(bounds: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(n,) the largest rho^2 |zeta| / r^5 over the box ``bounds`` ((3, 2), m) seen from each
    point of ``p`` ((n, 3), m): on the box of (|zeta|, rho) it spans, the function has no critical
    point inside and one maximum along each edge (|zeta| = rho / 2 at a fixed rho,
    rho = |zeta| sqrt(2/3) at a fixed zeta), so the largest of the four edges' clipped maxima."""
    lo, hi = bounds[:, 0], bounds[:, 1]
    zl, zh = lo[2] - p[:, 2], hi[2] - p[:, 2]
    z_lo = np.where(zl * zh <= 0, 0.0, np.minimum(np.abs(zl), np.abs(zh)))
    z_hi = np.maximum(np.abs(zl), np.abs(zh))
    near = np.maximum(np.maximum(lo[:2] - p[:, :2], p[:, :2] - hi[:2]), 0.0)
    far = np.maximum(np.abs(lo[:2] - p[:, :2]), np.abs(hi[:2] - p[:, :2]))
    r_lo, r_hi = np.hypot(near[:, 0], near[:, 1]), np.hypot(far[:, 0], far[:, 1])

    def rate(z, rho):
        with np.errstate(divide="ignore", invalid="ignore"):
            out = rho * rho * z / np.hypot(z, rho) ** 5
        return np.where((z == 0) & (rho == 0), np.inf, out)

    return np.max([rate(np.clip(r_lo / 2, z_lo, z_hi), r_lo), rate(np.clip(r_hi / 2, z_lo, z_hi), r_hi),
                   rate(z_lo, np.clip(z_lo * np.sqrt(2 / 3), r_lo, r_hi)),
                   rate(z_hi, np.clip(z_hi * np.sqrt(2 / 3), r_lo, r_hi))], axis=0)


def range_expansion_error(grid: VoxelGrid, tx_positions: np.ndarray, rx_positions: np.ndarray,
                          c_mps: float | np.ndarray, fc_hz: float, run: int,
                          dtau_s: float | None = None) -> float:
    """The largest error of the -DRANGE_EXPANSION build against the exact paths, relative to the
    image's peak, predicted from :func:`expansion_path_error`.

    A path error delta moves a pair's value V = p(tau) exp(j 2 pi fc tau) by at most
    (delta / c) max |dV/dtau|: 2 pi fc delta / c of its size through the carrier (the phase
    error) and, for profiles linearly interpolated between samples ``dtau_s`` apart (which move
    by at most twice their largest value per sample), 2 delta / (c dtau) through the envelope.
    Relative to an image whose peak is the coherent sum of its pairs (a focused reflector).

    Parameters
    ----------
    grid : VoxelGrid
    tx_positions, rx_positions : (n_meas, 3) m
    c_mps : float or (n_meas,) speed of sound, m/s
    fc_hz : carrier frequency, Hz
    run : voxels per expansion (the build's -DRANGE_EXPANSION)
    dtau_s : float, optional
        Profile lag step, s: the envelope's share is included; None: the phase error only.

    Returns
    -------
    float: the bound, a fraction of the peak (0 where nothing is expanded).
    """
    tx = np.asarray(tx_positions, float)
    rx = np.asarray(rx_positions, float)
    if tx.ndim != 2 or tx.shape[1] != 3 or rx.shape != tx.shape:
        raise ValueError(f"tx_positions and rx_positions must both be (n_meas, 3), got {tx.shape} and {rx.shape}")
    c = np.broadcast_to(np.asarray(c_mps, float), (len(tx),))
    if not np.all(c > 0):
        raise ValueError(f"c_mps must be positive, got {c_mps!r}")
    if not (np.isfinite(fc_hz) and fc_hz >= 0):
        raise ValueError(f"fc_hz must be finite and >= 0, got {fc_hz!r}")
    if dtau_s is not None and not dtau_s > 0:
        raise ValueError(f"dtau_s must be None or positive, got {dtau_s!r}")
    if len(tx) == 0:
        return 0.0
    rate = 2 * np.pi * fc_hz + (0.0 if dtau_s is None else 2.0 / dtau_s)  # value change per second of delay
    return float(np.max(expansion_path_error(grid, tx, rx, run) * rate / c))


# fc dtau, carrier cycles per profile sample, up to which backproject.cl's sub-sample rotation
# (a polynomial for |angle| <= 0.6 pi) holds; coarser profiles are upsampled first
MAX_CYCLES_PER_SAMPLE = 0.6


def upsample_factor(fc_hz: float, dtau_s: float) -> int:
    """The smallest integer factor that brings a profile to :data:`MAX_CYCLES_PER_SAMPLE` or less."""
    return max(1, int(np.ceil(abs(fc_hz) * dtau_s / MAX_CYCLES_PER_SAMPLE - 1e-9)))


def upsample(prof: np.ndarray, up: int) -> np.ndarray:
    """(n, L) profiles -> (n, (L - 1) up + 1) by linear interpolation between their samples
    (their linear interpolation is unchanged)."""
    n, L = prof.shape
    fine = np.zeros((n, (L - 1) * up + 1), prof.dtype)
    for i in range(up):
        fine[:, i : (L - 1) * up : up] = (1 - i / up) * prof[:, :-1] + (i / up) * prof[:, 1:]
    fine[:, -1] = prof[:, -1]
    return fine


def upsample_adjoint(fine: np.ndarray, up: int) -> np.ndarray:
    """The adjoint of :func:`upsample`: (n, (L - 1) up + 1) -> (n, L)."""
    n = fine.shape[0]
    L = (fine.shape[1] - 1) // up + 1
    out = np.zeros((n, L), fine.dtype)
    out[:, -1] = fine[:, -1]
    for i in range(up):
        part = fine[:, i : (L - 1) * up : up]
        out[:, :-1] += (1 - i / up) * part
        out[:, 1:] += (i / up) * part
    return out


def carrier_factors(n_records: int, tau0_s, dtau_s: float, fc_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The two factors of :func:`carrier_rotation`, complex64, each computed in double precision
    and reduced to a turn: ``(n_records,) exp(j 2 pi fc dtau (k + 1/2))`` and
    ``(n_meas,) exp(j 2 pi fc tau0_m)``."""
    cycles = fc_hz * dtau_s
    k = np.arange(n_records)
    s0 = np.asarray(tau0_s, float) / dtau_s
    return (np.exp(2j * np.pi * np.mod(cycles * (k + 0.5), 1.0)).astype(np.complex64),
            np.exp(2j * np.pi * np.mod(cycles * s0, 1.0)).astype(np.complex64))


def carrier_rotation(n_records: int, tau0_s, dtau_s: float, fc_hz: float) -> np.ndarray:
    """(n_meas, n_records) complex64: ``exp(j 2 pi fc dtau (k + 1/2 + tau0_m / dtau))``, the
    carrier at the middle of record k, the product of :func:`carrier_factors` in complex64."""
    rot, rot0 = carrier_factors(n_records, tau0_s, dtau_s, fc_hz)
    return rot[None, :] * rot0[:, None]


def carrier_records(data: np.ndarray, n_lags: int, tau0_s, dtau_s: float, fc_hz: float):
    """The profiles as kernels/backproject.cl reads them (the twin of records.cl's
    ``carrier_records``): record k of measurement m holds samples
    k and k + 1, both rotated by :func:`carrier_rotation`, so that the kernel's carrier is the
    sub-sample rotation only.

    ``data`` (n_meas, <= n_lags) is zero-padded to ``n_lags`` samples. Where ``fc dtau`` exceeds
    :data:`MAX_CYCLES_PER_SAMPLE` the profile is first upsampled (:func:`upsample`). Returns
    ``(records (n_meas, n_lags', 2) complex64, dtau', phi = 2 pi fc dtau')``.
    """
    n_meas = data.shape[0]
    prof = np.zeros((n_meas, n_lags), np.complex64)
    prof[:, : data.shape[1]] = data
    up = upsample_factor(fc_hz, dtau_s)
    if up > 1:
        prof, dtau_s = upsample(prof, up), dtau_s / up
    rot = carrier_rotation(prof.shape[1], tau0_s, dtau_s, fc_hz)
    pairs = np.zeros((n_meas, prof.shape[1], 2), np.complex64)  # p[n_lags] = 0
    np.multiply(prof, rot, out=pairs[:, :, 0])
    np.multiply(prof[:, 1:], rot[:, :-1], out=pairs[:, :-1, 1])
    return pairs, dtau_s, 2 * np.pi * fc_hz * dtau_s
