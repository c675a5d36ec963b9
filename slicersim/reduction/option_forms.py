"""The two forms of a reduction function's options: an options object (a frozen dataclass whose
fields are checked when it is built) or the same names as keywords (the form of earlier releases),
which build the object or replace fields of a given one (:func:`build_options`)."""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["build_options", "set_field", "pair"]


def build_options(cls, options, keywords, where):
    """An instance of the options dataclass ``cls`` from ``options`` (an instance, or None for the
    defaults) with the fields named in ``keywords`` replaced; an unknown keyword is a
    ParameterError with the valid names (and a "did you mean")."""
    names = [f.name for f in dataclasses.fields(cls)]
    for key in keywords:
        validation.choice("keyword", key, names, what=f"{where} keyword")
    if options is None:
        return cls(**keywords)
    if not isinstance(options, cls):
        raise ParameterError(f"{where}: options must be a {cls.__name__}, got {validation.short_repr(options)}")
    return dataclasses.replace(options, **keywords) if keywords else options


def set_field(obj, name, value):
    """Set a field of a frozen dataclass (to store its checked, normalised value in __post_init__)."""
    object.__setattr__(obj, name, value)


def pair(name, value, positive=False):
    """(x, y) as two finite floats (> 0 with ``positive``)."""
    if isinstance(value, (str, bytes, os.PathLike)) or np.ndim(value) != 1 or np.size(value) != 2:
        raise ParameterError(f"{name} must be a pair (x, y) of numbers, got {validation.short_repr(value)}")
    low = 0.0 if positive else -np.inf
    return tuple(validation.number(f"{name}[{i}]", v, low=low, low_open=positive) for i, v in enumerate(value))
