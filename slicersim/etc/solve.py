"""Batch exposure-time calculator: thousands of point sources in one call.

The instrument (PSF, throughput, QE, background, thermal terms) is computed
once; each target only changes the point-source spectrum.  For every target the
single-ramp band SNR of every candidate readout is evaluated at once (OpenCL
kernel ``band_variance.cl`` or its NumPy twin), then the readout is chosen with
:func:`slicersim.snr.search.exact_choice` (or the reference walk).

What keeps it fast: extraction weights below 1e-16 of their bin's largest are
skipped (:func:`~slicersim.snr.snr_table.extraction_weights`; the band SNR moves
by < 1e-13), and only the cells still weighted are modelled; targets are chunked
by band, so a chunk's window of bins stays close to its bands (:func:`_chunks`);
the reference walk asks the kernel only for the readouts it visits
(:func:`_reference_chunk`: the same values as the full table).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from slicersim import validation
from slicersim.assembly import check_field
from slicersim.backends.dispatch import DEFAULT_MAX_BYTES
from slicersim.errors import ETCError, ParameterError, SpectrumError
from slicersim.instrument.names import check_parameter_names
from slicersim.io.row_blocks import show_progress
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions
from slicersim.sources.spectra import MAX_FLAMBDA, check_flambda
from slicersim.simulation import FRAMES, resolve_frame
from slicersim.snr.bands import check_band_in_grid, warn_partial_spectrum
from slicersim.snr.search import (candidate_readouts, check_reference_result, check_search,
                                  check_snr_target, exact_choice, limit_error, max_frames_for,
                                  reference_walk)
from slicersim.snr.snr_table import band_snr_table_for_models, extraction_weights, template_psf

#: the unit of the fluxes of `solve_many` (an astropy Quantity is converted to it)
FLAMBDA_UNIT = "erg / (s cm2 Angstrom)"

__all__ = ["solve_many", "solve_batch", "SolveOptions", "SOLVE_OPTIONS"]


def _interp_matrix(lbda_in, lbda_out):
    """Indices and weights of the linear interpolation λ_in → λ_out (NaN outside)."""
    idx = np.clip(np.searchsorted(lbda_in, lbda_out) - 1, 0, lbda_in.size - 2)
    w = (lbda_out - lbda_in[idx]) / (lbda_in[idx + 1] - lbda_in[idx])
    outside = (lbda_out < lbda_in[0]) | (lbda_out > lbda_in[-1])
    return idx, w, outside


def _validate_batch(lbda, fluxes, lbda_ranges):
    # Quantities converted (an F_ν or a length never taken as F_λ or Å), strings and objects refused
    lbda = validation.array("lbda", lbda, finite=False, unit="Angstrom", error=SpectrumError)
    fluxes = np.atleast_2d(validation.array("fluxes", fluxes, finite=False, unit=FLAMBDA_UNIT, error=SpectrumError))
    lbda_ranges = validation.array("lbda_ranges", lbda_ranges, finite=False, unit="Angstrom", error=ETCError)
    if lbda.ndim != 1 or lbda.size < 2:
        raise SpectrumError("lbda must be a 1-D array with at least 2 wavelengths")
    if not np.all(np.isfinite(lbda)) or np.any(np.diff(lbda) <= 0):
        raise SpectrumError("lbda must be finite and strictly increasing")
    if fluxes.ndim != 2 or fluxes.shape[1] != lbda.size or fluxes.shape[0] == 0:
        raise SpectrumError(f"fluxes must have shape (N, {lbda.size}), got {fluxes.shape}")
    bad = ~np.all(np.isfinite(fluxes), axis=1)
    if bad.any():
        raise SpectrumError(f"fluxes of target(s) {np.nonzero(bad)[0][:10].tolist()} contain NaN/inf")
    neg = np.any(fluxes < 0, axis=1)
    if neg.any():
        raise SpectrumError(f"fluxes of target(s) {np.nonzero(neg)[0][:10].tolist()} contain negative values")
    bright = np.nonzero(fluxes.max(axis=1) > MAX_FLAMBDA)[0]
    if bright.size:
        check_flambda(f"fluxes of target(s) {bright[:10].tolist()} (first)", fluxes[bright[0]])
    ranges = np.asarray(lbda_ranges, dtype=float)
    if ranges.shape == (2,):
        ranges = np.broadcast_to(ranges, (fluxes.shape[0], 2))
    if ranges.shape != (fluxes.shape[0], 2) or np.any(~(ranges[:, 1] > ranges[:, 0])):
        raise ETCError(f"lbda_ranges must have shape (N, 2) with lo < hi, got {np.shape(lbda_ranges)}")
    return lbda, fluxes, ranges


@validation.checked_fields
@dataclass(frozen=True)
class SolveOptions:
    """How ``solve_batch`` solves: every option of :func:`~slicersim.etc.solve_many` except the per-target data.

    Parameters
    ----------
    frame : {"rest", "obs"} or None, optional
        The frame ``lbda_ranges`` are given in (default: "rest" when ``redshifts`` are given,
        else "obs").
    config, field : optional
        Instrument (see :func:`slicersim.build_simulation`).
    search : {"exact", "reference"}, optional
        The readout search.
    per_resolution : bool, optional
        The target SNR is per resolution element (default) or per bin.
    backend : {"auto", "opencl", "numpy"}, optional
        Where the band variances are computed.
    max_bytes : int, optional
        Memory budget of one chunk of targets [bytes].
    progress : bool or None, optional
        None (a bar only when stderr is a terminal), True or False.
    conventions : {"physical", "slicersim-1.0"}, optional
        "physical" (default) or "slicersim-1.0" (``slicersim.physics.conventions``).
    allow_partial : bool, optional
        Bands partly outside the grid (≥ 50 % inside) or the input spectrum are answered on
        the covered part with one BandCoverageWarning naming the targets (default, batch);
        False raises SpectrumError (``slicersim.snr.bands``).
    precision : {"auto", "double", "single"}, optional
        Of the band-variance kernel (``slicersim.backends.precision``, product
        ``"batch_etc"``).
    """

    frame: str | None = None
    config: object = "cbe"
    field: str | None = "narrow"
    search: str = "exact"
    per_resolution: bool = True
    backend: str = "auto"
    max_bytes: int = DEFAULT_MAX_BYTES
    progress: bool | None = None
    conventions: str = DEFAULT_CONVENTIONS
    allow_partial: bool = True
    precision: object = "auto"

    def checked(self):
        """A copy with every option validated (ParameterError / ETCError naming the option)."""
        return replace(self, frame=validation.choice("frame", self.frame, FRAMES),
                       search=check_search(self.search), field=check_field(self.field),
                       per_resolution=validation.flag("per_resolution", self.per_resolution),
                       max_bytes=validation.integer("max_bytes", self.max_bytes, low=1),
                       progress=None if self.progress is None else validation.flag("progress", self.progress),
                       conventions=check_conventions(self.conventions),
                       allow_partial=validation.flag("allow_partial", self.allow_partial))


#: the option names :func:`solve_many` accepts as keywords
SOLVE_OPTIONS = tuple(f.name for f in fields(SolveOptions))


def solve_many(lbda, fluxes, snr, lbda_ranges, frame=None, config="cbe", field="narrow", search="exact",
               redshifts=None, *, options=None, **kwargs):
    """Solve the ETC for many point sources at once (keyword form of ``solve_batch``).

    Parameters
    ----------
    lbda : array_like of shape (k,)
        Wavelengths of the spectra [Å].
    fluxes : array_like of shape (N, k)
        F_λ of each target [erg/s/cm²/Å].
    snr : float or array_like of shape (N,)
        Target SNR (per resolution element when ``per_resolution``).
    lbda_ranges : array_like of shape (N, 2) or (2,)
        Band [Å] in ``frame``.
    frame : {"rest", "obs"} or None, optional
        The frame ``lbda_ranges`` are given in (default: "rest" when ``redshifts`` are given,
        else "obs").
    config : str, path-like or list, optional
        Instrument configuration (see :func:`~slicersim.build_simulation`).
    field : {"narrow", "wide"}, optional
        Lazuli field.
    search : {"exact", "reference"}, optional
        The readout search.
    redshifts : float or array_like of shape (N,), optional
        The targets' redshifts (``frame="rest"``).
    options : SolveOptions, optional
        All the options at once (``options=SolveOptions(...)``: the keywords given, and
        frame/config/field/search when not left at their defaults, override it).
    **kwargs
        The other fields of ``SolveOptions``: ``per_resolution``, ``backend``, ``max_bytes``,
        ``progress``, ``conventions``, ``allow_partial``, ``precision``.

    Returns
    -------
    astropy.table.Table
        One row per target: n, m, d, nramps, exposure_time [s], snr (band SNR per resolution
        element reached), snr_per_bin, data_volume [GB].
    """
    check_parameter_names("solve_many", kwargs, SOLVE_OPTIONS)
    base = SolveOptions() if options is None else options
    if not isinstance(base, SolveOptions):
        raise ParameterError(f"options must be a SolveOptions, got {validation.short_repr(options)}")
    named = {"frame": frame, "config": config, "field": field, "search": search}
    default = SolveOptions()
    # with options=, a named argument left at its default keeps the options' value
    named = {k: v for k, v in named.items() if options is None or v is not getattr(default, k)}
    opts = replace(base, **named, **kwargs)
    return solve_batch(lbda, fluxes, snr, lbda_ranges, redshifts, opts)


def solve_batch(lbda, fluxes, snr, lbda_ranges, redshifts=None, options=None):
    """Solve the ETC for many point sources at once: :func:`solve_many` with its options in one
    :class:`SolveOptions` (default ``SolveOptions()``).

    Steps: check the input (:func:`_validate_batch`, :func:`_check_snrs`), read the bands in the
    observer frame (:func:`_observer_ranges`), build the instrument once (:class:`_BatchInstrument`),
    then per chunk of targets with neighbouring bands (:func:`_chunks`) tabulate the single-ramp
    band SNR of every candidate readout and choose (:func:`_solve_chunk`); the table is assembled
    by :func:`_result_table`."""
    from slicersim.backends.precision import resolve_precision
    opts = (SolveOptions() if options is None else options).checked()
    backend, precision = resolve_precision(opts.precision, opts.backend, "batch_etc")  # bad names: before any work
    lbda, fluxes, ranges = _validate_batch(lbda, fluxes, lbda_ranges)
    snr = _check_snrs(snr, fluxes.shape[0])
    ranges = _observer_ranges(ranges, opts.frame, redshifts)
    inst = _BatchInstrument.build(opts, lbda, ranges)
    target = snr / math.sqrt(inst.spec.dispersion_resolution) if opts.per_resolution else snr.copy()
    rows = {k: np.zeros(fluxes.shape[0], dtype=int) for k in ("n", "m", "d", "nramps")}
    reached = np.full(fluxes.shape[0], np.nan)
    for chunk in _chunks(inst, opts):
        _solve_chunk(inst, fluxes, ranges, snr, target, chunk, opts.search, (backend, precision), rows, reached)
    failed = np.nonzero(rows["n"] == 0)[0]
    if failed.size:
        raise ETCError(_no_signal(lbda, fluxes, ranges, failed))
    return _result_table(inst, rows, reached, opts, precision)


def _no_signal(lbda, fluxes, ranges, failed):
    """The message for targets no readout reaches: which, and what their spectra hold in the band."""
    t = int(failed[0])
    lo, hi = ranges[t]
    inside = (lbda >= lo) & (lbda <= hi)
    found = (f"its F_λ there is at most {float(fluxes[t, inside].max()):g} erg/s/cm²/Å" if inside.any() else
             "its spectrum has no sample there")
    why = ("a signal that saturates the detector even in the shortest readout (too bright, or not F_λ in "
           "erg/s/cm²/Å)" if inside.any() and fluxes[t, inside].max() > 0 else "no signal in the band")
    return (f"target(s) {failed[:10].tolist()} cannot reach their SNR: {why} (target {t}, band "
            f"{lo:g}–{hi:g} Å observer frame: {found})")


def _check_snrs(snr, ntarget):
    """(N,) target SNRs, each finite > 0 (ETCError otherwise)."""
    snr = validation.array("snr", snr, finite=False, error=ETCError)
    if snr.ndim > 1 or snr.size not in (1, ntarget):
        raise ETCError(f"snr must be one value or one per target ({ntarget}), got shape {snr.shape}")
    snr = np.broadcast_to(snr.reshape(-1) if snr.ndim else snr, (ntarget,))
    for value in np.unique(snr):
        check_snr_target(value)
    return snr


def _observer_ranges(ranges, frame, redshifts):
    """Bands (N, 2) [Å] in the observer frame: ``frame`` None is "rest" with ``redshifts``, else "obs"."""
    if resolve_frame(frame, redshifts) == "obs":
        return ranges
    if redshifts is None:
        raise ETCError("frame='rest' needs the redshifts of the targets")
    z = np.asarray(redshifts, dtype=float)
    try:
        z = np.broadcast_to(z, (ranges.shape[0],))
    except ValueError:
        raise ETCError(f"redshifts must be one value or one per target ({ranges.shape[0]}), got shape "
                       f"{z.shape}") from None
    if not np.all(np.isfinite(z) & (z > -1)):
        raise ETCError("redshifts must be finite and > -1")
    if np.any(z > validation.MAX_REDSHIFT):
        raise ETCError(f"redshifts must be ≤ {validation.MAX_REDSHIFT:g}, the largest is {z.max():g}")
    return ranges * (1 + z)[:, None]


@dataclass
class _BatchInstrument:
    """The instrument of a batch, computed once: simulation, PSF template, LSF-convolved uniform
    light [ph/s/cell], f2p, QE, gain, the interpolation input → grid and the candidate readouts;
    ``band``: (N, 2) first/last+1 grid bin of each target's band; ``psf2``: the extraction weights
    (:func:`~slicersim.snr.snr_table.extraction_weights`: the negligible ones 0, skipped)."""

    sim: object
    psf: np.ndarray
    uniform: np.ndarray
    interp: tuple
    cand: tuple
    band: np.ndarray
    psf2: np.ndarray

    @property
    def spec(self):
        return self.sim.spectrograph

    @property
    def det(self):
        return self.sim.detector

    @classmethod
    def build(cls, opts, lbda, ranges):
        from slicersim.assembly import build_simulation
        sim = build_simulation(opts.config, opts.field, pointsource=None, conventions=opts.conventions)
        spec, det, grid = sim.spectrograph, sim.detector, sim.lbda
        if lbda[0] >= grid[-1] or lbda[-1] <= grid[0]:
            raise SpectrumError(f"input wavelengths {lbda[0]:g}–{lbda[-1]:g} Å do not overlap the "
                                f"instrument range {grid[0]:.0f}–{grid[-1]:.0f} Å")
        band = np.stack([np.searchsorted(grid, ranges[:, 0], side="left"),
                         np.searchsorted(grid, ranges[:, 1], side="right")], axis=1)
        empty = band[:, 1] <= band[:, 0]
        if empty.any():
            raise ETCError(f"band of target(s) {np.nonzero(empty)[0][:10].tolist()} contains no "
                           f"instrument bin ({grid[0]:.0f}–{grid[-1]:.0f} Å)")
        check_band_in_grid(ranges, spec.lbda_edges, who="batch", allow_partial=opts.allow_partial)
        warn_partial_spectrum(ranges, lbda[0], lbda[-1], who="batch", allow_partial=opts.allow_partial)
        uniform = sum(spec.apply_lsf(arr) for arr in (sim.background_photons, sim.thermal_photons_of("telescope"),
                                                      sim.thermal_photons_of("optics")))
        cand = candidate_readouts(det.min_group, det.max_group or 64, det.nmd[2])
        psf = template_psf(sim)
        return cls(sim, psf, uniform, _interp_matrix(lbda, grid), cand, band, extraction_weights(psf))

    @property
    def lsf_half(self):
        """Half-width [bins] of the LSF (the margin a window of bins needs on each side)."""
        return int(4.0 * self.spec.lsf_sigma + 0.5)

    def models(self, fluxes, band):
        """(Q [e-/s/cell] (n, nb, nc), signal rate [ADU/s] (n, nb), band − lo, psf2 (nb, nc)) of
        targets ``fluxes`` (n, k) [erg/s/cm²/Å] over the bins [lo, hi) their bands need and the nc
        cells with a non-zero extraction weight there (``psf2``: those weights)."""
        sim, spec, grid = self.sim, self.spec, self.sim.lbda
        idx, w, outside = self.interp
        half = self.lsf_half
        lo, hi = int(band[:, 0].min()), int(band[:, 1].max())
        s0, s1 = max(0, lo - half), min(grid.size, hi + half)     # + the LSF half-width margins
        # only the cells the extraction weighs in [lo, hi) (the LSF acts along λ, cell by cell)
        cells = np.nonzero(self.psf2[lo:hi].any(axis=0))[0]
        cells = slice(None) if cells.size == self.psf2.shape[1] else cells
        psf2 = self.psf2[lo:hi, cells]
        flux_grid = fluxes[:, idx[s0:s1]] * (1 - w[s0:s1]) + fluxes[:, idx[s0:s1] + 1] * w[s0:s1]
        flux_grid[:, outside[s0:s1]] = np.nan                                      # erg/s/cm²/Å
        photons = flux_grid * sim.flambda_to_photon[s0:s1]                         # ph/s
        keep, qe = slice(lo - s0, hi - s0), sim.qe
        # LSF with reflect ends: at a window edge inside the grid only the discarded margin bins change
        point = spec.apply_lsf(photons[:, :, None] * self.psf[None, s0:s1, cells], axis=1)[:, keep]  # ph/s/cell
        q = qe[None, lo:hi, None] * (point + self.uniform[None, lo:hi, None])                  # e-/s/cell
        signal_rate = spec.apply_lsf(photons * qe[s0:s1], axis=1)[:, keep] * self.det.gain     # ADU/s
        return q, signal_rate, band - lo, psf2

    def snr_table(self, model, kernel, targets=slice(None), columns=None):
        """Single-ramp band SNR per bin (n, K) of the targets ``targets`` of ``model``
        (:meth:`models`) for every candidate readout, or (n, J) for the candidates ``columns``
        (n, J) of each (the same values)."""
        q, signal_rate, sub_band, psf2 = model
        backend, precision = kernel
        return band_snr_table_for_models(self.sim, (q[targets], signal_rate[targets]), sub_band[targets],
                                         self.cand, backend=backend, psf2=psf2, precision=precision,
                                         columns=columns)


#: a target joins a chunk while the chunk's window of bins stays within its widest band plus this
#: fraction of it (bins outside a target's band are computed for nothing; each chunk costs a launch)
CHUNK_SLACK = 0.5


#: a chunk's working arrays (n, bins, cells) stay within this many bytes each (memory-bound steps run
#: several times faster on arrays that fit the CPU caches than on tens of MB)
CHUNK_CACHE_BYTES = 8 * 2**20


def _chunks(inst, opts):
    """Chunks of targets (index arrays) with neighbouring bands: the targets sorted by band, a chunk
    closed when its window of bins would exceed its widest band by more than :data:`CHUNK_SLACK` or
    its working arrays ``opts.max_bytes`` (with a progress bar)."""
    band = inst.band
    order = np.argsort(band[:, 0], kind="stable")
    cells, margin = inst.psf.shape[1], 2 * inst.lsf_half
    chunks, start = [], 0
    lo = hi = widest = 0
    for k, t in enumerate(order):
        b0, b1 = int(band[t, 0]), int(band[t, 1])
        if k > start:
            new_hi, new_widest = max(hi, b1), max(widest, b1 - b0)
            window = new_hi - lo
            one = (k + 1 - start) * (window + margin) * cells * 8       # bytes of one working array
            if window <= new_widest * (1 + CHUNK_SLACK) and one <= CHUNK_CACHE_BYTES and 3 * one <= opts.max_bytes:
                hi, widest = new_hi, new_widest
                continue
            chunks.append(order[start:k])
            start = k
        lo, hi, widest = b0, b1, b1 - b0
    chunks.append(order[start:])
    if show_progress(opts.progress):
        from tqdm.auto import tqdm
        return tqdm(chunks, total=len(chunks), desc="ETC", unit="chunk")
    return chunks


def _solve_chunk(inst, fluxes, ranges, snr, target, chunk, search, kernel, rows, reached):
    """Fill ``rows`` / ``reached`` for the targets ``chunk`` (index array)."""
    det = inst.det
    model = inst.models(fluxes[chunk], inst.band[chunk])
    if search == "exact":
        snr1 = inst.snr_table(model, kernel)
        choice = exact_choice(snr1, *inst.cand, target[chunk], max_frames=max_frames_for(det.tframe))
        if choice["limited"].any():
            t = int(chunk[choice["limited"]].min())
            raise ETCError(f"target {t}: {limit_error(snr[t], ranges[t], det.tframe)}")
        for key in rows:
            rows[key][chunk] = choice[key]
        reached[chunk] = choice["snr"]
        return
    _reference_chunk(inst, model, chunk, kernel, (snr, ranges, target), rows, reached)


class _Missing(Exception):
    """A reference walk asked for a candidate readout whose single-ramp SNR is not computed yet."""

    def __init__(self, key):
        super().__init__(key)
        self.key = key


#: least number of columns of a lazy SNR table (the kernel keeps its vector width: 8 doubles on the
#: AVX-512 CPUs of the VM; a lane computes the same values at any width)
_MIN_COLUMNS = 8
#: readouts of an n row computed when a reference walk reaches one not computed yet (around it)
_ROW_WINDOW = 16


def _reference_chunk(inst, model, chunk, kernel, goals, rows, reached):
    """The reference walks of the targets ``chunk``, their single-ramp SNRs computed on demand: first
    the walk's three opening readouts, then the n row (one m, d) a walk asks for (each value the same
    as in the full table, :meth:`_BatchInstrument.snr_table`); a walk that reaches a readout not
    computed yet stops (:class:`_Missing`) and runs again once its row is there."""
    snr, ranges, target = goals
    det = inst.det
    n_c, m_c, d_c = inst.cand
    lookup = {(int(a), int(b), int(c)): k for k, (a, b, c) in enumerate(zip(n_c, m_c, d_c))}
    row_of = {}
    for k, key in enumerate(zip(m_c.tolist(), d_c.tolist())):
        row_of.setdefault(key, []).append(k)
    nt = len(chunk)
    table = np.full((nt, n_c.size), np.nan)
    known = np.zeros((nt, n_c.size), dtype=bool)
    extra = [{} for _ in range(nt)]                         # off-table readouts, NumPy, per target
    opening = [lookup[k] for k in ((det.max_group or 64, 8, det.nmd[2]), (32, 4, 0), (8, 4, 0)) if k in lookup]
    pending = {local: opening for local in range(nt)}
    while pending:
        targets = np.fromiter(pending, dtype=np.intp, count=len(pending))
        width = max(_MIN_COLUMNS, max(len(c) for c in pending.values()))
        columns = np.array([c + [c[-1]] * (width - len(c)) for c in pending.values()], dtype=np.intp)
        table[targets[:, None], columns] = inst.snr_table(model, kernel, targets, columns)
        known[targets[:, None], columns] = True
        pending = {}
        for local in targets.tolist():
            t = int(chunk[local])
            one = (model[0][local:local + 1], model[1][local:local + 1], model[2][local:local + 1], model[3])
            try:
                nmd, r, s = _reference_one(inst, (table[local], known[local]), lookup, (one, extra[local]),
                                           snr[t], ranges[t], target[t], t)
            except _Missing as miss:                         # a window of its n row around it
                row = row_of[tuple(miss.key[1:])]
                at = row.index(lookup[miss.key])
                start = max(0, min(at - _ROW_WINDOW // 2, len(row) - _ROW_WINDOW))
                pending[local] = row[start:start + _ROW_WINDOW]
                continue
            rows["n"][t], rows["m"][t], rows["d"][t] = nmd
            rows["nramps"][t], reached[t] = r, s


def _reference_one(inst, snr1, lookup, model, snr, band, target, t):
    """The reference walk of one target: the single-ramp SNR is read in its table row ``snr1`` =
    (values, computed?), readouts off the table are evaluated on ``model`` = ((Q, signal rate,
    band, psf2), cache) (NumPy); returns (nmd, nramps, snr reached).  :class:`_Missing` when the walk
    reaches a table readout not computed yet."""
    det = inst.det
    (q, signal_rate, sub_band, psf2), extra = model
    values, known = snr1

    def snr_of(n, m, d, r):
        key = (n, m, d)
        if key in lookup:
            k = lookup[key]
            if not known[k]:
                raise _Missing(key)
            return values[k] * math.sqrt(r)
        if key not in extra:
            one = (np.array([n]), np.array([m]), np.array([d]))
            extra[key] = band_snr_table_for_models(inst.sim, (q, signal_rate), sub_band, one, backend="numpy",
                                                   psf2=psf2)[0, 0]
        return extra[key] * math.sqrt(r)
    nmd, r, s, _ = reference_walk(snr_of, target, det.max_group or 64, det.nmd[2])
    try:
        check_reference_result(snr, band, target, s, r * (nmd[0] * (nmd[1] + nmd[2]) - nmd[2]) * det.tframe,
                               det.tframe, nmd=nmd, max_group=det.max_group)
    except ETCError as exc:
        raise ETCError(f"target {t}: {exc}") from None
    return nmd, r, s


def _result_table(inst, rows, reached, opts, precision):
    """The astropy Table of :func:`solve_many` (ETCError for targets no readout reaches)."""
    from astropy.table import Table
    det, spec = inst.det, inst.spec
    frames = rows["n"] * (rows["m"] + rows["d"]) - rows["d"]
    table = Table(rows)
    table["exposure_time"] = rows["nramps"] * frames * det.tframe
    table["exposure_time"].unit = "s"
    table["snr"] = reached * (math.sqrt(spec.dispersion_resolution) if opts.per_resolution else 1.0)
    table["snr_per_bin"] = reached
    table["data_volume"] = rows["nramps"] * rows["n"] * det.shape[0] * det.shape[1] * 16 / 8e9
    table["data_volume"].unit = "GB"
    table.meta.update(config=str(opts.config), field=opts.field, search=opts.search, frame=opts.frame,
                      conventions=opts.conventions, precision=precision)
    return table
