"""Point-source spectrum fitted on the detector pixels with the instrument's own forward model.

The rectified cube is a coarse, linear summary of the detector image: its cells (2 native bins ×
58 columns by default) do not reproduce the native-resolution spot, so a PSF model fitted on the
cube is a model error (−3 % on a noiseless Lazuli SN Ia at z = 0.5 even with the true PSF on the
coarse cells).  Here the point source is fitted where the data are, on the pixels, with the model
that made them:

    d_p = Σ_j F_j A_jp + Σ_j B_j U_jp + n_p,        A_j = 𝒫 (P̃_j δ_j),   U_j = 𝒫 (1 δ_j),

with 𝒫 the flux-conserving projection of native cells to pixels (the mapper's, exactly the tables
the simulation deposits with), P̃_j the point source's fraction per native cell in native bin j
(the configuration's PSF profile at the source position, averaged over the LSF: P̃_j =
LSF[φ P]_j / LSF[φ]_j with φ the photon spectrum, taken from the fit itself), F_j [e-/s per native
bin] the point source's *total* photo-electron rate (light outside the field included: P̃ is
normalised on the sky, not on the field) and B_j [e-/s per native cell per bin] a background
uniform over the field (sky, zodiacal and thermal light).  The fit uses every usable pixel the
source's slices reach; the unknowns are solved jointly by weighted least squares,

    θ̂ = (AᵀWA)⁻¹ AᵀW d,   Cov θ̂ = (AᵀWA)⁻¹,   W = diag(1/v),

with v the model variance var_rnoise + k · max(model + dark, 0) from a first pass (weights
that do not follow each pixel's own noisy rate: no Poisson-weighting bias), and the position
(x, y) [native cells from the field centre] refined jointly by Gauss–Newton (∂A/∂x, ∂A/∂y).
The native F̂_j are then summed into the output bins (their covariance with them).

Noiseless, the model is the simulation's: F̂ returns the input (3e-8 per native bin on the Lazuli
detector, the iterative fit's tolerance; the LSF weights φ come from Van Cittert iterations on F̂).  A fit that does not converge, a source on the field edge, a position far from
the light's centroid or no significant source raise :class:`~slicersim.errors.ReductionError`.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from slicersim.errors import ParameterError, RampFileError, ReductionError
from slicersim.reduction.spectrum_product import SpectrumProduct

__all__ = ["extract_forward", "instrument_model", "model_config", "aggregate_bins", "FORWARD_PSF_PROFILES"]

#: PSF profiles the forward model reproduces (those the simulation's cube builder uses)
FORWARD_PSF_PROFILES = ("gaussian", "airy")

#: rows (slices) whose PSF fraction in some bin is above this fraction of the peak row are fitted
_ROW_REACH = 1e-6
#: Gauss–Newton: stop when the position moves less than this [native cells]
_POSITION_TOL = 1e-3
_MAX_ITER = 16
#: a fitted position farther than this from the light's centroid [cells, or σ of the PSF] is refused
_CENTROID_TOL_CELLS = 3.0
#: least significance [σ] of the white-light peak for a point source to be fitted
MIN_DETECTION = 5.0
#: pixels whose residual exceeds this many σ of the model variance are left out of the fit
_REJECT_SIGMA = 5.0
#: the rejection threshold [σ] of the first iterations, then ``_REJECT_SIGMA``: the first model is fitted
#: with every pixel, hot pixels and the unflagged neighbours of cosmic rays included (tens to thousands of
#: σ), and a 5 σ cut against that model also removed the brightest good pixels of the source, for good
#: (z = 0.9, wide field, ``effects = "lazuli"``: 37 % of the core pixels, band flux −6 %).  Each
#: iteration decides the rejected pixels afresh from its own model, so a pixel left out early returns
#: once the model is right.
_REJECT_SCHEDULE = (100.0, 20.0)
#: the fit has converged when the position moves less than ``_POSITION_TOL`` and at most this fraction
#: of the pixels changed side of the rejection threshold (pixels right at the threshold may flip)
_REJECT_STABLE = 1e-4
#: times the converged fit looks for outliers it absorbed (:func:`_leveraged_outliers`) and goes on without them
_LEVERAGE_ROUNDS = 3
#: 1 − leverage below which a pixel's residual says nothing of it (it alone determines a parameter)
_NO_INFORMATION = 1e-6
#: a fit that rejects more than this fraction of its pixels is refused: no model explains the image (with
#: 60 % of the pixels outliers the fit left out 90 % of them and returned native fluxes of 1e150 e-/s)
_MAX_REJECTED = 0.5


def instrument_model(config="cbe", field="narrow", conventions=None):
    """The :class:`~slicersim.simulation.Simulation` whose PSF, LSF, QE and native λ grid the forward
    model uses (``config`` as :func:`slicersim.assembly.build_simulation`; the last four built are
    kept: a reduction checks the configuration before reading data, then uses it)."""
    import json
    key = json.dumps([config, field, conventions], default=str)
    sim = _MODELS.get(key)
    if sim is None:
        from slicersim.assembly import build_simulation
        from slicersim.physics.conventions import DEFAULT_CONVENTIONS
        sim = build_simulation(config, field, conventions=conventions or DEFAULT_CONVENTIONS)
        _MODELS[key] = sim
        while len(_MODELS) > 4:
            _MODELS.pop(next(iter(_MODELS)))
    return sim


_MODELS = {}


def model_config(attrs, config=None):
    """The instrument model a raw file was simulated with: ``{"config", "field", "conventions",
    "psf_profile", "recorded"}`` from its ``CONFIG`` keyword (a JSON object, written by
    ``Target.get_ramps``); ``config`` (a name, TOML path or list, as
    :func:`slicersim.io.config.load_config`) replaces the recorded configuration only (the file's field,
    conventions and PSF profile are kept; ``recorded`` is the file's own).  None when neither names a
    configuration (ramps of a bare rate image, a foreign level-1b file).  A CONFIG keyword that is
    present but not such an object is a :class:`~slicersim.errors.RampFileError`."""
    import json
    raw = (attrs or {}).get("CONFIG", {})
    if isinstance(raw, bytes):
        raw = raw.decode(errors="replace")
    if isinstance(raw, str):
        try:
            raw = json.loads(raw) if raw.strip() else {}
        except ValueError:
            raw = None
    hint = "give the configuration explicitly (config=, CLI --config cbe|eol|PATH)"
    if raw is None or not isinstance(raw, dict):
        raise RampFileError(f"the file's CONFIG keyword is not a JSON object naming the configuration: {hint}")
    recorded = raw.get("config")
    if recorded not in (None, "") and not _config_like(recorded):
        raise RampFileError(f"the file's CONFIG names the configuration {recorded!r}, not a name, a TOML path or "
                            f"a list of them: {hint}")
    chosen = config if config is not None else recorded
    if chosen in (None, "", []):
        return None
    for key in ("field", "conventions", "psf_profile"):
        if raw.get(key) is not None and not isinstance(raw.get(key), str):
            raise RampFileError(f"the file's CONFIG has {key} = {raw[key]!r}, not a name: {hint}")
    return {"config": chosen, "field": raw.get("field") or None, "conventions": raw.get("conventions"),
            "psf_profile": raw.get("psf_profile") or "gaussian", "recorded": recorded}


def _config_like(value):
    items = value if isinstance(value, list) else [value]
    return bool(items) and all(isinstance(c, str) and c for c in items)


def aggregate_bins(native_edges, lbda_edges):
    """(nb, nλ_native) matrix M: the fraction of native bin j inside output bin b (M F sums fluxes)."""
    ne, ce = np.asarray(native_edges, float), np.asarray(lbda_edges, float)
    lo = np.maximum(ce[:-1, None], ne[None, :-1])
    hi = np.minimum(ce[1:, None], ne[None, 1:])
    return np.clip(hi - lo, 0.0, None) / np.diff(ne)[None, :]


class _Footprint:
    """The projection 𝒫 restricted to the field's rows that the source reaches: entries (pixel row
    of the fit, native bin, cube row, column, weight) and the fitted pixels (flat indices)."""

    def __init__(self, tables, rows, usable):
        from slicersim.backends.projection_transpose import matrix_entries
        S, E, Q = tables.grid
        self.ny = S
        core = sorted(S - 1 - int(r) for r in rows)          # cube row r ↔ table slice S − 1 − r
        meta = tables.meta.reshape(S, E * Q, 4)                  # int32 windows: no int64 copy of all cells
        x0, y0 = meta[..., 0].min(1).astype(np.int64), meta[..., 1].min(1).astype(np.int64)
        x1 = (meta[..., 0] + meta[..., 2]).max(1).astype(np.int64)
        y1 = (meta[..., 1] + meta[..., 3]).max(1).astype(np.int64)
        # slices whose windows may share pixels with the fitted ones: their light is modelled too
        guard = [s for s in range(S) if s not in core and any(
            x0[s] < x1[c] and x0[c] < x1[s] and y0[s] < y1[c] and y0[c] < y1[s] for c in core)]
        size = int(np.prod(tables.detector_shape))
        itype = np.int32 if max(size, S * E * Q) < 2 ** 31 else np.int64   # half the bytes to sort and gather
        mark = np.zeros(size, bool)                              # a mask, not np.unique / np.isin (sorts)
        parts = []
        for s in core + guard:
            p, c, w = matrix_entries(tables, s * E * Q, (s + 1) * E * Q)
            parts.append((p.astype(itype), c.astype(itype), w))
            if s in core:
                mark[p] = True
        pix = np.concatenate([p for p, _, _ in parts])
        cell = np.concatenate([c for _, c, _ in parts])
        wgt = np.concatenate([w for _, _, w in parts])
        del parts
        fitted = np.flatnonzero(mark)
        fitted = fitted[usable(fitted)]
        mark[:] = False
        mark[fitted] = True
        keep = np.flatnonzero(mark[pix])
        pix, cell, wgt = pix[keep], cell[keep], wgt[keep]
        self.pixels = fitted                                   # flat detector indices
        row = np.searchsorted(fitted, pix).astype(itype)
        nbin = (cell // Q) % E
        order = np.argsort(row.astype(np.int64) * E + nbin, kind="stable")   # CSR order, built once (values change)
        row, nbin, cell = row[order], nbin[order], cell[order]
        self.weight = wgt[order]
        self.bin = nbin.astype(np.int32)
        self.cube_row = S - 1 - cell // (E * Q)
        self.col = cell % Q
        self.nbin = E
        # entries sharing a pixel and a native bin (cells of one bin reaching one pixel) summed into one
        # slot: the matrices have one entry per (pixel, bin), half as many as the entries (Lazuli SN Ia)
        new = np.ones(row.size, bool)
        new[1:] = (row[1:] != row[:-1]) | (nbin[1:] != nbin[:-1])
        self.slot = np.cumsum(new) - 1
        self.nslot = int(self.slot[-1]) + 1 if row.size else 0
        self.slot_bin = nbin[new].astype(np.int32)
        counts = np.bincount(row[new], minlength=fitted.size)
        self.indptr = np.concatenate([[0], np.cumsum(counts)])
        # [𝒫(values) | 𝒫(1)] of one row: its slots' bins, then the same bins + nλ (built once)
        first = np.repeat(self.indptr[:-1], counts)                  # each slot's row start
        within = np.arange(self.nslot) - first
        self._pos_p = 2 * first + within
        self._pos_u = self._pos_p + np.repeat(counts, counts)
        self._both_indices = np.empty(2 * self.nslot, np.int32)
        self._both_indices[self._pos_p] = self.slot_bin
        self._both_indices[self._pos_u] = self.slot_bin + E
        self._both_indptr = 2 * self.indptr

    def _slots(self, values):
        """Per (pixel, bin) slot: Σ weight · values[bin, cube row, column] over the slot's cells."""
        return np.bincount(self.slot, weights=self.weight * values[self.bin, self.cube_row, self.col],
                           minlength=self.nslot)

    def matrix(self, values):
        """Sparse (pixels × native bins) 𝒫 applied to per-cell values (nλ, ny, nx) bin by bin (CSR, one
        entry per pixel and bin: the cells of a bin sharing a pixel summed)."""
        return sp.csr_matrix((self._slots(values), self.slot_bin, self.indptr), shape=(self.pixels.size, self.nbin))

    def background(self):
        return self.matrix(np.ones((self.nbin, int(self.cube_row.max()) + 1 if self.cube_row.size else 1,
                                    int(self.col.max()) + 1 if self.col.size else 1)))

    def with_background(self, values):
        """[𝒫(values) | 𝒫(1)]: the design with a uniform background per bin (pixels × 2 nλ), built in
        place of a sparse hstack."""
        data = np.empty(2 * self.nslot)
        data[self._pos_p] = self._slots(values)
        data[self._pos_u] = self._ones()
        return sp.csr_matrix((data, self._both_indices, self._both_indptr), shape=(self.pixels.size, 2 * self.nbin))

    def _ones(self):
        if not hasattr(self, "_ones_cache"):
            self._ones_cache = np.bincount(self.slot, weights=self.weight, minlength=self.nslot)
        return self._ones_cache


def _psf(sim, profile, position):
    """P[λ, y, x] of the configuration's PSF profile at ``position`` [native cells] (NumPy: the fit's
    finite differences need the same arithmetic at every call)."""
    from slicersim.products.cube import psf_block
    return np.asarray(psf_block(sim, profile, 0, sim.lbda.size, position=tuple(position), backend="numpy"), float)


def _lsf_averaged(sim, P, phi):
    """P̃_j = LSF[φ P]_j / LSF[φ]_j (the PSF of native bin j after the LSF mixes its neighbours)."""
    lsf = sim.spectrograph.apply_lsf
    num = lsf(phi[:, None, None] * P, axis=0)
    den = lsf(phi)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den[:, None, None]
    return np.where(np.isfinite(out), out, P)


#: Van Cittert iterations of the photon spectrum behind the LSF (the LSF's response is ≥ 0.29 at the
#: native grid's Nyquist frequency for σ ≤ ½ bin: 60 iterations leave < 1e-9 of the first-order error)
_DECONVOLUTION_STEPS = 60


def _photon_spectrum(sim, F, qe):
    """φ ≥ 0 [ph/s per native bin] with QE · LSF[φ] = F: the weights of :func:`_lsf_averaged`
    (Van Cittert iterations with positivity; exact for a noiseless F, smoothed noise otherwise — the
    weights enter P̃ only through the PSF's change across the LSF, a second-order effect)."""
    g = np.maximum(F, 0.0) / np.where(qe > 0, qe, 1.0)
    phi = g.copy()
    lsf = sim.spectrograph.apply_lsf
    for _ in range(_DECONVOLUTION_STEPS):
        phi = np.maximum(phi + (g - lsf(phi)), 0.0)
    return phi + 1e-30


#: smallest LU pivot of the unit-diagonal normal matrix, relative to the largest, taken as regular
_SINGULAR_PIVOT = 1e-10


def _solve(A, d, v):
    """Weighted LS: (θ̂, covariance) over the columns the data constrain (others NaN / 0); the
    covariance is a callable computing the (AᵀWA)⁻¹ on demand (only the last fit needs it).

    AᵀWA stays sparse (native bins couple only their neighbours: ~10 entries per row for a Lazuli
    SN Ia, 1020 columns with the background) and is solved by a sparse LU of its unit-diagonal
    scaling: milliseconds, where the dense Cholesky took 0.1–0.3 s per call on the 2-core VM (BLAS
    threads waiting on a busy core).  A singular system (an LU pivot below ``_SINGULAR_PIVOT`` of the
    largest) falls back to the pseudo-inverse."""
    from scipy.sparse.linalg import splu
    w = 1.0 / v
    Aw = A.copy()
    Aw.data = Aw.data * np.repeat(w, np.diff(A.indptr))
    G = (A.T @ Aw).tocsc()
    b = A.T @ (w * d)
    diag = G.diagonal()
    ok = diag > 0
    n = G.shape[0]
    theta = np.full(n, np.nan)
    if not ok.any():
        return theta, lambda: np.zeros((n, n))
    keep = np.flatnonzero(ok)
    scale = 1.0 / np.sqrt(diag[keep])
    Gs = (sp.diags(scale) @ G[keep][:, keep] @ sp.diags(scale)).tocsc()
    try:
        lu = splu(Gs)
        pivots = np.abs(lu.U.diagonal())                  # unit-diagonal Gs: pivots ~1 unless (near) singular
        x = lu.solve(scale * b[keep])
        if not (pivots.min() > _SINGULAR_PIVOT * pivots.max() and np.all(np.isfinite(x))):
            raise RuntimeError("singular")
    except RuntimeError:                                   # singular: the pseudo-inverse's answer
        lu, x = None, np.linalg.pinv(Gs.toarray()) @ (scale * b[keep])
    theta[keep] = scale * x

    def covariance():
        inv = lu.solve(np.eye(keep.size)) if lu is not None else np.linalg.pinv(Gs.toarray())
        cov = np.zeros((n, n))
        cov[np.ix_(keep, keep)] = inv * scale[:, None] * scale[None, :]
        return cov
    return theta, covariance


def extract_forward(rate, variance, options=None, *, sim, mapper, noise=None, **keywords):
    """Spectrum of a point source fitted on the detector pixels (module docstring).

    rate : (H, W) [e-/s] dark-subtracted rates (0 where unusable);  variance : (H, W) [(e-/s)²], +inf
        where unusable (the ramp fit's)
    options : a :class:`~slicersim.reduction.options.ForwardOptions` (None: its defaults); its fields as
        keywords replace those of ``options``:
        field : "narrow" or "wide";  lbda_edges : output bin edges [Å] (default: the native grid);
        native fluxes are summed into them;  position : (x, y) [native cells from the field centre],
        fixed; None: fitted, starting from ``start`` (same units; e.g. :func:`~slicersim.reduction.white_light.locate_source` on a
        cube, times ``cell_scale``);  background : fit a uniform background;  psf_profile : the
        simulation's PSF profile (:func:`slicersim.products.psf_profiles.get_psf_profile`)
    sim : the instrument model (:func:`instrument_model`) of ``field``;  mapper : its detector mapper
    noise : a :class:`~slicersim.reduction.options.PixelNoise` (the ramp fit's read-noise and Poisson
        variances, its rate before the dark was subtracted, the dark [e-/s]): the model variance
        var_rnoise + k·max(model + dark, 0) with k = var_poisson / raw_rate (median over the fitted
        pixels); None: the data variance.  The keywords var_rnoise, var_poisson, raw_rate and
        dark_rate build it (the earlier form).

    Returns a :class:`SpectrumProduct` [e-/s per output bin] with ``method="forward"``,
    ``background`` [e-/s per native cell per bin, mean over each output bin], ``diagnostics``:
    position, iterations, chi2 / dof of the pixels, the native flux and its covariance, pixels fitted.
    """
    opts, noise = _forward_options(options, noise, keywords)
    if noise is not None:
        _check_noise_shapes(noise, np.shape(rate))
    prob = _Problem(rate, variance, sim, mapper, opts)
    fit = _fit(prob, noise)
    return _spectrum(prob, fit, noise is not None)


def _check_noise_shapes(noise, shape):
    """ParameterError unless the PixelNoise images have the rates' shape (``dark_rate``: or a number):
    they are read at the fitted pixels' flat indices, so a number was an IndexError and an image of
    another shape gave other pixels' noise silently."""
    for name in ("var_rnoise", "var_poisson", "raw_rate", "dark_rate"):
        got = np.shape(getattr(noise, name))
        if got != tuple(shape) and not (name == "dark_rate" and got == ()):
            want = f"{tuple(shape)}" + (" or a number" if name == "dark_rate" else "")
            raise ParameterError(f"noise {name} must be an image of the rates' shape {want}, got shape {got}")


_NOISE_KEYWORDS = ("var_rnoise", "var_poisson", "raw_rate", "dark_rate")


def _forward_options(options, noise, keywords):
    """(ForwardOptions, PixelNoise or None) from the arguments of :func:`extract_forward`."""
    from slicersim.reduction.option_forms import build_options
    from slicersim.reduction.options import ForwardOptions, PixelNoise
    terms = {k: keywords.pop(k) for k in _NOISE_KEYWORDS if k in keywords}
    opts = build_options(ForwardOptions, options, keywords, "extract_forward")
    if terms and noise is not None:
        raise ParameterError(f"extract_forward: give noise= or {', '.join(terms)}, not both")
    if terms.get("var_rnoise") is not None:
        missing = [k for k in _NOISE_KEYWORDS[:3] if terms.get(k) is None]
        if missing:
            raise ParameterError(f"extract_forward: var_rnoise needs {' and '.join(missing)} too")
        noise = PixelNoise(terms["var_rnoise"], terms["var_poisson"], terms["raw_rate"], terms.get("dark_rate", 0.0))
    elif any(v is not None for v in terms.values()):          # they were ignored: the data variance was used
        given = [k for k, v in terms.items() if v is not None]
        raise ParameterError(f"extract_forward: {' and '.join(given)} need{'s' if len(given) == 1 else ''} "
                             "var_rnoise, var_poisson and raw_rate together (the model variance), or none of them")
    if noise is not None and not isinstance(noise, PixelNoise):
        raise ParameterError(f"noise must be a PixelNoise or None, got {type(noise).__name__}")
    return opts, noise


class _Problem:
    """The fixed part of a forward fit: the data on the pixels the source's slices reach, the
    footprint of the projection there, the native grid and the output bins."""

    def __init__(self, rate, variance, sim, mapper, opts):
        from slicersim.instrument.mapper import NARROW_SLICES, WIDE_SLICES
        slices = {"narrow": NARROW_SLICES, "wide": WIDE_SLICES}[opts.field]
        rate = np.asarray(rate, float)
        variance = np.asarray(variance, float)
        if rate.shape != tuple(mapper.detector_shape) or variance.shape != rate.shape:
            raise ParameterError(f"rate and variance must be the mapper's detector {tuple(mapper.detector_shape)}, "
                                 f"got {rate.shape} and {variance.shape}")
        self.sim, self.profile, self.opts, self.field = sim, opts.psf_profile, opts, opts.field
        self.ne = np.asarray(sim.spectrograph.lbda_edges, float)
        self.nl = self.ne.size - 1
        self.shape = ny, nx = sim.spectrograph.shape
        if len(slices) != ny:
            raise ParameterError(f"the instrument model has {ny} slices, the {opts.field} field {len(slices)}")
        self.edges = self.ne if opts.lbda_edges is None else np.asarray(opts.lbda_edges, float)
        self.fixed = opts.position is not None
        pos = opts.position if self.fixed else (opts.start if opts.start is not None else (0.0, 0.0))
        self.start = np.array(pos, float)
        _check_position(self.start, self.shape, "the light's centroid" if not self.fixed else "position",
                        opts.cell_scale, self.fixed)
        tables = mapper.projection_tables(slices, nx, self.ne).host()
        P = self.psf(self.start)
        reach = P.sum(axis=2).max(axis=0)
        rows = np.flatnonzero(reach > _ROW_REACH * reach.max())
        self.rows = np.arange(max(rows.min() - 2, 0), min(rows.max() + 3, ny))   # margin for the position's moves
        self.pixel_var = variance.ravel()
        self.pixel_rate = rate.ravel()
        self.fp = _Footprint(tables, self.rows, self.usable)
        if self.fp.pixels.size == 0:
            raise ReductionError(f"no usable pixel in the {opts.field} field around the source")
        self.d = rate.ravel()[self.fp.pixels]
        self.v = self.pixel_var[self.fp.pixels]
        self.U = self.fp.background() if opts.background else None
        self.qe = np.asarray(sim.qe, float)

    def usable(self, pix):
        """Pixels with a variance and a finite rate (a NaN or inf rate is no rate: fitted, it made every
        bin NaN)."""
        v = self.pixel_var[pix]
        return np.isfinite(v) & (v > 0) & np.isfinite(self.pixel_rate[pix])

    def psf(self, pos):
        return _psf(self.sim, self.profile, pos)

    def design(self, pos, phi):
        """The sparse design matrix A = [𝒫(P̃ δ_j) | 𝒫(1 δ_j)] at ``pos`` (P̃ LSF-averaged with ``phi``)."""
        P = self.psf(pos)
        Pt = P if phi is None else _lsf_averaged(self.sim, P, phi)
        return self.fp.with_background(Pt) if self.U is not None else self.fp.matrix(Pt)


class _Fit:
    """The state of the iterative fit: position [native cells], θ̂ and its covariance, the design
    matrix, the pixel variance, the rejected pixels, the photon spectrum φ."""

    def __init__(self, prob):
        self.pos = prob.start.copy()
        self.v = prob.v
        self.rejected = np.zeros(prob.d.size, bool)
        self.phi = None
        self.converged, self.iterations = prob.fixed, 0
        self.A = self.theta = self.cov = None
        self.leveraged = 0


def _fit(prob, noise):
    """Weighted least squares of the flux (and background), model variance, pixel rejection (afresh at
    every iteration, at the thresholds of ``_REJECT_SCHEDULE`` then ``_REJECT_SIGMA``) and Gauss–Newton
    steps of the position until it moves less than ``_POSITION_TOL`` and the rejected pixels are
    stable; then the outliers the fit absorbed (:func:`_leveraged_outliers`) leave it and it goes on
    (at most ``_LEVERAGE_ROUNDS`` times).  ReductionError when it does not converge or lands far from
    the light's centroid."""
    fit = _Fit(prob)
    sticky = np.zeros(prob.d.size, bool)
    first = 1
    for round_ in range(_LEVERAGE_ROUNDS + 1):
        _iterate(prob, noise, fit, sticky, first)
        _check_fit(prob, fit)
        cov = fit.cov()                                   # (AᵀWA)⁻¹ of the final solve only
        if round_ == _LEVERAGE_ROUNDS:                    # no fit left to go on without them: the fit
            break                                         # returned is the one solved (was: unconverged, with them in)
        extra = _leveraged_outliers(prob, fit, cov)
        if not extra.any():
            break
        sticky |= extra
        fit.rejected = fit.rejected | extra
        fit.v = np.where(extra, np.inf, fit.v)
        fit.converged = prob.fixed
        first = len(_REJECT_SCHEDULE) + 1                 # at the final threshold straight away
    fit.leveraged = int(sticky.sum())
    fit.cov = cov
    return fit


def _iterate(prob, noise, fit, sticky, first):
    """Iterations ``first`` … of :func:`_fit` (``first`` > 1: the schedule is over); the pixels of
    ``sticky`` stay rejected."""
    schedule = _REJECT_SCHEDULE + (_REJECT_SIGMA,)
    for it in range(first, first + _MAX_ITER):
        fit.iterations += 1
        fit.A = prob.design(fit.pos, fit.phi)
        fit.theta, fit.cov = _solve(fit.A, prob.d, fit.v)
        F = np.nan_to_num(fit.theta[:prob.nl])
        model = fit.A @ np.nan_to_num(fit.theta)
        v = _data_or_model(prob, noise, model)
        # pixels the model cannot explain (an unflagged cosmic ray or hot pixel) leave the fit
        with np.errstate(invalid="ignore", divide="ignore"):
            rejected = np.abs(prob.d - model) > schedule[min(it, len(schedule)) - 1] * np.sqrt(v)
        rejected |= sticky
        stable = it >= len(schedule) and np.count_nonzero(rejected != fit.rejected) <= _REJECT_STABLE * rejected.size
        fit.rejected = rejected
        fit.v = np.where(rejected, np.inf, v)
        fit.phi = _photon_spectrum(prob.sim, F, prob.qe)
        if prob.fixed:
            if stable:
                return
            continue
        delta = _position_step(prob, fit, F)
        fit.pos = fit.pos + delta
        _check_position(fit.pos, prob.shape, "the fitted position", prob.opts.cell_scale)
        if np.all(np.abs(delta) < _POSITION_TOL) and stable:
            fit.converged = True
            fit.A = prob.design(fit.pos, fit.phi)
            fit.theta, fit.cov = _solve(fit.A, prob.d, fit.v)
            return


def _leveraged_outliers(prob, fit, cov):
    """Fitted pixels whose studentized residual |r| / √(v (1 − h)) exceeds ``_REJECT_SIGMA`` (h: the
    pixel's leverage w aᵀ C a).  A pixel that alone determines some combination of the native fluxes
    (h → 1: at the blue end a bin is seen by few pixels) is followed by the model: its plain residual is
    small whatever its rate.  One outlier among 2 % (h = 0.9993, plain 0.25 σ, studentized 9.2 σ) set
    native bins 4–8 of a Lazuli SN Ia to +25, −7, +2 … e-/s against a truth of 0.003, χ² normal.
    Pixels with 1 − h < ``_NO_INFORMATION`` say nothing of themselves and are kept."""
    kept = np.isfinite(fit.v)
    out = np.zeros(kept.size, bool)
    if not kept.any():
        return out
    A = fit.A.tocsr()
    w = np.where(kept, 1.0 / np.where(kept, fit.v, 1.0), 0.0)
    r = prob.d - A @ np.nan_to_num(fit.theta)
    z2 = r * r * w
    # h ≤ w (Σ |a_s| √C_ss)² (Cauchy–Schwarz): the exact leverage only where that bound could flag
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    per_entry = np.abs(A.data) * sd[A.indices]
    counts = np.diff(A.indptr)
    row_sum = np.zeros(A.shape[0])
    has = counts > 0
    row_sum[has] = np.add.reduceat(per_entry, A.indptr[:-1][has]) if per_entry.size else 0.0
    need = np.flatnonzero(kept & (w * row_sum ** 2 >= 1.0 - z2 / _REJECT_SIGMA ** 2))
    if need.size == 0:
        return out
    room = 1.0 - _leverage(A[need], w[need], cov)
    with np.errstate(invalid="ignore"):
        out[need] = (room > _NO_INFORMATION) & (z2[need] > _REJECT_SIGMA ** 2 * room)
    return out


def _leverage(A, w, cov):
    """h_i = w_i a_iᵀ C a_i per row of the CSR design ``A`` (C the covariance of the fit)."""
    counts = np.diff(A.indptr)
    start = A.indptr[:-1]
    h = np.zeros(A.shape[0])
    rows = [np.flatnonzero(counts > p) for p in range(int(counts.max(initial=0)))]
    for p, rp in enumerate(rows):
        ip = start[rp] + p
        cp, ap = A.indices[ip], A.data[ip]
        h[rp] += ap * ap * cov[cp, cp]
        for q in range(p + 1, len(rows)):
            rq = rows[q]                                   # rows with more than q entries (⊂ rp)
            ip, iq = start[rq] + p, start[rq] + q
            h[rq] += 2.0 * A.data[ip] * A.data[iq] * cov[A.indices[ip], A.indices[iq]]
    return w * h


def _data_or_model(prob, noise, model):
    """The pixel variance of the next pass: the model variance (``noise`` given), else the data's."""
    if noise is None:
        return prob.v
    return _model_variance(model, prob.fp.pixels, noise, prob.pixel_var)


def _position_step(prob, fit, F, h=0.02):
    """Gauss–Newton step in (x, y) [native cells, at most 1 per axis]: ∂(Σ F_j A_j)/∂x by central
    differences of the PSF (step ``h``)."""
    dcols = []
    for axis in (0, 1):
        step = np.zeros(2)
        step[axis] = h
        dP = (prob.psf(fit.pos + step) - prob.psf(fit.pos - step)) / (2 * h)
        dcols.append(prob.fp.matrix(dP) @ F)
    J = sp.hstack([fit.A, sp.csr_matrix(np.stack(dcols, axis=1))]).tocsr()
    theta_j, _ = _solve(J, prob.d - fit.A @ np.nan_to_num(fit.theta), fit.v)
    return np.clip(np.nan_to_num(theta_j[-2:]), -1.0, 1.0)


def _check_fit(prob, fit):
    """Refuse a fit that did not converge, that rejected more than ``_MAX_REJECTED`` of its pixels, or whose
    position is far from the light's centroid."""
    pos, start = fit.pos, prob.start
    if not fit.converged:
        raise ReductionError(f"the point-source fit in the {prob.field} field did not converge in {_MAX_ITER} "
                             f"iterations (position ({pos[0] / prob.opts.cell_scale[0]:.3f}, {pos[1]:.3f}) cells): "
                             "give position=")
    frac = np.count_nonzero(fit.rejected) / max(fit.rejected.size, 1)
    if frac > _MAX_REJECTED:
        raise ReductionError(f"the point-source fit in the {prob.field} field rejected {100 * frac:.0f} % of its "
                             f"{fit.rejected.size} pixels (more than {100 * _MAX_REJECTED:.0f} %): no point-source model "
                             "explains the image (outliers or light that is not a point source)")
    if prob.fixed:
        return
    sig = np.asarray(prob.sim.psf_sigmas, float)                 # (σ_y, σ_x) per bin [cells]
    tol = max(_CENTROID_TOL_CELLS, 3.0 * float(np.median(sig)))
    if np.hypot(*(pos - start)) > tol:
        raise ReductionError(f"the fitted position ({pos[0]:.2f}, {pos[1]:.2f}) is {np.hypot(*(pos - start)):.1f} "
                             f"native cells from the light's centroid ({start[0]:.2f}, {start[1]:.2f}): "
                             "no reliable point source (give position=)")


def _spectrum(prob, fit, model_variance):
    """The native fit summed into the output bins: a SpectrumProduct with its diagnostics."""
    sim, M, nl, theta, cov = prob.sim, aggregate_bins(prob.ne, prob.edges), prob.nl, fit.theta, fit.cov
    resid = prob.d - fit.A @ np.nan_to_num(theta)
    npix, nrej = prob.fp.pixels.size, int(fit.rejected.sum())
    dof = max(npix - nrej - int(np.sum(np.diag(cov) > 0)) - (0 if prob.fixed else 2), 1)
    chi2 = float(np.sum(np.where(fit.rejected, 0.0, resid ** 2 / np.where(fit.rejected, 1.0, fit.v))))
    Fn, Cn = theta[:nl], cov[:nl, :nl]
    seen = np.diag(Cn) > 0
    flux, cbin = M @ np.where(seen, Fn, 0.0), M @ Cn @ M.T
    wsum = M.sum(axis=1)
    flux = np.where(((M * seen[None]).sum(axis=1) >= 0.999 * wsum) & (wsum > 0), flux, np.nan)
    cvar = np.where(np.isfinite(flux), np.diag(cbin), np.inf)
    bkg = bvar = None
    with np.errstate(invalid="ignore", divide="ignore"):
        if prob.opts.background:
            bkg = (M @ np.nan_to_num(theta[nl:2 * nl])) / wsum
            bvar = (M ** 2 @ np.diag(cov[nl:2 * nl, nl:2 * nl])) / wsum ** 2
        sig_y, sig_x = (np.asarray(s, float) for s in sim.psf_sigmas)
        psf_sigma = np.stack([M @ sig_x, M @ sig_y], axis=1) / wsum[:, None]
        # F_λ [erg/s/cm²/Å]: the rate over the response R_j = QE_j f2p_j [e-/s per erg/s/cm²/Å] (telescope
        # area, throughput, bin width, QE), F_λ(b) = Σ_j M_bj F_j / Σ_j M_bj R_j (exact for F_λ flat in b)
        response = M @ (prob.qe * np.asarray(sim.flambda_to_photon, float))
        to_flambda = np.where(response > 0, 1.0 / response, np.nan)
    ee = M @ prob.psf(fit.pos).sum(axis=(1, 2)) / np.where(wsum > 0, wsum, 1.0)
    diag = {"position_native_cells": tuple(float(p) for p in fit.pos), "start": tuple(float(p) for p in prob.start),
            "iterations": fit.iterations, "converged": fit.converged, "chi2": chi2, "dof": dof, "chi2_dof": chi2 / dof,
            "pixels": int(npix), "rejected_pixels": nrej, "leveraged_pixels": fit.leveraged, "native_flux": Fn, "native_covariance": Cn,
            "covariance": cbin, "rows": prob.rows.tolist(),
            "variance_model": "(AᵀWA)⁻¹, W the model variance" if model_variance else "(AᵀWA)⁻¹",
            "pixel_index": prob.fp.pixels, "pixel_variance": fit.v, "residual": np.where(fit.rejected, 0.0, resid),
            "flambda_per_rate": to_flambda, "flambda": flux * to_flambda, "flambda_variance": cvar * to_flambda ** 2}
    edges = prob.edges
    return SpectrumProduct(lbda=0.5 * (edges[1:] + edges[:-1]), lbda_edges=edges, flux=flux, variance=cvar,
                           method="forward", unit="e-/s",
                           position=tuple(float(p) for p in fit.pos / np.asarray(prob.opts.cell_scale, float)),
                           aperture=float("nan"), psf_sigma=psf_sigma, background=bkg, background_variance=bvar,
                           enclosed_energy=ee, diagnostics=diag)


def _check_position(pos, shape, what, scale=(1.0, 1.0), given=False):
    """A position [native cells] the fit can use: finite and at least half a cell inside the field
    (messages in the caller's cells: native cells ÷ ``scale``)."""
    ny, nx = shape
    sx, sy = (float(v) for v in scale)
    if not np.all(np.isfinite(pos)):
        raise ReductionError(f"{what} is not finite: ({float(pos[0])}, {float(pos[1])})")
    hx, hy = nx / 2.0 - 0.5, ny / 2.0 - 0.5
    if abs(pos[0]) > hx or abs(pos[1]) > hy:
        advice = "" if given else " (give position= to extract elsewhere)"
        raise ReductionError(f"{what} ({pos[0] / sx:.2f}, {pos[1] / sy:.2f}) cells is too close to the field edge "
                             f"to fit a point source (|x| ≤ {hx / sx:.2f}, |y| ≤ {hy / sy:.2f}){advice}")


def _model_variance(model, pixels, noise, data_var):
    """var_rnoise + k·max(model + dark, 0) on the fitted pixels; k = var_poisson / rate (median)."""
    vr = np.asarray(noise.var_rnoise, float).ravel()[pixels]
    vp = np.asarray(noise.var_poisson, float).ravel()[pixels]
    rr = np.asarray(noise.raw_rate, float).ravel()[pixels]
    ok = np.isfinite(vp) & (vp > 0) & (rr > 0)
    k = float(np.median(vp[ok] / rr[ok])) if ok.any() else 0.0
    dark = np.asarray(noise.dark_rate, float)
    dark = dark.ravel()[pixels] if dark.ndim == 2 else float(dark)
    out = vr + k * np.maximum(model + dark, 0.0)
    bad = ~np.isfinite(out) | ~(out > 0)
    return np.where(bad, data_var[pixels], out)
