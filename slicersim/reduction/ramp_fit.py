"""Ramps → rates: up-the-ramp fitting of raw MACC ramps (our HDF5 files, JWST level-1b FITS, arrays).

Per block of detector rows, all integrations at once (the JWST order of steps):

1. saturation: GROUPDQ SATURATED, or a raw group ≥ ``saturation`` [DN], and every later group;
2. with corrections (float DN): superbias subtracted (``truth/bias`` when the file has it, else
   the BIAS attribute), reference-pixel correction (:func:`slicersim.reduction.refpix.refpix_correct`,
   JWST's algorithm, applied to whole frames in a first pass that keeps its column and row terms),
   classical nonlinearity (:func:`slicersim.physics.nonlinearity.apply_correction`, JWST coefficients);
3. the fit (``kernels/ramp_fit.cl`` or its NumPy twin, :mod:`slicersim.backends.ramp_fit`): jumps by
   two-point differences, segments, ``gls`` (default: generalised least squares with the exact
   covariance of MACC group means at the OLS rate) or ``ols`` (unweighted, stcal's combination of
   segments); rate [e-/s], variance = Poisson + read [e-²/s²], DQ (JWST bits), jumps per pixel.

Why GLS by default: with the exact covariance (read noise on the diagonal, Poisson covariance of
overlapping group means) it is the minimum-variance linear estimator — σ 1–8 % below OLS from
0.005 to 5 e-/s at MACC(64,8,0); JWST's OLS_C "optimal" weighting approximates it with power-law
weights.  Its weights come from the pixel's own OLS rate, which biases it by −0.007 σ at
0.005 e-/s and ≤ 0.003 σ above 0.05 e-/s (1e6-pixel Monte Carlo); OLS is unbiased and its
variance is Rauscher07's.  The Poisson term of the reported variance uses the pixel's own rate
(as stcal does): for pixels near zero flux the reported errors are noisy (pulls up to ≈ 1.15
wide) while the scatter matches the variance at the true rate.

The rate is the total charge rate measured: photo-current plus dark, thermal dark and ROIC glow
(their expectation is the attribute DARK_RATE when the file records them).
"""
from __future__ import annotations

import inspect
import json
import math
import os
from dataclasses import dataclass, field, fields

import numpy as np

from slicersim import validation
from slicersim.backends.dispatch import BACKENDS, resolve_backend
from slicersim.backends.ramp_fit import (DQ_DO_NOT_USE, DQ_SATURATED, WEIGHTINGS, check_launch, fit_block_numpy,
                                         fit_block_opencl, fit_constants)
from slicersim.errors import ParameterError, RampFileError
from slicersim.io.atomic import AtomicH5File, one_line
from slicersim.io.row_blocks import SIMULATED_ROWS, BufferRing, RowBlocks, pipelined, row_ranges, rows_per_block
from slicersim.reduction.ramp_sources import keyword_number, open_ramps, ramp_readout

__all__ = ["fit_ramps", "FitOptions", "FIT_DEFAULTS", "FIT_RENAMED", "RateProduct", "DEFAULT_JUMP_THRESHOLD"]

DEFAULT_JUMP_THRESHOLD = 4.0          # σ (stcal's default rejection threshold)
_LINEARITY_TRUTH = "nonlinearity/inverse_coefficients"


@dataclass
class RateProduct:
    """Rates of a ramp file (made by :func:`fit_ramps`).

    Parameters
    ----------
    rate : numpy.ndarray of shape (ny, nx)
        Fitted rate [e-/s], float64.
    variance, var_poisson, var_rnoise : numpy.ndarray of shape (ny, nx)
        Total, Poisson and read-noise variances of the rate [e-²/s²], float64.
    dq : numpy.ndarray of shape (ny, nx)
        uint32 JWST bits: PIXELDQ | SATURATED | JUMP_DET | DO_NOT_USE where no rate.
    njumps : numpy.ndarray of shape (ny, nx)
        int32 number of jumps detected.
    attrs : dict, optional
        Readout, corrections, units.
    groupdq : numpy.ndarray of shape (nints, ngroups, ny, nx), optional
        GROUPDQ with the jump flags (``return_groupdq``).
    truth_rate : numpy.ndarray of shape (ny, nx), optional
        The true rate [e-/s] (``with_truth``)."""

    rate: np.ndarray
    variance: np.ndarray
    var_poisson: np.ndarray
    var_rnoise: np.ndarray
    dq: np.ndarray
    njumps: np.ndarray
    attrs: dict = field(default_factory=dict)
    groupdq: np.ndarray | None = None
    truth_rate: np.ndarray | None = None

    @property
    def err(self):
        """√variance [e-/s]."""
        return np.sqrt(self.variance)

    def datasets(self):
        """The images as files store them.

        RATE, VAR, VAR_POISSON, VAR_RNOISE in float32 (``RATE_STORAGE``, as JWST rate files; 6e-8
        relative, far below any rate's noise: half the disk and write time of float64), DQ and
        NJUMPS compressed (``FLAG_COMPRESSION``: gzip 1 with shuffle).  The truth rate is not among
        them (kept in float64).

        Yields
        ------
        tuple of (str, numpy.ndarray, dict)
            Dataset name, its (ny, nx) array and the h5py ``create_dataset`` options.
        """
        for name, data in (("RATE", self.rate), ("VAR", self.variance), ("VAR_POISSON", self.var_poisson),
                           ("VAR_RNOISE", self.var_rnoise)):
            with np.errstate(over="raise"):               # finite beyond float32: inf in the file, silently
                try:
                    stored = np.asarray(data, RATE_STORAGE)
                except FloatingPointError:
                    big = float(np.max(np.abs(np.asarray(data, float)), where=np.isfinite(data), initial=0.0))
                    raise RampFileError(f"{name} holds finite values up to {big:.3g}, beyond the range of the rate "
                                        f"file's float32 ({float(np.finfo(RATE_STORAGE).max):.3g}): they would be stored "
                                        "as inf (check the ramps' units and values)") from None
            yield name, stored, {}
        yield "DQ", self.dq, FLAG_COMPRESSION
        yield "NJUMPS", self.njumps, FLAG_COMPRESSION

    def write(self, path, overwrite=False):
        """Write RATE, VAR, VAR_POISSON, VAR_RNOISE, DQ, NJUMPS (and TRUTH_RATE) to HDF5 with the
        attributes, atomically; returns the absolute path."""
        class _Writer(AtomicH5File):
            error_class = RampFileError
        writer = _Writer(path, overwrite=overwrite)
        writer.check()
        with writer as w:
            for name, data, options in self.datasets():
                w.write(name, data, **options)
            if self.truth_rate is not None:
                w.write("TRUTH_RATE", self.truth_rate)
            w.set_attrs({k: (json.dumps(v) if isinstance(v, (dict, list, tuple)) else v)
                         for k, v in self.attrs.items() if v is not None})
        return os.path.abspath(os.fspath(path))


#: how the rate and variance images are stored in files (the RateProduct in memory is float64)
RATE_STORAGE = np.float32

#: how the flag images (DQ, NJUMPS: mostly 0) are stored: gzip level 1 with shuffle, which every HDF5
#: reader has (a full-detector DQ + NJUMPS: 128 MiB → ~1 MiB; lossless, the values are those fitted)
FLAG_COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}


# ----------------------------------------------------------------------------- corrections
def _effects(attrs):
    text = attrs.get("EFFECTS")
    if text is None:
        return {}
    try:
        return json.loads(text.decode() if isinstance(text, bytes) else text).get("effects", {})
    except (ValueError, AttributeError):
        return {}


def _plan_corrections(src, refpix, linearity, superbias, where):
    """(refpix kwargs or None, linearity coefficients or None, superbias, labels) before any reading."""
    effects = _effects(src.attrs)
    enabled = effects.get("enabled", [])
    ny, nx = src.shape[2:]
    if refpix is None:
        refpix = "reference_pixels" in enabled
    refpix_kw = None
    if refpix is not False:
        params = effects.get("reference_pixels", {})
        refpix_kw = {k: params[k] for k in ("border", "n_outputs") if k in params}
        if isinstance(refpix, dict):
            refpix_kw.update(refpix)
        elif refpix is not True:
            raise ParameterError(f"refpix must be None, True, False or a dict of refpix_correct options, got {refpix!r}")
    coeffs, lin_label = None, "none"
    if linearity is None:
        linearity = "truth" if src.truth(_LINEARITY_TRUTH) is not None else False
    if isinstance(linearity, str):
        if linearity != "truth":
            raise ParameterError(f"linearity must be None, False, 'truth' or coefficients (k, ny, nx), got {linearity!r}")
        coeffs = src.truth(_LINEARITY_TRUTH)
        if coeffs is None:
            raise RampFileError(f"{where}: linearity='truth' but the file has no truth/{_LINEARITY_TRUTH} "
                                "(simulated without the nonlinearity effect?)")
        lin_label = "truth"
    elif linearity is not False:
        coeffs, lin_label = np.asarray(linearity, np.float64), "user"
    if coeffs is not None and (len(coeffs.shape) != 3 or tuple(coeffs.shape[1:]) != (ny, nx) or coeffs.shape[0] < 2):
        raise RampFileError(f"{where}: linearity coefficients must be (k ≥ 2, {ny}, {nx}), got {tuple(coeffs.shape)}")
    bias, bias_label = None, "none"
    if refpix_kw is not None or coeffs is not None:
        if superbias is None:
            bias = src.truth("bias")
            bias_label = "truth/bias"
            if bias is None and "BIAS" in src.attrs:
                bias, bias_label = keyword_number(src.attrs, "BIAS", where), "BIAS keyword"
            if bias is None and coeffs is not None:
                raise RampFileError(f"{where}: the linearity correction needs the bias: no truth/bias, no BIAS "
                                    "keyword (pass superbias=)")
        else:
            bias, bias_label = superbias, "user"
            if isinstance(superbias, (str, bytes)) or not np.all(np.isfinite(np.asarray(superbias, np.float64))):
                raise ParameterError(f"superbias must be a finite number or ({ny}, {nx}) map [DN], got {superbias!r}")
        if bias is not None and np.ndim(bias) and tuple(np.shape(bias)) != (ny, nx):
            raise RampFileError(f"{where}: superbias must be a number or ({ny}, {nx}), got {np.shape(bias)}")
    return refpix_kw, coeffs, bias, {"REFPIX": refpix_kw is not None, "LINEARITY": lin_label, "SUPERBIAS": bias_label}


def _bias_rows(bias, y0, y1):
    if bias is None:
        return 0.0
    return float(bias) if not np.ndim(bias) else _rows(bias, y0, y1)


def _rows(data, y0, y1):
    """float64 rows y0:y1 (of the last two axes) of an array or of a file's dataset; RampFileError
    naming the dataset when the file's chunks cannot be read (damaged, a failed filter)."""
    try:
        return np.asarray(data[..., y0:y1, :], np.float64)
    except OSError as exc:
        where = f"{getattr(data, 'name', 'dataset')} of {getattr(getattr(data, 'file', None), 'filename', 'the file')}"
        raise RampFileError(f"{where}: unreadable rows {y0}-{y1} ({one_line(exc)})") from exc


def _refpix_terms(src, bias, kw):
    """Column and row terms of JWST's reference-pixel correction of every frame (bias removed):
    correction(y, x) = col[i, g, x] + row[i, g, y], from each frame's reference pixels only
    (:func:`~slicersim.reduction.refpix.refpix_offsets`)."""
    from slicersim.reduction.refpix import check_refpix_layout, refpix_offsets
    nints, n, ny, nx = src.shape
    check_refpix_layout((ny, nx), **kw)
    b = int(kw.get("border", 4))
    col, row = np.empty((nints, n, nx)), np.empty((nints, n, ny))
    full_bias = _bias_rows(bias, 0, ny)
    bias_rows = full_bias if not np.ndim(full_bias) else np.concatenate([full_bias[:b], full_bias[-b:]], axis=0)
    bias_cols = full_bias if not np.ndim(full_bias) else np.concatenate([full_bias[:, :b], full_bias[:, -b:]], axis=1)
    for i in range(nints):
        for g in range(n):
            # a file of some rows holds the reference rows (checked): only its rows are read, and the side
            # terms of each range come from that range's rows
            refrows = np.concatenate([src.frame(i, g, 0, b), src.frame(i, g, ny - b, ny)],
                                     axis=0).astype(np.float64) - bias_rows
            row[i, g] = np.nan
            for y0, y1 in src.rows or ((0, ny),):
                part = src.frame(i, g, y0, y1)
                refcols = np.concatenate([part[:, :b], part[:, -b:]], axis=1).astype(np.float64) - \
                    (bias_cols[y0:y1] if np.ndim(bias_cols) else bias_cols)
                col[i, g], row[i, g, y0:y1] = refpix_offsets(refrows, refcols, **kw)
    return col, row


def _check_partial_refpix(src, kw, where):
    """A file of some detector rows corrected with its reference pixels must hold the top and bottom
    reference rows (the column terms come from them alone)."""
    ny = src.shape[2]
    b = int(kw.get("border", 4))
    held = np.zeros(ny, bool)
    for a, c in src.rows:
        held[a:c] = True
    if not (held[:b].all() and held[ny - b:].all()):
        raise RampFileError(f"{where}: the reference-pixel correction needs the top and bottom {b} reference rows, "
                            f"and the file holds only rows {', '.join(f'{a}:{c}' for a, c in src.rows)} "
                            "(refpix=False in Python, --no-refpix on the command line, skips it)")


# ----------------------------------------------------------------------------- driver
@validation.checked_fields
@dataclass(frozen=True, kw_only=True)
class FitOptions:
    """Options of :func:`fit_ramps` (every keyword of its keyword form).

    The keyword form also takes the deprecated names ``read_noise`` (→ ``ron``) and
    ``memory_budget`` (→ ``max_bytes``) with a DeprecationWarning (:meth:`from_keywords`).

    Parameters
    ----------
    refpix, linearity, superbias, jump_threshold, weighting, gain, ron, saturation, with_truth, \
return_groupdq, max_bytes, backend, progress, work_group
        As :func:`fit_ramps`.
    """

    refpix: object = None
    linearity: object = None
    superbias: object = None
    jump_threshold: float | None = DEFAULT_JUMP_THRESHOLD
    weighting: str = "gls"
    gain: float | None = None
    ron: float | None = None
    saturation: float | None = None
    with_truth: bool = False
    return_groupdq: bool = False
    max_bytes: int = 256 << 20
    backend: str = "auto"
    progress: bool | None = None
    work_group: int | None = None

    def __post_init__(self):
        validation.choice("weighting", self.weighting, WEIGHTINGS)
        validation.choice("backend", self.backend, BACKENDS)
        validation.positive_int("max_bytes", self.max_bytes)
        if isinstance(self.work_group, (int, np.integer)) and not isinstance(self.work_group, bool) \
                and self.work_group < 1:        # other types: the class's field check names them
            raise ParameterError(f"FitOptions.work_group must be an integer >= 1 or None, got {self.work_group}")
        for name in ("gain", "ron"):
            if getattr(self, name) is not None:
                low_open = name == "gain"
                unit = "adu / electron" if name == "gain" else "electron"
                object.__setattr__(self, name, validation.number(name, getattr(self, name), low=0, low_open=low_open,
                                                                 high=validation.DETECTOR_MAX[name], unit=unit))
        if self.saturation is not None and (isinstance(self.saturation, (bool, np.bool_, str, bytes)) or not (
                isinstance(self.saturation, (int, float, np.integer, np.floating)) and self.saturation > 0)):
            raise ParameterError(f"saturation must be a number of DN > 0 (or None: the file's), got "
                                 f"{validation.short_repr(self.saturation)}")

    @classmethod
    def from_keywords(cls, where="fit_ramps", /, **kwargs):
        """Options from keywords: each name checked (did-you-mean), the deprecated names
        (``FIT_RENAMED``) moved to their new ones with a DeprecationWarning."""
        for old, new in FIT_RENAMED.items():
            validation.renamed_keyword(kwargs, old, new, where, stacklevel=4)
        for key in kwargs:
            validation.choice("keyword", key, tuple(FIT_DEFAULTS), what=f"keyword of {where}")
        return cls(**kwargs)


#: every option of :func:`fit_ramps` and its default, as data (the reduction identity of a campaign
#: reduction is built from it)
FIT_DEFAULTS = {f.name: f.default for f in fields(FitOptions)}
#: deprecated keyword names of :func:`fit_ramps` → their names now (accepted with a DeprecationWarning)
FIT_RENAMED = {"read_noise": "ron", "memory_budget": "max_bytes"}


def fit_ramps(source, options=None, **kwargs):
    """Fit the rates of a raw ramp.

    Everything is checked before data are read.

    Parameters
    ----------
    source : str, path-like or tuple
        Path of a ramp file (our HDF5 or a JWST level-1b FITS, recognised by content) or arrays
        (SCI (nints, ngroups, ny, nx) [DN], GROUPDQ or None, PIXELDQ or None, attrs) as
        ``read_ramps`` returns them (attrs: NFRAMES, GROUPGAP, TFRAME, GAIN, READNOISE; NINTS,
        NGROUPS, TGROUP, READPATT are checked when present).
    options : FitOptions, optional
        The options, or give its fields as keywords (``fit_ramps(path, weighting="ols")``).
    refpix : bool or dict, optional
        None (when the file's EFFECTS has reference_pixels), True, False, or refpix_correct
        options.
    linearity : str, bool or numpy.ndarray of shape (k, ny, nx), optional
        None (the file's truth coefficients when present), False, "truth" (required), or
        coefficients of the JWST convention (corrected DN = Σ c_k DN^k, bias removed).
    superbias : float or numpy.ndarray of shape (ny, nx), optional
        Bias [DN] removed before the corrections: None (``truth/bias``, else the BIAS keyword),
        a number or a map.
    jump_threshold : float, optional
        σ of the two-point-difference jump test (None or 0: no detection).
    weighting : {"gls", "ols"}, optional
        "gls" (exact MACC covariance) or "ols" (unweighted; its variance is Rauscher07's).
    gain : float, optional
        Gain [DN/e-], overrides the file's GAIN (an astropy Quantity is converted).
    ron : float, optional
        Read noise per frame [electron], overrides READNOISE.
    saturation : float, optional
        Saturation [DN], overrides SATURATION (default 65535 for integer data).
    with_truth : bool, optional
        Also load ``truth/rate`` [e-/s] (RampFileError if the file has none).
    return_groupdq : bool, optional
        Keep GROUPDQ with the SATURATED and JUMP_DET flags set (nints, ngroups, ny, nx).
    max_bytes : int, optional
        Bytes for the row blocks in flight (besides the whole-detector results, and HDF5's chunk cache of
        at most 64 MiB per dataset read, ``io.rampfile.READ_CHUNK_CACHE``).
    backend : {"auto", "opencl", "numpy"}, optional
        Where the fit runs.
    progress : bool or None, optional
        Progress bar (None: when stderr is a terminal and there are more than 8 row blocks).
    work_group : int, optional
        OpenCL local size.

    Returns
    -------
    RateProduct
        The rates, their variances and flags.
    """
    if options is None:
        options = FitOptions.from_keywords(**kwargs)
    elif kwargs or not isinstance(options, FitOptions):
        raise ParameterError("fit_ramps: give options=FitOptions(...) or keywords, not both "
                             f"(got {validation.short_repr(options)} and {sorted(kwargs)})")
    backend = resolve_backend(options.backend)
    with open_ramps(source, "fit_ramps source") as src:
        _check_memory(src, options)
        if backend == "opencl":              # the device's limits, before any data are read
            check_launch(src.shape[1], options.work_group)
        setup = _FitSetup(src, options)
        out = {"rate": np.empty(src.shape[2:]), "variance": np.empty(src.shape[2:]),
               "var_poisson": np.empty(src.shape[2:]), "var_rnoise": np.empty(src.shape[2:]),
               "dq": np.empty(src.shape[2:], np.uint32), "njumps": np.empty(src.shape[2:], np.int32)}
        groupdq = np.empty(src.shape, np.uint8) if options.return_groupdq else None
        _fit_blocks(src, setup, options, backend, out, groupdq)
        attrs = _attrs(src, setup.nmd, setup.tframe, setup.gain, setup.ron, setup.saturation,
                       options.jump_threshold, options.weighting, backend, setup.labels)
    return RateProduct(**out, attrs=attrs, groupdq=groupdq, truth_rate=setup.truth_rate)


def _check_memory(src, options):
    """ResourceError naming the file and SCI's declared shape when the whole-detector outputs (rates,
    variances, DQ; GROUPDQ with ``return_groupdq``, the truth rate) exceed this machine's memory."""
    nints, n, ny, nx = src.shape
    nbytes = ny * nx * (40 + 8 * bool(options.with_truth)) + (nints * n * ny * nx if options.return_groupdq else 0)
    validation.memory(f"{src.name}: the rates of dataset SCI {tuple(src.shape)}", nbytes,
                      hint="the rate images of the whole detector are held in memory (max_bytes bounds only "
                           "the row blocks)")


fit_ramps.__signature__ = inspect.Signature(
    [inspect.Parameter("source", inspect.Parameter.POSITIONAL_OR_KEYWORD),
     inspect.Parameter("options", inspect.Parameter.POSITIONAL_OR_KEYWORD, default=None)]
    + [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default) for f in fields(FitOptions)])


class _FitSetup:
    """Everything :func:`fit_ramps` decides before reading data: readout, saturation, fit constants,
    corrections (refpix terms, linearity, bias), truth rate, rows per block."""

    def __init__(self, src, options):
        where = src.name
        nints, n, ny, nx = src.shape
        self.nmd, self.tframe, self.gain, self.ron = ramp_readout(src.attrs, src.shape, options.gain, options.ron,
                                                              where)
        self.saturation = options.saturation
        if self.saturation is None:
            self.saturation = keyword_number(src.attrs, "SATURATION", where) if "SATURATION" in src.attrs else (
                65535.0 if src.integer else math.inf)
            if not self.saturation > 0:
                raise RampFileError(f"{where}: keyword SATURATION = {self.saturation} DN must be > 0")
        self.consts = fit_constants(self.nmd, self.tframe, self.gain, self.ron,
                                    1.0 / 12.0 if src.integer else 0.0, self.saturation, options.jump_threshold,
                                    options.weighting)
        refpix_kw, self.coeffs, self.bias, self.labels = _plan_corrections(src, options.refpix, options.linearity,
                                                                           options.superbias, where)
        self.truth_rate = None
        if options.with_truth:
            truth = src.truth("rate")
            if truth is None:
                raise RampFileError(f"{where}: with_truth=True but the file has no truth/rate")
            from slicersim.io.rampfile import read_dataset     # a failed checksum named, not h5py's words
            self.truth_rate = np.asarray(read_dataset(truth, where) if hasattr(truth, "id") else truth[...],
                                         np.float64)
        self.corrected = refpix_kw is not None or self.coeffs is not None or not src.integer
        # bytes per pixel-group: SCI + GROUPDQ on the host and the device (+ GROUPDQ out, + float DN, its
        # temporary and device copy with corrections); per pixel: the outputs of a block, twice
        per_row = nx * (nints * n * (6 + (2 if options.return_groupdq else 0) + (24 if self.corrected else 0)) + 96)
        self.rows = rows_per_block(options.max_bytes, per_row, ny, chunk=getattr(src, "chunk_rows", 1),
                                   what="one detector row", name="max_bytes")
        if refpix_kw is not None and src.rows is not None:
            _check_partial_refpix(src, refpix_kw, where)
        self.terms = _refpix_terms(src, self.bias, refpix_kw) if refpix_kw is not None else None


#: the per-pixel images of a fit, in the order of the kernel's outputs
_OUT_KEYS = ("rate", "variance", "var_poisson", "var_rnoise", "dq", "njumps")


def _fit_blocks(src, setup, options, backend, out, groupdq):
    """Read, correct and fit every row block into ``out`` (and ``groupdq``); on OpenCL the next block is
    read while the device fits the last one (two host buffer sets, :func:`pipelined`)."""
    nints, n, ny, nx = src.shape
    blocks = RowBlocks(ny, setup.rows, progress=options.progress, desc="ramp fit", auto_min=8, ranges=src.rows)
    if src.rows is not None:
        _not_simulated(src.rows, out, groupdq)
    ring = BufferRing(nints * n * setup.rows * nx, (np.uint16 if src.integer else np.float64, np.uint8),
                      nsets=2 if backend == "opencl" else 1)
    workspace = {}

    def launch(step):
        _, y0, y1 = step
        shape = (nints, n, y1 - y0, nx)
        sci, gdq = ring.next(shape)
        src.read(y0, y1, sci, gdq)
        consts = setup.consts
        if setup.corrected:
            sci, consts = _correct(sci, gdq, y0, y1, setup.consts, setup.bias, setup.terms, setup.coeffs)
        npix = (y1 - y0) * nx
        flat = (sci.reshape(nints, n, npix), gdq.reshape(nints, n, npix), src.pixeldq(y0, y1).reshape(npix), consts)
        if backend == "opencl":                 # written straight into the images (no copy, no fresh memory)
            return fit_block_opencl(*flat, workspace=workspace, work_group=options.work_group,
                                    want_gdq=options.return_groupdq, wait=False,
                                    out=tuple(out[key][y0:y1].reshape(npix) for key in _OUT_KEYS))
        return fit_block_numpy(*flat)

    def store(step, results):
        _, y0, y1 = step
        fit, dq, nj, gout = results
        for key, val in zip(_OUT_KEYS, (*fit, dq, nj)):
            target = out[key][y0:y1]
            if not np.shares_memory(target, val):
                target[...] = val.reshape(y1 - y0, nx)
        if groupdq is not None:
            groupdq[:, :, y0:y1] = gout.reshape(nints, n, y1 - y0, nx)

    pipelined(blocks, launch, store)


def fitted_rows(rates):
    """The row ranges [y0, y1) a :class:`RateProduct` holds rates for (a ramp file of some rows), or None
    when it covers the whole detector."""
    value = rates.attrs.get(SIMULATED_ROWS)
    if value is None:
        return None
    if isinstance(value, (str, bytes)):
        value = json.loads(value)
    return row_ranges(value, rates.rate.shape[0], SIMULATED_ROWS)


def _not_simulated(ranges, out, groupdq):
    """Rows outside ``ranges`` (a file of some detector rows): NaN rates and variances, DO_NOT_USE."""
    edges = [0] + [y for pair in ranges for y in pair] + [out["rate"].shape[0]]
    for a, b in zip(edges[::2], edges[1::2]):                   # the gaps, as slices (no boolean indexing)
        for key in ("rate", "variance", "var_poisson", "var_rnoise"):
            out[key][a:b] = np.nan
        out["dq"][a:b] = DQ_DO_NOT_USE
        out["njumps"][a:b] = 0
        if groupdq is not None:
            groupdq[:, :, a:b] = DQ_DO_NOT_USE


def _correct(raw, gdq, y0, y1, consts, bias, terms, coeffs):
    """Float DN of a block after saturation flags (raw DN), superbias, reference pixels, linearity;
    one (integration, group) plane at a time, so that the polynomial's passes stay in the cache (the
    whole block at once was memory-bound: 30 of 76 CPU-s of an effects reduction)."""
    from dataclasses import replace
    from slicersim.physics.nonlinearity import apply_correction
    if raw.dtype == np.uint16:
        gdq |= (raw >= consts.satlim).view(np.uint8) * np.uint8(DQ_SATURATED)
    nints, n = raw.shape[:2]
    dn = np.empty(raw.shape, np.float64)
    base = _bias_rows(bias, y0, y1)
    c = None if coeffs is None else _rows(coeffs, y0, y1)
    scratch = np.empty(raw.shape[2:], np.float64) if c is not None else None
    for i in range(nints):
        for k in range(n):
            plane = dn[i, k]
            np.subtract(raw[i, k], base, out=plane)
            if terms is not None:
                col, row = terms
                plane -= col[i, k][None, :]
                plane -= row[i, k, y0:y1, None]
            if c is not None:
                np.copyto(scratch, plane)
                with np.errstate(invalid="ignore", over="ignore"):     # non-finite: DO_NOT_USE below
                    apply_correction(scratch, c, out=plane)
            bad = ~np.isfinite(plane)
            if bad.any():
                gdq[i, k][bad] |= np.uint8(DQ_DO_NOT_USE)
                plane[bad] = 0.0
    return dn, replace(consts, satlim=math.inf) if raw.dtype == np.uint16 else consts


def _attrs(src, nmd, tframe, gain, ron, saturation, jump_threshold, weighting, backend, labels):
    from slicersim.versioning import __version__
    n, m, d = nmd
    attrs = {"BUNIT": "e-/s", "VARUNIT": "e-2/s2", "SOURCE": src.name, "FORMAT": src.kind,
             "NINTS": src.shape[0], "NGROUPS": n, "NFRAMES": m, "GROUPGAP": d, "TFRAME": tframe,
             "TGROUP": (m + d) * tframe, "GAIN": gain, "READNOISE": ron, "SATURATION": saturation,
             "WEIGHTING": weighting, "JUMP_THRESHOLD": float(jump_threshold or 0.0), "BACKEND": backend,
             "SOFTWARE": "slicersim", "VERSION": __version__, **labels}
    if src.rows is not None:                 # a file of some rows: the others are NaN (DO_NOT_USE)
        attrs[SIMULATED_ROWS] = [list(r) for r in src.rows]
    keys = ("DARK", "THERMAL_DARK", "ROIC_GLOW")
    if all(k in src.attrs for k in keys):
        attrs["DARK_RATE"] = (keyword_number(src.attrs, "DARK", src.name) + keyword_number(src.attrs, "THERMAL_DARK", src.name)
                              + keyword_number(src.attrs, "ROIC_GLOW", src.name) / tframe)
    return attrs
