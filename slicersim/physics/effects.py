"""Detector systematics of an H4RG (pipeline stress tests): names and random streams.

Every effect is off unless asked for.  Each effect draws its random numbers from
its own Philox stream range (:data:`STREAMS`), keyed by (seed, position), so
switching one effect on or off leaves the draws of every other effect — and the
Poisson charge, read noise and kTC draws of the plain ramp — unchanged.

The plain ramp uses streams ``4·ramp + p`` (p < 4) and ``+ 0x80000000`` for PTRS;
effects use ``STREAMS[name] + sub`` with ``sub < 2**24`` (ramps enter the index,
never the stream), disjoint from those for any nramps < 2**26.
"""
from __future__ import annotations

import math

from slicersim.errors import EffectsError

__all__ = ["EFFECT_NAMES", "STREAMS", "check_number", "check_fraction"]

#: effect names accepted by ``--effects`` and :class:`DetectorEffects` (``"all"`` = every one)
EFFECT_NAMES = ("cosmic_rays", "ipc", "nonlinearity", "correlated_noise", "reference_pixels",
                "bad_pixels", "persistence")

#: first Philox stream of each effect (each owns [base, base + 2**24))
STREAMS = {
    "cosmic_rays": 0x10000000,
    "nonlinearity": 0x11000000,
    "correlated_noise": 0x12000000,
    "reference_pixels": 0x13000000,
    "bad_pixels": 0x14000000,
    "persistence": 0x15000000,
}


# --------------------------------------------------------------------------- validation helpers
def check_number(name, value, low=0.0, high=math.inf, *, low_open=False, high_open=False):
    """``value`` as a float in [low, high] (bounds open where asked), else EffectsError naming it."""
    try:
        val = float(value)
    except (TypeError, ValueError):
        raise EffectsError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(val) or val < low or val > high \
            or (low_open and val == low) or (high_open and val == high):
        lo, hi = "(" if low_open else "[", ")" if high_open or high == math.inf else "]"
        raise EffectsError(f"{name} must be in {lo}{low:g}, {high:g}{hi}, got {value!r}")
    return val


def check_fraction(name, value):
    """A fraction in [0, 1]."""
    return check_number(name, value, 0.0, 1.0)
