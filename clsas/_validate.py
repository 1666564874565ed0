"""Backwards alias of :mod:`clsas.validate` (the input checks, public since issue 25), kept for the
modules that still import ``clsas._validate``."""

from .validate import (  # noqa: F401
    array,
    cell_number,
    choice,
    finite,
    install_hint,
    non_negative,
    positive,
    positive_int,
    speeds,
)
