"""clsas: in-air synthetic-aperture audio imaging with OpenCL kernels and NumPy twins."""

from __future__ import annotations

__version__ = "0.1.0"

from . import preprocess  # a module: clsas.preprocess.apply(ds, ...)
from .apertures import aperture_from_csv, circular_aperture, helical_aperture
from .compress import Profiles, compress
from .dataset import Dataset, load
from .geometry import Aperture, Scene, VoxelGrid, Wall, raster_aperture
from .imaging import Backprojector, Image, ReconstructionPlan, backproject, reconstruct
from .physics import air_absorption_db_per_m, resolution_limits, speed_of_sound
from .quality import compare, tcr_db
from .signals import analytic, lfm_chirp
from .simulate import simulate

__all__ = [
    "Aperture", "Backprojector", "Dataset", "Image", "Profiles", "ReconstructionPlan", "Scene", "VoxelGrid",
    "Wall", "air_absorption_db_per_m", "analytic", "backproject", "compress", "lfm_chirp",
    "load", "raster_aperture", "reconstruct", "resolution_limits", "simulate", "speed_of_sound",
]
__all__ += ["preprocess"]
__all__ += ["aperture_from_csv", "circular_aperture", "compare", "helical_aperture", "tcr_db"]
