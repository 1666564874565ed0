"""Backprojection (NumPy twin and OpenCL plan behind one dispatcher) and ``reconstruct``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .. import _validate as v
from .. import cl as _cl
from ..compression import Profiles, compress
from ..dataset import Dataset
from ..geometry import VoxelGrid
from . import numpy as twin
from .guard import check_grid
from .image import Image, Peak
from .opencl import BackprojectPlan
from .plan import ReconstructionPlan, path_bounds, plan_reconstruction

__all__ = ["Backprojector", "Image", "Peak", "ReconstructionPlan", "backproject", "reconstruct", "path_bounds"]

log = logging.getLogger(__name__)

METHODS = ("bp", "bpdn", "cbp-taylor", "cbp-polar")


class Backprojector:
    """Backprojection onto one grid: built once, called many times.

    The OpenCL plan (kernel variant chosen and verified, buffers allocated) is made on the
    first call and kept while the profiles keep their number of measurements and do not grow
    longer; :func:`backproject` is one call of a fresh Backprojector.

    Parameters
    ----------
    grid : VoxelGrid
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"``. With ``"auto"``, a device that cannot
        build the kernel (:class:`clsas.cl.BuildError`) falls back to the NumPy twin with one
        warning naming the device and the reason; ``"opencl"`` raises instead. A Selection
        resolved by the caller (:func:`clsas.cl.select`) keeps its request.
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
        The OpenCL device (default: ``PYOPENCL_CTX``, else the preferred one); None with a
        Selection.
    chunk : int, optional
        Measurements per kernel launch.
    force : bool
        Go on even if the grid does not seem to fit in memory (otherwise a ``ValueError``
        gives the numbers and a spacing that fits; see :func:`clsas.imaging.guard.check_grid`).
    """

    def __init__(self, grid: VoxelGrid, *, backend: str | _cl.Selection | None = None, device: Any = None,
                 chunk: int | None = None, force: bool = False):
        if not isinstance(grid, VoxelGrid):
            raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
        if chunk is not None:
            chunk = v.positive_int("chunk", chunk)
        self.grid = grid
        self.chunk = chunk
        self.selection = _cl.select(backend, device)
        check_grid(grid, self.selection.kind, self.selection.cl_device, force=force)
        self._plan = None

    @property
    def backend(self) -> str:
        """``"opencl"`` or ``"numpy"``: where the next call runs."""
        return self.selection.kind

    def _opencl_plan(self, n_meas: int, n_lags: int):
        p = self._plan
        if p is None or p.n_meas != n_meas or p.n_lags < n_lags:
            self._plan, self.selection = self.selection.plan(
                lambda q: BackprojectPlan(self.grid, n_meas, n_lags, queue=q, chunk=self.chunk))
        return self._plan

    def __call__(
        self,
        profiles: Profiles,
        *,
        tx_positions: np.ndarray | None = None,
        rx_positions: np.ndarray | None = None,
        c_mps: float | np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> Image:
        """Backproject ``profiles`` (see :func:`backproject` for the arguments)."""
        if not isinstance(profiles, Profiles):
            raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
        n = profiles.n_meas
        tx = v.array("tx_positions", profiles.tx_positions if tx_positions is None else tx_positions, shape=(n, 3))
        rx = v.array("rx_positions", profiles.rx_positions if rx_positions is None else rx_positions, shape=(n, 3))
        c = v.speeds("c_mps", profiles.c_mps if c_mps is None else c_mps, n)
        data = v.array("profiles.data", profiles.data, ndim=2, dtype=None, allow_complex=True)
        tau0 = v.array("profiles.tau0_s", profiles.tau0_s, shape=(n,))
        dtau = v.positive("profiles.dtau_s", profiles.dtau_s)
        fc = v.non_negative("profiles.fc_hz", profiles.fc_hz)
        t_start = time.perf_counter()
        timings = {}
        plan = self._opencl_plan(n, data.shape[1]) if self.selection.opencl else None
        if plan is not None:
            values = plan(data, tau0, dtau, fc, tx, rx, c, progress)
            timings["backproject_kernel"] = plan.last_kernel_s
        else:
            values = twin.backproject(data.astype(np.complex128), tau0, dtau, fc, tx, rx, c, self.grid.points(),
                                      progress)
        timings["backproject"] = time.perf_counter() - t_start
        sel = self.selection
        return Image(values.reshape(self.grid.shape), self.grid, "bp", sel.kind, sel.device, timings)


def backproject(
    profiles: Profiles,
    grid: VoxelGrid,
    *,
    tx_positions: np.ndarray | None = None,
    rx_positions: np.ndarray | None = None,
    c_mps: float | np.ndarray | None = None,
    backend: str | _cl.Selection | None = None,
    device: Any = None,
    chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Image:
    """Bistatic delay-and-sum of complex baseband profiles onto ``grid``.

    For each voxel and measurement the profile is linearly interpolated at the bistatic
    delay ``(|v - tx| + |v - rx|) / c`` and the carrier phase restored; samples outside the
    profile window contribute nothing. Positions and ``c`` default to those the profiles
    carry (from a Dataset); ``c_mps`` may be an (n_meas,) array, one speed of sound per
    measurement (air that changes during a scan). To image many profile sets onto one grid, build a
    :class:`Backprojector` once and call it.

    Parameters
    ----------
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"`` (see :class:`Backprojector`).
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional

    Returns
    -------
    Image
        complex64 values (OpenCL) or complex128 (NumPy), shape ``grid.shape``.
    """
    if not isinstance(profiles, Profiles):
        raise TypeError(f"profiles must be clsas.Profiles (from clsas.compress), got {type(profiles).__name__}")
    bp = Backprojector(grid, backend=backend, device=device, chunk=chunk)
    return bp(profiles, tx_positions=tx_positions, rx_positions=rx_positions, c_mps=c_mps, progress=progress)


def reconstruct(
    dataset: Dataset,
    grid: VoxelGrid,
    method: str = "bp",
    *,
    compression: str = "matched",
    backend: str | None = None,
    device: Any = None,
    progress: Callable[[int, int], None] | None = None,
    sparse: dict | None = None,
    force: bool = False,
    formation: str = "bp",
    formation_options: dict | None = None,
) -> Image:
    """Image a dataset on a grid.

    The plan computes only what the grid needs: range profiles over the exact delay gate of
    the grid (min and max bistatic path over all voxels and stops), and only the kernels
    the pipeline uses. ``plan.describe()`` on the result says what was skipped.

    Parameters
    ----------
    dataset : Dataset or Profiles
        Recordings, or range profiles computed elsewhere
        (:meth:`clsas.Profiles.from_range_profiles`; imaged by ``method="bp"`` only).
    grid : VoxelGrid
    method : {"bp", "bpdn", "cbp-taylor", "cbp-polar"}
        ``"bp"``: pulse compression + backprojection. The sparse methods super-resolve each
        recording within its own range gate (complex amplitudes: echoes of unknown phase),
        render each echo as a pulse much narrower than the matched filter's, and backproject
        those profiles (see :func:`clsas.imaging.sparse.superres_profiles`).
    compression : {"matched", "fmcw"}
    backend : {"auto", "opencl", "numpy"}, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"``: OpenCL where a device exists and the
        kernels build, else the NumPy twins with one warning; ``"opencl"`` raises instead.
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, optional
        The OpenCL device for this call (default: ``PYOPENCL_CTX``, else the preferred one).
    progress : callable(done, total), optional
    sparse : dict, optional
        Options for the sparse methods: ``delta_s``, ``lam``, ``lam_frac``, ``render_width_s``,
        ``max_echoes`` (cap per recording, reported in ``Echoes.capped``), ``guard_s`` (the
        dictionary reaches this far past each end of the gate, so echoes straddling it are
        fitted there and dropped), ``method_options`` (passed to the method), ``absorption``
        (model ISO 9613-1 air absorption in the atom at each gate's mean path), ``pulse`` (the
        atom's waveform: the transmit waveform as heard through the transducers' response;
        default the dataset's waveform). A recording whose
        sparse recovery fails falls back to its matched-filter profile and says so in
        ``image.echoes[m].fallback`` and ``.status``; one warning sums them up.
    force : bool
        Image a grid even if it does not seem to fit in memory (see :class:`Backprojector`).
    formation : str
        How the profiles become an image (:data:`clsas.formation.FORMATIONS`): ``"bp"`` (exact
        backprojection, the default and the reference), ``"omega-k"`` (planar uniform apertures),
        ``"ffbp"`` (fast factorized backprojection, any trajectory). Works with every method.
    formation_options : dict, optional
        Passed to the formation (see its module).
    """
    from ..formation import FORMATIONS
    from ..formation import form as _form

    v.choice("formation", formation, tuple(FORMATIONS))
    if formation_options is not None and not isinstance(formation_options, dict):
        raise TypeError(f"formation_options must be a dict, got {type(formation_options).__name__}")
    fopts = dict(formation_options or {})
    if formation == "bp" and fopts:
        raise ValueError(f"formation_options: formation 'bp' takes none, got {sorted(fopts)}")

    def image_of(bp, prof):
        if formation == "bp":
            return bp(prof, progress=progress)
        return _form(prof, grid, formation, backend=bp.backend, device=bp.selection.queue, progress=progress,
                     force=force, **fopts)

    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    if isinstance(dataset, Profiles):  # input already compressed (Profiles.from_range_profiles)
        if method != "bp":
            raise ValueError(f"method={method!r} needs the recordings (a Dataset); range profiles are imaged "
                             "by method='bp'")
        t_start = time.perf_counter()
        image = image_of(Backprojector(grid, backend=backend, device=device, force=force), dataset)
        image.method = f"bp ({dataset.method} profiles)"
        image.timings_s["total"] = time.perf_counter() - t_start
        return image
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset or clsas.Profiles, got {type(dataset).__name__}")
    v.choice("method", method, METHODS)
    v.choice("compression", compression, ("matched", "fmcw"))
    sel = _cl.select(backend, device)
    bp = Backprojector(grid, backend=sel.requested if sel.opencl else "numpy", device=sel.queue, force=force)
    if method != "bp":
        return _reconstruct_sparse(dataset, grid, method, bp, progress, sparse or {}, image_of)
    plan = plan_reconstruction(dataset, grid, [])
    if compression == "fmcw":
        plan.notes.append("fmcw: delays are gated; the mixed window is the whole chirp overlap")
    t_start = time.perf_counter()
    prof = compress(dataset, method=compression, gate_s=plan.gate_s, backend=sel.requested if sel.opencl else "numpy",
                    device=sel.queue)
    plan.lags = prof.n_lags
    plan.lag_step = int(round(prof.dtau_s * dataset.fs_hz))
    image = image_of(bp, prof)
    plan.kernels = [k for k, b in ((f"compress ({compression})", prof.backend), ("backproject", image.backend))
                    if b == "opencl"]
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    image.method = method
    image.plan = plan
    image.timings_s = {**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start}
    return image


def _reconstruct_sparse(dataset, grid, method, bp, progress, options, image_of) -> Image:
    from .sparse import SPARSE_OPTIONS, superres_profiles

    unknown = set(options) - set(SPARSE_OPTIONS)
    if unknown:
        raise ValueError(f"sparse: unknown option(s) {sorted(unknown)}")
    plan = plan_reconstruction(dataset, grid, [])
    gates = plan.gates_s
    plan.notes.append(f"{method}: each recording super-resolved within its own gate, echoes rendered as pulses")
    t_start = time.perf_counter()
    prof, echoes = superres_profiles(dataset, gates, method, progress=progress, **options)
    plan.lags = prof.n_lags
    image = image_of(bp, prof)
    plan.kernels = ["backproject"] if image.backend == "opencl" else []
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    image.method = method
    image.plan = plan
    image.echoes = echoes
    image.timings_s = {**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start}
    return image
