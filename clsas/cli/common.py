"""What several commands share: progress bars, the grid and box options, the device options, simulating a scene
and imaging a dataset with the command's flags."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

#: the arguments that name an input HDF5 file (dataset or image), in any command
H5_INPUTS = ("data", "a", "b", "image", "background")


def check_input_files(args) -> None:
    """Refuse an input HDF5 file that cannot be opened (truncated, corrupt, not HDF5), naming it,
    before any work (a ``ValueError``: exit 2)."""
    import h5py

    for name in H5_INPUTS:
        path = getattr(args, name, None)
        if not isinstance(path, str) or not Path(path).is_file():
            continue  # a missing file is the command's to report; an import's background is a folder
        try:
            with h5py.File(path, "r"):
                pass
        except OSError as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ValueError(f"{path} is not a readable HDF5 file ({why}): it may be truncated or corrupt; "
                             "write it again (or restore a copy)") from None


#: the commands that write files, each refusing to replace one unless given --overwrite
WRITERS = ("simulate", "import", "preprocess", "autofocus", "export", "reconstruct", "inspect")


def output_files(args) -> list[Path]:
    """The files the command ``args`` names will write, named as it will name them."""
    cmd = getattr(args, "command", "")
    out: list[Path] = []
    if cmd in ("simulate", "import", "preprocess", "autofocus", "export") and getattr(args, "out", None):
        out.append(Path(args.out))
    if cmd == "export" and Path(args.out).suffix.lower() == ".npy":
        out.append(Path(args.out).with_suffix(".json"))  # the .npy's scale and origin beside it
    if cmd == "autofocus" and getattr(args, "png", None):
        out.append(Path(args.png))
    if cmd == "reconstruct":
        image = Path(args.out or Path(args.data).with_name(Path(args.data).stem + "-image.h5"))
        tiled = args.max_memory is not None or args.scheduler is not None or image.suffix.lower() == ".zarr"
        if not tiled:  # a file formed in tiles is resumed where an earlier run stopped, not replaced
            out.append(image)
        out += ([image.with_suffix(".png")] if args.png else []) + ([Path(args.plot)] if args.plot else [])
    if cmd == "inspect" and args.png:  # (its default picture, <data>-inspect.png, is its own to redraw)
        out.append(Path(args.png))
    return out


def check_output_files(args) -> None:
    """Refuse, before any work, to replace a file the command would write (a ``FileExistsError``:
    exit 2) unless ``--overwrite`` was given."""
    if getattr(args, "overwrite", False):
        return
    for path in output_files(args):
        if path.exists():
            raise FileExistsError(f"{path} exists and clsas {args.command} would replace it: pass --overwrite to "
                                  "replace it, or name another file")


#: the methods the CLI offers instead of a slow one, fastest last (docs/guide/super-resolution.md)
FASTER = {"cbp-taylor": ("cbp-polar", "bpdn", "bp"), "cbp-polar-socp": ("cbp-polar", "bpdn", "bp"),
          "cbp-polar": ("bpdn", "bp"), "bpdn": ("bp",)}
#: a job estimated to take longer than this is announced with the faster alternatives
SLOW_JOB_S = 60.0


@contextmanager
def progress_bar(desc: str, total: int, enabled: bool = True):
    """A progress bar (on stderr) named ``desc``, for a callback ``(done, total)``."""
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="stop", disable=not enabled, leave=False) as bar:
        def update(done: int, _total: int) -> None:
            if bar.total != _total:
                bar.total = _total
            bar.update(done - bar.n)

        yield update


def stage_label(report) -> str:
    """What the bar says for a :class:`clsas.Progress` report: ``step k of n: <stage>``."""
    return f"step {report.step} of {len(report.stages)}: {report.stage}"


@contextmanager
def stage_bar(enabled: bool = True, announce=None):
    """A progress bar (on stderr) for a call that reports :class:`clsas.Progress` records
    (:func:`clsas.reconstruct`): named by :func:`stage_label` after the stage reporting, and
    started again at each stage. ``announce(stage, elapsed_s, done, total)`` is called once per
    stage, after its first count, to warn of a long job.
    """
    import time

    from tqdm import tqdm

    state = {"stage": None, "t0": time.perf_counter(), "announced": set()}
    with tqdm(total=None, desc="", disable=not enabled, leave=False) as bar:
        def update(report) -> None:
            if report.stage != state["stage"]:
                state["stage"], state["t0"] = report.stage, time.perf_counter()
                bar.set_description_str(stage_label(report))
                bar.reset(total=report.total)
            if report.total is not None and bar.total != report.total:  # a stage counts in its own unit
                bar.total = report.total
            bar.update(report.done - bar.n)
            if announce is not None and report.done > 0 and report.stage not in state["announced"]:
                state["announced"].add(report.stage)
                announce(report.stage, time.perf_counter() - state["t0"], report.done, report.total)

        yield update


def slow_job_notice(method: str):
    """An ``announce`` for :func:`stage_bar`: after the first recording of a sparse method,
    the estimated time of the whole job on stderr when it is over :data:`SLOW_JOB_S`, with the
    faster methods."""
    import sys

    def announce(step: str, elapsed_s: float, done: int, total: int) -> None:
        if not step.startswith("super-resolve") or done <= 0:
            return
        estimate = elapsed_s / done * total
        if estimate > SLOW_JOB_S:
            faster = ", ".join(f"--method {m}" for m in FASTER.get(method, ()))
            print(f"\nnote: {method} took {elapsed_s:.1f} s for the first {done} of {total} recordings: about "
                  f"{_duration(estimate)} for all of them (Ctrl-C stops it; faster: {faster})",
                  file=sys.stderr, flush=True)

    return announce


def estimated_sparse_s(ds, grid, method: str) -> float | None:
    """A rough time (s) for super-resolving every recording of ``ds`` on ``grid`` by a convex
    (cvxpy) method, from the gates' lengths, before any solve; None for the other methods
    (:func:`clsas.sparse.registry.convex_estimate_s`)."""
    from clsas.sparse.registry import CONVEX_S_PER_RECORDING, convex_estimate_s
    from clsas.types.rangegate import plan_reconstruction

    if method not in CONVEX_S_PER_RECORDING:
        return None
    gates = plan_reconstruction(ds, grid, []).gates_s
    k = (gates[:, 1] - gates[:, 0] + 2 * len(ds.waveform) / ds.fs_hz) * ds.fs_hz + 1  # atoms at one per sample
    return convex_estimate_s(method, k)


def announce_slow_method(ds, grid, method: str) -> None:
    """Before any work: say when a convex method's rough estimate for the job is over a minute."""
    import sys

    est = estimated_sparse_s(ds, grid, method)
    if est is not None and est > SLOW_JOB_S:
        faster = ", ".join(f"--method {m}" for m in FASTER.get(method, ()))
        print(f"note: {method} solves a convex program per recording: roughly {_duration(est)} for these "
              f"{ds.n_meas} recordings on a 2-core CPU (the first recording's time will say more; Ctrl-C "
              f"stops it; faster: {faster})", file=sys.stderr, flush=True)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds // 3600:.0f} h {seconds % 3600 / 60:.0f} min"


def grid_arg(text: str | None, spacing: float | None, fallback):
    import clsas

    if text is None:
        if fallback is None:
            raise ValueError("--grid is required (the dataset stores no [grid] configuration)")
        if spacing is None:
            return fallback
        b = fallback.bounds()
        return clsas.VoxelGrid.from_bounds(tuple(b[0]), tuple(b[1]), tuple(b[2]), spacing)
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"--grid must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}") from None
    if len(vals) != 6:
        raise ValueError(f"--grid must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}")
    return clsas.VoxelGrid.from_bounds(tuple(vals[0:2]), tuple(vals[2:4]), tuple(vals[4:6]), spacing or 0.01)


def box_arg(option: str, text: str | None):
    if text is None:
        return None
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6:
        raise ValueError(f"{option} must be six numbers x0,x1,y0,y1,z0,z1 in metres, got {text!r}")
    return (tuple(vals[0:2]), tuple(vals[2:4]), tuple(vals[4:6]))


def simulate_scene(cfg, progress=True):
    import clsas

    with progress_bar("simulate", cfg.aperture.n_meas, progress) as cb:
        return clsas.simulate(cfg.scene, cfg.aperture, cfg.waveform, cfg.fs_hz, snr_db=cfg.snr_db,
                              seed=cfg.seed, chirp=cfg.chirp, config=cfg.text, progress=cb, beams=cfg.beams)


def formation_options(items: list[str] | None) -> dict:
    """``KEY=VALUE`` pairs; values read as TOML scalars (numbers, true/false, "text"), else as text."""
    import tomllib

    out = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--formation-option must be KEY=VALUE, got {item!r}")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out[key.strip()] = value
    return out


def reconstruct_image(ds, grid, args, progress=True):
    """``ds`` imaged on ``grid`` with the command's flags, its progress on stderr named by the
    stages the pipeline reports."""
    import clsas

    method = getattr(args, "method", "bp")
    announce_slow_method(ds, grid, method)
    with stage_bar(progress, announce=slow_job_notice(method)) as cb:
        return clsas.reconstruct(ds, grid, method=method,
                                 compression=getattr(args, "compression", "matched"),
                                 backend=args.backend, device=getattr(args, "device", None), progress=cb,
                                 force=getattr(args, "force", False), formation=getattr(args, "formation", "bp"),
                                 formation_options=formation_options(getattr(args, "formation_option", None)) or None,
                                 max_error_db=getattr(args, "max_error_db", None))


def add_device_options(sp) -> None:
    """``--backend``, ``--device``, ``-q`` and ``-v``: what every imaging command takes."""
    from clsas.cl import BACKENDS

    sp.add_argument("--backend", choices=BACKENDS, default=None,
                    help="compute backend (default: $CLSAS_BACKEND or auto)")
    sp.add_argument("--device", default=None, metavar="P:D",
                    help="OpenCL platform:device numbers from `clsas devices` (default: $PYOPENCL_CTX or the best)")
    sp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sp.add_argument("-v", "--verbose", action="store_true", help="log what is computed and skipped")


def check_method_dependencies(method: str | None) -> None:
    """Refuse a sparse method whose solver is not installed, naming the extra (ImportError: exit 1),
    instead of every recording falling back to the matched filter."""
    if not method or method == "bp":
        return  # (the sparse package is imported only where a sparse method is named)
    from clsas.sparse.registry import require_solver

    require_solver(method, parameter="--method")


def is_simulator(platform: str) -> bool:
    """Whether an OpenCL platform is a simulator (Oclgrind: checks kernels, 100-1000x slower)."""
    return "oclgrind" in platform.lower()


def check_device_request(args) -> None:
    """``--device P:D`` must name a device ``clsas devices`` lists (else a ValueError: exit 2), not
    fall back to NumPy unasked; a simulator is used only with a note that says so."""
    import os
    import re
    import sys

    if getattr(args, "command", "") == "devices" or not hasattr(args, "backend"):
        return
    spec, what = getattr(args, "device", None), "--device"
    if spec is None and os.environ.get("PYOPENCL_CTX", "").strip():
        spec, what = os.environ["PYOPENCL_CTX"].strip(), "PYOPENCL_CTX"  # as explicit a request as --device
    if spec is None:
        return
    if getattr(args, "backend", None) == "numpy":
        if what == "PYOPENCL_CTX":
            return  # the environment's choice does not bind a NumPy run
        raise ValueError(f"--device {spec} picks an OpenCL device, but --backend numpy runs without one: "
                         "give one of them")
    m = re.fullmatch(r"\s*(\d*)(?::(\d*))?\s*", str(spec))
    if m is None:
        raise ValueError(f"{what} must be P:D, the platform and device numbers `clsas devices` lists "
                         f"(e.g. 1:0), got {spec!r}")
    index = f"{int(m.group(1) or 0)}:{int(m.group(2) or 0)}"
    from clsas import cl

    try:
        rows = cl.list_devices()
    except cl.OpenCLUnavailable:
        rows = []
    row = next((r for r in rows if r.index == index), None)
    if row is None:
        listed = ", ".join(f"{r.index} ({r.device.strip()})" for r in rows) or "none (no OpenCL platform)"
        raise ValueError(f"{what}={spec}: no such OpenCL device; the devices are: {listed}. Leave it out "
                         "to use the best one (or NumPy where there is none)")
    if is_simulator(row.platform):
        print(f"note: {what}={index} is {row.device.strip()}, a simulator for checking kernels, 100 to 1000 "
              "times slower than a real device", file=sys.stderr)


def check_grids_fit(grids, args) -> None:
    """The memory guard for every grid a command will image, run before any of the work starts
    (``clsas demo`` images two scenes; ``reconstruct --autofocus`` works for minutes first)."""
    from clsas import cl
    from clsas.formation.guard import check_grid, mark_checked

    if getattr(args, "formation", "bp") not in ("bp", "auto"):
        return  # a formation checks its own memory (its tree or spectrum, not the grid alone)
    sel = cl.select(getattr(args, "backend", None), getattr(args, "device", None))
    for grid in grids:
        check_grid(grid, sel.kind, sel.queue.device if sel.opencl else None, force=getattr(args, "force", False))
        mark_checked(grid, sel.kind)  # not checked again by the library during this command
