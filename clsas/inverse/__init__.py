"""Model-based image reconstruction: the forward projector (the adjoint of backprojection), solvers
with sparsity and total-variation priors, PSF deconvolution, and off-grid reflectors (issue 28)."""

from __future__ import annotations

from .operator import ImagingOperator, compressed_pulse

__all__ = ["ImagingOperator", "compressed_pulse"]
