"""Option objects of the reduction: what :func:`~slicersim.reduction.pipeline.reduce_exposure` and
:func:`~slicersim.reduction.forward_extraction.extract_forward` are asked to do, in one frozen,
checked value each (:class:`~slicersim.reduction.rectify_checks.RectifyOptions` is rectify's).

Every function taking one accepts it as ``options=`` and the same names as keywords (the keyword
form of earlier releases keeps working: the keywords build the object, or replace fields of a
given one).  Values are checked when the object is built (a :class:`~slicersim.errors.ParameterError`
naming the field), so a bad option is refused before any data are read.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.reduction.checks import DEFAULT_NCOL, FORWARD, check_fit_options, check_spectra_options, dark_rate_of
from slicersim.reduction.option_forms import pair, set_field

__all__ = ["ReduceOptions", "ForwardOptions", "PixelNoise"]


@validation.checked_fields
@dataclass(frozen=True, eq=False)
class ReduceOptions:
    """Options of :func:`~slicersim.reduction.pipeline.reduce_exposure` (see its docstring for each).

    Parameters
    ----------
    mapper : SlicerMapper, optional
        The detector mapping (None: ``SlicerMapper.default()``).
    field : {"narrow", "wide", "both"} or None, optional
        None: the field the file records, else "narrow".
    lbda_edges : array_like or astropy.units.Quantity, optional
        Rectification λ edges [Å] (None: 2 native bins per bin).
    ncol : int, optional
        Columns per slice of the cubes.
    rectify_method : {"lsq", "drizzle"}, optional
        Rectification method (None: "lsq"; giving it asks for the cube, ``cubes``).
    extraction : {"forward", "gls", "optimal", "aperture"}, optional
        None: forward when the instrument is known.
    psf : str or numpy.ndarray, optional
        "fit" or an (nλ, slices, columns) array / (K, nλ, slices, columns) template.
    position : tuple of float, optional
        (x, y) [cells from the field centre] or None (fitted).
    aperture : float, optional
        Aperture radius [white-light PSF σ] ("optimal", "aperture").
    background, propagate, keep_information : bool, optional
        Switches (True, True, False).
    fit_options : dict, optional
        ``fit_ramps`` keywords or None.
    weights : {"forward", "model", "data"}, optional
        Or None (the method's default).
    dark : {"auto"}, float, numpy.ndarray or None, optional
        "auto", None, a rate [e-/s] or an image.
    config : str, path-like or list, optional
        Instrument configuration of the forward model (name, TOML path or list) or None.
    ipc : bool, optional
        None (deconvolve the file's IPC when it records one) or False.
    cubes : bool, optional
        Rectify the cube(s) too.  None (default): only when the extraction needs them (a cube
        extraction) or a cube option (``rectify_method``, ``weights``, ``keep_information``) is
        given; the forward extraction's spectrum comes from the pixels and needs none.
    """

    mapper: object = None
    field: str | None = None
    lbda_edges: object = None
    ncol: int = DEFAULT_NCOL
    rectify_method: str | None = None
    extraction: str | None = None
    psf: object = "fit"
    position: tuple | None = None
    aperture: float = 3.0
    background: bool = True
    propagate: bool = True
    fit_options: dict | None = None
    keep_information: bool = False
    weights: str | None = None
    dark: object = "auto"
    config: object = None
    ipc: bool | None = None
    cubes: bool | None = None

    def __post_init__(self):
        from slicersim.reduction.rectify_checks import angstrom
        set_field(self, "lbda_edges", angstrom("lbda_edges", self.lbda_edges))
        given = {name: getattr(self, name) for name in ("field", "ncol", "rectify_method", "extraction", "position",
                                                        "background", "weights", "config", "ipc", "cubes")}
        checked = check_spectra_options(**{k: v for k, v in given.items() if v is not None})
        for name in ("ncol", "position", "background"):
            if name in checked:
                set_field(self, name, checked[name])
        set_field(self, "propagate", validation.flag("propagate", self.propagate))
        set_field(self, "keep_information", validation.flag("keep_information", self.keep_information))
        if self.keep_information and self.cubes is False:
            raise ParameterError("keep_information keeps the cube's inverse covariance, and cubes=False asks for no cube")
        set_field(self, "aperture", validation.number("aperture [PSF σ]", self.aperture, low=0.0, low_open=True))
        if self.fit_options is not None:
            set_field(self, "fit_options", check_fit_options(self.fit_options))
        if isinstance(self.psf, str):
            validation.choice("psf", self.psf, ("fit",))
        if not (isinstance(self.dark, str) and self.dark == "auto") and self.dark is not None:
            dark_rate_of(self.dark, None, np.shape(self.dark) if np.ndim(self.dark) == 2 else ())

    @property
    def lsq(self):
        """True for a least-squares cube (``rectify_method`` "lsq" or None)."""
        return self.rectify_method in (None, "lsq")

    def resolved_weights(self):
        """The lsq weights used: the given ones, or "forward" (lsq) / "data" (drizzle)."""
        if self.weights is not None:
            return self.weights
        return "forward" if self.lsq else "data"

    def default_extraction(self, model):
        """The extraction used when none is given: forward with an instrument ``model``, else "gls"
        (lsq) or "optimal" (drizzle)."""
        if self.extraction is not None:
            return self.extraction
        return FORWARD if model is not None else ("gls" if self.lsq else "optimal")

    def resolved_cubes(self, extraction):
        """Whether the cube(s) are rectified beside ``extraction``: ``cubes`` when given, else for a cube
        extraction or when a cube option (rectify_method, weights, keep_information) is given."""
        if self.cubes is not None:
            return self.cubes
        asked = self.rectify_method is not None or self.weights is not None or self.keep_information
        return extraction != FORWARD or bool(asked)

    @classmethod
    def defaults(cls):
        """{field name: default} (a reduction's identity fills these in)."""
        return {f.name: f.default for f in dataclasses.fields(cls)}


@validation.checked_fields
@dataclass(frozen=True, eq=False)
class ForwardOptions:
    """Options of :func:`~slicersim.reduction.forward_extraction.extract_forward` (see its docstring).

    field : "narrow" or "wide";  lbda_edges : output bin edges [Å] (None: the native grid)
    position : (x, y) [native cells from the field centre] fixed, or None (fitted from ``start``)
    start : the fit's first position [native cells] (None: the field centre)
    background : fit a background uniform over the field;  psf_profile : the simulation's profile
    cell_scale : native cells per caller's cell (x, y), for the messages and the returned position
    """

    field: str = "narrow"
    lbda_edges: object = None
    position: tuple | None = None
    start: tuple | None = None
    background: bool = True
    psf_profile: str = "gaussian"
    cell_scale: tuple = (1.0, 1.0)

    def __post_init__(self):
        from slicersim.reduction.rectify_checks import angstrom
        validation.choice("field", self.field, ("narrow", "wide"))
        set_field(self, "lbda_edges", angstrom("lbda_edges", self.lbda_edges))
        set_field(self, "background", validation.flag("background", self.background))
        for name in ("position", "start"):
            value = getattr(self, name)
            if value is not None:
                set_field(self, name, pair(name, value))
        set_field(self, "cell_scale", pair("cell_scale", self.cell_scale, positive=True))


def _numbers(name, value):
    """``value`` as an array; a ragged sequence (numpy's ValueError) is a ParameterError naming it."""
    try:
        return np.asarray(value)
    except (ValueError, TypeError) as exc:
        raise ParameterError(f"{name} must be an array of numbers, got {type(value).__name__} ({exc})") from None


@validation.checked_fields
@dataclass(frozen=True, eq=False)
class PixelNoise:
    """The ramp fit's noise terms for the forward fit's model variance var_rnoise + k·max(model + dark, 0):
    read-noise and Poisson variances [(e-/s)²], the rate before the dark was subtracted [e-/s]
    ((H, W) images each) and the dark subtracted [e-/s] (a number or an image)."""

    var_rnoise: object
    var_poisson: object
    raw_rate: object
    dark_rate: object = 0.0

    def __post_init__(self):
        # real numbers: strings were numpy's ValueError in the fit, complex numbers lost their imaginary part;
        # a negative variance made the model variance negative: the fit ran all its iterations (64 s on a
        # test image), then "did not converge"
        for name, unit, variance in (("var_rnoise", "(e-/s)²", True), ("var_poisson", "(e-/s)²", True),
                                     ("raw_rate", "e-/s", False), ("dark_rate", "e-/s", False)):
            value = _numbers(name, getattr(self, name))
            if value.dtype.kind not in "biuf":
                raise ParameterError(f"{name} must be real numbers [{unit}], got {value.dtype}")
            with np.errstate(invalid="ignore"):
                if variance and np.any(value < 0):
                    raise ParameterError(f"{name} must be ≥ 0 [{unit}] (NaN or inf where a pixel has no "
                                         f"rate), got a minimum of {float(np.nanmin(value)):g}")
