"""Several steps in their fixed order: :func:`apply` (keyword arguments) and :func:`from_table`
(a ``[preprocess]`` table)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import validate as v
from ..io.config import PREPROCESS_KEYS
from ..types.dataset import Dataset
from ._base import _check_ds
from .background import attach_background, subtract_background
from .common import remove_common
from .direct import blank_direct, clock_from_direct
from .filters import bandpass, remove_dc, remove_delay

__all__ = ["PREPROCESS_KEYS", "apply", "from_table"]

# keys of a [preprocess] table and of apply()'s keyword arguments


# apply() takes arguments named like the steps; these names reach the step functions
_bandpass_step = bandpass
_blank_step = blank_direct
_clock_step = clock_from_direct


def apply(ds: Dataset, *, group_delay_s: float | None = None, group_delay_samples: float | None = None,
               direct_clock: bool = False, dc: bool = False, bandpass: bool | dict | tuple = False,
               background: bool | str | Dataset | np.ndarray | dict | None = None,
               common: bool | str = False, blank_direct: bool | dict = False) -> Dataset:
    """Several preprocessing steps in their natural order (see the module docstring).

    Parameters
    ----------
    group_delay_s, group_delay_samples : float, optional
        System delay to remove (:func:`remove_delay`), in seconds or in samples.
    direct_clock : bool
        :func:`clock_from_direct`, after DC removal and band-pass (on the filtered recordings,
        before the background subtraction removes the direct sound; an attached background,
        on the same samples, keeps its alignment).
    dc : bool
        :func:`remove_dc`.
    bandpass : bool, (f_lo_hz, f_hi_hz) or dict
        :func:`bandpass`; ``True`` for the chirp's band, a pair for a given band, a dict for
        its keyword arguments.
    background : True, path, Dataset, array or dict, optional
        :func:`subtract_background`: ``True`` uses the dataset's own ``background``; a path
        names an HDF5 dataset file of the empty scene; a dict holds ``path`` (or nothing, for
        the own background) and the keyword arguments ``align_s``, ``fit_gain``. A given
        background is attached first (:func:`attach_background`), so the group delay, DC and
        band-pass steps treat it as they treat the scan.
    common : bool or {"mean", "median"}
        :func:`remove_common` (``True``: the mean), after the background subtraction.
    blank_direct : bool or dict
        :func:`blank_direct`, with a dict for its keyword arguments.

    Examples
    --------
    >>> from clsas import preprocess as pp
    >>> from clsas.synthesis.synthetic import turntable_scan
    >>> scan = turntable_scan(30)
    >>> clean = pp.apply(scan.dataset, group_delay_samples=62.33, dc=True, bandpass=True,
    ...                  background=scan.background, blank_direct=True)
    >>> clean.signals.shape == scan.dataset.signals.shape
    True
    """
    ds = _check_ds(ds)
    src, bg_opts = _background_source(ds, background)
    if group_delay_s is not None and group_delay_samples is not None:
        raise ValueError("give group_delay_s or group_delay_samples, not both")
    if group_delay_samples is not None:
        group_delay_s = v.finite("group_delay_samples", group_delay_samples) / ds.fs_hz
    if group_delay_s is not None:
        ds = remove_delay(ds, group_delay_s)
    if background is not None and background is not False and src is not True:
        if isinstance(src, Dataset) and group_delay_s is not None:
            src = remove_delay(src, group_delay_s)  # the same rig, the same delay
        ds = attach_background(ds, src)
    if _flag("dc", dc):
        ds = remove_dc(ds)
    ds = _bandpass_option(ds, bandpass)
    if _flag("direct_clock", direct_clock):  # on the filtered recordings; the background moves with them
        ds = _clock_step(ds)
    if background is not None and background is not False:
        ds = subtract_background(ds, **bg_opts)
    if isinstance(common, str):
        ds = remove_common(ds, common)
    elif _flag("common", common):
        ds = remove_common(ds)
    if isinstance(blank_direct, dict):
        ds = _blank_step(ds, **_only(blank_direct, "blank_direct", ("guard_s", "taper_s")))
    elif _flag("blank_direct", blank_direct):
        ds = _blank_step(ds)
    return ds


def _background_source(ds: Dataset, background) -> tuple[Any, dict]:
    """apply()'s ``background``: (True for the dataset's own, a Dataset, an array, or None;
    subtract_background's keyword arguments). A path is loaded here."""
    if background is None or background is False:
        return None, {}
    # the empty scene goes through the same steps as the scan: attach it first
    bg_opts: dict = {}
    src = background
    if isinstance(background, dict):
        bg_opts = _only(background, "background", ("path", "align_s", "fit_gain"))
        src = bg_opts.pop("path", True)
    if isinstance(src, str):
        from ..types.dataset import load

        bg_opts["label"] = src
        src = load(src)
    elif isinstance(src, Dataset):
        bg_opts["label"] = "background dataset"
    if src is True and ds.background is None:
        raise ValueError("background=True: the dataset has no background scan of its own")
    return src, bg_opts


def _bandpass_option(ds: Dataset, bandpass) -> Dataset:
    """apply()'s ``bandpass``: True, (f_lo_hz, f_hi_hz) or a dict of options."""
    if isinstance(bandpass, tuple | list):
        if len(bandpass) != 2:
            raise ValueError(f"bandpass must be (f_lo_hz, f_hi_hz), got {bandpass!r}")
        return _bandpass_step(ds, *bandpass)
    if isinstance(bandpass, dict):
        return _bandpass_step(ds, **_only(bandpass, "bandpass", ("f_lo_hz", "f_hi_hz", "margin_hz", "transition_hz")))
    return _bandpass_step(ds) if _flag("bandpass", bandpass) else ds


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be true or false here, got {value!r}")
    return bool(value)


def _only(opts: dict, name: str, allowed: tuple[str, ...]) -> dict:
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}")
    return dict(opts)


def from_table(ds: Dataset, table: dict, *, where: str = "[preprocess]") -> Dataset:
    """Apply a ``[preprocess]`` TOML table (keys as :func:`apply`'s arguments)."""
    if not isinstance(table, dict):
        raise ValueError(f"{where} must be a table")
    unknown = sorted(set(table) - set(PREPROCESS_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(PREPROCESS_KEYS)}")
    args = dict(table)
    if isinstance(args.get("bandpass"), list):
        args["bandpass"] = tuple(args["bandpass"])
    return apply(ds, **args)
