"""``reconstruct``: a dataset to an image, in named stages.

select the device once -> plan the range gate -> range profiles (pulse compression, or the
per-profile sparse step) -> form the image with the chosen formation. Each stage is a function
of its own; the device request is resolved once (:func:`clsas.cl.select`) and the same
selection goes to every stage, so ``backend="auto"`` can still fall back to the NumPy twins
where a kernel will not build.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from . import cl
from . import validate as v
from .compression import COMPRESSIONS, compress
from .dataset import Dataset
from .formation import FORMATIONS
from .formation.guard import check_grid
from .geometry import VoxelGrid
from .image import Image
from .profiles import Profiles
from .rangegate import ReconstructionPlan, plan_reconstruction

__all__ = ["methods", "reconstruct"]

log = logging.getLogger(__name__)


def methods() -> tuple[str, ...]:
    """The names ``reconstruct(method=...)`` takes: ``"bp"`` and every registered sparse method."""
    from .sparse import SPARSE_METHODS  # scipy.optimize: imported when asked, not by `import clsas`

    return ("bp", *SPARSE_METHODS.names())


def reconstruct(
    dataset: Dataset | Profiles,
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

    Only what the grid needs is computed: range profiles over the exact delay gate of the grid
    (min and max bistatic path over all voxels and stops); ``image.plan.describe()`` says what was skipped.

    Parameters
    ----------
    dataset : Dataset or Profiles
        Recordings, or range profiles computed elsewhere
        (:meth:`clsas.Profiles.from_range_profiles`; imaged by ``method="bp"`` only).
    grid : VoxelGrid
    method : str
        ``"bp"``: pulse compression + the formation. A registered sparse method
        (:data:`clsas.sparse.SPARSE_METHODS`: ``"bpdn"``, ``"cbp-taylor"``, ``"cbp-polar"``, ...)
        super-resolves each recording within its own range gate (complex amplitudes: echoes of
        unknown phase), renders each echo as a pulse much narrower than the matched filter's,
        and forms the image of those profiles (see :func:`clsas.sparse.profiles.superres_profiles`).
    compression : str
        A registered compression (:data:`clsas.compression.COMPRESSIONS`): ``"matched"`` or ``"fmcw"``.
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
        atom's waveform as heard through the transducers; default the dataset's waveform). A
        recording whose sparse recovery fails falls back to its matched-filter profile and says so
        in ``image.echoes[m].fallback`` and ``.status``; one warning sums them up.
    force : bool
        Image a grid even if it does not seem to fit in memory.
    formation : str
        How the profiles become an image (:data:`clsas.formation.FORMATIONS`): ``"bp"`` (exact
        backprojection, the default and the reference), ``"omega-k"`` (planar uniform apertures),
        ``"ffbp"`` (fast factorized backprojection, any trajectory). Works with every method.
    formation_options : dict, optional
        Passed to the formation (see its module).
    """
    fopts = _check_request(dataset, grid, method, compression, sparse, formation, formation_options)
    selection = cl.select(backend, device)
    if not force:  # the image must fit before any work starts (with force, the formation warns)
        check_grid(grid, selection.kind, selection.cl_device)
    t_start = time.perf_counter()
    if isinstance(dataset, Profiles):  # input already compressed (Profiles.from_range_profiles)
        image = _form(dataset, grid, formation, fopts, selection, progress, force)
        return replace(image, method=f"bp ({dataset.method} profiles)",
                       timings_s={**image.timings_s, "total": time.perf_counter() - t_start})
    plan = plan_reconstruction(dataset, grid)
    if method == "bp":
        prof, echoes, plan = _compressed(dataset, plan, compression, selection)
    else:
        prof, echoes, plan = _super_resolved(dataset, plan, method, sparse or {}, progress)
    image = _form(prof, grid, formation, fopts, selection, progress, force)
    plan = replace(plan, kernels=[k for k, b in ((f"compress ({compression})", prof.backend),
                                                 ("backproject" if formation == "bp" else formation, image.backend))
                                  if b == "opencl"])
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    return replace(image, method=method, plan=plan, echoes=echoes,
                   timings_s={**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start})


def _check_request(dataset, grid, method, compression, sparse, formation, formation_options) -> dict:
    """Every argument checked before any work; the formation's options as a new dict."""
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    FORMATIONS.check(formation)
    if formation_options is not None and not isinstance(formation_options, dict):
        raise TypeError(f"formation_options must be a dict, got {type(formation_options).__name__}")
    fopts = dict(formation_options or {})
    if formation == "bp" and fopts:
        raise ValueError(f"formation_options: formation 'bp' takes none, got {sorted(fopts)}")
    if isinstance(dataset, Profiles):
        if method != "bp":
            raise ValueError(f"method={method!r} needs the recordings (a Dataset); range profiles are imaged "
                             "by method='bp'")
        return fopts
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset must be a clsas.Dataset or clsas.Profiles, got {type(dataset).__name__}")
    v.choice("method", method, methods() if method != "bp" else ("bp",))
    COMPRESSIONS.check(compression, "compression")
    if sparse is not None and not isinstance(sparse, dict):
        raise TypeError(f"sparse must be a dict of options, got {type(sparse).__name__}")
    if method != "bp" and sparse:
        from .sparse.profiles import SPARSE_OPTIONS

        unknown = set(sparse) - set(SPARSE_OPTIONS)
        if unknown:
            raise ValueError(f"sparse: unknown option(s) {sorted(unknown)}")
    return fopts


def _compressed(dataset: Dataset, plan: ReconstructionPlan, compression: str, selection: cl.Selection):
    """Stage: pulse compression over the plan's gate -> (profiles, no echoes, plan with the lags)."""
    if compression == "fmcw":
        plan = replace(plan, notes=[*plan.notes, "fmcw: delays are gated; the mixed window is the whole chirp overlap"])
    prof = compress(dataset, method=compression, gate_s=plan.gate_s, backend=selection)
    return prof, None, replace(plan, lags=prof.n_lags, lag_step=int(round(prof.dtau_s * dataset.fs_hz)))


def _super_resolved(dataset: Dataset, plan: ReconstructionPlan, method: str, options: dict, progress):
    """Stage: each recording super-resolved in its own gate -> (profiles, echoes, plan with the lags)."""
    from .sparse.profiles import superres_profiles

    prof, echoes = superres_profiles(dataset, plan.gates_s, method, progress=progress, **options)
    note = f"{method}: each recording super-resolved within its own gate, echoes rendered as pulses"
    return prof, echoes, replace(plan, lags=prof.n_lags, notes=[*plan.notes, note])


def _form(prof: Profiles, grid: VoxelGrid, formation: str, options: dict, selection: cl.Selection, progress,
          force: bool) -> Image:
    """Stage: the registered formation -> Image (its name recorded in the provenance)."""
    from .formation import form

    return form(prof, grid, formation, backend=selection, progress=progress, force=force, **options)
