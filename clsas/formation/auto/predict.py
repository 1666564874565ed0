"""``formation="auto"``'s cost and error model: each formation's predicted time and error.

For a request (profiles, grid, device), each formation gets a predicted run time and a
predicted error against exact backprojection (complex error-to-signal over the grid, dB, as
:func:`clsas.formation.error_to_signal_db` measures it) (:func:`estimate`); :func:`.choice.choose`
takes the fastest whose predicted error is at most ``max_error_db - MARGIN_DB``, and says why. The
seconds per unit of work, their scaling to a device and the device's calibration factors are in
:mod:`.timing`; which predictions auto trusts, and what it forms and measures in turn, in
:mod:`.trust`.

Time. Each formation's time is a sum of counted work times seconds per unit:

- ``bp``: voxel-measurement pairs;
- ``omega-k``: the delay FFT (``n_meas n_fft log2 n_fft``), the lattice FFTs (``mu mv n_f log2(mu mv)``
  per lattice), the Stolt spreading (columns x frequencies x bistatic terms x kernel width), the depth FFTs
  (columns x cells x log2 cells x terms) and the chirp-z transforms onto the grid, sizes from
  :func:`clsas.formation.omega_k.plan_sizes` (no data transformed);
- ``ffbp``: the tree's own planning (timed, it is run), the leaves (leaf samples x measurements
  per leaf), the merges (samples x factor x taps³ per level) and the last step (voxels x factor
  x taps³), sizes from :func:`clsas.formation.ffbp.plan_tree`.

The built-in seconds per unit (:data:`.timing.BUILTIN`) were fitted on a quiet 2-core AMD EPYC VM (PoCL
CPU device; see docs/guide/fast-formation.md) and are scaled to other devices by
their compute units (kernels; a GPU's four times a CPU's); ω-k's host work by the host's cores
over 2 to the power :data:`.timing.OMEGA_K_CORE_EXPONENT` (0.2: its FFTs gain little from many cores at
these sizes). ``clsas calibrate`` (:func:`.calibrate.calibrate_auto`) measures the formations
on the device and stores one factor per formation (measured over predicted, the median over its
cases) beside the kernel-variant verdicts (:func:`.timing.calibration_path`); :func:`estimate` applies it.
The model need only rank the formations: within a factor of two is enough where they differ by
more. Sizing ω-k and planning an FFBP tree cost time themselves (0.03 s and 0.07 s at 64 x 64
stops), lost where that formation is not chosen: each is done only where a lower bound of its time
is under ``PLAN_IF_UNDER`` (0.7) times the best time so far.

Error. ``bp`` is the reference (exact; auto forms it with :func:`.trust.bp_options`, which lets its
kernel take a variant stated within the target less the margin). ``omega-k`` is refused for apertures that are not
planar-uniform (:class:`~clsas.formation.planar.NotPlanarUniform`); otherwise its error is its
method's (:data:`OMEGA_K_BASE_DB`, measured -44 to -48 dB inside the well-sampled cone; worse on lattices
of fewer than 16 stops a side, :data:`OMEGA_K_DB_PER_STOP`) plus the
backprojection contributions it leaves out: those of stop-voxel pairs whose angle the lattice
samples aliased (the grating lobes, see :mod:`clsas.formation.planar`), counted per voxel over
the stops (weighted by their spreading loss) and the band (:func:`alias_fraction`) and taken as
an amplitude fraction of a reflector's focus, RMS over the grid: 0.5 to 4 dB above the error
measured on the crossover scans and the dense case (conservative). ``ffbp``'s error is a
systematic loss per level that adds almost coherently:
``FFBP_BASE_DB[oversample] + 20 log10(depth + 1)`` (module notes of :mod:`clsas.formation.ffbp`,
refitted to the crossover scans); auto tries a few depths and oversampling rates and keeps
the fastest that meets the target.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ...physics.geometry import VoxelGrid
from ...types.profiles import Profiles
from .rules import DEFAULT_MAX_ERROR_DB, check_max_error_db
from .timing import BUILTIN, _device, _seconds, load_calibration, work_bp, work_ffbp, work_omega_k
from .trust import CHECK_IF_UNDER, MARGIN_DB, Estimate, _near, _safe, bp_options, check_seconds

__all__ = ["alias_fraction", "estimate", "lattice_aliases", "predict_time"]

OMEGA_K_BASE_DB = -42.0
# ... on lattices of at least OMEGA_K_FULL_SIDE stops a side (the crossover scans, 16-128); on fewer the
# method's own error grows: on the planar requests of the formation family's fit seeds 500-599 that the
# lattice samples unaliased, 8-10 stops a side measured -27.8 to -40.5 dB (8 of 8 worse than -42, 5 of 8
# worse than -33), 13-48 a side -32.0 to -49.6 dB. The base is taken this much worse per stop short of
# OMEGA_K_FULL_SIDE on the shorter side (-26.6 dB at 9 a side, -33.2 at 12): above every one measured
OMEGA_K_FULL_SIDE = 16
OMEGA_K_DB_PER_STOP = 2.2
# ω-k with the aliased angles formed (``upsample="auto"``, a lattice ``up`` times as fine): on the 15
# aliased planar requests of the family's fit seeds 500-599 it measured -31.7 to -49.8 dB where the
# plain ω-k measured -1.9 to -34 (at up = 2: -42.6 to -46.2; 3: -36.2 to -49.8; 4: -42.5, -47.0; 5:
# -31.7, -34.6), and was faster than bp on 8 of them. Its base is taken this much worse per step of up
OMEGA_K_UP_DB = 3.0
# ... weighed only where no voxel-stop angle is steeper than this sine: its padding counts the angles'
# spread up to a sine of 0.9 and its look-angle window ends near it. Steeper, it measured -27.0 dB on the
# 128 x 128-stop crossover scan (sine 0.82; predicted -36) and -31.7, -34.6 dB on the fit requests at 0.80-0.81
OMEGA_K_UP_MAX_SINE = 0.75
FFBP_BASE_DB = {1.5: -39.0, 2.0: -49.0, 2.5: -56.0, 3.0: -62.0}  # at order 3, lsq weights, depth 0
FFBP_CANDIDATES = (1.5, 2.0, 2.5, 3.0)
# the tree's planning (host, Python) takes about this per measurement (0.07 s for 4096 stops, 0.3 s
# for 16384, its sampling rates worked out per node where they can be; 27-46 ms, 1.7-2.8e-5 s each, for
# 1155-1634 measurements on the formation family's fit seeds; the bound takes less); with part of the
# last step's time it bounds FFBP's time from below before a tree is planned (FFBP_FLOOR_GRID)
FFBP_PLAN_S_PER_MEAS = 1.2e-5
PLAN_IF_UNDER = 0.7
# FFBP's lower bound: this fixed part, s, this share of its last step's modelled time, and its planning
# (FFBP_PLAN_S_PER_MEAS). Counting 1.5 times the model's whole last step, its 5 ms fixed part included,
# and planning at 1.7e-5 s a measurement gives more than FFBP's whole time on 21 of the 63 planar and
# off-lattice fit requests of the formation family (seeds 500-599, up to 1.66x), and auto would take bp
# where FFBP is up to 2.2x faster. These constants are under FFBP's time on all 63 (at most 0.98x)
FFBP_FLOOR_FIXED_S = 1e-3
FFBP_FLOOR_GRID = 0.75
# sizing ω-k (its lattice, band and aliased share, host side) takes about this fixed part and this per
# measurement, s: 1.1-4.7 ms on the 32 planar requests of the formation family's fit seeds 500-579
# (measured / predicted 0.6-1.9); it counts in ω-k's lower bound, since it is lost where bp is chosen
# (on scans bp forms in 2-6 ms it had doubled auto's time)
OMEGA_K_SIZING_S = (1.5e-3, 8e-7)


def _never_aliased(g, pu, pv, depth_min: float, k2_max: float) -> bool:
    """Whether no voxel-stop pair of the lattice group ``g`` is steep enough to be sampled aliased at the
    two-way wavenumber ``k2_max`` (the steepest ``|sin theta|`` per axis: at the nearest depth, the
    other axis' offset 0)."""
    from ..omega_k import farthest_offsets

    du, dv = farthest_offsets(g, pu, pv)
    su, sv = du / math.hypot(du, depth_min), dv / math.hypot(dv, depth_min)
    return bool(k2_max * su * g.spacing_uv[0] <= np.pi and k2_max * sv * g.spacing_uv[1] <= np.pi)


def lattice_aliases(sizes: dict) -> bool:
    """Whether any voxel-stop pair is sampled aliased at the top of the band (the test
    :func:`alias_fraction` makes before counting)."""
    pu, pv, depth = sizes["axes"]
    k2_max = 2 * 2 * np.pi * sizes["f_top_hz"] / sizes["c_mps"]
    return not all(_never_aliased(g, pu, pv, float(np.min(depth)), k2_max) for g in sizes["aperture"].groups)


def alias_fraction(sizes: dict, n_vox: int = 7, n_stops: int = 144, n_freq: int = 8) -> np.ndarray:
    """Per voxel (a coarse sub-grid, up to ``n_vox`` per axis), the share of (stop, frequency)
    pairs the lattice samples aliased: ``2 k |sin theta_a| > pi / d_a`` on a lattice axis ``a``,
    each stop weighted by its echo's spreading loss ``1 / r^2``.

    ``sizes`` is :func:`clsas.formation.omega_k.plan_sizes`'s; the frequencies are spread evenly
    over the band up to the top of its -20 dB band, the stops over each lattice.
    """
    pu, pv, depth = sizes["axes"]

    def sub(a):
        return a[np.unique(np.linspace(0, len(a) - 1, min(len(a), n_vox)).astype(int))]

    U, V, W = np.meshgrid(sub(pu), sub(pv), sub(depth), indexing="ij")
    f = np.linspace(max(sizes["f_band_hz"][0], 1.0), sizes["f_top_hz"], n_freq)
    k2 = 2 * 2 * np.pi * f / sizes["c_mps"]  # two-way wavenumber, (n_freq,)
    if not lattice_aliases(sizes):
        return np.zeros(U.shape)
    aliased = np.zeros(U.shape)
    total = 0
    for g in sizes["aperture"].groups:
        (u0, u1), (v0, v1) = g.extent_uv
        nu, nv = g.shape
        su = np.linspace(u0, u1, min(nu, int(math.sqrt(n_stops)) + 1))
        sv = np.linspace(v0, v1, min(nv, int(math.sqrt(n_stops)) + 1))
        SU, SV = (a.ravel() for a in np.meshgrid(su, sv, indexing="ij"))
        du_, dv_ = U[..., None] - SU, V[..., None] - SV
        r = np.sqrt(du_**2 + dv_**2 + W[..., None] ** 2)
        lim_u, lim_v = np.pi / g.spacing_uv[0], np.pi / g.spacing_uv[1]
        # a pair is aliased at every wavenumber above the lower of its two axes' limits
        # (k2 |sin_a| > lim_a): the share of the (increasing) k2 above it, by one search
        with np.errstate(divide="ignore"):
            k_alias = np.minimum(lim_u * r / np.abs(du_), lim_v * r / np.abs(dv_))
        bad_share = (len(k2) - np.searchsorted(k2, k_alias, side="right")) / len(k2)
        wt = 1.0 / r**2  # a stop's echo falls as 1 / (r_tx r_rx): the steep (aliased) stops weigh less
        aliased += (bad_share * wt).sum(axis=-1)
        total = total + wt.sum(axis=-1)
    return aliased / total


def _omega_k_estimate(profiles, grid, selection, factors, options: dict | None = None) -> Estimate:
    """ω-k's predicted time and error; ``options`` ``{"upsample": "auto"}`` costs it forming the aliased
    angles too (:data:`OMEGA_K_UP_DB`), else the lattice's aliased share is what it leaves out."""
    return _omega_k_sized(profiles, grid, selection, factors, options)[0]


def _omega_k_sized(profiles, grid, selection, factors, options: dict | None = None) -> tuple[Estimate, float, float]:
    """:func:`_omega_k_estimate`, the aliased share it counted (RMS over the grid; 0 when upsampled) and
    the sine of the steepest voxel-stop angle."""
    from ..omega_k import plan_sizes, steepest_sine

    options = dict(options or {})
    try:
        sizes = plan_sizes(profiles, grid, **options)
    except ValueError as exc:  # NotPlanarUniform is one
        return Estimate("omega-k", math.inf, math.inf, options, note=str(exc).split(";")[0]), 0.0, 1.0
    pu, pv, depth = sizes["axes"]
    sine = max(steepest_sine(g, pu, pv, float(np.min(depth))) for g in sizes["aperture"].groups)
    side = min((n for g in sizes["aperture"].groups for n in g.shape if n > 1), default=OMEGA_K_FULL_SIDE)
    base = OMEGA_K_BASE_DB + OMEGA_K_DB_PER_STOP * max(0, OMEGA_K_FULL_SIDE - side)
    work = work_omega_k(sizes, _device(selection) is not None)
    if options.get("upsample") == "auto":
        up = max(g["up"] for g in sizes["groups"])
        err = base + OMEGA_K_UP_DB * (up - 1)
        note = (f"method {base:.0f} dB ({side} stops on the lattice's shorter side), the aliased angles formed on a "
                f"lattice {up}x as fine ({OMEGA_K_UP_DB:g} dB a step)")
        return Estimate("omega-k", _seconds("omega-k", work, selection, factors), err, options, note=note), 0.0, sine
    aliases = lattice_aliases(sizes)
    frac = alias_fraction(sizes) if aliases else np.zeros(1)  # the same test alias_fraction makes first
    lost = float(np.sqrt(np.mean(frac**2)))
    err = 10 * math.log10(10 ** (base / 10) + lost**2)
    note = (f"method {base:.0f} dB ({side} stops on the lattice's shorter side); {100 * float(frac.mean()):.1f} % "
            "of stop-voxel-frequency samples "
            f"aliased on the lattice (RMS over the grid {100 * lost:.1f} %), which omega-k leaves out"
            + ("; with any pair aliased this is not trusted (measured before it is taken)" if aliases else ""))
    return (Estimate("omega-k", _seconds("omega-k", work, selection, factors), err, note=note, unpredicted=aliases),
            lost, sine)


def _omega_k_estimates(profiles, grid, selection, factors, target_db: float, best_s: float) -> list[Estimate]:
    """ω-k as it comes, and where that leaves out aliased angles and misses ``target_db``, with them
    formed (``upsample="auto"``) if that could still beat ``best_s``."""
    plain, lost, sine = _omega_k_sized(profiles, grid, selection, factors)
    if not plain.feasible or plain.error_db <= target_db or lost == 0 or plain.time_s >= best_s:
        return [plain]
    if sine > OMEGA_K_UP_MAX_SINE:
        return [plain, Estimate("omega-k", math.inf, math.inf, {"upsample": "auto"},
                                f"not weighed with upsample='auto': voxel-stop angles reach past a sine of "
                                f"{OMEGA_K_UP_MAX_SINE:g}")]
    return [plain, _omega_k_estimate(profiles, grid, selection, factors, {"upsample": "auto"})]


def _ffbp_candidates(n_meas: int) -> list[int]:
    """Tree depths to try: the default (leaves of 16 or more measurements) first, then one either side."""
    from ..ffbp_tree import default_depth, max_depth

    d0 = default_depth(n_meas, 4)
    return [d for d in (d0, d0 - 1, d0 + 1) if 1 <= d <= max_depth(n_meas, 4)]


def _ffbp_estimates(profiles, grid, selection, factors, target_db: float, best_s: float) -> list[Estimate]:
    """FFBP at the depths near its default, each at the lowest oversampling that meets the target.

    Planning a tree costs time (tenths of a second at thousands of stops) and is lost where FFBP
    is not chosen, so a tree is planned only where a lower bound of FFBP's time (its planning and
    its last step) is under ``PLAN_IF_UNDER`` times ``best_s``, and further
    depths only while the planning spent stays under a tenth of the best time so far.
    """
    from ..ffbp import plan_tree

    floor = (FFBP_FLOOR_FIXED_S + FFBP_FLOOR_GRID * _seconds("ffbp", {"grid": float(grid.size) * 4 * 4**3},
                                                              selection, factors)
             + FFBP_PLAN_S_PER_MEAS * profiles.n_meas)
    if floor >= PLAN_IF_UNDER * best_s:
        return [Estimate("ffbp", floor, math.nan, note=f"not planned: its planning and last step alone take about "
                         f"{floor:.3g} s")]
    out: list[Estimate] = []
    spent = 0.0
    for depth in _ffbp_candidates(profiles.n_meas):
        if out and spent > 0.1 * min(best_s, *(e.time_s for e in out)):
            break
        grow = 20 * math.log10(depth + 1)
        ovs = next((o for o in FFBP_CANDIDATES if FFBP_BASE_DB[o] + grow <= target_db), FFBP_CANDIDATES[-1])
        opts = {"depth": depth, "oversample": ovs, "range_oversample": ovs}
        t = time.perf_counter()
        try:
            tree = plan_tree(profiles, grid, **opts)
        except ValueError as exc:
            return [Estimate("ffbp", math.inf, math.inf, opts, str(exc).split(";")[0])]
        plan_s = time.perf_counter() - t
        spent += plan_s
        work = work_ffbp(tree, grid, 4, plan_s)
        out.append(Estimate("ffbp", _seconds("ffbp", work, selection, factors), FFBP_BASE_DB[ovs] + grow, opts,
                            f"{depth} levels at {ovs:g}x the Nyquist rate, {sum(lv.samples for lv in tree.levels):,} "
                            "sub-image samples"))
    return out or [Estimate("ffbp", math.inf, math.inf, note="too few measurements for a tree")]


def estimate(profiles: Profiles, grid: VoxelGrid, selection=None, *, max_error_db: float | None = None,
             factors: dict | None = None, formations=("bp", "omega-k", "ffbp")) -> list[Estimate]:
    """Predicted time and error of each formation (FFBP: several trees) for this request
    (``max_error_db`` None: :data:`DEFAULT_MAX_ERROR_DB`, bp exact)."""
    factors = load_calibration(selection) if factors is None else factors
    goal = check_max_error_db(DEFAULT_MAX_ERROR_DB if max_error_db is None else max_error_db)
    target = goal - MARGIN_DB
    out = []
    if "bp" in formations:
        out.append(Estimate("bp", _seconds("bp", work_bp(profiles, grid), selection, factors), -math.inf,
                            bp_options(None if max_error_db is None else goal), note="exact (the reference)"))
    if "omega-k" in formations:
        n_fft = 1.5 * profiles.n_lags
        floor = _seconds("omega-k", {"fixed": 1, "delay": profiles.n_meas * n_fft * math.log2(max(n_fft, 2))},
                         selection, factors) + OMEGA_K_SIZING_S[0] + OMEGA_K_SIZING_S[1] * profiles.n_meas
        best = min((e.time_s for e in out if e.feasible), default=math.inf)
        if floor < PLAN_IF_UNDER * best:  # sizing it costs time too, lost where it is not chosen
            out.extend(_omega_k_estimates(profiles, grid, selection, factors, target, best))
        else:  # sizing it would cost more than the whole of the fastest
            out.append(Estimate("omega-k", floor, math.nan,
                                note=f"not sized: its sizing and fixed cost alone are about {floor:.3g} s"))
    if "ffbp" in formations:
        check_s = check_seconds(profiles, grid, selection, factors)
        best = min((e.time_s for e in out if _safe(e, target + MARGIN_DB, check_s)), default=math.inf)
        near = [e.time_s for e in out if _near(e, target + MARGIN_DB, check_s)]
        if near:  # one _steps would form and measure first may make planning a tree a loss too
            tried = min(near) + check_s
            if tried < CHECK_IF_UNDER * best:
                best = tried
        out.extend(_ffbp_estimates(profiles, grid, selection, factors, target, best))
    return out


def predict_time(formation: str, profiles: Profiles, grid: VoxelGrid, selection=None, options: dict | None = None,
                 factors: dict | None = None) -> float:
    """Predicted run time of ``formation`` with ``options`` (s); ``factors`` default to none (the built-in
    model, as ``python -m bench`` calibrates it), not the stored calibration. FFBP plans its tree to count."""
    factors = {} if factors is None else factors
    options = dict(options or {})
    if formation == "bp":
        return _seconds("bp", work_bp(profiles, grid), selection, factors)
    if formation == "omega-k":
        from ..omega_k import plan_sizes

        work = work_omega_k(plan_sizes(profiles, grid, **options), _device(selection) is not None)
        return _seconds("omega-k", work, selection, factors)
    if formation == "ffbp":
        from ..ffbp import plan_tree

        t = time.perf_counter()
        tree = plan_tree(profiles, grid, **options)
        taps = int(options.get("order", 3)) + 1
        return _seconds("ffbp", work_ffbp(tree, grid, taps, time.perf_counter() - t), selection, factors)
    raise ValueError(f"formation must be one of {tuple(BUILTIN)}, got {formation!r}")
