"""Compatibility import path: the cube builder lives in :mod:`slicersim.products.cube`.

``from slicersim.cube import build_cube`` (documented since 0.1) keeps working.
"""
from slicersim.products.cube import *  # noqa: F401,F403
from slicersim.products.cube import __all__  # noqa: F401
