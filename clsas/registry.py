"""One registry pattern for every family of algorithms clsas chooses between by name.

Formations (:data:`clsas.formation.FORMATIONS`), per-profile sparse methods
(:data:`clsas.sparse.SPARSE_METHODS`), pulse compressions (:data:`clsas.compression.COMPRESSIONS`)
and importers (:data:`clsas.io.IMPORTERS`) are each a :class:`Registry`. An algorithm registers
itself where it is defined::

    from clsas.formation import FORMATIONS

    @FORMATIONS.register("my-formation")
    def form(profiles, grid, *, backend=None, device=None, progress=None, force=False, **options):
        ...

and the family's package imports that module once (one line), so ``reconstruct``, the command
line's choices, the benchmarks and the docs all see it. A user's own module registers the same
way after ``import clsas``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, MutableMapping
from typing import Generic, TypeVar

T = TypeVar("T")

__all__ = ["Registry"]


class Registry(MutableMapping[str, T], Generic[T]):
    """Names -> algorithms of one family, in registration order.

    Parameters
    ----------
    family : str
        What the entries are, for messages (e.g. ``"formation"``).
    parameter : str
        The public parameter that takes these names (e.g. ``"formation"``), named in errors.

    Examples
    --------
    >>> from clsas.registry import Registry
    >>> SHAPES = Registry("shape", "shape")
    >>> @SHAPES.register("double")
    ... def double(x):
    ...     return 2 * x
    >>> SHAPES["double"](3), SHAPES.names()
    (6, ('double',))
    """

    def __init__(self, family: str, parameter: str):
        self.family = family
        self.parameter = parameter
        self._entries: dict[str, T] = {}

    def register(self, name: str, entry: T | None = None, *, replace: bool = False):
        """Register ``entry`` under ``name``; without ``entry``, a decorator that does.

        A name already taken is refused unless ``replace=True`` (a second module must not
        silently shadow a built-in algorithm).
        """
        if not isinstance(name, str) or not name.strip() or name != name.strip():
            raise ValueError(f"{self.family} name must be a non-empty string without surrounding spaces, "
                             f"got {name!r}")

        def add(obj: T) -> T:
            if name in self._entries and not replace and self._entries[name] is not obj:
                raise ValueError(f"{self.family} {name!r} is already registered "
                                 f"({_describe(self._entries[name])}); pass replace=True to replace it")
            self._entries[name] = obj
            return obj

        if entry is None:
            return add
        return add(entry)

    def unregister(self, name: str) -> T:
        """Remove and return the entry ``name`` (for tests and plug-ins that clean up)."""
        return self._entries.pop(self.check(name))

    def check(self, name: str, parameter: str | None = None) -> str:
        """``name`` if registered, else a ValueError naming the parameter (default :attr:`parameter`)
        and the known names."""
        if not isinstance(name, str) or name not in self._entries:
            raise ValueError(f"{parameter or self.parameter} must be one of {self.names()}, got {name!r}")
        return name

    def choose(self, name: str) -> T:
        """The entry registered as ``name`` (checked as :meth:`check` does)."""
        return self._entries[self.check(name)]

    def names(self) -> tuple[str, ...]:
        """The registered names, in registration order."""
        return tuple(self._entries)

    def __getitem__(self, name: str) -> T:
        return self._entries[name]

    def __setitem__(self, name: str, entry: T) -> None:  # replaces, as monkeypatch.setitem needs
        self.register(name, entry, replace=True)

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.family!r}: {', '.join(self._entries)})"


def _describe(obj: object) -> str:
    if isinstance(obj, Callable):  # type: ignore[arg-type]
        return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', type(obj).__name__)}"
    return type(obj).__name__
