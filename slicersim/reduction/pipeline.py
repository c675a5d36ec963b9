"""End-to-end reduction of one exposure: raw ramps → rates → rectified cube → point-source spectrum.

:func:`reduce_exposure` chains :func:`~slicersim.reduction.ramp_fit.fit_ramps`,
:func:`~slicersim.reduction.rectify.rectify` (weighted by the ramp-fit variance; pixels without
a rate — DO_NOT_USE, non-finite or non-positive variance — get variance +inf) and
:func:`~slicersim.reduction.spectra.extract_spectrum`, and writes the three products to one HDF5
file (atomic) when ``out`` is given:

| group | datasets |
|---|---|
| ``rates/`` | RATE, VAR, VAR_POISSON, VAR_RNOISE [e-/s, e-²/s²], DQ, NJUMPS (TRUTH_RATE with the truth; DARK_SUBTRACTED, an image dark) |
| ``cubes/<field>/`` | FLUX, VAR (nλ, slices, columns) [e-/s per cell per bin], LBDA, LBDA_EDGES [Å] |
| ``spectra/<field>/`` | FLUX, VAR [e-/s per bin], LBDA, LBDA_EDGES, PSF_SIGMA, BACKGROUND, ... |
| ``truth/target`` | the raw file's target truth, when it has one (:mod:`slicersim.io.target_truth`) |
"""
from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass

import numpy as np

from slicersim.backends.precision import float64_kwargs
from slicersim.errors import ParameterError, RampFileError, ReductionError, SlicersimError
from slicersim.io.atomic import AtomicH5File
from slicersim.reduction.checks import (FORWARD, check_raw_attrs, check_spectra_options, dark_rate_of,
                                        default_lbda_edges)
from slicersim.reduction.option_forms import build_options
from slicersim.reduction.options import ReduceOptions
from slicersim.reduction.ramp_sources import check_source

__all__ = ["reduce_exposure", "ReduceOptions", "default_lbda_edges", "check_forward_fit", "check_spectrum_has_signal",
           "SUSPECT_CHI2_DOF", "SUSPECT_NOISE_LEVEL", "noise_scale"]

_DO_NOT_USE = 1


def rate_variance(rates):
    """Per-pixel variance [e-²/s²] for rectification: the ramp-fit variance, +inf where the pixel
    has no usable rate (DO_NOT_USE, non-finite rate or variance, variance ≤ 0)."""
    var = np.array(rates.variance, dtype=np.float64)
    good = var > 0                                   # False for NaN too
    good &= np.isfinite(var)
    good &= np.isfinite(rates.rate)
    good &= (np.asarray(rates.dq) & _DO_NOT_USE) == 0
    var[~good] = np.inf
    return var


#: most columns per slice of the cubes whose model image gives the "model" weights (reduce_exposure):
#: Lazuli's cells are 116 columns wide per slice, so on 58 columns a cell averages about two pixels
#: along the slice.  With the model taken on the data's own 116 columns the weights followed the
#: noise: a Lazuli SN Ia at z = 0.8 came out −2.9 ± 0.7 % low against exact weights (3 paired
#: realisations, ``benchmarks/closed_loop_bias.py --ncol 116``); the first pass on 58 columns fixes that
MODEL_NCOL = 58


def model_variance(rates, var, cubes, mapper, lbda_edges, dark_rate=0.0):
    """Pixel variance [e-²/s²] from the model image instead of each pixel's own rate.

    The ramp fit's Poisson variance is ∝ the pixel's own noisy rate, so an upward fluctuation
    weighs less in the rectification and fluxes come out low (the Poisson-weighting bias:
    −2.1 ± 0.5 % on a Lazuli SN Ia at z = 0.3, −0.4 ± 0.4 % with these weights).  Here
    var = var_rnoise + k·max(m + dark, 0), with m = P x̂ the image of the first cubes (smooth: fewer
    cells than pixels), ``dark_rate`` [e-/s] what was subtracted before rectification (its charge is
    in the Poisson noise) and k = var_poisson / rate the pixel's Poisson variance per unit rate
    (the median k where the rate is ≤ 0); pixels no cube reaches and unusable ones keep ``var``."""
    m = np.zeros(tuple(mapper.detector_shape))
    for name, cube in cubes.items():
        mapper.project_fields(np.asarray(cube.lbda), lbda_edges, out=m, **{name: np.nan_to_num(np.asarray(cube.flux))},
                              **float64_kwargs())
    rate = np.asarray(rates.rate, float)
    vp = np.asarray(rates.var_poisson, float)
    ok = np.isfinite(var) & np.isfinite(vp) & (vp > 0) & (rate > 0)
    if not ok.any():
        return var
    k = np.where(ok, vp / np.where(ok, rate, 1.0), np.median(vp[ok] / rate[ok]))
    out = np.asarray(rates.var_rnoise, float) + k * np.maximum(m + dark_rate, 0.0)
    keep = ~np.isfinite(var) | (m == 0) | ~np.isfinite(out) | ~(out > 0)
    return np.where(keep, var, out)


def forward_model_cubes(cubes, spectra, psf=None):
    """The extraction's own model of each cube, F̂_λ P_λ + B̂_λ [the cube's unit]: the point source
    (a template's Σ_k F̂_k T_k, a given PSF, or the Gaussian fitted on the cube: ``spectrum.psf_sigma``
    at ``spectrum.position``) on its uniform background.  Its noise is that of 2 nλ fitted numbers,
    not of every cell.  Returns {field: SimpleNamespace(lbda, flux)} for :func:`model_variance`."""
    from types import SimpleNamespace

    from slicersim.reduction.spectrum_product import _gaussian_field
    out = {}
    for name, cube in cubes.items():
        sp = spectra[name]
        shape = np.shape(cube.flux)[-3:]
        f = np.asarray(sp.flux, float)
        given = None if psf is None or isinstance(psf, str) else np.asarray(psf, float)
        if given is not None and given.ndim == 4:                      # template: Σ_k F_k T_k
            model = np.tensordot(f, given, axes=1)
        else:
            P = given if given is not None else _gaussian_field(shape[1:], sp.psf_sigma[:, 0], sp.psf_sigma[:, 1],
                                                                sp.position)
            model = f[:, None, None] * P
        if sp.background is not None:
            model = model + np.asarray(sp.background, float)[:, None, None]
        out[name] = SimpleNamespace(lbda=np.asarray(cube.lbda), flux=model)
    return out


def reduce_exposure(raw_path, options=None, *, out=None, overwrite=False, **keywords):
    """Reduce one raw exposure to rates, cube(s) and spectra.

    Parameters
    ----------
    raw_path : str, path-like or tuple
        Ramp file (our HDF5 or JWST level-1b) or the arrays ``fit_ramps`` accepts.
    options : ReduceOptions, optional
        A :class:`~slicersim.reduction.options.ReduceOptions` (None: its defaults); the
        keywords below are its fields and replace those of ``options``
        (``reduce_exposure(raw, ncol=116)`` is ``reduce_exposure(raw, ReduceOptions(ncol=116))``).
    out : str or path-like, optional
        HDF5 path written atomically with all three products (module docstring).
    overwrite : bool, optional
        Replace ``out``.
    mapper : SlicerMapper, optional
        Default ``SlicerMapper.default()``.
    field : {"narrow", "wide", "both"}, optional
        The field(s) reduced.
    lbda_edges : array_like of shape (nλ+1,), optional
        Rectification λ edges [Å] (default ``default_lbda_edges``: 2 native bins).
    ncol : int, optional
        Columns per slice.
    rectify_method : {"lsq", "drizzle"}, optional
        Rectification method.
    weights : {"forward", "model", "data"}, optional
        None (default): "forward" for an lsq cube, "data" for drizzle (which has no other).
        "forward" (lsq): rectify a second time with the pixel variance (``model_variance``) of
        the image of the first extraction's own model F̂_λ P_λ + B̂_λ (``forward_model_cubes``;
        GLS on first cubes of ``ncol`` columns): weights almost free of noise — a Lazuli SN Ia
        at z = 0.8 on 116 columns: pipeline − exact weights 0.20 % per realisation (0.88 %
        with "model"), bias −0.08 ± 0.06 %, long-band SNR 1.007 ± 0.008 of the ETC.  It models
        a point source on a uniform background, as the extraction does.  With light it lacks
        (e.g. a host galaxy) the extraction's own model is wrong anyway, and its result then
        depends on the weights: +0.2–0.4 % against exact weights on the test layout with a
        host of half the point source's flux (model weights: < 0.1 %); use "model" for such
        scenes.  "model": the same with the image of the first cubes themselves (first pass
        on min(ncol, MODEL_NCOL) columns; follows any scene, noisier).  "data": the ramp fit's
        own per-pixel variance only (Poisson-weighting bias).
    dark : {"auto"}, float, numpy.ndarray of shape (ny, nx) or None, optional
        Dark rate subtracted from the rates before rectification (``dark_rate_of``): "auto"
        (default) the file's DARK_RATE plus, where the file records its bad pixels
        (``truth/bad_pixels/extra_dark``), the warm and hot pixels' extra dark seen through IPC
        (the per-pixel dark of its reference files); a number or an image [e-/s]; None for none
        (written: DARK_SUBTRACTED [e-/s, the image's mean], DARK_SUBTRACTED_KIND, and an image
        given as rates/DARK_SUBTRACTED).  A pedestal that is uniform over the pixels is not uniform
        over the cells (pixel coverage varies across a slice), so the cube's background B_λ
        cannot absorb it: left in, the dark biased a Lazuli SN Ia at z = 0.8 by −2.0 %
        (noiseless, exact weights).
    extraction : {"forward", "gls", "optimal", "aperture"}, optional
        None (default): "forward" when the instrument is known (the file's CONFIG, or
        ``config``): the point source fitted on the detector pixels with the configuration's
        own PSF, LSF and projection (``slicersim.reduction.forward_extraction.extract_forward``;
        unbiased whatever the cube's grid, position fitted); otherwise, with a warning, the
        cube extraction "gls" (LSQ cube) or "optimal" (drizzle).  Explicit "gls", "optimal",
        "aperture": an ``extract_spectrum`` method on the cube; with a Gaussian PSF fitted on
        the cube (``psf="fit"``) they are refused when the instrument is known, since the
        coarse cells bias them (−3 % on a noiseless Lazuli SN Ia at z = 0.5 even with the true
        PSF): give ``psf`` a forward-modelled template
        (``slicersim.reduction.templates.point_source_template``).
    cubes : bool, optional
        Rectify the cube(s) too.  None (default): when the extraction needs them (a cube
        extraction) or a cube option (``rectify_method``, ``weights``, ``keep_information``) is
        given; not beside the default forward extraction, whose spectrum comes from the pixels
        (the cube was ~30 % of a full-detector reduction's CPU time and played no part in its
        spectrum; ``benchmarks/reduce_spectra_speed.py``).  Without cubes the file has no
        ``cubes/`` group and no ``rates/RECTIFY_VAR``.
    config : str, path-like or list, optional
        Instrument configuration of the forward model (a name, TOML path or list, as
        :func:`~slicersim.load_config`); None: the one the file records.
    ipc : bool, optional
        Deconvolve the rates by the file's inter-pixel capacitance kernel before
        rectification and extraction (``slicersim.reduction.ipc_correction``): None (default)
        when the file records the IPC effect, False never.
    psf, position, aperture, background
        ``extract_spectrum`` options.
    propagate : bool, optional
        "optimal" / "aperture" on an LSQ cube: spectrum variance with the full cube covariance
        (``propagate_variance``; the cells-independent sum is kept as
        ``diagnostics["variance_diagonal"]``).
    keep_information : bool, optional
        Keep the LSQ cube's inverse covariance from the rectification (rectify's
        ``keep_information``: faster GLS, memory ``InverseCovariance.nbytes``) instead of
        rebuilding it for the extraction.
    fit_options : dict, optional
        Keyword arguments of ``fit_ramps`` (refpix, linearity, jump_threshold, weighting, ...).

    Returns
    -------
    dict
        ``"rates"``: the RateProduct; ``"rate"``: the rate image rectified and extracted
        [e-/s] (dark subtracted, IPC deconvolved, 0 where unusable); ``"cubes"``: {field:
        CubeProduct}; ``"spectra"``: {field: SpectrumProduct}; ``"variance"``: the pixel
        variance the cubes were rectified with; ``"dark_rate"``: the dark subtracted;
        ``"dark_kind"``: how it was chosen; ``"noise_information"``: {field: B} for the
        sandwich variance of a GLS extraction or of ``propagate_variance`` on model-weighted
        cubes (``slicersim.reduction.rectify.noise_information``; empty otherwise); and
        ``"path"``, the absolute path written, with ``out``.
    """
    check_source(raw_path, "reduce_exposure raw_path")
    opts = build_options(ReduceOptions, options, keywords, "reduce_exposure")
    plan = _plan(raw_path, opts, out, overwrite)            # every option checked before any data are read
    rates, rate, var = _fit_rates(raw_path, plan)
    if plan.extraction == FORWARD:
        result = _reduce_forward(rates, rate, var, plan)
    else:
        result = _reduce_cube(rates, rate, var, plan)
    if isinstance(raw_path, (str, os.PathLike)):          # the target's truth travels with its spectrum
        from slicersim.io.target_truth import read_target_truth
        result["target"] = read_target_truth(raw_path)
    if plan.writer is not None:
        result["path"] = _write(plan.writer, result)
    return result


@dataclass
class _Plan:
    """What :func:`reduce_exposure` decides before reading the ramps (and the dark it subtracts)."""

    opts: ReduceOptions
    raw_attrs: dict | None
    model: dict | None            # the forward model's instrument (None: unknown)
    field: str                    # "narrow", "wide" or "both"
    extraction: str
    weights: str
    mapper: object
    edges: np.ndarray             # rectification λ edges [Å]
    writer: object = None
    dark_rate: object = 0.0       # [e-/s]: a number or an image
    dark_kind: str = "none"
    cubes: bool = True            # rectify the cube(s) (ReduceOptions.resolved_cubes)


def _plan(raw_path, opts, out, overwrite):
    """Read the raw file's keywords and its instrument; resolve field, extraction and weights; check
    every option against them and refuse the output file before any work."""
    from slicersim.reduction.rectify import FIELDS, _default_mapper
    raw_attrs = _raw_attrs(raw_path)
    if raw_attrs is not None:                     # GAIN = 1e-300, DARK = NaN, a corrupt EFFECTS: named here
        fit = opts.fit_options or {}
        check_raw_attrs(raw_attrs, raw_path if isinstance(raw_path, (str, os.PathLike)) else "the ramps' attrs",
                        gain=fit.get("gain"), ron=fit.get("ron", fit.get("read_noise")))
    model = _instrument(raw_attrs, opts.config, opts.extraction, opts.psf)
    field = opts.field
    if field is None:                                  # the field the file was simulated in
        recorded = (model or {}).get("field") or _recorded_field(raw_attrs)
        field = recorded if recorded in FIELDS else "narrow"
    extraction = opts.default_extraction(model)
    check_spectra_options(mapper=opts.mapper, field=field, lbda_edges=opts.lbda_edges, ncol=opts.ncol,
                          rectify_method=opts.rectify_method, extraction=extraction, psf=opts.psf,
                          position=opts.position, aperture=None if extraction in ("gls", FORWARD) else opts.aperture,
                          background=opts.background, weights=opts.weights, cubes=opts.cubes)
    writer = None
    if out is not None:                                           # refuse before any work
        writer = _Writer(out, overwrite=overwrite)
        writer.check()
    mapper = _default_mapper() if opts.mapper is None else opts.mapper
    if not (isinstance(opts.dark, str) and opts.dark == "auto"):           # checked before the ramps are read
        dark_rate_of(opts.dark, None, mapper.detector_shape)
    edges = default_lbda_edges(mapper) if opts.lbda_edges is None else np.asarray(opts.lbda_edges, float)
    return _Plan(opts, raw_attrs, model, field, extraction, opts.resolved_weights(), mapper, edges, writer,
                 cubes=opts.resolved_cubes(extraction))


def _fit_rates(raw_path, plan):
    """Ramps → (RateProduct, rate, var): the fitted rates, the rate image rectified and extracted
    [e-/s] (dark subtracted, IPC deconvolved when the file records it, 0 where unusable) and the
    pixel variance [(e-/s)²] (+inf where unusable); the dark subtracted is kept in ``plan``."""
    from slicersim.reduction.ramp_fit import fit_ramps, fitted_rows
    shape = tuple(plan.mapper.detector_shape)
    rates = fit_ramps(raw_path, **(plan.opts.fit_options or {}))
    if rates.rate.shape != shape:
        raise ParameterError(f"mapper: the rate image {rates.rate.shape} is not the mapper's detector {shape}")
    plan.dark_rate, plan.dark_kind = dark_rate_of(plan.opts.dark, rates, shape)
    var = rate_variance(rates)
    kernel = None
    if plan.opts.ipc is None:
        from slicersim.reduction.ipc_correction import ipc_kernel_of
        kernel = ipc_kernel_of(plan.raw_attrs)
    # a ramp of some rows (a streaming campaign's): the per-pixel steps on those rows only, range by range
    rows = fitted_rows(rates)
    if plan.dark_kind == "file DARK_RATE":
        from slicersim.reduction.dark import extra_dark, ipc_kernel_seen
        # the per-pixel part of the detector's dark, through IPC whether or not the rates are deconvolved
        extra = extra_dark(raw_path, shape, kernel if plan.opts.ipc is None else ipc_kernel_seen(plan.raw_attrs),
                           rows=rows)
        if extra is not None:
            plan.dark_rate, plan.dark_kind = plan.dark_rate + extra, "file DARK_RATE + bad pixels' extra dark"
    rate = np.subtract(rates.rate, plan.dark_rate)          # one image, no temporaries (first touches are dear)
    rate[~np.isfinite(var)] = 0.0
    if kernel is not None:
        from slicersim.reduction.ipc_correction import deconvolve_ipc
        usable = np.isfinite(var)
        if rows is None:
            rate = deconvolve_ipc(rate, usable, kernel)
        else:
            for y0, y1 in rows:
                rate[y0:y1] = deconvolve_ipc(rate[y0:y1], usable[y0:y1], kernel)
    rates.attrs["IPC_CORRECTED"] = kernel is not None
    return rates, rate, var


def _rectify(rate, var, plan, ncol, keep_information):
    """rectify() into {field: CubeProduct} on the plan's grid (looked up at each call: tests record it)."""
    from slicersim.reduction.rectify import rectify
    cubes = rectify(rate, var, mapper=plan.mapper, field=plan.field, lbda_edges=plan.edges, ncol=ncol,
                    method=plan.opts.rectify_method or "lsq", keep_information=bool(keep_information))
    return cubes if plan.field == "both" else {plan.field: cubes}


def _result(rates, rate, cubes, spectra, var, noise, plan):
    for name, spec in (spectra or {}).items():           # every extraction method: no all-NaN spectrum
        check_spectrum_has_signal(spec, name, plan.dark_rate)
    return {"rates": rates, "rate": rate, "cubes": cubes, "spectra": spectra, "variance": var,
            "dark_rate": plan.dark_rate, "dark_kind": plan.dark_kind, "noise_information": noise,
            "weights": plan.weights}


def _reduce_cube(rates, rate, var, plan):
    """reduce_exposure with a cube extraction: cubes weighted as asked, then spectra from them."""
    cubes, var_cube = _weighted_cubes(rates, rate, var, plan)
    spectra, noise = _cube_spectra(cubes, var_cube, var, plan)
    return _result(rates, rate, cubes, spectra, var_cube, noise, plan)


def _weighted_cubes(rates, rate, var, plan):
    """The cubes and the pixel variance they were rectified with: the data's own (weights "data",
    drizzle), or a second pass weighted by the image of the first cubes ("model") or of the first
    extraction's own model ("forward")."""
    opts = plan.opts
    model_pass = plan.weights in ("model", "forward") and opts.lsq
    forward = model_pass and plan.weights == "forward"
    # the model weights' first pass on at most MODEL_NCOL columns: on a finer grid a cell holds about
    # one pixel, its model image follows the pixels' noise and the Poisson-weighting bias returns
    # (the forward model is fitted, not cell by cell: its first pass keeps ncol)
    ncol_first = min(opts.ncol, MODEL_NCOL) if model_pass and not forward else opts.ncol
    cubes = _rectify(rate, var, plan, ncol_first, opts.keep_information and ncol_first == opts.ncol)
    if not model_pass:
        return cubes, var
    if forward:
        from slicersim.reduction.spectra import extract_spectrum
        first = {name: extract_spectrum(cube, method="gls", psf=opts.psf, position=opts.position,
                                        background=opts.background) for name, cube in cubes.items()}
        cubes = forward_model_cubes(cubes, first, opts.psf)
    var = model_variance(rates, var, cubes, plan.mapper, plan.edges, plan.dark_rate)
    return _rectify(rate, var, plan, opts.ncol, opts.keep_information), var


def _cube_spectra(cubes, var, var_data, plan):
    """Spectra of the cubes ({field: SpectrumProduct}) and the noise information of model-weighted
    cubes ({field: B}, for the sandwich variance); "optimal" / "aperture" on an lsq cube get the full
    cube covariance (``propagate``)."""
    from slicersim.reduction.spectra import extract_spectrum, propagate_variance
    opts, extraction = plan.opts, plan.extraction
    propagate = opts.propagate and opts.lsq
    noise = {}
    if var is not var_data and (extraction == "gls" or propagate):
        # the model image misses the point source's sharp core (the coarse cells smooth it): its
        # variance is ~16 % low on the brightest pixels (Lazuli SN Ia z = 0.3), so (MᵀNM)⁻¹ would
        # under-report; the sandwich with the data's own variance (unbiased) is exact for the
        # weights used
        from slicersim.reduction.rectify import noise_information
        noise = {name: noise_information(cube.inverse_covariance, var_data) for name, cube in cubes.items()}
    gls_noise = noise if extraction == "gls" else {}
    spectra = {name: extract_spectrum(cube, method=extraction, psf=opts.psf, position=opts.position,
                                      aperture=opts.aperture, background=opts.background,
                                      **({"noise_information": gls_noise[name]} if gls_noise else {}))
               for name, cube in cubes.items()}
    if propagate and extraction != "gls":
        for name, spec in spectra.items():
            spec.diagnostics["variance_diagonal"] = spec.variance
            spec.variance = propagate_variance(spec, cubes[name], noise_information=noise.get(name))
            spec.diagnostics["variance_model"] = ("full LSQ cube covariance (propagate_variance)" if not noise else
                                                  "full LSQ cube covariance, sandwich N⁻¹BN⁻¹ with the pixels' "
                                                  "variance (propagate_variance)")
    return spectra, noise


def _raw_attrs(raw_path):
    """The raw file's keywords (CONFIG, EFFECTS, ...); None when it cannot be read (fit_ramps then says why)."""
    if isinstance(raw_path, (str, os.PathLike)):
        if not os.path.isfile(raw_path):
            return None
        from slicersim.reduction.ramp_fit import open_ramps
        try:
            with open_ramps(raw_path) as src:
                return dict(src.attrs)
        except (SlicersimError, OSError):
            return None
    if isinstance(raw_path, (tuple, list)) and len(raw_path) == 4 and isinstance(raw_path[3], dict):
        return dict(raw_path[3])
    return None


def _recorded_field(attrs):
    """The field a raw file's CONFIG names (None if none or unreadable)."""
    try:
        from slicersim.reduction.forward_extraction import model_config
        return (model_config(attrs, "cbe") or {}).get("field")
    except SlicersimError:
        return None


def _instrument(attrs, config, extraction, psf):
    """The forward model's instrument (:func:`~slicersim.reduction.forward_extraction.model_config`) of
    this file, loaded (a bad configuration is refused before any data are read), or None; refuses the
    combinations that cannot give an unbiased spectrum (``config`` and ``extraction`` are checked
    values: :class:`~slicersim.reduction.options.ReduceOptions`)."""
    from slicersim.reduction.forward_extraction import FORWARD_PSF_PROFILES, instrument_model, model_config
    if attrs is None:                                 # unreadable: fit_ramps will say why
        attrs, unreadable = {}, True
    else:
        unreadable = False
    model = model_config(attrs, config)
    given_psf = psf is not None and not isinstance(psf, str)
    if model is not None and model["psf_profile"] not in FORWARD_PSF_PROFILES:
        if extraction == FORWARD:
            raise ParameterError(f"the file's PSF profile {model['psf_profile']!r} has no forward model "
                                 f"({', '.join(FORWARD_PSF_PROFILES)}): extract from the cube with a PSF of your "
                                 "own (extraction='gls', psf=FILE; CLI --extraction gls --psf FILE.npy)")
        model = None
    if extraction == FORWARD:
        if model is None:
            raise ParameterError("extraction 'forward' needs the instrument configuration: the file records none "
                                 "(its CONFIG keyword); give config= (CLI: --config cbe|eol|PATH)")
        if given_psf:
            raise ParameterError("psf= (a PSF on the cube's cells) is for the cube extractions; 'forward' uses the "
                                 "configuration's own PSF on the pixels")
    elif extraction is None:
        if model is None and not unreadable:
            warnings.warn("no instrument configuration (the file records none): the spectrum is extracted from the "
                          "cube with a PSF fitted on its coarse cells, which biases it (+5 to +8 % on a Lazuli SN Ia "
                          "at z = 0.5); give config= (CLI: --config) for the forward-model extraction",
                          RuntimeWarning, stacklevel=4)
        elif given_psf:
            return None                                  # the user's PSF: the cube extraction it was made for
    elif model is not None and not given_psf:
        raise ParameterError(f"extraction {extraction!r} with a Gaussian PSF fitted on the cube is biased by the "
                             "coarse cells (−3 % on a noiseless Lazuli SN Ia at z = 0.5 even with the true PSF): "
                             "use the default extraction 'forward' (fitted on the pixels), or give a "
                             "forward-modelled template (psf=point_source_template(...); CLI --psf FILE.npy)")
    if model is None or extraction not in (None, FORWARD):
        return model
    where = "the configuration given" if config is not None else "the file's CONFIG"
    try:
        instrument_model(model["config"], model["field"] or "narrow", model["conventions"])
    except (OSError, ValueError) as exc:
        from slicersim.io.atomic import one_line
        raise ParameterError(f"{where} ({model['config']!r}) cannot be loaded: {one_line(exc)}"
                             + ("" if config is not None else "; give config= (CLI --config cbe|eol|PATH)")) from None
    if config is not None and model["recorded"] not in (None, "") and str(config) != str(model["recorded"]):
        warnings.warn(f"the file was simulated with the configuration {model['recorded']!r}; its spectrum is fitted "
                      f"with {config!r} as asked (throughput, QE and PSF differ: so do flux and F_λ)",
                      RuntimeWarning, stacklevel=4)      # after the load: no warning before an error
    return model


def _reduce_forward(rates, rate, var, plan):
    """reduce_exposure with the forward-model extraction: spectra from the pixels, then the cube(s),
    weighted (lsq, ``weights="forward"``) by the fitted model's pixel variance."""
    from slicersim.reduction.rectify import FIELDS
    names = list(FIELDS) if plan.field == "both" else [plan.field]
    spectra, var_cube, missing = {}, np.array(var, copy=True), []
    forward_weights = plan.weights == "forward" and plan.opts.lsq
    for name in names:
        spec = _forward_field(name, rates, rate, var, plan)
        if isinstance(spec, str):
            missing.append(spec)
            continue
        if forward_weights:
            d = spec.diagnostics
            var_cube.ravel()[d["pixel_index"]] = d["pixel_variance"]
        spectra[name] = spec
    if missing and not spectra:
        raise ReductionError("; ".join(missing) + " (recorded field: "
                             f"{plan.model.get('field') or 'none'}); give position= (CLI --position) to extract "
                             "there anyway, or field= (CLI --field) for the other field")
    for text in missing:                                          # field="both": the other field is empty
        warnings.warn(text + ": no spectrum for it", RuntimeWarning, stacklevel=3)
    cube_var = var_cube if forward_weights else var
    cubes = _rectify(rate, cube_var, plan, plan.opts.ncol, plan.opts.keep_information) if plan.cubes else {}
    result = _result(rates, rate, cubes, spectra, cube_var, {}, plan)
    result.update(instrument=plan.model, raw_config=(plan.raw_attrs or {}).get("CONFIG"))
    return result


def _forward_field(name, rates, rate, var, plan):
    """The forward fit of one field (a SpectrumProduct, checked by :func:`check_forward_fit`), or the
    reason there is none (a str: no significant point source and no ``position`` given)."""
    from slicersim.reduction.forward_extraction import MIN_DETECTION, extract_forward, instrument_model
    from slicersim.reduction.white_light import white_light_start
    from slicersim.reduction.options import ForwardOptions, PixelNoise
    from slicersim.reduction.rectify import FIELDS
    model, position = plan.model, plan.opts.position
    sim = instrument_model(model["config"], name, model["conventions"])
    ny, nx = sim.spectrograph.shape
    scale = (nx / plan.opts.ncol, 1.0)                                 # native cells per cube cell (x, y)
    fixed = None if position is None else (position[0] * scale[0], position[1] * scale[1])
    start = None
    tables = plan.mapper.projection_tables(FIELDS[name], nx, sim.spectrograph.lbda_edges)
    if fixed is None:
        start, signif = white_light_start(rate, var, tables)
        if not signif >= MIN_DETECTION:
            return (f"no point source in the {name} field: the brightest white light is "
                    f"{signif:.1f} σ above the field's scatter (< {MIN_DETECTION:g} σ)")
    options = ForwardOptions(field=name, lbda_edges=plan.edges, position=fixed, start=start,
                             background=plan.opts.background, psf_profile=model["psf_profile"], cell_scale=scale)
    noise = PixelNoise(rates.var_rnoise, rates.var_poisson, rates.rate, plan.dark_rate)
    spec = extract_forward(rate, var, options, sim=sim, mapper=plan.mapper, noise=noise)
    check_forward_fit(spec, rate, var, tables, name, forced=fixed is not None)
    return spec


#: units of the written datasets (attribute BUNIT on every dataset; e- are photo-electrons, rates are
#: slopes: charge per second of integration time)
UNITS = {"RATE": "e-/s", "VAR": "(e-/s)^2", "LBDA": "Angstrom", "FLAMBDA": "erg/s/cm^2/Angstrom",
         "VAR_FLAMBDA": "(erg/s/cm^2/Angstrom)^2"}
RATE_UNITS = {"RATE": "e-/s", "VAR": "(e-/s)^2", "VAR_POISSON": "(e-/s)^2", "VAR_RNOISE": "(e-/s)^2",
              "DQ": "flags", "NJUMPS": "count"}
SPECTRUM_UNITS = {"LBDA": "Angstrom", "LBDA_EDGES": "Angstrom", "FLUX": "e-/s per bin", "VAR": "(e-/s per bin)^2",
                  "PSF_SIGMA": "cell", "BACKGROUND": "e-/s per cell per bin", "BACKGROUND_VAR": "(e-/s per cell per bin)^2",
                  "ENCLOSED_ENERGY": "fraction"}


#: pixel χ²/dof above which a forward fit is flagged, in units of the noise level measured on the fit's own
#: pixels when that is above the ramp fit's variance (:func:`noise_scale`: correlated read noise and the
#: other detector effects raise every pixel's scatter, not the model's misfit).  Single point sources give
#: χ²/dof ÷ noise level 1.001 (white noise) and 1.003 (``effects = "lazuli"``, χ²/dof 1.34); two sources
#: 4–20 cells apart gave χ²/dof 1.036–1.038 on white noise
SUSPECT_CHI2_DOF = 1.02
#: noise level (:func:`noise_scale`) above which a forward fit is flagged for errors that are too small: the
#: pixels scatter more than the ramp fit's variance says (1.003 measured on a white-noise ramp; 1.34 with
#: ``effects = "lazuli"``, whose correlated noise makes spectra scatter 2.5× their reported errors)
SUSPECT_NOISE_LEVEL = 1.02
#: the central fraction of the normalised residuals whose mean square measures the noise level
_NOISE_CORE = 0.999


def noise_scale(residual, variance):
    """The pixels' noise level in units of their variance: the mean of z² = residual² / variance over the
    central ``_NOISE_CORE`` of |z|, divided by its value for Gaussian noise (1 for noise as the ramp fit
    says; the few pixels a second source or a misfit lights up fall outside the core).

    Parameters
    ----------
    residual : numpy.ndarray of shape (N,)
        Data − model of the fitted pixels [e-/s] (0 for rejected pixels, left out).
    variance : numpy.ndarray of shape (N,)
        Their variance [(e-/s)²] (+inf for rejected pixels, left out).

    Returns
    -------
    float
        The noise level (≈ 1 for the ramp fit's noise; 0 without usable pixels).
    """
    from scipy.special import ndtri                 # not scipy.stats: its import costs 0.6 s per reduction
    r, v = np.asarray(residual, float), np.asarray(variance, float)
    ok = np.isfinite(v) & (v > 0) & (r != 0)
    if not ok.any():
        return 0.0
    z2 = r[ok] ** 2 / v[ok]
    cut = np.quantile(z2, _NOISE_CORE)
    q = float(ndtri(0.5 + _NOISE_CORE / 2))
    pdf = np.exp(-0.5 * q * q) / np.sqrt(2.0 * np.pi)
    gaussian = 1.0 - 2.0 * q * pdf / _NOISE_CORE                 # E[z² | |z| ≤ q] for N(0, 1)
    return float(np.mean(z2[z2 <= cut]) / gaussian)


def check_spectrum_has_signal(spec, name, dark_rate=0.0):
    """Refuse (ReductionError naming the likely cause) a spectrum without one finite bin: writing it would be
    exit 0 with every F_λ NaN (``--dark 1e6`` removed all the signal, or every pixel of the source is flagged)."""
    flux = np.asarray(spec.flux, float)
    if np.isfinite(flux).any():
        return
    dark = float(np.median(dark_rate)) if np.size(dark_rate) else 0.0     # a typical pixel's, not a hot pixel's
    cause = (f"the dark rate subtracted ({dark:g} e-/s per pixel) exceeds the signal everywhere: check --dark"
             if dark > 0 else "every pixel of the source is flagged (saturated or bad) or has no variance")
    raise ReductionError(f"the {name} field's spectrum has no finite bin: {cause}")


def check_forward_fit(spec, rate, var, tables, name, forced=False):
    """Warn and flag (``diagnostics["warnings"]``, written in SPECTRUM_<FIELD>) a forward fit whose
    pixels are not explained: χ²/dof above :data:`SUSPECT_CHI2_DOF` times the noise level of its own
    pixels (:func:`noise_scale`, at least 1; kept as ``diagnostics["noise_scale"]``); pixels that scatter
    more than their variance (noise level above :data:`SUSPECT_NOISE_LEVEL`: the errors are too small); or light left in its residual
    image (a second source ≥ 5 σ in white light).  With a ``forced`` position the residual is searched
    over the whole field (a source elsewhere, e.g. the SN the position missed, is light left), and a
    spectrum whose band total is below 5 σ is flagged: nothing significant at the position given."""
    from slicersim.reduction.forward_extraction import MIN_DETECTION
    from slicersim.reduction.white_light import white_light_start
    d = spec.diagnostics
    flags = []
    d["noise_scale"] = level = noise_scale(d["residual"], d["pixel_variance"])
    if d["chi2_dof"] > SUSPECT_CHI2_DOF * max(level, 1.0):
        flags.append(f"pixel χ²/dof {d['chi2_dof']:.3f} > {SUSPECT_CHI2_DOF} × the pixels' noise level "
                     f"{max(level, 1.0):.3f} (the model does not explain the data: another source, extended light "
                     "or unmodelled detector effects)")
    if level > SUSPECT_NOISE_LEVEL:
        flags.append(f"the pixels scatter {level:.3f}× the ramp fit's variance (correlated read noise or other "
                     "noise the ramp fit does not model): the spectrum's reported errors are too small, by at "
                     f"least √{level:.3f} = {np.sqrt(level):.2f}× (more where the excess noise is correlated "
                     "between pixels)")
    resid = np.zeros(rate.shape)
    resid.ravel()[d["pixel_index"]] = d["residual"]
    (x, y), signif = white_light_start(resid, var, tables, rows=None if forced else d["rows"], noise_floor=True)
    if signif >= MIN_DETECTION:
        flags.append(f"light left at ({x:.1f}, {y:.1f}) native cells, {signif:.1f} σ in the residual's white "
                     "light (a second source?" + (" or the source the given position missed)" if forced else ")"))
    if forced:
        flux, variance = np.asarray(spec.flux, float), np.asarray(spec.variance, float)
        ok = np.isfinite(flux) & np.isfinite(variance) & (variance > 0)
        total = float(flux[ok].sum() / np.sqrt(variance[ok].sum())) if ok.any() else 0.0
        if not total >= MIN_DETECTION:
            flags.append(f"the spectrum at the given position totals {total:.1f} σ (< {MIN_DETECTION:g} σ): no "
                         "significant source there")
    d["warnings"] = flags
    for text in flags:
        warnings.warn(f"{name} field: {text}", RuntimeWarning, stacklevel=5)


def _fit_summary(spec):
    """The forward fit's convergence and goodness of fit, for the file's attributes."""
    d = spec.diagnostics
    if spec.method != FORWARD:
        return {}
    return {"position_native_cells": list(d["position_native_cells"]), "iterations": d["iterations"],
            "converged": bool(d["converged"]), "chi2_dof_pixels": d["chi2_dof"], "pixels": d["pixels"],
            "rejected_pixels": d.get("rejected_pixels", 0), "noise_scale": d.get("noise_scale"),
            "warnings": list(d.get("warnings", []))}


class _Writer(AtomicH5File):
    error_class = RampFileError


def _write(writer, result):
    rates = result["rates"]
    with writer as w:
        for name, data, options in rates.datasets():
            w.write(f"rates/{name}", data, attrs={"BUNIT": RATE_UNITS[name]}, **options)
        if rates.truth_rate is not None:                          # fit_options with_truth=True
            w.write("rates/TRUTH_RATE", rates.truth_rate, attrs={"BUNIT": UNITS["RATE"]})
        for name, cube in result["cubes"].items():
            w.write(f"cubes/{name}/FLUX", cube.flux, attrs={"BUNIT": f"{cube.unit} per cell per bin",
                                                            "METHOD": cube.method})
            if cube.variance is not None:
                w.write(f"cubes/{name}/VAR", cube.variance, attrs={"BUNIT": f"({cube.unit})^2 per cell per bin"})
            w.write(f"cubes/{name}/LBDA", cube.lbda, attrs={"BUNIT": UNITS["LBDA"]})
            w.write(f"cubes/{name}/LBDA_EDGES", cube.lbda_edges, attrs={"BUNIT": UNITS["LBDA"]})
            w.write(f"cubes/{name}/SLICE_OF_ROW", np.asarray(cube.slices), attrs={"BUNIT": "slice number"})
        for name, spec in result["spectra"].items():
            for key, arr in spec.arrays().items():
                w.write(f"spectra/{name}/{key}", arr, attrs={"BUNIT": SPECTRUM_UNITS[key]})
            if spec.method == FORWARD:                  # neighbouring bins share pixels: their covariance
                d = spec.diagnostics
                w.write(f"spectra/{name}/COVARIANCE", np.asarray(d["covariance"]),
                        attrs={"BUNIT": SPECTRUM_UNITS["VAR"]})
                w.write(f"spectra/{name}/FLUX_FLAMBDA", np.asarray(d["flambda"]), attrs={"BUNIT": UNITS["FLAMBDA"]})
                w.write(f"spectra/{name}/VAR_FLAMBDA", np.asarray(d["flambda_variance"]),
                        attrs={"BUNIT": UNITS["VAR_FLAMBDA"]})
        attrs = {k: (json.dumps(v) if isinstance(v, (dict, list, tuple)) else v)
                 for k, v in rates.attrs.items() if v is not None}
        attrs.update(PRODUCTS="rates,cubes,spectra" if result["cubes"] else "rates,spectra",
                     SPECTRUM_UNIT="e-/s per bin")
        dark = result.get("dark_rate", 0.0)
        attrs["DARK_SUBTRACTED"] = float(np.mean(dark))          # [e-/s]; the image's mean for an image
        attrs["DARK_SUBTRACTED_KIND"] = result.get("dark_kind", "none")
        if np.ndim(dark) == 2 and result.get("dark_kind") == "image":      # the file's own: read again from it
            w.write("rates/DARK_SUBTRACTED", np.asarray(dark, np.float64), attrs={"BUNIT": UNITS["RATE"]})
        attrs.update({f"SPECTRUM_{n.upper()}": json.dumps({"method": s.method, "position": list(s.position),
                                                          "aperture_sigma": s.aperture if np.isfinite(s.aperture)
                                                          else None,
                                                          **_fit_summary(s)})
                      for n, s in result["spectra"].items()})
        if result.get("instrument"):
            attrs["INSTRUMENT_MODEL"] = json.dumps(result["instrument"], default=str)
        if result.get("raw_config") is not None:
            attrs["RAW_CONFIG"] = result["raw_config"]
        # how the cubes were weighted, and the pixel variance they were rectified with (a template
        # must be built with the same: point_source_template(..., variance=))
        attrs["WEIGHTS"] = result.get("weights", "data")
        attrs["RECTIFY_METHOD"] = next(iter(result["cubes"].values())).method if result["cubes"] else "none"
        if result["cubes"]:
            var = np.asarray(result["variance"], np.float32)
            w.write("rates/RECTIFY_VAR", var, attrs={"BUNIT": UNITS["VAR"], "WEIGHTS": attrs["WEIGHTS"]})
        if result.get("target") is not None:
            from slicersim.io.target_truth import write_target_truth
            write_target_truth(w, result["target"])
        w.set_attrs(attrs)
    return os.path.abspath(os.fspath(writer.path))
