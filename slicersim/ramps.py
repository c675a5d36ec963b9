"""Compatibility import path: the raw-ramp generator lives in :mod:`slicersim.products.ramps`.

``from slicersim.ramps import simulate`` (documented since 0.1) keeps working.
"""
from slicersim.products.ramps import *  # noqa: F401,F403
from slicersim.products.ramps import __all__  # noqa: F401
