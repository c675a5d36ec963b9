"""Names of model parameters: the check shared by every ``update`` / ``updated`` of the instrument,
the simulation and the targets (a ParameterError naming the unknown names, a "did you mean" for a
near miss and the accepted list)."""
from __future__ import annotations

import difflib

from slicersim.errors import ParameterError

__all__ = ["check_parameter_names"]


def check_parameter_names(kind, names, accepted, hint=""):
    """Raise ParameterError unless every name of ``names`` is in ``accepted``; the message names
    the unknown ones (``kind``: "detector", "spectrograph", ...), suggests the closest accepted
    name and lists them all; ``hint`` is appended before the list."""
    accepted = list(accepted)
    unknown = sorted(set(names) - set(accepted))
    if not unknown:
        return
    close = [m for u in unknown for m in difflib.get_close_matches(str(u), accepted, n=1, cutoff=0.6)]
    guess = f" (did you mean {close[0]!r}?)" if close else ""
    raise ParameterError(f"unknown {kind} parameter(s) {unknown}{guess}{hint}; accepted: {', '.join(accepted)}")
