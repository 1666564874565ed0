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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .. import cl
from .. import validate as v
from ..compression import COMPRESSIONS, compress
from ..formation import FORMATIONS, check_options, declared_options
from ..formation.auto import check_max_error_db, rule_reason
from ..formation.guard import check_grid, checked_once
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from ..types.image import Image
from ..types.profiles import Profiles
from ..types.progress import Progress, Reporter
from ..types.rangegate import ReconstructionPlan, plan_reconstruction
from ..types.sanity import check_grid_against_data
from . import tiling

__all__ = ["methods", "reconstruct"]

log = logging.getLogger(__name__)


def methods() -> tuple[str, ...]:
    """The names ``reconstruct(method=...)`` takes: ``"bp"``, every registered sparse method and every
    model-based one (:data:`clsas.inverse.MODEL_METHODS`)."""
    from ..inverse import MODEL_METHODS
    from ..sparse import SPARSE_METHODS  # scipy.optimize: imported when asked, not by `import clsas`

    return ("bp", *SPARSE_METHODS.names(), *MODEL_METHODS.names())


def reconstruct(
    dataset: Dataset | Profiles, grid: VoxelGrid, method: str = "bp", *, compression: str = "matched",
    backend: str | None = None, device: Any = None, progress: Callable[[Progress], None] | None = None,
    sparse: dict | None = None, force: bool = False, formation: str = "auto", formation_options: dict | None = None,
    out: str | Path | None = None, max_memory: float | str | None = None, client: Any = None,
    tile_shape: tuple[int, int, int] | None = None, max_error_db: float | None = None,
    inverse: dict | None = None,
) -> Image:
    """Image a dataset on a grid: profiles over the grid's exact delay gate only (``image.plan.describe()``).

    Parameters
    ----------
    dataset : Dataset or Profiles
        Recordings, or range profiles computed elsewhere
        (:meth:`clsas.Profiles.from_range_profiles`; imaged by ``method="bp"`` only).
    grid : VoxelGrid
    method : str
        ``"bp"``: pulse compression + the formation. A sparse method (:data:`clsas.sparse.SPARSE_METHODS`:
        ``"bpdn"``, ``"cbp-polar"``, ...) super-resolves each recording first; a model-based one
        (:data:`clsas.inverse.MODEL_METHODS`: ``"ls"``, ``"l1"``, ``"tv"``, ``"l1-tv"``, ``"psf"``,
        ``"offgrid"``) solves for the image through the forward projector.
    compression : str
        A registered compression (:data:`clsas.compression.COMPRESSIONS`): ``"matched"`` or ``"fmcw"``.
    backend : {"auto", "opencl", "numpy"}, optional
        Default ``$CLSAS_BACKEND``, else ``"auto"``: OpenCL where a device exists and the
        kernels build, else the NumPy twins with one warning; ``"opencl"`` raises instead.
    device : None, "P:D", pyopencl.Device or pyopencl.CommandQueue, or a list of them, optional
        The OpenCL device (default: ``PYOPENCL_CTX``, else the preferred one); a list spreads tiles.
    progress : callable(Progress), optional
        Called with :class:`clsas.Progress` records naming the stage running; the first announces every
        stage of the call, in order (:mod:`clsas.types.progress`). ``progress(done, total)`` gets the counts alone.
    sparse : dict, optional
        Options of the sparse step (:func:`clsas.sparse.profiles.superres_profiles`). A recording whose
        recovery fails is imaged by its matched filter (``image.echoes[m].fallback``, one warning).
    force : bool
        Image a grid even if it does not seem to fit in memory.
    formation : str
        ``"auto"`` (default) or one of :data:`clsas.formation.FORMATIONS` (``"bp"``, exact; ``"omega-k"``;
        ``"ffbp"``). ``"auto"`` takes the fastest whose predicted error meets ``max_error_db``
        (:mod:`clsas.formation.auto`; logged, kept in ``image.provenance["formation_auto"]``);
        sparse methods, tiled requests and directional beams take ``"bp"``. Where auto forms by bp
        under a ``max_error_db`` the caller gave, bp's kernel may take a variant stated within it
        less auto's 3 dB margin (half-precision records, the range expansion, where the device runs
        them faster); ``image.provenance["bp"]`` names the kernel that ran and its bound.
    formation_options : dict, optional
        Passed to the formation (see its module); ``"auto"`` takes none (its target is ``max_error_db``).
    out : str or Path, optional
        A chunked file (``.h5``/``.zarr``) formed tile by tile, read lazily; the same request resumes it.
    max_memory : float or str, optional
        Host memory budget (bytes, or ``"2GB"``) of this process or of each Dask worker; sizes the tiles.
    client : distributed.Client or str, optional
        A Dask client or scheduler address: tiles (:mod:`clsas.pipeline.tiling.dask`) and a sparse method's
        recordings (:mod:`clsas.sparse.parallel`) run there. Needs the ``distributed`` extra.
    tile_shape : (int, int, int), optional
        Voxels per tile along x, y, z (default from ``max_memory`` and the workers or devices).
    max_error_db : float, optional
        The largest error against exact bp allowed (dB, a finite number below 0), given to any
        formation that takes an error target: ``"auto"`` and ``"bp"``, whose kernel may then take a
        variant whose stated error against the float64 twin, relative to the image's peak, is
        within it (:class:`clsas.Backprojector`: half-precision records, the range expansion).
        None (default): auto aims at -30 dB and bp, named or chosen, runs its exact float kernels.
        The one source of the target: ``formation_options`` may not hold it.
    inverse : dict, optional
        Options of a model-based method (:data:`clsas.inverse.methods.INVERSE_OPTIONS`).

    With ``"bp"`` a tiled image equals the whole one (to float32 rounding).
    """
    req = _request(dataset, grid, method, compression=compression, backend=backend, device=device,
                   progress=progress, sparse=sparse, force=force, formation=formation,
                   formation_options=formation_options, out=out, max_memory=max_memory, client=client,
                   tile_shape=tile_shape, max_error_db=max_error_db, inverse=inverse)
    # the grid must hold the recordings' echoes (a grid in millimetres does not) ...
    grid_check = check_grid_against_data(dataset, grid) if isinstance(dataset, Dataset) else None
    if req.tiled is not None:
        return _with_grid_check(_reconstruct(dataset, req), grid_check)
    check_grid(grid, req.selection.kind, req.selection.cl_device, force=force)  # ... and fit, before any work
    with checked_once(grid, req.selection.kind):  # ... and is not checked again by the stages
        return _with_grid_check(_reconstruct(dataset, req), grid_check)


def _with_grid_check(image: Image, check) -> Image:
    """The image with the share of the echo energy its grid holds, and any warning about it."""
    if check is None:
        return image
    record = {"echo_share": check.share, "warnings": list(check.warnings)}
    return replace(image, provenance={**image.provenance, "grid_check": record})


@dataclass(frozen=True)
class Request:
    """One :func:`reconstruct` call's request, checked once and passed whole to its stages."""

    grid: VoxelGrid
    method: str
    compression: str
    sparse: dict
    formation: str  # a registered formation ("auto" among them)
    formation_options: dict
    selection: cl.Selection
    progress: Reporter  # the caller's callback, told the stages below
    force: bool
    tiled: tiling.TiledRequest | None
    max_error_db: float | None  # None: not given (auto's default target; bp exact)
    inverse: dict | None
    stages: tuple[str, ...]  # what the request runs, in order, as its progress reports name them


def _request(dataset, grid, method, *, compression, backend, device, progress, sparse, force, formation,
             formation_options, out, max_memory, client, tile_shape, max_error_db, inverse) -> Request:
    """Every argument of :func:`reconstruct` checked before any work, as one :class:`Request`."""
    fopts = _check_request(dataset, grid, method, compression, sparse, formation, formation_options, inverse)
    max_error_db = None if max_error_db is None else check_max_error_db(max_error_db)
    tiled = tiling.check_request(grid, out=out, max_memory=max_memory, client=client, tile_shape=tile_shape,
                                 device=device)
    stages = _stages(dataset, method, compression, formation, tiled is not None)
    return Request(grid, method, compression, dict(sparse or {}), formation, fopts, _selection(backend, device, tiled),
                   Reporter(progress, stages), bool(force), tiled, max_error_db, inverse, stages)


def _stages(dataset, method: str, compression: str, formation: str, tiled: bool) -> tuple[str, ...]:
    """The stages a request runs, in order, by the names its progress reports carry."""
    if _is_model(method):
        return (f"compress ({compression})", f"solve ({method})")
    if isinstance(dataset, Profiles):
        return (_formation_stage(formation, dataset.method, tiled, dataset.beams),)
    made_by = compression if method == "bp" else method  # what makes the profiles the formation forms
    first = f"compress ({compression})" if method == "bp" else f"super-resolve ({method})"
    return (first, _formation_stage(formation, made_by, tiled, dataset.beams))


def _formation_stage(formation: str, made_by: str, tiled: bool, beams) -> str:
    """The formation stage's name: ``"auto"`` named by the formation it takes by rule, where a rule
    takes one (:func:`clsas.formation.auto.rule_reason`)."""
    if formation == "auto" and rule_reason(made_by, tiled=tiled, beams=beams) is not None:
        formation = "bp"
    name = "backproject" if formation == "bp" else f"form ({formation})"
    return f"{name} in tiles" if tiled else name


def _counting(req: Request, stage: str) -> Callable[[int, int], None] | None:
    """Announce ``stage``; the ``(done, total)`` callable it counts through."""
    req.progress.start(stage)
    return req.progress.counter(stage)


def _reconstruct(dataset: Dataset | Profiles, req: Request) -> Image:
    """The stages of :func:`reconstruct`: profiles (compression or the sparse step), then the image."""
    t_start = time.perf_counter()
    if isinstance(dataset, Profiles):  # input already compressed (Profiles.from_range_profiles)
        image, _ = _image(dataset, dataset, replace(req, method="bp"))
        return _finish(image, req.tiled, method=f"bp ({dataset.method} profiles)",
                       timings_s={**image.timings_s, "total": time.perf_counter() - t_start})
    plan = plan_reconstruction(dataset, req.grid)
    if req.method == "bp" or _is_model(req.method):
        req.progress.start(req.stages[0])
        prof, echoes, plan = _compressed(dataset, plan, req.compression, req.selection)
        req.progress.finished(req.stages[0])
    else:
        progress = _counting(req, req.stages[0])
        prof, echoes, plan = _super_resolved(dataset, plan, req.method, req.sparse, progress, req.tiled)
    image, step = _image(dataset, prof, req)
    plan = _with_kernels(plan, (f"compress ({req.compression})", prof.backend), (step, image.backend))
    return _finish(image, req.tiled, method=req.method, plan=plan, echoes=echoes,
                   timings_s={**prof.timings_s, **image.timings_s, "total": time.perf_counter() - t_start})


def _image(dataset, prof: Profiles, req: Request) -> tuple[Image, str]:
    """Stage: the image from the profiles (a model-based method, or the formation), with the name of
    the step that formed it."""
    if _is_model(req.method):
        return _with_runtime(_model_based(dataset, prof, req), req.selection), req.method
    image = _form(prof, req)
    formation = image.provenance["formation"]  # the one that formed it (auto names the one it kept)
    return _with_runtime(image, req.selection), ("backproject" if formation == "bp" else formation)


def _model_based(dataset, prof: Profiles, req: Request) -> Image:
    """Stage: the model-based method (:mod:`clsas.inverse`) forms the image from the compressed profiles."""
    from ..inverse.methods import model_reconstruct

    if req.tiled is not None:
        raise ValueError(f"method={req.method!r} is not formed in tiles: out, max_memory, client, tile_shape and "
                         "several devices are for the other methods")
    progress = _counting(req, req.stages[-1])
    return model_reconstruct(req.method, dataset, prof, req.grid, req.selection, progress, req.inverse)


def _check_inverse(method: str, inverse: dict | None, formation: str) -> None:
    """A model-based method's options checked; ``inverse`` refused for any other method."""
    if not _is_model(method):
        if inverse is not None:
            raise ValueError(f"inverse: options of the model-based methods, but method={method!r}")
        return
    from ..inverse.methods import check_options

    check_options(inverse)
    if formation not in ("bp", "auto"):
        raise ValueError(f"formation={formation!r}: model-based method {method!r} forms its own image (leave "
                         "formation at its default)")


def _is_model(method: str) -> bool:
    from ..inverse import MODEL_METHODS

    return method in MODEL_METHODS


def _with_kernels(plan: ReconstructionPlan, *steps: tuple[str, str]) -> ReconstructionPlan:
    """The plan with the steps that ran on OpenCL ((name, backend) pairs) as its kernels, logged."""
    plan = replace(plan, kernels=[name for name, backend in steps if backend == "opencl"])
    for line in plan.describe().splitlines():
        log.info("plan: %s", line)
    return plan


def _finish(image: Image, tiled, **changes) -> Image:
    """Stage: the image with what the pipeline knows; an out-of-core one re-opened from its file."""
    image = replace(image, **changes)
    return image if tiled is None or tiled.out is None else tiling.finish(image, tiled.out)


def _check_request(dataset, grid, method, compression, sparse, formation, formation_options, inverse=None) -> dict:
    """Every argument checked before any work; the formation's options as a new dict."""
    _check_inverse(method, inverse, formation)
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
    FORMATIONS.check(formation)
    if formation_options is not None and not isinstance(formation_options, dict):
        raise TypeError(f"formation_options must be a dict, got {type(formation_options).__name__}")
    fopts = dict(formation_options or {})
    if "max_error_db" in fopts:
        raise ValueError("formation_options: max_error_db is reconstruct's own parameter (max_error_db=...)")
    check_options(formation, FORMATIONS[formation], fopts)
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
        from ..sparse.profiles import SPARSE_OPTIONS

        unknown = set(sparse) - set(SPARSE_OPTIONS)
        if unknown:
            raise ValueError(f"sparse: unknown option(s) {sorted(unknown)}")
    return fopts


def _selection(backend, device, tiled: tiling.TiledRequest | None) -> cl.Selection:
    """The device request resolved once; with several devices, the first (it compresses)."""
    if tiled is None or not tiled.devices:
        return cl.select(backend, device)
    first = tiled.devices[0]
    return cl.select("numpy") if isinstance(first, str) and first == "numpy" else cl.select(backend, first)


def _compressed(dataset: Dataset, plan: ReconstructionPlan, compression: str, selection: cl.Selection):
    """Stage: pulse compression over the plan's gate -> (profiles, no echoes, plan with the lags)."""
    if compression == "fmcw":
        plan = replace(plan, notes=[*plan.notes, "fmcw: delays are gated; the mixed window is the whole chirp overlap"])
    prof = compress(dataset, method=compression, gate_s=plan.gate_s, backend=selection)
    return prof, None, replace(plan, lags=prof.n_lags, lag_step=int(round(prof.dtau_s * dataset.fs_hz)))


def _super_resolved(dataset: Dataset, plan: ReconstructionPlan, method: str, options: dict, progress,
                    tiled: tiling.TiledRequest | None = None):
    """Stage: each recording super-resolved in its own gate (on the Dask cluster where the tiled
    request has a client) -> (profiles, echoes, plan with the lags)."""
    from ..sparse.profiles import superres_profiles

    client = None if tiled is None else tiled.client
    prof, echoes = superres_profiles(dataset, plan.gates_s, method, progress=progress, client=client, **options)
    note = f"{method}: each recording super-resolved within its own gate, echoes rendered as pulses"
    return prof, echoes, replace(plan, lags=prof.n_lags, notes=[*plan.notes, note])


def _form(prof: Profiles, req: Request) -> Image:
    """Stage: the registered formation -> Image (its name recorded in the provenance); in tiles
    (:mod:`clsas.pipeline.tiling`) where ``out``, ``max_memory``, ``client``, ``tile_shape`` or several
    devices were given."""
    from ..formation import form

    formation, options = req.formation, _formation_options(req)
    progress = _counting(req, req.stages[-1])
    if req.tiled is None:
        return form(prof, req.grid, formation, backend=req.selection, progress=progress, force=req.force,
                    **options)
    record = {}
    for_tiles = getattr(FORMATIONS[formation], "for_tiles", None)  # a formation that forms by another (auto)
    if for_tiles is not None:
        formation, options, record = for_tiles(prof, req.grid, backend=req.selection, **options)
    image = tiling.form_tiled(prof, req.grid, formation, options, req.selection, req.tiled,
                              progress=progress, force=req.force)
    provenance = {**image.provenance, "formation": formation, **record}
    if options:
        provenance["formation_options"] = dict(options)
    return replace(image, provenance=provenance)


def _formation_options(req: Request) -> dict:
    """The request's formation options, with its error target where one was given and the formation
    takes one (without, auto keeps its default target and bp its exact kernels)."""
    if req.max_error_db is not None and "max_error_db" in (declared_options(FORMATIONS[req.formation]) or ()):
        return {**req.formation_options, "max_error_db": req.max_error_db}
    return dict(req.formation_options)


def _with_runtime(image: Image, selection: cl.Selection) -> Image:
    """The OpenCL runtime an image was formed on (platform, version, device, driver, kernel widths)
    in its provenance, so that every figure made from it names its runtime."""
    if image.backend != "opencl" or not selection.opencl:
        return image
    return replace(image, provenance={**image.provenance, "opencl": cl.runtime_record(selection.queue)})
