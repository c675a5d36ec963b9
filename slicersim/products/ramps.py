"""Raw up-the-ramp H4RG reads: exact sampling of MACC(n, m, d) ramps.

Readout physics in small documented steps (cf. romanisim ``l1``), run by :func:`simulate`:

1. inputs checked (:func:`check_rate`), effects resolved, sizes planned (row blocks of the shared
   engine :mod:`slicersim.io.row_blocks`) and the output checked before anything is allocated;
2. *expected counts* — :func:`expected_frame_charge`: the mean charge collected per frame
   μ = (rate + dark + thermal dark)·t_f + ROIC glow [e-/frame] (:func:`frame_mean_charge`), after
   the detector effects' photo-response (bad pixels' QE and dark, reference pixels);
3. *noise realization* — :func:`realize_ramps`: per row block, charge accumulation as a Poisson
   process sampled exactly by one of two paths chosen from μ only (*dense*: a Poisson increment
   in every frame; *sparse*, μ·(m+d) < ``sparse_max_group``: per group window a Poisson count and
   a uniform frame for each event), full-well clipping, group averaging of the m reads with read
   noise σ_r/√m per group, kTC reset noise once per ramp, then :func:`to_adu` (bias + gain,
   rounding, uint16 saturation) and the GROUPDQ flags (JWST SATURATED = 2).

Randomness is Philox4x32-10 keyed by (seed, ramp, pixel, frame or group): the output is identical
for any chunking, work-group size, vector width or device count.  The OpenCL kernels are in
``kernels/ramp.cl``; :func:`simulate_block_numpy` is their bit-exact NumPy twin.

Two call forms give the same ramps for the same seed::

    simulate(rate, RampParameters(nmd=(16, 8, 0), ron=12.0), seed=1, out="raw.h5")   # -> RampResult
    simulate(rate, nmd=(16, 8, 0), ron=12.0, seed=1, out="raw.h5")                   # -> path (as before)
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from slicersim import validation
from slicersim.backends.dispatch import BACKENDS
from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
from slicersim.errors import EffectsError, ParameterError, ResourceError
from slicersim.io.rampfile import DQ, RampWriter
from slicersim.io.row_blocks import SIMULATED_ROWS, BackgroundLanes, BufferRing, RowBlocks, row_ranges, rows_per_block
from slicersim.io.uncal_meta import GROUPDQ_FLAGS  # noqa: F401
from slicersim.products.ramp_options import (DEFAULT_MAX_BYTES, FILE_FORMATS, DetectorMaps, RampIO,  # noqa: F401
                                             RampResult, RunOptions)
from slicersim.physics.ramp import (DEFAULT_BIAS, RampParameters, check_frame_charge, frame_mean_charge,  # noqa: F401
                                    macc_frame_schedule, readpatt)
from slicersim.physics.readout import readout_times  # noqa: F401

__all__ = ["simulate", "RampParameters", "RampIO", "RunOptions", "DetectorMaps", "RampResult",
           "check_rate", "expected_frame_charge", "realize_ramps", "frame_mean_charge", "macc_frame_schedule",
           "readpatt", "fit_slopes", "DEFAULT_BIAS", "DEFAULT_MAX_BYTES"]

#: the keyword form of :func:`simulate`, in its historical positional order after ``rate``
_LEGACY_ORDER = ("nmd", "nramps", "seed", "out", "tframe", "ron", "dark", "thermal_dark", "roic_glow", "gain",
                 "saturation", "bias", "ktc_noise", "full_well", "dead_pixels", "pixeldq", "sparse_max_group",
                 "gauss_min_mean", "compression", "max_bytes", "truth", "config", "backend", "progress",
                 "work_group", "return_dq", "overwrite", "effects", "previous_charge", "file_format", "precision",
                 "target", "groupdq", "window", "rows")
_READOUT_KEYS = ("nmd", "nramps", "tframe", "ron", "dark", "thermal_dark", "roic_glow", "gain", "saturation",
                 "bias", "ktc_noise", "full_well", "sparse_max_group", "gauss_min_mean")
_LEGACY_READOUT_DEFAULTS = {"nmd": (16, 8, 0), "nramps": 1, "tframe": 2.83, "ron": 12.0, "dark": 2.8e-3,
                            "thermal_dark": 0.0, "roic_glow": 3e-3, "gain": 1.0, "saturation": 65535,
                            "bias": DEFAULT_BIAS, "ktc_noise": 0.0, "full_well": None, "sparse_max_group": None,
                            "gauss_min_mean": np.inf}
_IO_KEYS = {"file_format": "format", "overwrite": "overwrite", "compression": "compression", "truth": "truth",
            "config": "config", "return_dq": "return_dq", "target": "target", "groupdq": "groupdq",
            "window": "window", "rows": "rows"}
_RUN_KEYS = ("max_bytes", "progress", "work_group")
_MAP_KEYS = ("dead_pixels", "pixeldq", "previous_charge")
_NAMED = ("seed", "out", "backend", "effects", "precision")


def simulate(rate, readout=None, *args, seed=None, effects=None, out=None, backend="auto", precision="auto",
             io=None, run=None, maps=None, **kwargs):
    """Simulate raw MACC ramps of a rate image.

    The output size is checked against the free disk space (``out``) or memory (``out`` None)
    before anything is allocated.

    Parameters
    ----------
    rate : array_like of shape (ny, nx)
        Photo-electron rate [e-/s] (detector terms are added here).
    readout : RampParameters
        Readout and detector: nmd, nramps, tframe [s], ron [electron], dark [e-/s, scalar or
        image], thermal_dark [e-/s], roic_glow [e-/frame], gain [ADU/e-], saturation [ADU],
        bias [ADU], ktc_noise [e-], full_well [e-], sparse_max_group, gauss_min_mean.
    *args
        The keyword form's positional arguments (see Notes).
    seed : int, optional
        Integer in [0, 2⁶⁴), or None (default): a fresh seed
        (:func:`slicersim.validation.new_seed`), recorded in the file's SEED attribute and
        returned.
    effects : str, dict or object, optional
        Detector systematics (off by default): names (``"cosmic_rays,ipc"``, ``"all"``), a
        preset (``"lazuli"``), a config dict or a ``DetectorEffects``
        (``slicersim.products.effects``); their truth goes to ``truth/<name>`` of ``out``.
        ``"all"`` includes ``persistence`` only with ``maps.previous_charge``.
    out : str or path-like, optional
        Output path (HDF5 or JWST level-1b FITS, see ``RampIO``) or None (SCI in memory).
    backend : {"auto", "opencl", "numpy"}, optional
        Where the ramps are computed.
    precision : {"auto", "double", "single"}, optional
        Arithmetic of the kernel (single: the same Philox words, ~1e-3 of the values differ by
        1 ADU, same statistics).
    io : RampIO, optional
        Output options (format, overwrite, compression, truth, config, return_dq, target, groupdq, window).
    run : RunOptions, optional
        Execution options (max_bytes, progress, work_group).
    maps : DetectorMaps, optional
        Per-pixel detector maps.
    **kwargs
        The keyword form (see Notes).

    Returns
    -------
    RampResult
        ``seed`` (the one used: record it to repeat the run), ``path`` of the file (None in
        memory), ``sci`` of shape (nramps, ngroups, ny, nx) uint16 [ADU] and ``groupdq`` uint8
        in memory (None with a file; GROUPDQ only with ``io.return_dq``), ``attrs`` (the
        file's root attributes).  The keyword form returns what it did before (see Notes).

    Notes
    -----
    **Keyword form** (kept from slicersim 0.1): ``simulate(rate, nmd=(16, 8, 0), nramps=1, seed=None,
    out=None, tframe=2.83, ron=12.0, dark=2.8e-3, ..., memory_budget=2**29, file_format=None, ...)``:
    every keyword of :class:`RampParameters`, :class:`RampIO` (``file_format`` for ``format``),
    :class:`RunOptions` (``memory_budget`` is the deprecated name of ``max_bytes``) and
    :class:`DetectorMaps`, loose; it returns, as before, the absolute path written (a str; the seed is
    its SEED attribute) or SCI (and GROUPDQ with ``return_dq``).  The same seed gives the same ramps in
    both forms.
    """
    named = {"seed": seed, "effects": effects, "out": out, "backend": backend, "precision": precision}
    if isinstance(readout, RampParameters):
        if args or kwargs:
            extra = list(kwargs) or [f"{len(args)} positional argument(s)"]
            raise ParameterError(f"simulate(rate, readout=RampParameters(...)): put {', '.join(extra)} in "
                                 "readout, io=RampIO(...), run=RunOptions(...) or maps=DetectorMaps(...)")
        for name, obj, cls in (("io", io, RampIO), ("run", run, RunOptions), ("maps", maps, DetectorMaps)):
            if obj is not None and not isinstance(obj, cls):
                raise ParameterError(f"{name} must be a {cls.__name__} or None, got {validation.short_repr(obj)}")
        return _simulate(rate, readout, named, io or RampIO(), run or RunOptions(), maps or DetectorMaps())
    return _simulate_keywords(rate, readout, args, kwargs, named, (io, run, maps))


def _simulate_keywords(rate, nmd, args, kwargs, named, objects):
    """The keyword form of :func:`simulate`: loose keywords → RampParameters, RampIO, RunOptions,
    DetectorMaps; returns the path or SCI [, GROUPDQ] as slicersim 0.1 did."""
    if any(o is not None for o in objects):
        raise ParameterError("io=, run= and maps= go with readout=RampParameters(...); with nmd= give their "
                             "fields as keywords")
    validation.renamed_keyword(kwargs, "memory_budget", "max_bytes", "simulate", stacklevel=4)
    validation.renamed_keyword(kwargs, "read_noise", "ron", "simulate", stacklevel=4)
    if len(args) > len(_LEGACY_ORDER) - 1:
        raise ParameterError(f"simulate takes at most {len(_LEGACY_ORDER)} positional arguments after rate")
    given = dict(zip(_LEGACY_ORDER[1:], args))
    if nmd is not None:
        given["nmd"] = nmd
    for key, val in kwargs.items():
        if key not in _LEGACY_ORDER:
            validation.choice("keyword", key, list(_LEGACY_ORDER), what="keyword of simulate")
        if key in given:
            raise ParameterError(f"simulate: {key} given twice (positionally and as a keyword)")
        given[key] = val
    for key in _NAMED:
        if key in given:
            if named[key] not in (None, "auto"):
                raise ParameterError(f"simulate: {key} given twice (positionally and as a keyword)")
            named[key] = given.pop(key)
    readout = RampParameters(**(_LEGACY_READOUT_DEFAULTS | {k: given[k] for k in _READOUT_KEYS if k in given}))
    io = RampIO(**{_IO_KEYS[k]: given[k] for k in _IO_KEYS if k in given})
    run = RunOptions(**{k: given[k] for k in _RUN_KEYS if k in given})
    maps = DetectorMaps(**{k: given[k] for k in _MAP_KEYS if k in given})
    result = _simulate(rate, readout, named, io, run, maps)
    if result.path is not None:
        return result.path
    return (result.sci, result.groupdq) if io.return_dq else result.sci


def check_rate(rate):
    """The rate image [e-/s] as a finite, non-negative (ny, nx) float64 array (ParameterError naming
    ``rate`` for NaN, negative, complex, structured, object or non-2-D input)."""
    rate = validation.array("rate", rate, ndim=2, low=0.0, unit="electron / s")
    if rate.size == 0:
        raise ParameterError(f"{validation.shown('rate')} must be a non-empty 2-D image (ny, nx), got shape "
                             f"{rate.shape}")
    if rate.size >= 2**32:
        raise ParameterError(f"rate has {rate.size} pixels: pixel indices must fit in 32 bits")
    return rate


def _check_maps(maps, shape):
    """(dead mask (ny, nx) bool, pixeldq or None, previous charge or None) checked against ``shape``."""
    dead = None
    if maps.dead_pixels is not None:
        dead = np.asarray(maps.dead_pixels, bool)
        if dead.shape != shape:
            raise ParameterError(f"dead_pixels must have the shape of rate {shape}, got {dead.shape}")
    pixeldq = None
    if maps.pixeldq is not None:
        pixeldq = validation.array("pixeldq", maps.pixeldq, ndim=2, dtype=np.uint32, low=0)
        if pixeldq.shape != shape:
            raise ParameterError(f"pixeldq must have the shape of rate {shape}, got {pixeldq.shape}")
    return dead, pixeldq, maps.previous_charge


def _simulate(rate, p, named, io, run, maps):
    """The steps of :func:`simulate` (see the module docstring); returns a :class:`RampResult`."""
    rate = check_rate(rate)
    if np.ndim(p.dark) and np.shape(p.dark) != rate.shape:
        raise ParameterError(f"dark must be a number or an image of the shape of rate {rate.shape}, "
                             f"got shape {np.shape(p.dark)}")
    check_frame_charge(rate, p)
    seed = validation.seed(named["seed"])
    seed = validation.new_seed() if seed is None else seed
    dead, pixeldq, previous_charge = _check_maps(maps, rate.shape)
    fx = _resolve_effects(named["effects"], previous_charge)
    backend, precision = _resolve_backend(named["backend"], named["precision"])
    out = named["out"]
    if out is not None and not isinstance(out, (str, bytes, os.PathLike)):
        raise ParameterError(f"out must be a file path (str or os.PathLike) or None, got {validation.short_repr(out)}")
    from slicersim.products.windows import check_window
    window = check_window(io.window, rate.shape)
    out_shape = rate.shape if window is None else window.shape
    ranges = _check_rows(io, window, out, rate.shape)
    rows, noise_cache = _block_rows(p, fx, rate.shape, run.max_bytes)
    writer = _open_writer(out, io, p, fx, rate.shape, rows, window, ranges) if out is not None else None
    if writer is None:
        _check_memory(p, out_shape, io.return_dq, run.max_bytes)
    expected = expected_frame_charge(rate, p, seed, fx, dead, pixeldq, previous_charge, noise_cache, precision)
    noise = getattr(expected.plan, "noise", None)
    if ranges is not None and noise is not None:
        noise.rows = ranges                 # the correlated noise's per-ramp terms on those rows only
    attrs = _file_attrs(p, seed, backend, precision, io.config, fx)
    if window is not None:
        attrs.update(window.attrs())
    if ranges is not None:
        attrs[SIMULATED_ROWS] = [list(r) for r in ranges]
    want_dq = io.return_dq if writer is None else getattr(writer, "groupdq_flags", "truth") == "truth"
    sampler = _Sampler(p, seed, backend, precision, run.work_group, want_dq=want_dq)
    first, last = (0, rate.shape[0]) if window is None else (window.y0, window.y0 + window.ny)
    blocks = RowBlocks(last, rows, nouter=p.nramps, progress=run.progress, desc="ramps", first=first, ranges=ranges)
    if writer is None:
        sci, gdq = realize_ramps(expected, sampler, blocks, None, io, window)
        return RampResult(seed=seed, sci=sci, groupdq=gdq, attrs=attrs)
    writer.attrs = attrs
    with writer as w:
        if io.target is not None:
            from slicersim.io.target_truth import write_target_truth
            write_target_truth(w, io.target)
        realize_ramps(expected, sampler, blocks, w, io, window)
    return RampResult(seed=seed, path=os.path.abspath(out), attrs=attrs)


def _check_rows(io, window, out, shape):
    """The row ranges of ``io.rows`` (None: every row), refused with a window or without an out file."""
    if io.rows is None:
        return None
    if window is not None:
        raise ParameterError("give window or rows, not both")
    if out is None:
        raise ParameterError("rows (a ramp of some detector rows) needs an HDF5 out file: in memory the other "
                             "rows would be undefined")
    if _writer_class(out, io.format) is not RampWriter:
        raise ParameterError("rows (a ramp of some detector rows) needs an HDF5 out file: a level-1b file "
                             "holds whole frames")
    return row_ranges(io.rows, shape[0], "rows")


def _resolve_effects(effects, previous_charge):
    from slicersim.products.effects import resolve_effects
    fx = resolve_effects(effects, has_previous_charge=previous_charge is not None)
    if previous_charge is not None and (fx is None or "persistence" not in fx.enabled):
        raise EffectsError("previous_charge is given but the persistence effect is not enabled "
                           "(add 'persistence' to effects)")
    return fx


def _resolve_backend(backend, precision):
    """(backend, precision) resolved for the ramp samplers; ParameterError naming a bad one."""
    from slicersim.backends.precision import check_precision, resolve_precision
    validation.choice("backend", backend, BACKENDS)
    check_precision(precision)
    return resolve_precision(precision, backend, "ramp")


def _block_rows(p, fx, shape, max_bytes):
    """(rows per block, bytes kept for the correlated-noise cache) for ``max_bytes``."""
    ny, nx = shape
    n = p.nmd[0]
    # bytes per pixel in flight: mu + dead + index list + SCI + GDQ (host and device copies); with
    # effects also the group means (8 B), flags, read-domain noise (4 B) and deposits
    per_row = nx * (8 + 1 + 4 + 3 * n) * 2 if fx is None else nx * (8 + 1 + 4 + 16 + 16 * n) * 2
    # with correlated noise, up to half of the budget keeps the noise segments that span row blocks: one per
    # group (below that, segments are synthesised again block after block)
    noise_cache = 0
    if fx is not None and "correlated_noise" in fx.enabled:
        from slicersim.backends.correlated_noise import segment_cache_bytes
        need = segment_cache_bytes(fx.params("correlated_noise"), shape, p.nmd, p.tframe)
        noise_cache = min(max_bytes // 2, max(max_bytes // 3, need + need // 16))
    what = f"one detector row for {n} groups"
    return rows_per_block(max_bytes, per_row, ny, reserve=noise_cache, what=what), noise_cache


def _open_writer(out, io, p, fx, shape, rows, window=None, ranges=None):
    """The checked (not yet opened) writer of ``out`` (of the row ``ranges`` only, when given): nothing is
    simulated before it is known to fit."""
    from slicersim.products.effects import EffectsPlan
    writer_class = _writer_class(out, io.format)
    truth_bytes = EffectsPlan.truth_nbytes(fx, p, shape) if (fx is not None and io.truth) else 0
    extra = {}
    if writer_class is RampWriter:
        if io.groupdq not in (None, "truth"):
            raise ParameterError(f"groupdq {io.groupdq!r} is for level-1b files (jwst-uncal): an HDF5 ramp file "
                                 "keeps the simulator's flags")
        if ranges is not None:
            extra["rows"] = ranges
    else:
        extra["groupdq_flags"] = io.groupdq or "none"
        if window is not None:
            extra.update(detector_shape=shape, substrt=window.substrt)
    shape = shape if window is None else window.shape
    return writer_class(out, p.nramps, p.nmd[0], shape, row_block=min(rows, 256), compression=io.compression,
                        truth_rate=io.truth, overwrite=io.overwrite, extra_bytes=truth_bytes, **extra).check()


def _check_memory(p, shape, return_dq, max_bytes):
    """ResourceError (a MemoryError) when SCI (and GROUPDQ) in memory would exceed 16 × max_bytes or the
    memory available."""
    full_bytes = p.nramps * p.nmd[0] * shape[0] * shape[1] * (3 if return_dq else 2)
    if full_bytes > 16 * max_bytes:
        raise ResourceError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB (more than 16 × max_bytes): "
                            "pass out=<file.h5>")
    avail = _available_memory()
    if avail is not None and full_bytes > avail:
        raise ResourceError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB, "
                          f"{avail / 2**30:.1f} GiB available: pass out=<file.h5>")


@dataclass
class ExpectedCharge:
    """The expected-counts step's result: ``mu`` (ny, nx) mean charge per frame [e-]; ``dead`` pixels
    collecting no charge; ``dq_dead`` the user's dead pixels (flagged DEAD); ``pixeldq`` flags;
    ``rate`` the input rate (truth); ``plan`` the effects plan or None."""

    mu: np.ndarray
    dead: np.ndarray
    dq_dead: np.ndarray
    pixeldq: np.ndarray | None
    rate: np.ndarray
    plan: object = None


def expected_frame_charge(rate, p, seed, fx, dead, pixeldq, previous_charge, noise_cache, precision):
    """Expected counts: μ [e-/frame] per pixel (no noise drawn here), after the effects' photo-response
    (their maps are drawn from ``seed``); returns an :class:`ExpectedCharge`."""
    dead = np.zeros(rate.shape, bool) if dead is None else dead
    dq_dead, plan, rate_in = dead, None, rate
    dark = np.asarray(p.dark, dtype=float)
    if fx is not None:
        from slicersim.products.effects import EffectsPlan
        plan = EffectsPlan(fx, p, seed, rate.shape, previous_charge, noise_cache_bytes=noise_cache)
        rate, dark, no_charge, flags = plan.rate_and_dark(rate, dark, dead)
        flags[dead] |= np.uint32(DQ["DEAD"] | DQ["DO_NOT_USE"])              # the user's dead pixels
        pixeldq = flags if pixeldq is None else (pixeldq | flags)
        dead = dead | no_charge
    mu = frame_mean_charge(rate, dark, p.thermal_dark, p.roic_glow, p.tframe)
    if precision == "single":
        mu = _single_frame_means(mu, p)
    return ExpectedCharge(mu, dead, dq_dead, pixeldq, rate_in, plan)


def _file_attrs(p, seed, backend, precision, config, fx):
    """Root attributes of the raw file (JWST-like names, the seed, the detector terms)."""
    attrs = p.attrs(seed)
    attrs.update({"SOFTWARE": "slicersim", "VERSION": _version(), "BACKEND": backend, "PRECISION": precision,
                  "CONFIG": config if config is not None else {}, "DARK": float(np.mean(p.dark)),
                  "THERMAL_DARK": p.thermal_dark, "ROIC_GLOW": p.roic_glow, "KTC_NOISE": p.ktc_noise})
    if fx is not None:
        attrs["EFFECTS"] = fx.to_config()
    return attrs


class _Sampler:
    """The noise realization of one row block: SCI, GROUPDQ (n, rows, nx) of one ramp, by the plain
    samplers or, with effects, the charge sampler and the readout (:func:`_effects_block`)."""

    def __init__(self, p, seed, backend, precision, work_group, want_dq):
        self.p, self.seed, self.backend, self.precision = p, seed, backend, precision
        self.opencl = backend == "opencl"
        self.kwargs = {"work_group": work_group, "want_dq": want_dq, "workspace": {}, "precision": precision} \
            if self.opencl else {}
        self.ring = None

    def effects(self, expected, ramp, y0, y1):
        return _effects_block(expected.plan, expected.mu, expected.dead, ramp, y0, y1, self.seed, self.p,
                              self.backend, self.kwargs)

    def plain(self, expected, ramp, y0, y1, out=None):
        """SCI, GROUPDQ (n, rows·nx) of rows [y0, y1); ``out``: (sci, gdq) host buffers to fill (OpenCL)."""
        mu, dead, nx = expected.mu, expected.dead, expected.mu.shape[1]
        block = simulate_block_opencl if self.opencl else simulate_block_numpy
        extra = {} if out is None else {"out": out}
        return block(mu[y0:y1].ravel(), dead[y0:y1].ravel(), y0 * nx, ramp, self.seed, self.p,
                     **self.kwargs, **extra)

    def reused(self, rows, nx, npix):
        """One pair of host buffers for every block of a file (OpenCL), cut to ``npix`` pixels."""
        n = self.p.nmd[0]
        if self.ring is None:
            self.ring = BufferRing(n * rows * nx, (np.uint16, np.uint8))
        sci, gdq = self.ring.sets[0]
        return sci[:n * npix].reshape(n, npix), gdq[:n * npix].reshape(n, npix)


def realize_ramps(expected, sampler, blocks, writer, io, window=None):
    """Noise realization of every ramp, block by block: to ``writer`` (with the PIXELDQ and truth), or
    in memory; returns (SCI, GROUPDQ or None) in memory, else (None, None).  ``window``: a
    :class:`~slicersim.products.windows.Window`, the only pixels kept (``blocks`` cover its rows)."""
    p, plan = sampler.p, expected.plan
    ny, nx = expected.mu.shape if window is None else window.shape
    cut = (lambda image: image) if window is None else window.cut
    n = p.nmd[0]
    if writer is None:
        sci = np.empty((p.nramps, n, ny, nx), np.uint16)
        gdq = np.empty((p.nramps, n, ny, nx), np.uint8) if io.return_dq else None
        sink = memory = _MemorySink(sci, gdq)
    else:
        writer.write_pixeldq(cut(_pixeldq(expected.pixeldq, expected.dq_dead, expected.rate.shape)))
        if io.truth:
            writer.write_truth(cut(expected.rate))
        sink = writer
    if window is not None:
        from slicersim.products.windows import WindowSink
        sink = WindowSink(sink, window)
    expected.pixeldq = None                            # written: 4 B per pixel less in the blocks
    # effects into an HDF5 file: their truth (mostly single-threaded NumPy) and the HDF5 writes of
    # the blocks run in two background threads while this one computes the next blocks
    lanes = BackgroundLanes() if (plan is not None and isinstance(writer, RampWriter)) else None
    try:
        _write_effects_truth(plan, writer, lanes, p.nramps, io.truth)
        for ramp, y0, y1 in blocks:
            _realize_block(expected, sampler, sink, lanes, ramp, y0, y1, blocks.rows)
    except BaseException:
        if lanes is not None:
            lanes.finish(raise_error=False)            # the file is aborted after the lanes stop
        raise
    if lanes is not None:
        lanes.finish()
    return (memory.sci, memory.gdq) if writer is None else (None, None)


def _write_effects_truth(plan, writer, lanes, nramps, truth):
    """The effects' truth: with lanes, the bad-pixel maps first, here, then freed (3 × 4 B per pixel
    less while the blocks run) and the rest in the background; else all of it now."""
    if plan is None:
        return
    if lanes is not None:
        if truth:
            plan.write_truth(writer, nramps, part="maps")
        plan.drop_photo_maps()
        if truth:
            lanes.submit("truth", plan.write_truth, writer, nramps, "rest")
        return
    if writer is not None and truth:
        plan.write_truth(writer, nramps)
    plan.drop_photo_maps()                             # used by rate_and_dark and the truth only


class _Observed:
    """A writer's ``write_block`` given the saturation level of the block."""

    def __init__(self, write_block):
        self.write_block = write_block


class _MemorySink:
    """SCI (and GROUPDQ) in memory, written like a file by row blocks."""

    def __init__(self, sci, gdq):
        self.sci, self.gdq = sci, gdq

    def write_block(self, ramp, y0, sci, gdq):
        self.sci[ramp, :, y0:y0 + sci.shape[1]] = sci
        if self.gdq is not None:
            self.gdq[ramp, :, y0:y0 + sci.shape[1]] = gdq


def _observed_level(p, plan, y0, y1):
    """Saturation level [DN] a level-1b file's observed flags use for rows [y0, y1) (per pixel with
    effects: bias map, nonlinear full well), :func:`slicersim.io.uncal_meta.saturation_reference`."""
    from slicersim.io.uncal_meta import group_sigma_dn, saturation_reference
    plateau = p.bias + p.gain * p.full_well if plan is None else plan.plateau_block(y0, y1)
    return saturation_reference(plateau, p.saturation, group_sigma_dn(p.gain, p.ron, p.nmd[1], p.ktc_noise))


def _realize_block(expected, sampler, sink, lanes, ramp, y0, y1, rows):
    """One row block of one ramp into ``sink`` (a writer, or memory)."""
    ny, nx = expected.mu.shape
    n = sampler.p.nmd[0]
    shape = (n, y1 - y0, nx)
    if getattr(sink, "groupdq_flags", None) == "observed":         # level-1b: flags from the observed DN
        level = _observed_level(sampler.p, expected.plan, y0, y1)
        write = sink.write_block
        sink = _Observed(lambda r, y, s, q: write(r, y, s, q, saturation=level))
    if expected.plan is not None:
        sci, gdq = sampler.effects(expected, ramp, y0, y1)
        if lanes is not None:                          # fresh arrays each block: handed over
            lanes.submit("write", sink.write_block, ramp, y0, sci, gdq)
        else:
            sink.write_block(ramp, y0, sci, gdq)
        return
    if isinstance(sink, _MemorySink) and sampler.opencl and y0 == 0 and y1 == ny:     # whole ramp: no copy
        gdq = None if sink.gdq is None else sink.gdq[ramp].reshape(n, -1)
        sampler.plain(expected, ramp, y0, y1, out=(sink.sci[ramp].reshape(n, -1), gdq))
        return
    out = sampler.reused(rows, nx, (y1 - y0) * nx) if (sampler.opencl and not isinstance(sink, _MemorySink)) \
        else None
    sci, gdq = sampler.plain(expected, ramp, y0, y1, out=out)
    sink.write_block(ramp, y0, sci.reshape(shape), None if gdq is None else gdq.reshape(shape))


def _effects_block(plan, mu, dead, ramp, y0, y1, seed, p, backend, kwargs):
    """SCI, GROUPDQ (n, y1 − y0, nx) of rows [y0, y1) with detector effects (charge on the rows ± the
    IPC halo, then the readout)."""
    from slicersim.backends import ramp_effects as rfx
    ny, nx = mu.shape
    n = p.nmd[0]
    yi0, yi1 = max(0, y0 - plan.halo), min(ny, y1 + plan.halo)
    start, frame, electrons = plan.block_deposits(ramp, yi0, yi1)
    a2, a3 = plan.nonlinearity_block(yi0, yi1)
    charge_fx = rfx.ChargeEffects(start, frame, electrons, a2, a3)
    args = (mu[yi0:yi1].ravel(), dead[yi0:yi1].ravel(), yi0 * nx, ramp, seed, p, charge_fx)
    shape_in = (n, yi1 - yi0, nx)
    noise = plan.read_noise_block(ramp, y0, y1)
    common = dict(ipc=plan.ipc, extra=noise, bias_map=plan.bias_block(y0, y1))
    if backend == "opencl":               # group means stay on the device between the two kernels
        d_gmean, d_flags = rfx.charge_block_opencl(*args, work_group=kwargs.get("work_group"),
                                                   workspace=kwargs.get("workspace"), to_host=False,
                                                   precision=kwargs["precision"])
        return rfx.readout_opencl(d_gmean, d_flags, y1 - y0, y0 - yi0, y0, ny, ramp, seed, p,
                                  workspace=kwargs.get("workspace"), shape_in=shape_in,
                                  precision=kwargs["precision"], **common)
    gmean, qsat = rfx.charge_block_numpy(*args)
    return rfx.readout_numpy(gmean.reshape(shape_in), qsat.reshape(shape_in), y1 - y0, y0 - yi0, y0, ny, ramp,
                             seed, p, **common)


#: largest mean charge per frame [e-] the float samplers draw (float32 Poisson counts, as noise.cl)
SINGLE_MAX_FRAME_MEAN = float(2**22)


def _single_frame_means(mu, p):
    """μ [e-/frame] for the float samplers: a pixel whose μ exceeds the full well by 64 σ fills it in its
    first frame whatever μ (otherwise with probability < e⁻²⁰⁰⁰), so μ is capped there — float32
    would turn 1e39 into inf, and lose the draw's accuracy far below that.  Means above
    :data:`SINGLE_MAX_FRAME_MEAN` that the cap leaves (a full well above it) are refused."""
    cap = p.full_well + 64.0 * math.sqrt(p.full_well) + 64.0
    mu = np.minimum(mu, cap)
    if cap > SINGLE_MAX_FRAME_MEAN and float(np.max(mu, initial=0.0)) > SINGLE_MAX_FRAME_MEAN:
        from slicersim.errors import ParameterError
        raise ParameterError(f"precision 'single' draws at most {SINGLE_MAX_FRAME_MEAN:.4g} e- per frame; this ramp "
                             f"has pixels up to {float(np.max(mu)):.4g} e- per frame with a full well of "
                             f"{p.full_well:.4g} e-: use precision 'double'")
    return mu




def _writer_class(out, file_format):
    """RampWriter or UncalWriter for ``file_format`` (None: from the extension of ``out``)."""
    if str(out).lower().endswith((".gz", ".bz2", ".xz", ".zip")):
        raise ParameterError(f"out: {out}: ramp files are not written compressed by a file suffix; use a plain "
                             ".h5/.fits name (HDF5 compresses internally with compression=)")
    lower = str(out).lower()
    by_name = "jwst-uncal" if lower.endswith((".fits", ".fit")) else "hdf5" if lower.endswith((".h5", ".hdf5")) else None
    file_format = file_format or by_name or "hdf5"
    if by_name not in (None, file_format):                  # e.g. --format jwst-uncal --out x.h5: FITS named .h5
        flag = "--format" if validation.shown("out") == "--out" else "file_format"
        raise ParameterError(f"{validation.shown('out')}: {out}: {flag} {file_format!r} writes "
                             f"{'FITS' if by_name == 'hdf5' else 'HDF5'}: name it .{'fits' if by_name == 'hdf5' else 'h5'}"
                             " or leave the format to the extension")
    if file_format == "hdf5":
        return RampWriter
    if file_format == "jwst-uncal":
        from slicersim.io.uncal import UncalWriter
        return UncalWriter
    validation.choice("file_format", file_format, FILE_FORMATS)


def _available_memory():
    """Bytes of memory available to this process (Linux MemAvailable, else free pages), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _pixeldq(pixeldq, dead, shape):
    flags = np.zeros(shape, np.uint32) if pixeldq is None else np.asarray(pixeldq, np.uint32).copy()
    flags[dead] |= DQ["DEAD"] | DQ["DO_NOT_USE"]
    return flags


def _version():
    from slicersim.versioning import __version__
    return __version__


def fit_slopes(sci, nmd, tframe, gain=1.0, groupdq=None):
    """Unweighted least-squares slopes over group means [e-/s] of SCI (ngroups, ...) ADU.

    Groups flagged in ``groupdq`` (any bit) are excluded; a ramp broken by flagged groups is fitted
    per segment, the segments combined with read-noise weights.  This is the OLS fit of
    :mod:`slicersim.backends.ramp_fit` (NumPy twin) without jump detection; the full reduction
    (jumps, GLS weights, variances, corrections, files) is
    :func:`slicersim.reduction.ramp_fit.fit_ramps`.  Pixels with no two consecutive good groups give NaN.
    """
    from slicersim.backends.ramp_fit import fit_block_numpy, fit_constants
    sci = np.asarray(sci, dtype=float)
    flat = sci.reshape(1, sci.shape[0], -1)
    flags = np.zeros(flat.shape, np.uint8) if groupdq is None else \
        (np.asarray(groupdq).reshape(flat.shape) != 0).astype(np.uint8)        # DO_NOT_USE
    consts = fit_constants(nmd, tframe, gain, 0.0, 0.0, None, None, "ols")
    fit = fit_block_numpy(flat, flags, np.zeros(flat.shape[2], np.uint32), consts)[0]
    return fit[0].reshape(sci.shape[1:])
