"""Names and keywords of user input, below :mod:`slicersim.validation`, which re-exports every
name here (import them from there): how a checked parameter is named and shown in messages
(:func:`flag_names`, :func:`shown`, :func:`short_repr`), a choice among valid values with a
"did you mean" (:func:`choice`), a deprecated keyword (:func:`renamed_keyword`) and the fields
of a dataclass (:func:`checked_fields`).

Inside :func:`flag_names` (the CLI runs every command in one), a checked parameter is shown by
the command-line flag that gave it (``--nramps``, not ``nramps``).
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import difflib
import functools
import inspect
import math
import numbers
import warnings

import numpy as np

from slicersim.errors import ParameterError, SlicersimError

__all__ = ["flag_names", "shown", "short_repr", "choice", "renamed_keyword", "checked_fields"]

#: Python parameter name → what the user typed it as (a CLI flag), set by :func:`flag_names`
_SHOWN_NAMES = contextvars.ContextVar("slicersim_shown_names", default={})


@contextlib.contextmanager
def flag_names(names):
    """Within the block, :func:`shown` (and so every checker here) names a parameter by ``names``
    (``{"nramps": "--nramps", "population.redshift.min": "--zmin"}``); nested blocks add to the
    outer one's names.

    Parameters
    ----------
    names : dict
        {parameter name: name shown}.

    Returns
    -------
    contextlib.AbstractContextManager
        A context manager (use it in a ``with`` statement); it yields None.
    """
    token = _SHOWN_NAMES.set({**_SHOWN_NAMES.get(), **names})
    try:
        yield
    finally:
        _SHOWN_NAMES.reset(token)


def shown(name) -> str:
    """``name`` as the user gave the parameter: its flag inside :func:`flag_names`, else itself.

    Parameters
    ----------
    name : str
        A parameter name (anything else is returned unchanged).

    Returns
    -------
    str
        The name shown.
    """
    return _SHOWN_NAMES.get().get(name, name) if isinstance(name, str) else name


def short_repr(value, limit=60) -> str:
    """``repr(value)`` short enough for one line of an error message: arrays as their shape and
    dtype, long representations cut with an ellipsis.

    Parameters
    ----------
    value : object
        Anything.
    limit : int, optional
        Most characters of the result.

    Returns
    -------
    str
        The representation.
    """
    if isinstance(value, np.ndarray) and hasattr(value, "unit") and value.shape == ():
        return str(value)                  # an astropy Quantity scalar, e.g. "3.0 m"
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)) and abs(int(value)) >= 10**15:
        try:
            return f"{float(value):g}"                      # 10**300 as 1e+300, not 301 digits
        except OverflowError:
            return f"an integer of {len(str(abs(int(value))))} digits"
    try:
        text = repr(value)
    except Exception:  # a broken __repr__ must not hide the real error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 1] + "…"


def choice(name, value, valid, *, error=ParameterError, what=None):
    """``value`` if it is one of ``valid`` (compared as given; strings case-sensitively), else an
    error listing the valid ones, with a "did you mean" for a near miss.

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : object
        The value.
    valid : sequence
        The valid values.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.
    what : str, optional
        What the value is, in the message (default: ``name``).

    Returns
    -------
    object
        ``value``.
    """
    name = shown(name)
    valid = list(valid)
    try:
        if value in valid:
            return value
    except TypeError:  # unhashable/uncomparable value
        pass
    listed = ", ".join(repr(v) for v in valid)
    hint = ""
    if isinstance(value, str):
        close = difflib.get_close_matches(value, [v for v in valid if isinstance(v, str)], n=1, cutoff=0.6)
        if not close:
            close = [v for v in valid if isinstance(v, str) and v.lower() == value.lower()]
        if close:
            hint = f" (did you mean {close[0]!r}?)"
    raise error(f"unknown {what or name} {short_repr(value)}{hint}; valid: {listed}")


def renamed_keyword(kwargs, old, new, where, *, stacklevel=3):
    """Move a deprecated keyword ``old`` to ``new`` in ``kwargs`` (in place) with a
    DeprecationWarning; both given is an error.

    Parameters
    ----------
    kwargs : dict
        The keywords, changed in place.
    old : str
        The deprecated name.
    new : str
        Its name now.
    where : str
        The function, in messages.
    stacklevel : int, optional
        ``stacklevel`` of the warning.

    Returns
    -------
    dict
        ``kwargs``.
    """
    if old not in kwargs:
        return kwargs
    if new in kwargs:
        raise ParameterError(f"{where}: give {new!r} only ({old!r} is its deprecated name)")
    warnings.warn(f"{where}: keyword {old!r} is deprecated, use {new!r}", DeprecationWarning,
                  stacklevel=stacklevel)
    kwargs[new] = kwargs.pop(old)
    return kwargs


#: atoms of a field annotation :func:`checked_fields` checks, and what a value of each must be: as
#: lenient as the most lenient class (0/1 for a bool, 3.0 for an int, a Quantity for a float); the
#: class's own checks then apply its rules
_FIELD_TYPES = {
    "bool": ("True or False", lambda v: isinstance(v, (bool, np.bool_)) or (
        isinstance(v, numbers.Integral) and v in (0, 1))),
    "int": ("an integer", lambda v: not isinstance(v, (bool, np.bool_)) and (
        isinstance(v, numbers.Integral) or (isinstance(v, numbers.Real) and math.isfinite(v) and v == int(v)))),
    "float": ("a number", lambda v: not isinstance(v, (bool, np.bool_)) and (
        isinstance(v, numbers.Real) or hasattr(v, "unit") and np.ndim(v) == 0
        or isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "iuf")),
    "str": ("a string", lambda v: isinstance(v, str)),
    "None": ("None", lambda v: v is None),
    "tuple": ("a sequence", lambda v: isinstance(v, (tuple, list, np.ndarray))),
    "list": ("a sequence", lambda v: isinstance(v, (tuple, list, np.ndarray))),
    "dict": ("a dict", lambda v: isinstance(v, dict) or hasattr(v, "keys") and hasattr(v, "__getitem__")),
}


def _field_rule(annotation):
    """(description, test) of a field annotation made of :data:`_FIELD_TYPES` atoms ("float | None"),
    or None where it has another (``object``, a class): such a field is checked by its class only."""
    atoms = [a.strip() for a in str(annotation).split("|")]
    if not all(a in _FIELD_TYPES for a in atoms):
        return None
    rules = [_FIELD_TYPES[a] for a in atoms]
    return " or ".join(r[0] for r in rules), (lambda v: any(r[1](v) for r in rules))


def checked_fields(cls=None, *, error=ParameterError):
    """Class decorator (after ``@dataclass``): building the class with an unknown keyword, a missing
    or extra argument, or a field of the wrong type (from its annotation: bool, int, float, str,
    None, tuple, list, dict and their unions) raises ``error`` naming the class and the field, with
    the valid field names and a did-you-mean, instead of Python's ``TypeError``.  The class's own
    ``__post_init__`` runs first (its messages are the more precise); the type check names a field
    it let through, or failed on with another exception than a SlicersimError.

    Parameters
    ----------
    cls : type, optional
        The dataclass (``@checked_fields`` or ``@checked_fields(error=...)``).
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    type or callable
        The class, its ``__init__`` wrapped; a decorator without ``cls``.
    """
    if cls is None:
        return functools.partial(checked_fields, error=error)
    init = cls.__init__
    signature = inspect.signature(init)
    fields = [f for f in dataclasses.fields(cls) if f.init]
    names = [f.name for f in fields]
    rules = {f.name: _field_rule(f.type) for f in fields}

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        for key in kwargs:
            if key not in names:
                choice("keyword", key, names, error=error, what=f"field of {cls.__name__}")
        try:
            bound = signature.bind(self, *args, **kwargs)
        except TypeError as exc:          # a missing argument, too many positional ones
            raise error(f"{cls.__name__}: {exc}; its fields: {', '.join(names)}") from None
        wrong = next((f"{cls.__name__}.{key} must be {rules[key][0]}, got {short_repr(value)}"
                      for key, value in list(bound.arguments.items())[1:]
                      if rules.get(key) is not None and not rules[key][1](value)), None)
        try:                              # the class's own checks first: their words are the most precise
            init(self, *args, **kwargs)
        except SlicersimError:
            raise
        except Exception:                 # a TypeError deep inside: the wrong type is the reason
            if wrong is None:
                raise
            raise error(wrong) from None
        if wrong is not None:             # a field the class does not check
            raise error(wrong)

    cls.__init__ = __init__
    return cls
