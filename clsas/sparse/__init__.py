"""Sparse super-resolution of range profiles: dictionaries, BPDN, CBP-Taylor, CBP-Polar, metrics."""

from .atoms import Atom, Dictionary, PolarTriple, coherence, decaying_exponential
from .bpdn import BpdnResult, ShiftOperator, bpdn, bpdn_cvxpy, lam_max

__all__ = [
    "Atom", "BpdnResult", "Dictionary", "PolarTriple", "ShiftOperator", "bpdn", "bpdn_cvxpy",
    "coherence", "decaying_exponential", "lam_max",
]
