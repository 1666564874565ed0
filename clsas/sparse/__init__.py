"""Sparse super-resolution of range profiles: dictionaries, BPDN, CBP-Taylor, CBP-Polar, metrics,
and one registry of the methods (:data:`SPARSE_METHODS`), all returning :class:`Echoes`."""

from .atoms import (
                   Atom,
                   Dictionary,
                   PolarTriple,
                   absorbed_pulse,
                   coherence,
                   decaying_exponential,
                   default_max_echoes,
                   pulse_length_s,
)
from .bpdn import BpdnResult, ShiftOperator, bpdn, bpdn_cvxpy, group_atoms, lam_max
from .cbp import cbp_polar, cbp_taylor
from .detect import detect_echoes
from .metrics import DelayError, Echoes, crb_delays, delay_error
from .noise import colour_factor, correlation_sigma, echo_threshold, lam_noise, noise_lam, noise_sigma
from .refined import cbp_polar_refined
from .registry import SPARSE_METHODS, cap_echoes, sparse_echoes, succeeded, superres

__all__ = [
    "Atom", "BpdnResult", "DelayError", "Dictionary", "Echoes", "PolarTriple", "SPARSE_METHODS", "ShiftOperator",
    "absorbed_pulse",
    "bpdn", "bpdn_cvxpy", "cap_echoes", "cbp_polar", "cbp_polar_refined", "cbp_taylor", "coherence", "colour_factor",
    "correlation_sigma", "crb_delays", "decaying_exponential", "default_max_echoes", "delay_error", "detect_echoes",
    "echo_threshold", "group_atoms",
    "lam_max", "lam_noise", "noise_lam", "noise_sigma", "pulse_length_s", "sparse_echoes", "succeeded", "superres",
]
