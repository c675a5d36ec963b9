"""Validation of user input, in one place: numbers, integers, ranges, choices, readouts,
seeds, arrays and paths.

Every checker takes the parameter's ``name`` first and raises a :class:`~slicersim.errors.SlicersimError`
subclass (``ParameterError`` unless told otherwise with ``error=``) whose message names the
parameter, states the rule and shows the value (arrays and long values summarised).  Checkers
return the value converted (``float``, ``int``, tuple, array), so a call site reads
``gain = validation.number("gain", gain, low=0, low_open=True, unit="ADU/e-")``.

A number given as an astropy ``Quantity`` is converted to the unit the parameter is documented
in (``unit=``); a plain number is taken to be in that unit already.

Inside :func:`flag_names` (the CLI runs every command in one), a checked parameter is shown by
the command-line flag that gave it (``--nramps``, not ``nramps``): messages written without a
checker name their parameter with :func:`shown`.

The checkers of names and keywords (:func:`flag_names`, :func:`shown`, :func:`short_repr`,
:func:`choice`, :func:`renamed_keyword`, :func:`checked_fields`) live in ``slicersim.keywords``
and are re-exported here: ``validation.X`` is the import path of every checker.
"""
from __future__ import annotations

import math
import numbers
import os
import secrets
import stat
import warnings

import numpy as np

from slicersim.errors import ParameterError, ReadoutError, ResourceError
from slicersim.keywords import checked_fields, choice, flag_names, renamed_keyword, short_repr, shown

__all__ = ["short_repr", "number", "integer", "positive_int", "fraction", "flag", "choice", "readout", "nramps",
           "seed", "new_seed", "array", "shape", "regular_file", "renamed_keyword", "flag_names", "shown", "redshift",
           "checked_fields", "memory", "physical_memory", "MAX_GROUPS", "MAX_DROPS", "MAX_FRAMES", "MAX_REDSHIFT",
           "DETECTOR_MAX", "MAX_TRUNCATE", "PLAUSIBLE", "warn_implausible"]

#: the largest readout this package accepts: groups per ramp, dropped frames between groups and
#: frames per ramp (an H4RG ramp of 512 groups of 16 frames at 2.83 s is 6.4 h, longer than any
#: exposure the ETC plans; 65 536 frames bounds the run time and memory of a per-frame sampler)
MAX_GROUPS = 4096
MAX_DROPS = 4096
MAX_FRAMES = 65536

#: the highest redshift accepted: the model spectra end at 2 µm, so beyond z ≈ 21 every wavelength
#: observed was emitted below the Lyman limit (912 Å), absorbed by intergalactic hydrogen, and no
#: luminous source is expected before z ≈ 30 (the first stars); 50 leaves a margin for toy spectra
MAX_REDSHIFT = 50.0
#: upper physical bound of the detector numbers wherever they come from (arguments, options, configuration
#: files; the raw-file keywords' ranges of ``slicersim.reduction.checks.ATTR_RANGES``): gain [ADU/e-], read
#: noise per frame [electron], dark [e-/s], ROIC glow [e-/frame], frame time [s].  Beyond them the variance
#: model overflows (ron = 1e300 squared) instead of giving an answer.
DETECTOR_MAX = {"gain": 1e3, "ron": 1e4, "dark": 1e6, "roic_glow": 1e6, "tframe": 1e4}
#: plausible ranges of the paper's parameters as bare numbers in their documented units: outside
#: them :func:`number` warns (the value is kept) — e.g. ``guiding_sigma=10`` meant as 10 mas is
#: 10 arcsec, 1000× the jitter of the paper's table
PLAUSIBLE = {"guiding_sigma": (0.0, 1.0),            # arcsec (space: ~0.01; a very poor ground site ~1)
             "spatial_scale": (0.003, 3.0),          # arcsec per slice / spaxel
             "diameter_ext": (0.05, 50.0),           # m
             "diameter_int": (0.0, 20.0),            # m
             "pixel_size": (1.0, 100.0),             # µm
             "gain": (0.05, 50.0),                   # ADU / e-
             "ron": (0.0, 500.0),                    # e- per frame (0: a noise-free detector)
             "dark": (0.0, 100.0),                   # e- / s / pixel
             "tframe": (1e-3, 100.0),                # s
             "dispersion_resolution": (1.0, 20.0),   # px
             "temperature": (2.0, 400.0)}            # K
#: largest projection window half-width beyond a cell [spot rms] (``truncate``): a Gaussian is exactly 0 in
#: float64 beyond ~38 rms, and 1e300 rms made every window the whole detector (footprints ran for ever)
MAX_TRUNCATE = 100.0


def _quantity_value(name, value, unit, error, plain="a plain number"):
    """The plain value(s) of an astropy Quantity in ``unit`` (anything else unchanged); a Quantity
    where ``unit`` is None, or in an inconvertible unit, is refused (never its unit dropped).
    A per-pixel quantity (the paper's e-/s/pix) is read per pixel: ``unit`` is already per pixel."""
    if not hasattr(value, "unit") or not hasattr(value, "to_value"):
        return value
    if unit is None:
        raise error(f"{name} is {plain}, got a quantity in {value.unit}")
    import astropy.units as u
    try:                        # temperatures: °C and °F convert to K
        return value.to_value(unit, equivalencies=u.temperature())
    except Exception:
        pass
    try:                        # e-/s/pix against e-/s: the documented unit is already per pixel
        return (value * u.pix).to_value(unit)
    except Exception:
        shown = short_repr(value) if np.ndim(value) == 0 else str(value.unit)
        raise error(f"{name} must be in units convertible to {unit}, got {shown}") from None


def number(name, value, *, low=-math.inf, high=math.inf, low_open=False, high_open=False, unit=None,
           error=ParameterError, plausible=None) -> float:
    """``value`` as a finite float in [low, high] (a bound excluded where ``*_open``); an astropy
    Quantity is converted to ``unit`` first.  ``plausible`` = (lo, hi): a *bare* number outside it
    (not a Quantity, whose unit is explicit) warns :class:`~slicersim.errors.ImplausibleValueWarning`
    naming the unit it is read in (10 of ``guiding_sigma`` is 10 arcsec, not the paper's 10 mas).

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : float or astropy.units.Quantity
        The value.
    low, high : float, optional
        Bounds of the accepted interval (in ``unit``).
    low_open, high_open : bool, optional
        Exclude that bound.
    unit : str or astropy.units.Unit, optional
        The unit the parameter is documented in; a Quantity is converted to it (refused when
        None or inconvertible).
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.
    plausible : tuple of float, optional
        (lo, hi) plausible range of a bare number, in ``unit``.

    Returns
    -------
    float
        The value in ``unit``.
    """
    name = shown(name)
    bare = not hasattr(value, "unit")
    value = _quantity_value(name, value, unit, error)
    in_unit = f" [{unit}]" if unit else ""
    if isinstance(value, (bool, np.bool_, str, bytes)) or not isinstance(value, (numbers.Real, np.ndarray)) \
            or (isinstance(value, np.ndarray) and value.shape != ()):
        raise error(f"{name}{in_unit} must be a number, got {short_repr(value)}")
    try:
        val = float(value)
    except OverflowError:                          # an int beyond the float range (10**400)
        val = math.inf
    if not math.isfinite(val) and not isinstance(value, numbers.Integral):   # inf > 0 holds: say what is wrong
        raise error(f"{name}{in_unit} must be finite{_finite_bounds(low, high, low_open, high_open)}, "
                    f"got {short_repr(value)}")
    if val < low or val > high or (low_open and val == low) or (high_open and val == high):
        raise error(f"{name}{in_unit} must be {_interval(low, high, low_open, high_open)}, got {short_repr(value)}")
    if plausible is not None and bare and not plausible[0] <= val <= plausible[1]:
        warn_implausible(name, val, unit, plausible)
    return val


def warn_implausible(name, value, unit, plausible):
    """Warn (:class:`~slicersim.errors.ImplausibleValueWarning`) that a bare ``value`` of ``name`` is
    outside the ``plausible`` (lo, hi) range of its documented ``unit``: a number meant in another unit.

    Parameters
    ----------
    name : str
        The parameter's name.
    value : float
        The bare value.
    unit : str or None
        Its documented unit.
    plausible : tuple of float
        (lo, hi) plausible range in ``unit``.

    Returns
    -------
    None
        It only warns.
    """
    import warnings
    from slicersim.errors import ImplausibleValueWarning
    unit_text = f" {unit}" if unit else ""
    hint = "; give an astropy Quantity (value * unit) to say which unit you mean" if unit else ""
    warnings.warn(f"{name} = {value:g}{unit_text} is implausible (expected {plausible[0]:g} to {plausible[1]:g}"
                  f"{unit_text}): a bare number of {name} is read in{unit_text or ' its documented unit'}{hint}",
                  ImplausibleValueWarning, stacklevel=4)


def _finite_bounds(low, high, low_open, high_open):
    """" and > 0"-style suffix of a finiteness message; "" without bounds."""
    interval = _interval(low, high, low_open, high_open)
    return "" if interval == "finite" else f" and {interval}"


def _interval(low, high, low_open, high_open):
    if low == -math.inf and high == math.inf:
        return "finite"
    if high == math.inf:
        return f"{'>' if low_open else '≥'} {low:g}"
    if low == -math.inf:
        return f"{'<' if high_open else '≤'} {high:g}"
    return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


def integer(name, value, *, low=None, high=None, error=ParameterError) -> int:
    """``value`` as an int in [low, high]; integral floats (``3.0``) are accepted, ``2.7``, NaN,
    bools and strings are refused.

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : int or float
        The value.
    low, high : int, optional
        Bounds of the accepted interval (included).
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    int
        The value.
    """
    name = shown(name)
    bounds = (f" ≥ {low}" if high is None else f" in [{low}, {high}]") if low is not None else \
        (f" ≤ {high}" if high is not None else "")
    if isinstance(value, (bool, np.bool_, str, bytes)) or not isinstance(value, numbers.Real):
        raise error(f"{name} must be an integer{bounds}, got {short_repr(value)}")
    if isinstance(value, numbers.Integral):
        val = int(value)
    else:
        fval = float(value)
        if not math.isfinite(fval) or fval != int(fval):
            raise error(f"{name} must be an integer{bounds}, got {short_repr(value)}")
        val = int(fval)
    if (low is not None and val < low) or (high is not None and val > high):
        raise error(f"{name} must be an integer{bounds}, got {short_repr(value)}")
    return val


def positive_int(name, value, low=1, *, high=None, error=ParameterError) -> int:
    """An integer ≥ ``low`` (default 1).

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : int or float
        The value (integral floats accepted).
    low : int, optional
        Least value accepted.
    high : int, optional
        Largest value accepted.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    int
        The value.
    """
    return integer(name, value, low=low, high=high, error=error)


def fraction(name, value, *, error=ParameterError) -> float:
    """A number in [0, 1].

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : float
        The value.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    float
        The value.
    """
    return number(name, value, low=0.0, high=1.0, error=error)


def flag(name, value, *, error=ParameterError) -> bool:
    """A bool (``True``/``False`` or NumPy's); 0, 1 and strings are refused so a misplaced
    positional argument is not read as a switch.

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : bool
        The value.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    bool
        The value.
    """
    name = shown(name)
    if not isinstance(value, (bool, np.bool_)):
        raise error(f"{name} must be True or False, got {short_repr(value)}")
    return bool(value)


def readout(nmd, *, name="nmd", min_group=2, max_group=None, error=ReadoutError) -> tuple[int, int, int]:
    """A MACC readout (n groups, m frames per group, d dropped frames) as three ints:
    2 ≤ n ≤ ``max_group`` (≤ :data:`MAX_GROUPS`), 1 ≤ m, 0 ≤ d ≤ ``MAX_DROPS``, and at most
    ``MAX_FRAMES`` frames per ramp.  Non-integers (``2.7``) are refused, not truncated.

    Parameters
    ----------
    nmd : sequence of int
        (n, m, d).
    name : str, optional
        The parameter's name in messages.
    min_group : int, optional
        Least n (at least 2).
    max_group : int, optional
        Largest n (default :data:`MAX_GROUPS`).
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    tuple of int
        (n, m, d).
    """
    name = shown(name)
    if isinstance(nmd, (str, bytes)) or not hasattr(nmd, "__len__") or len(nmd) != 3:
        raise error(f"{name} must be a triple (n, m, d) of integers, got {short_repr(nmd)}")
    n_low = max(2, int(min_group or 2))
    n_high = MAX_GROUPS if max_group is None else min(int(max_group), MAX_GROUPS)
    n = integer(f"{name}[0] (n, groups per ramp)", nmd[0], low=n_low, high=n_high, error=error)
    m = integer(f"{name}[1] (m, frames per group)", nmd[1], low=1, high=MAX_FRAMES, error=error)
    d = integer(f"{name}[2] (d, dropped frames between groups)", nmd[2], low=0, high=MAX_DROPS, error=error)
    nframes = n * (m + d) - d
    if nframes > MAX_FRAMES:
        raise error(f"{name} = ({n}, {m}, {d}) reads {nframes} frames per ramp; at most {MAX_FRAMES} are "
                    "supported")
    return n, m, d


def nramps(value, *, name="nramps", error=ReadoutError) -> int:
    """A number of ramps: an integer ≥ 1.

    Parameters
    ----------
    value : int
        The value (at most 2³¹ − 1).
    name : str, optional
        The parameter's name in messages.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    int
        The value.
    """
    return integer(name, value, low=1, high=2**31 - 1, error=error)


def seed(value, *, name="seed", allow_none=True, error=ParameterError):
    """A noise seed: an integer in [0, 2⁶⁴), or None where a fresh seed is drawn (see
    :func:`new_seed`).  A NumPy ``Generator`` is accepted for one release with a
    DeprecationWarning: an integer seed is drawn from it (counter-based noise needs an integer key).

    Parameters
    ----------
    value : int or None
        The seed.
    name : str, optional
        The parameter's name in messages.
    allow_none : bool, optional
        Accept None.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    int or None
        The seed.
    """
    name = shown(name)
    if value is None:
        if allow_none:
            return None
        raise error(f"{name} must be an integer in [0, 2**64), got None")
    if isinstance(value, np.random.Generator):
        warnings.warn(f"{name} as a numpy Generator is deprecated: pass an integer seed (an integer was drawn "
                      "from the Generator)", DeprecationWarning, stacklevel=3)
        return int(value.integers(0, 2**63))
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise error(f"{name} must be an integer in [0, 2**64){' or None' if allow_none else ''}, "
                    f"got {short_repr(value)}")
    if not 0 <= int(value) < 2**64:
        shown_value = f"{int(value)}" if abs(int(value)) < 10**30 else short_repr(value)   # 2**64 exactly, not 1.8e19
        what = " (2**64 itself is one too many: the largest seed is 2**64 - 1)" if int(value) == 2**64 else ""
        raise error(f"{name} must be in [0, 2**64), got {shown_value}{what}")
    return int(value)


def new_seed() -> int:
    """A fresh seed in [0, 2⁶³) from the operating system's entropy (record it to reproduce).

    Returns
    -------
    int
        The seed.
    """
    return secrets.randbits(63)


def array(name, value, *, ndim=None, dtype=np.float64, finite=True, low=None, high=None, unit=None,
          error=ParameterError) -> np.ndarray:
    """``value`` as a NumPy array of real numbers converted to ``dtype``; refuses object,
    structured, complex and string arrays, a wrong number of dimensions, non-finite values
    (``finite``) and values below ``low`` or above ``high``.  An astropy Quantity is converted to ``unit`` (refused
    when ``unit`` is None or not convertible: its unit must never be dropped silently).

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : array_like or astropy.units.Quantity
        The values.
    ndim : int or sequence of int, optional
        Accepted number(s) of dimensions.
    dtype : numpy.dtype, optional
        The dtype of the result.
    finite : bool, optional
        Refuse non-finite values.
    low, high : float, optional
        Bounds of the values (included).
    unit : str or astropy.units.Unit, optional
        The unit the parameter is documented in.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    numpy.ndarray
        The values, of the shape given.
    """
    name = shown(name)
    value = _quantity_value(name, value, unit, error, plain="an array of plain numbers")
    try:
        arr = np.asarray(value)
    except Exception as exc:
        raise error(f"{name} must be an array of numbers, got {short_repr(value)} ({exc})") from None
    if arr.dtype.kind not in "biuf":
        raise error(f"{name} must be an array of real numbers, got dtype {arr.dtype}")
    if ndim is not None and arr.ndim not in np.atleast_1d(ndim):
        raise error(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    arr = arr.astype(dtype, copy=False)
    if finite and arr.size and not np.isfinite(arr).all():
        raise error(f"{name} has {int(np.size(arr) - np.isfinite(arr).sum())} non-finite value(s)")
    if low is not None and arr.size and float(arr.min()) < low:
        raise error(f"{name} must be ≥ {low:g}, its minimum is {float(arr.min()):g}")
    top = float(np.max(arr, initial=-np.inf, where=~np.isnan(arr))) if high is not None and arr.size else None
    if top is not None and top > high:
        raise error(f"{name} must be ≤ {high:g}, its maximum is {top:g}")
    return arr


def shape(name, value, *, ndim=2, max_side=65536, error=ParameterError) -> tuple[int, ...]:
    """A shape of ``ndim`` integers in [1, max_side].

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : sequence of int
        The shape.
    ndim : int, optional
        Its number of dimensions.
    max_side : int, optional
        The largest side accepted.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    tuple of int
        The shape.
    """
    name = shown(name)
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != ndim:
        raise error(f"{name} must be {ndim} integers, got {short_repr(value)}")
    return tuple(integer(f"{name}[{i}]", v, low=1, high=max_side, error=error) for i, v in enumerate(value))


def regular_file(name, path, *, error=ParameterError, max_bytes=None) -> str:
    """``path`` (str or os.PathLike) of an existing regular file (not a directory, FIFO or
    device), at most ``max_bytes`` long when given.

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    path : str or os.PathLike
        The path.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.
    max_bytes : int, optional
        Largest file size accepted [bytes].

    Returns
    -------
    str
        The path.
    """
    name = shown(name)
    try:
        path = os.fspath(path)
    except TypeError:
        raise error(f"{name} must be a file path, got {short_repr(path)}") from None
    try:
        st = os.stat(path)
    except OSError as exc:
        raise error(f"{name}: {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a directory" if stat.S_ISDIR(st.st_mode) else "not a regular file"
        raise error(f"{name}: {path} is {kind}")
    if max_bytes is not None and st.st_size > max_bytes:
        raise error(f"{name}: {path} is {st.st_size} bytes, more than the {max_bytes} accepted")
    return path


def redshift(name, value, *, allow_zero=False, error=ParameterError) -> float:
    """A redshift as a float in (0, :data:`MAX_REDSHIFT`] ([0, ...] with ``allow_zero``).

    Parameters
    ----------
    name : str
        The parameter's name in messages (its CLI flag inside :func:`flag_names`).
    value : float
        The redshift.
    allow_zero : bool, optional
        Accept 0.
    error : type, optional
        The :class:`~slicersim.errors.SlicersimError` subclass raised.

    Returns
    -------
    float
        The redshift.
    """
    try:
        beyond = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) \
            and float(value) > MAX_REDSHIFT
    except OverflowError:                          # an int beyond the float range
        beyond = value > 0
    if beyond:
        raise error(f"{shown(name)} must be ≤ {MAX_REDSHIFT:g}, got {short_repr(value)} (beyond z ≈ 21 all the light "
                    "reaching the 2 µm end of the model grid was emitted below the Lyman limit)")
    return number(name, value, low=0.0, low_open=not allow_zero, high=MAX_REDSHIFT, error=error)


def physical_memory() -> int | None:
    """Bytes of physical memory of this machine (None where the system does not say).

    Returns
    -------
    int or None
        The physical memory [bytes].
    """
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def memory(what, nbytes, *, hint=""):
    """Refuse (:class:`~slicersim.errors.ResourceError`) before allocating ``nbytes`` for ``what``
    when they exceed this machine's physical memory; ``hint`` says what bounds them.

    Parameters
    ----------
    what : str
        What would be allocated, in the message.
    nbytes : int
        Its size [bytes].
    hint : str, optional
        What bounds them, in the message.

    Returns
    -------
    None
        It only raises.
    """
    total = physical_memory()
    if total is not None and nbytes > total:
        raise ResourceError(f"{what} would take {nbytes / 2**30:.3g} GiB, more than this machine's "
                            f"{total / 2**30:.3g} GiB of memory{'; ' + hint if hint else ''}")
