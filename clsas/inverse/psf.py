"""PSF deconvolution in the image domain (``method="psf"``): the cheap baseline the AirSAS data's owners
compare against (Reed et al. 2022: Wiener filtering of the delay-and-sum image).

The point-spread function is clsas's own: the backprojection of a simulated point echo at the grid's
centre through the same operator (``A^H A e_centre``, forward projector and compressed pulse), so it
matches the grid, the geometry and the waveform. The deconvolution treats it as shift-invariant over
the grid (true near the centre, an approximation at the edges of a wide grid) and applies a Wiener
filter ``conj(H) / (|H|^2 + max|H|^2 10^(-snr_db/10))`` in the 3-D Fourier domain, to complex values.
"""

from __future__ import annotations

import time

import numpy as np

from .. import cl as _cl
from ..physics.geometry import VoxelGrid
from ..types.dataset import Dataset
from ..types.image import Image
from ..types.profiles import Profiles
from .methods import MODEL_METHODS, check_options, operator_for
from .operator import ImagingOperator

__all__ = ["point_spread", "wiener"]


def point_spread(A: ImagingOperator) -> np.ndarray:
    """The grid-shaped PSF of ``A``: the image ``A^H A e_c`` of a unit point at the centre voxel,
    peak-normalised, with the centre voxel at index ``(n // 2)`` along each axis."""
    shape = A.grid.shape
    e = np.zeros(shape, np.complex128)
    e[tuple(n // 2 for n in shape)] = 1.0
    psf = A.rmatvec(A.matvec(e.ravel())).reshape(shape)
    peak = psf[tuple(n // 2 for n in shape)]
    return psf / peak if peak != 0 else psf


def wiener(image: np.ndarray, psf: np.ndarray, snr_db: float = 30.0) -> np.ndarray:
    """Wiener deconvolution of a complex image by a centred PSF of the same shape (zero-padded to
    twice the size against wrap-around)."""
    if image.shape != psf.shape:
        raise ValueError(f"psf shape {psf.shape} must equal the image's {image.shape}")
    pad = tuple(2 * n if n > 1 else 1 for n in image.shape)
    centre = tuple(n // 2 for n in image.shape)
    kernel = np.zeros(pad, np.complex128)
    kernel[tuple(slice(0, n) for n in psf.shape)] = psf
    kernel = np.roll(kernel, [-c for c in centre], axis=(0, 1, 2))
    H = np.fft.fftn(kernel)
    Y = np.fft.fftn(image, pad, axes=(0, 1, 2))
    power = np.abs(H) ** 2
    X = np.conj(H) * Y / (power + power.max() * 10 ** (-snr_db / 10))
    return np.fft.ifftn(X)[tuple(slice(0, n) for n in image.shape)]


@MODEL_METHODS.register("psf")
def psf_deconvolve(dataset: Dataset, profiles: Profiles, grid: VoxelGrid, selection: _cl.Selection,
                   progress=None, **options) -> Image:
    """``method="psf"``: backprojection, then Wiener deconvolution by clsas's PSF (option
    ``psf_snr_db``, default 20 dB)."""
    o = check_options(options)
    t0 = time.perf_counter()
    A = operator_for(dataset, profiles, grid, selection, o["pulse"], o["beam"], o["beam_floor_db"])
    bp = A.rmatvec(A.data).reshape(grid.shape)
    if progress is not None:
        progress(1, 3)
    psf = point_spread(A)
    if progress is not None:
        progress(2, 3)
    x = wiener(bp, psf, o["psf_snr_db"])
    if progress is not None:
        progress(3, 3)
    sel = A.selection
    info = {"solver": "wiener", "psf_snr_db": o["psf_snr_db"], "iterations": 1, "stopped": "direct",
            "n_forward": A.n_forward, "n_adjoint": A.n_adjoint}
    return Image(x, grid, "psf", sel.kind, sel.device, {"solve": time.perf_counter() - t0},
                 provenance={"inverse": info})
