"""Model-based image reconstruction: the forward projector (the adjoint of backprojection),
solvers with sparsity and total-variation priors, PSF deconvolution, and off-grid reflectors.

- :mod:`.project_numpy`, :mod:`.project_opencl`: the forward projector's twin and OpenCL plan
  (kernels/project.cl).
- :mod:`.operator`: :class:`ImagingOperator`, projection and backprojection as a LinearOperator.
- :mod:`.solvers`: CGLS and monotone FISTA (L1 and TV priors on the magnitude).
- :mod:`.psf`: PSF deconvolution in the image domain (``method="psf"``).
- :mod:`.gram`: L1 on the PSF-convolution model of ``A^H A`` (``method="l1-psf"``).
- :mod:`.offgrid`: off-grid point reflectors by ADCG (``method="offgrid"``).
- :mod:`.methods`: the methods ``reconstruct(method=...)`` takes (:data:`MODEL_METHODS`) and the
  noise-level rule for their weights.
"""

from __future__ import annotations

from . import gram, offgrid, psf  # noqa: F401 - register methods 'l1-psf', 'offgrid' and 'psf'
from .methods import MODEL_METHODS, noise_weight
from .operator import ImagingOperator, compressed_pulse

__all__ = ["ImagingOperator", "MODEL_METHODS", "compressed_pulse", "noise_weight"]
