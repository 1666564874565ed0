"""clsas: in-air synthetic-aperture audio imaging with OpenCL kernels and NumPy twins."""

from __future__ import annotations

from . import preprocess  # a module: clsas.preprocess.apply(ds, ...)
from .compression import compress

# the function, not its package: clsas.autofocus(dataset, grid) (the package's other names are
# imported from it: from clsas.focus import AutofocusReport, score)
from .focus import autofocus
from .formation.bp import Backprojector, backproject
from .physics.apertures import aperture_from_csv, circular_aperture, helical_aperture
from .physics.geometry import Aperture, Scene, VoxelGrid, Wall, raster_aperture
from .physics.signals import analytic, lfm_chirp
from .physics.sound import air_absorption_db_per_m, resolution_limits, speed_of_sound
from .pipeline.reconstruction import reconstruct
from .presenting.quality import compare, tcr_db
from .synthesis.simulation import simulate
from .types.dataset import Dataset, load
from .types.image import Image
from .types.profiles import Profiles
from .types.progress import Progress
from .types.rangegate import ReconstructionPlan
from .version import __version__  # noqa: F401 - clsas.__version__

__all__ = [
    "Aperture", "Backprojector", "Dataset", "Image", "Profiles", "Progress", "ReconstructionPlan", "Scene", "VoxelGrid",
    "Wall", "air_absorption_db_per_m", "analytic", "backproject", "compress", "lfm_chirp",
    "load", "raster_aperture", "reconstruct", "resolution_limits", "simulate", "speed_of_sound",
]
__all__ += ["preprocess", "autofocus"]
__all__ += ["aperture_from_csv", "circular_aperture", "compare", "helical_aperture", "tcr_db"]

# the sparse-recovery entry points of the public contract, imported on first use (they bring
# scipy.optimize; cvxpy and nlopt only when a method needs them), so `import clsas` stays light
_LAZY = {"superres": "clsas.sparse", "delay_error": "clsas.sparse", "coherence": "clsas.sparse"}
__all__ += sorted(_LAZY)


# subpackages reached as attributes after a plain `import clsas` (clsas.io.import_folder,
# clsas.synthetic.turntable_scan()), imported on first use; the short names stand for modules in
# their floors
_SUBMODULES = {
    "cl": "clsas.cl", "formation": "clsas.formation", "io": "clsas.io", "rig": "clsas.rig", "sparse": "clsas.sparse",
    "physics": "clsas.physics", "types": "clsas.types", "synthesis": "clsas.synthesis", "pipeline": "clsas.pipeline",
    "presenting": "clsas.presenting",
    "config": "clsas.io.config", "export": "clsas.presenting.export", "plots": "clsas.types.pictures",
    "scan_errors": "clsas.physics.scan_errors", "scenes": "clsas.synthesis.scenes",
    "synthetic": "clsas.synthesis.synthetic",
}


def __getattr__(name: str):
    if name in _SUBMODULES:
        import importlib

        return importlib.import_module(_SUBMODULES[name])
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'clsas' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
