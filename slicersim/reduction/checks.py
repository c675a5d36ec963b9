"""Checks made before a reduction reads any data: the raw file, the readout keywords, the options.

:func:`check_ramp_file` refuses, with one :class:`~slicersim.errors.RampFileError` each, what
:func:`~slicersim.reduction.ramp_fit.fit_ramps` cannot reduce or would reduce wrongly, reading
headers only:

* files of another layout, named for what they are: a rates file or a reduced exposure (outputs
  of ``slicersim reduce``), a campaign spectrum / cube / detector-image product, a directory;
* an empty SCI, GROUPDQ or PIXELDQ of the wrong type, data compressed with an HDF5 filter this
  installation lacks (``hdf5plugin``), ``truth/rate`` missing or of the wrong shape when the
  truth is asked for;
* inconsistent readout keywords: those ``fit_ramps`` checks (NGROUPS, NINTS against SCI, TGROUP =
  (NFRAMES + GROUPGAP)·TFRAME, READPATT, missing or non-numeric keywords), and in files written by
  slicersim the timing keywords (FRMDIVSR = NFRAMES, EFFINTTM = (NGROUPS − 1)·TGROUP,
  TMEASURE = EFFINTTM·NINTS, EFFEXPTM = XPOSURE = TFRAME·(NGROUPS·NFRAMES + (NGROUPS − 1)·GROUPGAP
  + DRPFRMS1)·NINTS) and, in level-1b FITS, the ``SLICERSIM`` copies of the readout keywords
  against the JWST ones.

:func:`check_spectra_options` validates the options of
:func:`~slicersim.reduction.pipeline.reduce_exposure` (and the ``fit_ramps`` ones) the same way.
"""
from __future__ import annotations

import inspect
import math
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError, RampFileError
from slicersim.io.atomic import one_line

__all__ = ["check_ramp_file", "check_raw_attrs", "ATTR_RANGES", "check_spectra_options", "check_fit_options", "register_hdf5_filters",
           "MAX_NCOL", "DEFAULT_NCOL", "WEIGHTS", "FORWARD", "default_lbda_edges", "dark_rate_of"]

#: largest number of columns per slice accepted (a slice is 58 cells wide in the Lazuli design)
MAX_NCOL = 1024
#: columns per slice of reduce_exposure's cubes by default
DEFAULT_NCOL = 58
#: reduce_exposure's extraction on the detector pixels with the instrument's forward model
FORWARD = "forward"
#: reduce_exposure's lsq weights (see its docstring)
WEIGHTS = ("model", "forward", "data")
_READOUT_KEYS = ("NINTS", "NGROUPS", "NFRAMES", "GROUPGAP", "TFRAME", "TGROUP")
_TIMING_KEYS = ("FRMDIVSR", "EFFINTTM", "TMEASURE", "EFFEXPTM", "XPOSURE", "DURATION", "TELAPSE", "DRPFRMS1")


def register_hdf5_filters():
    """Make the compression filters of ``hdf5plugin`` (Blosc2/LZ4, Zstd, Bitshuffle: the
    campaigns' ramp compressions) readable in this process; False without the package."""
    try:
        import hdf5plugin  # noqa: F401  (registers the filters on import)
    except ImportError:
        return False
    return True


# ----------------------------------------------------------------------------- the raw file
def check_ramp_file(path, with_truth=False, gain=None, ron=None, detector_shape=None, **renamed):
    """Refuse (RampFileError) a raw ramp file the reduction cannot use; headers only.

    with_truth : ``truth/rate`` must exist with the detector's shape
    gain, ron : overrides of the file's GAIN [DN/e-] / READNOISE [electron] (as ``fit_ramps``; ``read_noise``:
        the deprecated name of ``ron``)
    detector_shape : (ny, nx) the data must have (the mapper's detector, for spectra)

    Returns {"kind", "shape" (nints, ngroups, ny, nx), "nmd", "tframe"}.
    """
    from slicersim.reduction.ramp_sources import open_ramps, ramp_file_kind, ramp_readout
    validation.renamed_keyword(renamed, "read_noise", "ron", "check_ramp_file")
    for key in renamed:
        validation.choice("keyword", key, ("ron",), what="check_ramp_file keyword")
    ron = renamed.get("ron", ron)
    register_hdf5_filters()
    if not isinstance(path, (str, bytes, os.PathLike)):
        raise ParameterError(f"check_ramp_file path must be a ramp file path (str or os.PathLike), got "
                             f"{validation.short_repr(path)}")
    path = os.fsdecode(path)
    if os.path.isdir(path):
        raise RampFileError(f"{path} is a directory, not a ramp file (a campaign dataset needs spec.json "
                            "and catalog.ecsv)")
    if not os.path.lexists(path):
        raise RampFileError(f"{path}: no such ramp file")
    validation.regular_file("ramp file", path, error=RampFileError)     # no FIFO, device: never opened
    kind = ramp_file_kind(path)
    header = None
    if kind == "hdf5":
        _check_hdf5_layout(path, with_truth)
    elif kind == "fits":
        header = _fits_primary_header(path)
    with open_ramps(path) as src:                    # its own layout checks (SCI, shapes, completeness)
        shape = tuple(int(s) for s in src.shape)
        if 0 in shape:
            raise RampFileError(f"{path}: SCI is empty {shape}")
        check_raw_attrs(src.attrs, path, gain=gain, ron=ron)
        nmd, tframe, _, _ = ramp_readout(src.attrs, src.shape, gain, ron, path)
        if header is not None:
            _check_fits_duplicates(header, path)
        if _made_by_slicersim(src.attrs, header):
            timing = {k: header[k] for k in _TIMING_KEYS if k in header} if header is not None else {}
            _check_timing({**src.attrs, **timing}, shape, nmd, tframe, path)
        _check_linearity_truth(src, path)
        if with_truth:
            truth = src.truth("rate")
            if truth is None:
                raise RampFileError(f"{path}: the truth is asked for (--with-truth) but the file has no truth/rate")
            if tuple(truth.shape) != shape[2:]:
                raise RampFileError(f"{path}: truth/rate has shape {tuple(truth.shape)}, the data {shape[2:]}")
    if detector_shape is not None and shape[2:] != tuple(detector_shape):
        raise RampFileError(f"{path}: the ramps are {shape[2]}×{shape[3]} pixels, the mapper's detector "
                            f"{detector_shape[0]}×{detector_shape[1]}: cubes and spectra need the full detector "
                            "(reduce without --spectra for rates only)")
    return {"kind": "jwst-uncal" if header is not None else "hdf5", "shape": shape, "nmd": nmd, "tframe": tframe}


#: physical range of a raw file's numeric keywords: (low, high, unit); outside it the file is refused
#: (GAIN = 1e-300 divided to inf, READNOISE = 1e300 overflowed, DARK = NaN gave DARK_RATE = NaN)
ATTR_RANGES = {"GAIN": (1e-3, 1e3, "DN/e-"), "READNOISE": (0.0, 1e4, "electron"), "TFRAME": (1e-6, 1e4, "s"),
               "DARK": (0.0, 1e6, "e-/s"), "THERMAL_DARK": (0.0, 1e6, "e-/s"), "ROIC_GLOW": (0.0, 1e6, "e-/frame"),
               "DARK_RATE": (0.0, 1e6, "e-/s")}
#: the truth coefficients of the linearity correction (``fit_ramps(linearity=None)`` applies them)
_LINEARITY_TRUTH = "nonlinearity/inverse_coefficients"


def check_raw_attrs(attrs, path, gain=None, ron=None):
    """Refuse (RampFileError naming the keyword) a raw file's keywords outside their physical range
    (:data:`ATTR_RANGES`; GAIN and READNOISE not when ``gain`` / ``ron`` override them), a readout
    (NGROUPS, NFRAMES, GROUPGAP) beyond :func:`~slicersim.validation.readout`'s bounds, and an
    EFFECTS keyword that is not a JSON object (the corrections it enables would be skipped)."""
    import json
    for key, (low, high, unit) in ATTR_RANGES.items():
        if key not in attrs or (key == "GAIN" and gain is not None) or (key == "READNOISE" and ron is not None):
            continue
        value = _num(attrs, key, path)
        if not low <= value <= high:
            raise RampFileError(f"{path}: keyword {key} = {value!r} is outside the physical range "
                                f"[{low:g}, {high:g}] {unit}")
    if all(k in attrs for k in ("NGROUPS", "NFRAMES", "GROUPGAP")):
        nmd = tuple(_num(attrs, k, path) for k in ("NGROUPS", "NFRAMES", "GROUPGAP"))
        validation.readout(nmd, name=f"{path}: keywords (NGROUPS, NFRAMES, GROUPGAP)", error=RampFileError)
    text = attrs.get("EFFECTS")
    if text is not None:
        try:
            doc = json.loads(text.decode() if isinstance(text, bytes) else str(text))
        except (ValueError, UnicodeDecodeError):
            doc = None
        if not isinstance(doc, dict) or not isinstance(doc.get("effects", {}), dict):
            raise RampFileError(f"{path}: keyword EFFECTS = {validation.short_repr(text)} is not the JSON object of "
                                "the detector effects simulated: cannot tell which corrections the ramps need")


def _check_linearity_truth(src, path, block_bytes=64 << 20):
    """The file's linearity truth coefficients, when present, must be finite (NaN coefficients made
    every rate NaN); read in blocks of rows."""
    coeffs = src.truth(_LINEARITY_TRUTH)
    if coeffs is None or getattr(coeffs, "ndim", 0) != 3:
        return
    from slicersim.io.rampfile import read_dataset
    k, ny, nx = coeffs.shape
    rows = max(1, block_bytes // max(1, 8 * k * nx))
    for a, b in getattr(src, "rows", None) or ((0, ny),):       # a file of some rows: those rows
        for y0 in range(a, b, rows):
            y1 = min(b, y0 + rows)
            block = read_dataset(coeffs, path, np.s_[:, y0:y1]) if hasattr(coeffs, "id") else \
                np.asarray(coeffs[:, y0:y1])
            if not np.all(np.isfinite(block)):
                raise RampFileError(f"{path}: truth/{_LINEARITY_TRUTH} has non-finite values (rows from {y0}): the "
                                    "linearity correction would make the rates NaN (fit_ramps(linearity=False) skips "
                                    "it)")


def _check_hdf5_layout(path, with_truth):
    """Name what a foreign HDF5 file is; no data from outside the file (external storage or
    links, virtual datasets: :func:`~slicersim.io.rampfile.check_hdf5_input`); types and filters
    of the ramp datasets."""
    import h5py

    from slicersim.io.rampfile import check_hdf5_input, metadata_errors
    try:
        with metadata_errors(path):
            fh = h5py.File(path, "r")
    except RampFileError:
        raise
    except OSError as exc:
        raise RampFileError(f"{path}: not a readable HDF5 ramp file ({one_line(exc)})") from exc
    with fh:
        with metadata_errors(path):
            dict(fh.attrs)
        what = _foreign_product(fh)
        if what:
            raise RampFileError(f"{path} is {what}, not a raw ramp file")
        check_hdf5_input(fh, path, ("SCI", "GROUPDQ", "PIXELDQ", "truth/rate"), partial_rows=True)
        for name, kinds in (("SCI", "u"), ("GROUPDQ", "u"), ("PIXELDQ", "ui")):
            dset = fh.get(name)
            if not isinstance(dset, h5py.Dataset):
                continue
            if dset.dtype.kind not in kinds:
                raise RampFileError(f"{path}: {name} has type {dset.dtype}, expected unsigned integers")
            _check_filters(dset, path, name)
        truth = fh.get("truth/rate")
        if with_truth and isinstance(truth, h5py.Dataset):
            _check_filters(truth, path, "truth/rate")


def _foreign_product(fh):
    """A description of a known non-ramp slicersim file, or ''."""
    attrs = fh.attrs
    product = attrs.get("product")
    if isinstance(product, bytes):
        product = product.decode(errors="replace")
    if product in ("spectrum", "cube", "detector_image"):
        return f"a campaign {product.replace('_', ' ')} product"
    if "rates" in fh and ("cubes" in fh or "spectra" in fh):
        return "a reduced exposure (rates, cubes, spectra from `slicersim reduce --spectra`)"
    if "RATE" in fh and "VAR" in fh and "SCI" not in fh:
        return "a rates file (from `slicersim reduce`)"
    return ""


def _check_filters(dset, path, name):
    import h5py
    plist = dset.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        code, _, _, label = plist.get_filter(i)
        if not h5py.h5z.filter_avail(code):
            label = label.decode(errors="replace") if isinstance(label, bytes) else str(label)
            raise RampFileError(f"{path}: {name} is compressed with HDF5 filter {code} ({label or 'unknown'}), "
                                "which this installation cannot decode (install the 'hdf5plugin' package)")


def _fits_primary_header(path):
    from astropy.io import fits
    try:
        return fits.getheader(path, 0)
    except (OSError, ValueError, IndexError) as exc:
        raise RampFileError(f"{path}: not a readable FITS file ({one_line(exc)})") from exc


def _made_by_slicersim(attrs, header):
    def text(v):
        return v.decode(errors="replace") if isinstance(v, bytes) else str(v)
    if header is not None:
        return text(header.get("ORIGIN", "")).strip().lower() == "slicersim" or \
            any(str(k).startswith("SLICERSIM ") for k in header)
    return text(attrs.get("SOFTWARE", "")).strip().lower() == "slicersim"


def _check_fits_duplicates(header, path):
    """The SLICERSIM copies of the readout keywords (HIERARCH) must agree with the JWST ones."""
    for key in _READOUT_KEYS:
        copy = f"SLICERSIM {key}"
        if key in header and copy in header:
            a, b = header[key], header[copy]
            try:
                same = math.isclose(float(a), float(b), rel_tol=1e-6)
            except (TypeError, ValueError):
                same = a == b
            if not same:
                raise RampFileError(f"{path}: inconsistent readout keywords: {key} = {a} but "
                                    f"SLICERSIM {key} = {b}")


def _num(attrs, key, path):
    val = attrs[key]
    if isinstance(val, bytes):
        val = val.decode(errors="replace")
    if isinstance(val, np.generic):
        val = val.item()
    try:
        out = float(val)
    except (TypeError, ValueError):
        raise RampFileError(f"{path}: keyword {key} = {val!r} is not a number") from None
    if not math.isfinite(out):
        raise RampFileError(f"{path}: keyword {key} = {val!r} is not finite")
    return out


def _check_timing(attrs, shape, nmd, tframe, path):
    """Timing keywords (JWST definitions, :mod:`slicersim.io.uncal`) against the readout."""
    nints = shape[0]
    n, m, d = nmd
    tgroup = (m + d) * tframe
    drop1 = _num(attrs, "DRPFRMS1", path) if "DRPFRMS1" in attrs else 0.0
    expect = {"FRMDIVSR": (m, "NFRAMES"),
              "EFFINTTM": ((n - 1) * tgroup, "(NGROUPS − 1)·TGROUP"),
              "TMEASURE": ((n - 1) * tgroup * nints, "(NGROUPS − 1)·TGROUP·NINTS"),
              "EFFEXPTM": (tframe * (n * m + (n - 1) * d + drop1) * nints,
                           "TFRAME·(NGROUPS·NFRAMES + (NGROUPS − 1)·GROUPGAP + DRPFRMS1)·NINTS"),
              "XPOSURE": (tframe * (n * m + (n - 1) * d + drop1) * nints,
                          "TFRAME·(NGROUPS·NFRAMES + (NGROUPS − 1)·GROUPGAP + DRPFRMS1)·NINTS")}
    for key, (value, formula) in expect.items():
        if key in attrs and not math.isclose(_num(attrs, key, path), value, rel_tol=1e-6, abs_tol=1e-9):
            raise RampFileError(f"{path}: inconsistent readout keywords: {key} = {attrs[key]} but {formula} = "
                                f"{value:g} (NGROUPS, NFRAMES, GROUPGAP, TFRAME, NINTS = {n}, {m}, {d}, "
                                f"{tframe:g}, {nints})")
    for key in ("DURATION", "TELAPSE"):
        if key in attrs and _num(attrs, key, path) < tframe * (n * m + (n - 1) * d) * nints * (1 - 1e-6):
            raise RampFileError(f"{path}: inconsistent readout keywords: {key} = {attrs[key]} s is shorter "
                                "than the frames read")


# ----------------------------------------------------------------------------- options
def _fit_ramps_keywords():
    """The option names fit_ramps takes (:data:`~slicersim.reduction.ramp_fit.FIT_DEFAULTS`) and its
    deprecated names (:data:`~slicersim.reduction.ramp_fit.FIT_RENAMED`, old → new)."""
    from slicersim.reduction.ramp_fit import FIT_DEFAULTS, FIT_RENAMED
    return set(FIT_DEFAULTS), dict(FIT_RENAMED)


def check_fit_options(fit_options):
    """A dict of ``fit_ramps`` keyword arguments, checked (names and the simple values)."""
    from slicersim.backends.ramp_fit import WEIGHTINGS
    if fit_options is None:
        return {}
    if not isinstance(fit_options, dict):
        raise ParameterError(f"fit_options must be a dict of fit_ramps keyword arguments, got "
                             f"{validation.short_repr(fit_options)}")
    known, renamed = _fit_ramps_keywords()
    for key in fit_options:                   # a deprecated name is accepted (and moved below)
        validation.choice("fit_options key", key, sorted(known | set(renamed)), what="fit_ramps option")
    opts = dict(fit_options)
    for old, new in renamed.items():
        validation.renamed_keyword(opts, old, new, "fit_options", stacklevel=4)
    if "weighting" in opts:
        validation.choice("weighting", opts["weighting"], WEIGHTINGS)
    if opts.get("jump_threshold") is not None:
        validation.number("jump_threshold [σ] (0: no jump detection)", opts["jump_threshold"], low=0.0)
    if opts.get("gain") is not None:
        low, high, _ = ATTR_RANGES["GAIN"]
        opts["gain"] = validation.number("gain", opts["gain"], low=low, high=high, unit="adu / electron")
    if opts.get("ron") is not None:           # the raw file's READNOISE range (1e300 overflowed the variance)
        low, high, _ = ATTR_RANGES["READNOISE"]
        opts["ron"] = validation.number("ron (read noise per frame)", opts["ron"], low=low, high=high,
                                        unit="electron")
    for key in ("with_truth", "return_groupdq"):
        if key in opts:
            validation.flag(key, opts[key])
    return opts


_UNSET = object()       # dark not given (None given: subtract nothing)
#: the options check_spectra_options knows (reduce_exposure's, with dark)
_SPECTRA_OPTIONS = ("field", "lbda_edges", "ncol", "rectify_method", "extraction", "psf", "position", "aperture",
                    "background", "propagate", "dark", "weights", "config", "ipc", "cubes")


def check_spectra_options(mapper=None, **options):
    """Validate :func:`~slicersim.reduction.pipeline.reduce_exposure` options before any data are
    read; returns the dict of those given (None: the pipeline's default), the λ edges as an array.

    Options: field, lbda_edges, ncol, rectify_method, extraction, psf, position, aperture,
    background, propagate, dark, weights, config, ipc, cubes (an unknown name is a ParameterError).  The λ
    grid is checked against ``mapper`` (default: the built-in layout) and a PSF array against the
    cube it will be applied to ((nλ, 58, ncol) for the Lazuli fields)."""
    for key in options:
        validation.choice("option", key, _SPECTRA_OPTIONS, what="reduction option")
    given = {k: v for k, v in options.items() if v is not None or k == "dark"}
    out = _check_grid_options(given)
    _check_extraction_options(given, out)
    _check_switches(given, out)
    _refuse_unused(out)
    dark = given.get("dark", _UNSET)
    if "lbda_edges" in given or not isinstance(given.get("psf", ""), str) or dark is not _UNSET:
        from slicersim.reduction.rectify import _default_mapper
        mapper = _default_mapper() if mapper is None else mapper
    if dark is not _UNSET:
        if not (isinstance(dark, str) and dark in ("auto", "none")):
            dark_rate_of(dark, None, mapper.detector_shape)
        out["dark"] = None if isinstance(dark, str) and dark == "none" else dark
    if "lbda_edges" in given:
        out["lbda_edges"] = _check_edges(given["lbda_edges"], mapper)
    if "psf" in given:
        from slicersim.reduction.rectify import FIELDS
        method = out.get("rectify_method", "lsq")
        extracted = out.get("extraction") or ("gls" if method == "lsq" else "optimal")
        out["psf"] = _check_psf(given["psf"], mapper, out, FIELDS, extracted)
    return out


def _check_grid_options(given):
    """field, ncol, rectify_method and position (inside the field of ``ncol`` columns)."""
    from slicersim.reduction.rectify import FIELDS, METHODS as RECTIFY_METHODS
    out = {}
    if "field" in given:
        out["field"] = validation.choice("field", given["field"], (*FIELDS, "both"))
    if "ncol" in given:
        if isinstance(given["ncol"], (float, np.floating)):      # 58.0 is a float: columns are counted
            raise ParameterError(f"ncol must be an integer in [1, {MAX_NCOL}] (columns per slice), got "
                                 f"{validation.short_repr(given['ncol'])}")
        out["ncol"] = validation.integer("ncol", given["ncol"], low=1, high=MAX_NCOL)
    if "rectify_method" in given:
        out["rectify_method"] = validation.choice("rectify_method", given["rectify_method"], RECTIFY_METHODS)
    if "position" in given:
        position = given["position"]
        try:
            pos = tuple(position)
        except TypeError:
            pos = ()
        if len(pos) != 2 or isinstance(position, (str, bytes)):
            raise ParameterError(f"position must be (x, y) [cells from the field centre], got "
                                 f"{validation.short_repr(position)}")
        x, y = (validation.number("position [cells]", v) for v in pos)
        ncol = out.get("ncol", DEFAULT_NCOL)
        rows = min(len(FIELDS[name]) for name in (FIELDS if out.get("field") in (None, "both") else [out["field"]]))
        if abs(x) > ncol / 2 or abs(y) > rows / 2:
            raise ParameterError(f"position ({x:g}, {y:g}) lies outside the field: |x| ≤ {ncol / 2:g} (columns), "
                                 f"|y| ≤ {rows / 2:g} (slices) [cells from the centre]")
        out["position"] = (x, y)
    return out


def _check_extraction_options(given, out):
    """extraction, weights and aperture (and their combinations with the rectification)."""
    from slicersim.reduction.spectra import METHODS, extract_spectrum
    method = out.get("rectify_method")
    if "extraction" in given:
        out["extraction"] = validation.choice("extraction", given["extraction"], (FORWARD, *METHODS))
        if out["extraction"] == "gls" and method == "drizzle":
            raise ParameterError("extraction 'gls' needs an lsq cube (its inverse covariance): not with "
                                 "rectify_method 'drizzle'")
    if "weights" in given:
        if not isinstance(given["weights"], str):
            raise ParameterError(f"weights must be one of {WEIGHTS}, got {validation.short_repr(given['weights'])}")
        out["weights"] = validation.choice("weights", given["weights"], WEIGHTS)
        if method == "drizzle":
            raise ParameterError("weights apply to rectify_method 'lsq' only (drizzle has no weights)")
    if "aperture" in given:
        radius = inspect.signature(extract_spectrum).parameters["background_radius"].default
        out["aperture"] = validation.number("aperture [PSF σ]", given["aperture"], low=0.0, low_open=True,
                                            high=radius if isinstance(radius, (int, float)) else math.inf,
                                            high_open=True)


def _check_switches(given, out):
    """background, propagate, cubes, ipc and config."""
    for key in ("background", "propagate", "cubes"):
        if key in given:
            out[key] = validation.flag(key, given[key])
    if "ipc" in given:
        if given["ipc"] is not False:
            raise ParameterError(f"ipc must be None (the file's IPC, when it records one) or False, got "
                                 f"{validation.short_repr(given['ipc'])}")
        out["ipc"] = False
    if "config" in given:
        config = given["config"]
        if isinstance(config, (list, tuple)):
            bad = not config or not all(isinstance(c, (str, os.PathLike)) for c in config)
        else:
            bad = not isinstance(config, (str, os.PathLike)) or not str(config)
        if bad:
            raise ParameterError(f"config must be 'cbe', 'eol', a TOML path or a list of them, got "
                                 f"{validation.short_repr(config)}")
        out["config"] = config


def _refuse_unused(out):
    """Options that would do nothing in this reduction are refused, not ignored."""
    method = out.get("rectify_method", "lsq")
    extracted = out.get("extraction") or ("gls" if method == "lsq" else "optimal")
    if "aperture" in out and extracted == FORWARD:
        raise ParameterError("aperture applies to the 'optimal' and 'aperture' extractions (the cells they use), "
                             "not to 'forward' (every pixel the source reaches)")
    if "aperture" in out and extracted == "gls":
        raise ParameterError("aperture applies to the 'optimal' and 'aperture' extractions (the cells they use), "
                             "not to 'gls' (every cell of the field)")
    if out.get("cubes") is False and out.get("extraction") not in (None, FORWARD):
        raise ParameterError(f"cubes=False: the {extracted!r} extraction works on the cube (CLI: it needs the cube)")
    if out.get("cubes") is False and "rectify_method" in out:
        raise ParameterError("rectify_method shapes the cube, and cubes=False asks for none")
    if out.get("cubes") is False and "weights" in out:
        raise ParameterError("weights shape the cube, and cubes=False asks for none")
    if "propagate" in out and (method != "lsq" or extracted in ("gls", FORWARD)):
        raise ParameterError(f"propagate applies to 'optimal' or 'aperture' extraction of an lsq cube only (this "
                             f"reduction: {extracted!r} on a {method!r} cube)")


def _check_edges(lbda_edges, mapper):
    """λ edges [Å] (or a Quantity) as a 1-D float array [Å] inside the mapper's traces."""
    from slicersim.reduction.rectify_checks import _check_grid, angstrom
    try:
        edges = np.asarray(angstrom("lbda_edges", lbda_edges), np.float64)
    except (TypeError, ValueError):
        raise ParameterError("lbda_edges must be numbers [Å]") from None
    if edges.ndim != 1 or edges.size < 2:
        raise ParameterError(f"lbda_edges must be a 1-D array of ≥ 2 edges [Å], got shape {edges.shape}")
    return _check_grid(None, edges, mapper)[1]


def _check_psf(psf, mapper, opts, fields, extraction="gls"):
    if isinstance(psf, str):
        if psf != "fit":
            raise ParameterError(f"psf must be 'fit' or an (nλ, ny, nx) array of PSF fractions, got "
                                 f"{validation.short_repr(psf)}")
        return psf
    try:
        arr = np.asarray(psf, np.float64)
    except (TypeError, ValueError):
        raise ParameterError("psf must be 'fit' or a numeric (nλ, ny, nx) array") from None
    if arr.ndim == 4:                       # a forward-modelled template (K, nλ, ny, nx): GLS only
        if extraction != "gls":
            raise ParameterError(f"a template psf (K, nλ, ny, nx) is for extraction 'gls' only, not {extraction!r}")
        if not np.all(np.isfinite(arr)) or arr.shape[0] != arr.shape[1]:
            raise ParameterError(f"a template psf must be finite, of shape (nλ, nλ, ny, nx), got {arr.shape}")
        _check_cube_shape(arr.shape[1:], mapper, opts, fields)
        if not (arr.reshape(arr.shape[0], -1) > 0).any(axis=1).all():
            raise ParameterError("a template psf has an unknown with no positive value (no light to fit)")
        return arr
    if arr.ndim != 3 or not np.all(np.isfinite(arr)) or (arr < 0).any():
        raise ParameterError(f"psf must be a finite (nλ, ny, nx) array of fractions ≥ 0, got shape {arr.shape}")
    if not (arr.reshape(arr.shape[0], -1) > 0).any(axis=1).all():
        raise ParameterError("psf has a λ bin with no positive fraction (no light to extract there)")
    _check_cube_shape(arr.shape, mapper, opts, fields)
    from slicersim.reduction.spectrum_product import _check_psf_sum
    _check_psf_sum(arr)
    return arr


def _check_cube_shape(shape, mapper, opts, fields):
    """A PSF (or template plane set) must have the shape of the cube it will be applied to."""
    edges = opts.get("lbda_edges")
    nbins = (edges.size if edges is not None else default_lbda_edges(mapper).size) - 1
    ncol = opts.get("ncol", DEFAULT_NCOL)
    names = list(fields) if opts.get("field") in (None, "both") else [opts["field"]]
    rows = {len(fields[name]) for name in names}
    if len(rows) == 1 and tuple(shape) != (nbins, rows.pop(), ncol):
        raise ParameterError(f"psf has shape {tuple(shape)}; the cube will be ({nbins}, {len(fields[names[0]])}, "
                             f"{ncol}) (λ bins, slices, columns)")


def default_lbda_edges(mapper, step=2, lbda_range=None):
    """λ edges [Å]: the CBE native grid (~1 px per bin) taken every ``step`` bins, inside the mapper's
    traces (and ``lbda_range`` [Å] when given)."""
    from slicersim.instrument.spectrograph import wavelength_grid_from_dispersion
    from slicersim.io.config import builtin_config_dir
    from slicersim.io.curves import read_curve
    step = validation.integer("step (native bins per bin)", step, low=1)
    lam, cols = read_curve(f"{builtin_config_dir()}/dispersion_prism.ecsv")
    _, edges = wavelength_grid_from_dispersion(lam, next(iter(cols.values())), (4000, 17000), 1.3, 2.3)
    lo, hi = mapper.lbda_nodes[0], mapper.lbda_nodes[-1]
    if lbda_range is not None:
        lo, hi = max(lo, float(lbda_range[0])), min(hi, float(lbda_range[1]))
    edges = edges[(edges >= lo) & (edges <= hi)][::step]
    if edges.size < 2:
        raise ParameterError(f"no λ bin lies in {lo:.0f}–{hi:.0f} Å")
    return edges


_DARK_MAX = 1e6          # e-/s: far above any H4RG dark current, glow or thermal dark


def _check_dark_value(arr, what):
    if not np.all(np.isfinite(arr)) or np.any(arr < 0) or np.any(arr > _DARK_MAX):
        bad = np.asarray(arr)[~(np.isfinite(arr) & (np.asarray(arr) >= 0) & (np.asarray(arr) <= _DARK_MAX))].flat[0]
        raise ParameterError(f"{what} must be finite, ≥ 0 and ≤ {_DARK_MAX:g} e-/s, got {float(bad):g}")


def dark_rate_of(dark, rates, shape):
    """The dark rate [e-/s] to subtract before rectification and how it was chosen:
    ``(float or (ny, nx) array, kind)``, kind "file DARK_RATE", "none available", "none", "value" or
    "image".

    ``"auto"``: the file's DARK_RATE (dark + thermal dark + ROIC glow / t_frame, the detector's
    expectation the simulator records; the bad pixels' extra dark, in the file's truth, is added by the pipeline:
    :func:`slicersim.reduction.dark.extra_dark`);
    a file without it (e.g. a JWST level-1b file) gets nothing subtracted, with a warning.  A number
    or a detector-shaped float image [e-/s]; None: nothing."""
    if dark is None:
        return 0.0, "none"
    if isinstance(dark, str):
        if dark != "auto":
            raise ParameterError(f"dark must be 'auto', None, a rate [e-/s] or an image, got "
                                 f"{validation.short_repr(dark)}")
        value = None if rates is None else rates.attrs.get("DARK_RATE")
        if value is None:
            if rates is not None:
                import warnings
                warnings.warn(f"{rates.attrs.get('SOURCE', 'the ramp file')}: no DARK_RATE (dark, thermal dark and "
                              "ROIC glow not all recorded): no dark subtracted — pass dark=<e-/s> or an image",
                              RuntimeWarning, stacklevel=3)
            return 0.0, "none available"
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"the file's DARK_RATE must be a number [e-/s], got {value!r}") from None
        _check_dark_value(value, "the file's DARK_RATE")
        return value, "file DARK_RATE"
    bad = isinstance(dark, (bool, np.bool_, complex, np.complexfloating)) or np.ma.isMaskedArray(dark)
    try:
        arr = np.asarray(dark)
    except (TypeError, ValueError):
        arr = None
    if bad or arr is None or arr.dtype.kind not in "iuf":
        raise ParameterError("dark must be 'auto', None, a real rate [e-/s] or a real image (not bool, complex "
                             f"or masked), got {type(dark).__name__}"
                             + (f" of {arr.dtype}" if arr is not None and arr.dtype != object else ""))
    arr = arr.astype(np.float64)
    if arr.ndim not in (0, 2) or (arr.ndim == 2 and arr.shape != tuple(shape)):
        raise ParameterError(f"{validation.shown('dark')}: a dark image must have the detector's shape {tuple(shape)}, "
                             f"got {arr.shape}")
    _check_dark_value(arr, f"{validation.shown('dark')} (dark rates)")
    return (float(arr), "value") if arr.ndim == 0 else (arr, "image")
