"""Progress reports that name their stage: :class:`Progress`, and the :class:`Reporter` that sends them.

A call that runs in stages (:func:`clsas.reconstruct`) reports to its ``progress`` callback with
:class:`Progress` records. Every record carries the names of all the stages the call will run, in
order, so the first one announces them; each stage is announced when it starts (``done=0``,
``total=None``), then reports its own counts (``done`` of ``total``: measurements, columns, levels,
tiles or iterations, as the stage counts them). ``reconstruct``'s stages are the profiles
(``"compress (matched)"``, ``"compress (fmcw)"`` or a sparse method's ``"super-resolve (bpdn)"``;
none for :class:`clsas.Profiles` given), then the image: ``"backproject"``, ``"form (omega-k)"``,
``"form (ffbp)"``, ``"form (auto)"`` (``"backproject"`` where ``auto`` takes bp by rule) with
``" in tiles"`` where the grid is formed in tiles, or a model-based method's ``"solve (ls)"``.

A callback that takes two positional arguments, ``progress(done, total)``, is still called that
way: with each stage's own counts and no stage names, as before records existed.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["Progress", "Reporter", "takes_record"]


@dataclass(frozen=True)
class Progress:
    """One progress report of a call that runs in stages.

    Attributes
    ----------
    stage : str
        The stage reporting, one of ``stages`` (e.g. ``"compress (matched)"``,
        ``"super-resolve (bpdn)"``, ``"backproject"``, ``"form (omega-k)"``, ``"solve (ls)"``).
    done : int
        How much of the stage is done (0 when it starts).
    total : int or None
        How much there is in all, in the stage's own unit; None until the stage first counts.
    stages : tuple of str
        Every stage the call runs, in the order it runs them.
    """

    stage: str
    done: int
    total: int | None
    stages: tuple[str, ...]

    @property
    def step(self) -> int:
        """The stage's place in ``stages``, from 1."""
        return self.stages.index(self.stage) + 1


def takes_record(callback: Callable) -> bool:
    """Whether a progress callback takes one :class:`Progress` record (one positional argument)
    rather than ``(done, total)``; a callable whose signature cannot be read, or that takes two
    positional arguments (``*args`` among them), is called with ``(done, total)``."""
    try:
        sig = inspect.signature(callback)
    except (TypeError, ValueError):
        return False
    return _binds(sig, 1) and not _binds(sig, 2)


def _binds(sig: inspect.Signature, n: int) -> bool:
    try:
        sig.bind(*range(n))
    except TypeError:
        return False
    return True


class Reporter:
    """A call's ``progress`` callback and the stages the call will run, in order.

    ``start(stage)`` announces a stage; ``counter(stage)`` is the ``(done, total)`` callable the
    stage counts through (None where there is no callback); ``finished(stage)`` reports a stage
    that does not count (done 1 of 1). A ``(done, total)`` callback receives the counts only.
    """

    def __init__(self, callback: Callable | None, stages: tuple[str, ...]):
        if callback is not None and not callable(callback):
            raise TypeError(f"progress must be callable(Progress) or callable(done, total), got "
                            f"{type(callback).__name__}")
        self.callback, self.stages = callback, tuple(stages)
        self._records = callback is not None and takes_record(callback)

    def start(self, stage: str) -> None:
        """Announce that ``stage`` starts (a record with ``done=0``, ``total=None``)."""
        self._send(stage, 0, None)

    def finished(self, stage: str) -> None:
        """Report that ``stage``, which does not count its own work, is done (1 of 1)."""
        self._send(stage, 1, 1)

    def counter(self, stage: str) -> Callable[[int, int], None] | None:
        """The ``(done, total)`` callable ``stage`` reports its counts through."""
        self._check(stage)
        if self.callback is None or not self._records:
            return self.callback
        return lambda done, total: self.callback(Progress(stage, int(done), int(total), self.stages))

    def _send(self, stage: str, done: int, total: int | None) -> None:
        self._check(stage)
        if self._records:
            self.callback(Progress(stage, done, total, self.stages))

    def _check(self, stage: str) -> None:
        if stage not in self.stages:
            raise ValueError(f"stage {stage!r} is not one of this call's stages {self.stages}")
