"""Versions: the package release ``__version__`` and the change tracking of model objects
(no slicersim imports: every layer may use it).

Every :class:`Versioned` object carries ``_version``, a number drawn from one
process-wide counter each time any of its attributes is assigned.  Versions are
therefore never reused, even across objects, and a tuple of versions
(:func:`state_token`) identifies the state of a set of objects: the
:class:`~slicersim.simulation.Simulation` keys its cache on the token of its
scene and instrument, so a cached value can never outlive the parameters it was
computed from.
"""
from __future__ import annotations

import itertools

__all__ = ["__version__", "Versioned", "state_token"]

#: release of the package (pyproject.toml reads it from here; ``slicersim.__version__`` re-exports it)
__version__ = "0.1.0"

_COUNTER = itertools.count(1)


class Versioned:
    """Mixin: any attribute assignment gives the object a new, globally unique ``_version``."""

    _version = 0

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)
        if name != "_version":
            object.__setattr__(self, "_version", next(_COUNTER))

    def touch(self):
        """Mark the object changed (after an in-place change of a mutable attribute).

        Returns
        -------
        None
            The version is bumped in place.
        """
        object.__setattr__(self, "_version", next(_COUNTER))

    def _adopt(self, other):
        """Take over every attribute of ``other`` (a validated copy), then bump the version."""
        for name, value in vars(other).items():
            if name != "_version":
                object.__setattr__(self, name, value)
        self.touch()


def state_token(obj):
    """Version of ``obj`` and of the sub-objects it declares in ``_state_parts()``.

    Objects that are not :class:`Versioned` count by identity (a user-supplied
    callable host, for instance)."""
    if obj is None:
        return None
    parts = getattr(obj, "_state_parts", None)
    own = getattr(obj, "_version", None)
    if own is None:
        own = ("id", id(obj))
    if parts is None:
        return own
    return (own,) + tuple(state_token(p) for p in parts())
