"""Checks of :func:`~slicersim.reduction.rectify.rectify`'s inputs: the λ grid, the images and the options
(each a :class:`~slicersim.errors.ParameterError` naming the parameter, before any work), and
:class:`RectifyOptions`, its options object."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.mapper import NARROW_SLICES, WIDE_SLICES
from slicersim.reduction.option_forms import set_field

__all__ = ["RectifyOptions", "angstrom", "FIELDS", "METHODS"]

FIELDS = {"narrow": NARROW_SLICES, "wide": WIDE_SLICES}
METHODS = ("lsq", "drizzle")
#: largest |rate| and variance accepted (and 1/_MAX_VALUE the smallest variance > 0): beyond, the
#: weights and sums overflow float64
_MAX_VALUE = 1e100


def _check_grid(lbda, lbda_edges, mapper):
    """(centres, edges) [Å] of the output λ grid, or ParameterError."""
    if lbda is None and lbda_edges is None:
        raise ParameterError("the λ grid is missing: give lbda (bin centres [Å]) and/or lbda_edges")
    try:
        c = None if lbda is None else np.asarray(lbda, np.float64)
        e = None if lbda_edges is None else np.asarray(lbda_edges, np.float64)
    except (TypeError, ValueError):
        raise ParameterError("inconsistent λ grid: lbda and lbda_edges must be numbers [Å]") from None
    for name, a in (("lbda", c), ("lbda_edges", e)):
        if a is not None and (a.ndim != 1 or a.size < (1 if name == "lbda" else 2) or not np.all(np.isfinite(a))):
            raise ParameterError(f"inconsistent λ grid: {name} must be a finite 1-D array, got shape "
                                 f"{a.shape}")
    if e is None:
        if c.size < 2:
            raise ParameterError("inconsistent λ grid: give lbda_edges for a single bin")
        mid = 0.5 * (c[1:] + c[:-1])
        e = np.concatenate([[1.5 * c[0] - 0.5 * c[1]], mid, [1.5 * c[-1] - 0.5 * c[-2]]])
    if np.any(np.diff(e) <= 0):
        raise ParameterError("inconsistent λ grid: lbda_edges must increase strictly")
    if c is None:
        c = 0.5 * (e[1:] + e[:-1])
    if c.shape != (e.size - 1,):
        raise ParameterError(f"inconsistent λ grid: {c.size} bin centres for {e.size} edges "
                             f"(need {e.size - 1})")
    if np.any(c < e[:-1]) or np.any(c > e[1:]):
        raise ParameterError("inconsistent λ grid: every centre lbda[i] must lie in [lbda_edges[i], "
                             "lbda_edges[i+1]]")
    lo, hi = mapper.lbda_nodes[0], mapper.lbda_nodes[-1]
    if e[0] < lo or e[-1] > hi:
        raise ParameterError(f"inconsistent λ grid: {e[0]:.1f}–{e[-1]:.1f} Å leaves the traces of the "
                             f"mapper ({lo:.1f}–{hi:.1f} Å)")
    return c, e


def _check_images(rate_image, variance, shape):
    got = np.shape(rate_image)                         # before any conversion (no copy of a bad input)
    if len(got) not in (2, 3) or got[-2:] != tuple(shape):
        raise ParameterError(f"rate_image must have shape {tuple(shape)} (the mapper's detector) or "
                             f"(N, {shape[0]}, {shape[1]}) for a stack, got {got}")
    if np.iscomplexobj(rate_image) or np.iscomplexobj(variance):
        raise ParameterError("rate_image and variance must be real numbers, got complex values")
    try:
        d = np.asarray(rate_image, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError("rate_image must be a numeric array") from None
    if (np.abs(d) > _MAX_VALUE).any():                 # NaN / ±inf pass: refused or left out per pixel
        raise ParameterError(f"rate_image has finite values beyond ±{_MAX_VALUE:.0e} (absurd: the sums of the "
                             "rectification overflow)")
    if variance is None:
        return d, None
    try:
        v = np.asarray(variance, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError("variance must be a numeric array") from None
    if v.shape != tuple(shape):
        raise ParameterError(f"variance must have shape {tuple(shape)} (one image for the stack), got {v.shape}")
    if np.isnan(v).any() or (v < 0).any():
        raise ParameterError("variance must be ≥ 0 (+inf marks an unusable pixel), got NaN or negative values")
    if ((v > _MAX_VALUE) & np.isfinite(v)).any() or ((v > 0) & (v < 1.0 / _MAX_VALUE)).any():
        raise ParameterError(f"variance has values outside [{1 / _MAX_VALUE:.0e}, {_MAX_VALUE:.0e}] (other than 0 "
                             "and +inf): absurd, their weights overflow")
    return d, v


def _check_options(field_name, method, ncol, backend, mapper):
    """The fields rectified (names); ``mapper`` None: the options alone."""
    from slicersim.backends.dispatch import BACKENDS
    validation.choice("field", field_name, (*FIELDS, "both"))
    validation.choice("method", method, METHODS)
    validation.choice("backend", backend, BACKENDS)
    if isinstance(ncol, (float, np.floating)):
        raise ParameterError(f"ncol must be an integer ≥ 1 (columns per slice), got {validation.short_repr(ncol)}")
    validation.integer("ncol", ncol, low=1)
    names = list(FIELDS) if field_name == "both" else [field_name]
    if mapper is None:
        return names
    for name in names:
        try:
            mapper.slice_index(FIELDS[name])
        except ValueError:
            raise ParameterError(f"the mapper has no {name} field (slices {FIELDS[name][0]}–"
                                 f"{FIELDS[name][-1]})") from None
    return names


def _check_projection(oversample, truncate, weights_dtype):
    """(oversample as two ints) of the projection's options, or ParameterError."""
    if isinstance(oversample, (str, bytes)) or np.size(oversample) != 2:
        raise ParameterError(f"oversample must be two positive integers, got {validation.short_repr(oversample)}")
    ov = tuple(validation.integer(f"oversample[{i}]", v, low=1) for i, v in enumerate(np.ravel(oversample)))
    validation.number("truncate [spot rms]", truncate, low=0.0, low_open=True, high=validation.MAX_TRUNCATE)
    try:
        dtype = np.dtype(weights_dtype)
    except TypeError:
        dtype = None
    if dtype is None or dtype not in (np.dtype(np.float32), np.dtype(np.float64)):  # None == float64 in NumPy
        raise ParameterError(f"weights_dtype must be float32 or float64, got {validation.short_repr(weights_dtype)}")
    return ov




def angstrom(name, value):
    """``value`` [Å] unchanged, or an astropy Quantity of wavelengths converted to Å (as an array);
    ParameterError naming ``name`` for another unit."""
    if value is None or not hasattr(value, "to_value"):
        return value
    try:
        return np.asarray(value.to_value("Angstrom"), np.float64)
    except Exception:
        raise ParameterError(f"{name} must be wavelengths [Å] (or a Quantity in a length unit), got "
                             f"{validation.short_repr(value)}") from None


@validation.checked_fields
@dataclass(frozen=True, eq=False)
class RectifyOptions:
    """Options of :func:`~slicersim.reduction.rectify.rectify` (see its docstring).

    mapper : SlicerMapper (None: the default layout);  field : "narrow", "wide" or "both"
    lbda, lbda_edges : output bin centres and/or edges [Å];  ncol : columns per slice
    method : "lsq" or "drizzle";  oversample, truncate, weights_dtype : the projection's options
    unit : the image's unit (e.g. "e-/s");  max_bytes : memory for one slice's factorisation [bytes]
    backend : "auto", "numpy" or "opencl";  keep_information : keep the cube's inverse covariance
    """

    mapper: object = None
    field: str = "narrow"
    lbda: object = None
    lbda_edges: object = None
    ncol: int = 116
    method: str = "lsq"
    oversample: tuple = (1, 1)
    truncate: float = 4.0
    weights_dtype: object = np.float32
    unit: str = "e-/s"
    max_bytes: int = 2**30
    backend: str = "auto"
    keep_information: bool = False

    def __post_init__(self):
        _check_options(self.field, self.method, self.ncol, self.backend, None)
        for name in ("lbda", "lbda_edges"):
            set_field(self, name, angstrom(name, getattr(self, name)))
        set_field(self, "ncol", int(self.ncol))
        set_field(self, "oversample", _check_projection(self.oversample, self.truncate, self.weights_dtype))
        set_field(self, "truncate", float(self.truncate))
        set_field(self, "max_bytes", validation.integer("max_bytes [bytes]", self.max_bytes, low=1))
        set_field(self, "keep_information", validation.flag("keep_information", self.keep_information))
        if not isinstance(self.unit, str):
            raise ParameterError(f"unit must be a str (e.g. 'e-/s'), got {validation.short_repr(self.unit)}")
