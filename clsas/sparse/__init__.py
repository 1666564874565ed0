"""Sparse super-resolution of range profiles: dictionaries, BPDN, CBP-Taylor, CBP-Polar, metrics."""

from .atoms import Atom, Dictionary, PolarTriple, coherence, decaying_exponential
from .bpdn import BpdnResult, ShiftOperator, bpdn, bpdn_cvxpy, lam_max, lam_noise, noise_sigma
from .cbp import cbp_polar, cbp_polar_refined, cbp_taylor, superres
from .metrics import DelayError, Echoes, crb_delays, delay_error

__all__ = [
    "Atom", "BpdnResult", "DelayError", "Dictionary", "Echoes", "PolarTriple", "ShiftOperator", "bpdn",
    "bpdn_cvxpy", "cbp_polar", "cbp_polar_refined", "cbp_taylor", "coherence", "crb_delays",
    "decaying_exponential", "delay_error", "lam_max", "lam_noise", "noise_sigma", "superres",
]
