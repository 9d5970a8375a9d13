"""Named entries the harness runs but does not define: agents, observation tracks, presets.

The harness never imports a learner or a track. The catalog above it
(:mod:`window_bench.catalog`, imported with the package) registers them in a
:class:`Registry`, and every name the harness reads from a command line or a file (a method's
agent kind, a policy file's ``agent_kind``, a grid's ``track``) is looked up there and only
there: a name is never imported. An unknown name is a one-line ``ValueError`` listing the
registered ones.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, MutableMapping


class _Load:
    """A registered entry not made yet: ``load()`` makes it."""

    def __init__(self, load: Callable[[], object]):
        self.load = load


class Registry(MutableMapping):
    """``name -> entry``, in registration order. An entry is registered as itself or as a
    zero-argument ``load`` function that returns it, called on the first lookup (so that
    registering a learner imports no torch). ``unknown`` words the error for a name that is
    not registered."""

    def __init__(self, what: str, unknown: str = "unknown {what} {name!r}; registered: {names}"):
        self.what, self.unknown = what, unknown
        self._entries: dict = {}

    def register(self, name: str, entry=None, *, load: Callable[[], object] | None = None):
        """Register ``entry``, or ``load`` to make it on first use; replaces ``name``."""
        if (entry is None) == (load is None):
            raise TypeError(f"register {name!r}: give the {self.what} or a function that "
                            f"loads it, not both")
        self._entries[name] = entry if load is None else _Load(load)
        return entry

    def lookup(self, name: str):
        """The entry of ``name``; a one-line ``ValueError`` naming the registered ones."""
        if name not in self:
            raise ValueError(self.unknown.format(what=self.what, name=name,
                                                 names=", ".join(self._entries)))
        return self[name]

    def __getitem__(self, name: str):
        entry = self._entries[name]
        if isinstance(entry, _Load):
            entry = self._entries[name] = entry.load()
        return entry

    def __setitem__(self, name: str, entry) -> None:
        self.register(name, entry)

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __contains__(self, name) -> bool:
        try:
            return name in self._entries
        except TypeError:   # an unhashable value read from a file is no name
            return False

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)
