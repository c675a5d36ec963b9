"""Rectification: detector rate image → (λ, y, x) cubes of the narrow and wide fields, with variance.

The forward model is linear: image = P · cube, P[pixel, cell] the weight with which a cube
cell (slice, λ bin, column along the slice) deposits on a pixel — its footprint blurred by
the spot, integrated over the pixel (:meth:`SlicerMapper.project_cube`, the deposit tables
of :mod:`slicersim.backends.projection`).  Every column of P sums to 1 for a cell on the
detector.  Cube row r ↔ slice ``slices[n_rows − 1 − r]`` as in ``project_cube``.  Two
estimators of the cube on a grid (λ edges, ``ncol`` columns per slice):

* ``method="lsq"`` (exact): weighted least squares x̂ = argmin Σ_p w_p ((P x)_p − d_p)²,
  w_p = 1/var_p (1 without a variance).  Noiseless data d = P x give x back (to κ(P)·ε);
  unbiased, flux-conserving (Σ x̂ = Σ P x̂: the model image carries the cube's flux) and
  its covariance is (PᵀWP)⁻¹, whose diagonal is the variance returned.  Neighbouring slices
  may share a few pixels (the ±``truncate``·σ tails of their spots meet between the traces
  when a layout's spots blur beyond the cube's own: none on the default layout, ~1.4 % of a
  field's footprint pixels with 1.2-px spots).  Those pixels are left out of the fit, so
  every slice is an independent problem, solved exactly (the price: the two end columns of a
  slice lose up to ~60 % of their flux to left-out pixels in the red, where the traces come
  closest, and their variance grows accordingly).  A slice's normal matrix PᵀWP (cells
  ordered λ-major, column-minor: block tridiagonal with blocks of the bandwidth) is
  factorised by block Cholesky, one step of refinement with the data residual (corrected
  semi-normal equations) restores the accuracy of the squared condition, and the diagonal
  of the inverse comes from the block Takahashi recursion.  The full inverse covariance
  N = PᵀWP travels with the cube (``CubeProduct.inverse_covariance``, one sparse block per
  slice, rebuilt on demand or kept): the GLS extraction uses it.  Pᵀ·(W d) and the model image
  P x̂ for the diagnostics go through the projection kernels (gather / deposit).
* ``method="drizzle"`` (pixel-to-cell): every pixel's rate is shared among the cells that
  deposit on it in proportion to their weight, x̂_c = Σ_p P_pc d_p / (P·1)_p, divided by
  Σ_p P_pc m_p (m: usable pixels; 1 without bad pixels).  One deposit and one gather: fast,
  conserves the total flux exactly and returns constant cubes exactly, but it is biased: the
  truth smoothed by PᵀD⁻¹P (about the spot blur twice plus pixel and cell boxes).  Variance
  Σ_p (P_pc/(P·1)_p)² var_p / (Σ_p P_pc m_p)²; neighbouring cells are correlated (only the
  diagonal is returned).

Conditioning: on the native Lazuli grid (510 bins ~1 px, 116 columns of ~0.9 px per
~105 px long slice) P is singular (more cells than pixels across a slice), so ``lsq`` refuses
it; with the default layout (the projection adds no blur to the cube's own) 58 columns and
1-px bins give κ₁(PᵀP) ≈ 43, 58 columns and 2-px bins ≈ 4 (with the spots applied a second time,
as before the projection fix, these were 4e2–2e5 and 13–220).  Noise is amplified as the
conditioning says: the variance returned shows it.
"""
from __future__ import annotations

import warnings

import functools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.linalg import LinAlgError

from slicersim.backends.projection import deposit, footprint_windows
from slicersim.backends.projection_transpose import gather, matrix_entries
from slicersim.errors import ParameterError
from slicersim import validation
from slicersim.backends.precision import float64_kwargs
from slicersim.instrument.mapper import SlicerMapper
from slicersim.reduction.block_cholesky import BlockCholesky
from slicersim.reduction.option_forms import build_options
from slicersim.reduction.rectify_checks import (FIELDS, METHODS, RectifyOptions, _check_grid, _check_images,
                                                _check_options, _check_projection)

__all__ = ["rectify", "CubeProduct", "InverseCovariance", "inverse_covariance", "FIELDS", "METHODS",
           "MAX_CONDITION"]

#: largest 1-norm condition number of a slice's normal matrix PᵀWP that ``lsq`` accepts
#: (beyond, float64 cannot resolve the cube: the grid is finer than the detector samples it)
MAX_CONDITION = 1e14
_ENTRY_CHUNK = 1 << 13           # sub-cells per matrix_entries call


@dataclass
class CubeProduct:
    """A rectified cube of one field.

    ``flux``: (nλ, n_rows, ncol), or (N, nλ, n_rows, ncol) for a stack of N images, in the
    image's unit per cell per bin (``unit``, e.g. e-/s); ``variance``: same shape minus the
    stack axis [unit²] (None without an input variance); NaN for cells no usable pixel sees.
    ``inverse_covariance`` (``lsq`` with a variance): the full inverse covariance of the cube,
    one sparse block per row (:class:`InverseCovariance`, :meth:`normal_matrix`).
    ``wcs``: the axes (λ centres and edges [Å], slice id of every row, fieldpos edges of the
    columns, −1 … +1 along the slice).  ``diagnostics``: see :func:`rectify`.
    """

    field: str
    method: str
    flux: np.ndarray
    variance: np.ndarray | None
    lbda: np.ndarray
    lbda_edges: np.ndarray
    slices: tuple
    unit: str = "e-/s"
    wcs: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    inverse_covariance: "InverseCovariance | None" = field(default=None, repr=False, compare=False)

    def normal_matrix(self, row):
        """The inverse covariance block N_s = P_sᵀW P_s of cube row ``row`` (:class:`InverseCovariance`;
        ``lsq`` cubes rectified with a variance only)."""
        if self.inverse_covariance is None:
            raise ParameterError(f"this {self.method} cube carries no inverse covariance (lsq with a "
                                 "variance only)")
        return self.inverse_covariance.matrix(row)


@functools.lru_cache(maxsize=1)
def _default_mapper():
    return SlicerMapper.default()


# --------------------------------------------------------------------------- pixels
def _slice_coverage(mapper, ncol, edges, oversample, truncate):
    """(H, W) int16: how many slices of the mapper reach each pixel (their ±truncate·σ windows)."""
    H, W = mapper.detector_shape
    count = np.zeros((H, W), np.int16)
    for sid in mapper.slice_ids:
        box = mapper.cell_boxes([int(sid)], ncol, edges, oversample)
        x0, nx = footprint_windows(box[:, 0], box[:, 1], box[:, 2], truncate)
        y0, ny = footprint_windows(box[:, 3], box[:, 4], box[:, 5], truncate)
        xa, xb = np.clip(x0, 0, W), np.clip(x0.astype(np.int64) + nx, 0, W)
        ya, yb = np.clip(y0, 0, H), np.clip(y0.astype(np.int64) + ny, 0, H)
        ok = (xa < xb) & (ya < yb)
        if not ok.any():
            continue
        xa, xb, ya, yb = xa[ok], xb[ok], ya[ok], yb[ok]
        bx0, by0 = int(xa.min()), int(ya.min())
        h, w = int(yb.max()) - by0, int(xb.max()) - bx0
        diff = np.zeros((h + 1, w + 1), np.int32)          # union of rectangles by 2-D prefix sums
        np.add.at(diff, (ya - by0, xa - bx0), 1)
        np.add.at(diff, (ya - by0, xb - bx0), -1)
        np.add.at(diff, (yb - by0, xa - bx0), -1)
        np.add.at(diff, (yb - by0, xb - bx0), 1)
        inside = np.cumsum(np.cumsum(diff, axis=0), axis=1)[:h, :w] > 0
        count[by0:by0 + h, bx0:bx0 + w] += inside
    return count


def _slice_matrix(tables, s, weight_of):
    """P of slice s on its usable pixels: (CSR (npix × ncell), flat pixel indices, their
    weights, flux fraction of every cell on excluded pixels).  ``weight_of(flat pixels)``:
    the LSQ weights (0: unusable)."""
    S, E, Q = tables.grid
    ne, nq = tables.oversample
    nc = (E // ne) * (Q // nq)
    pix, cell, wgt = [], [], []
    for c0 in range(s * E * Q, (s + 1) * E * Q, _ENTRY_CHUNK):
        p, c, w = matrix_entries(tables, c0, min(c0 + _ENTRY_CHUNK, (s + 1) * E * Q))
        pix.append(p)
        cell.append(c - s * nc)
        wgt.append(w)
    pix, cell, wgt = np.concatenate(pix), np.concatenate(cell), np.concatenate(wgt)
    use = weight_of(pix) > 0
    lost = np.bincount(cell[~use], weights=wgt[~use], minlength=nc)
    upix, row = np.unique(pix[use], return_inverse=True)
    P = sp.csr_matrix((wgt[use], (row, cell[use])), shape=(upix.size, nc))
    P.sum_duplicates()
    return P, upix, weight_of(upix), lost


def _normal_matrix(P, w):
    """PᵀWP (CSR, exactly symmetric) of one slice: the inverse covariance of its LSQ cells."""
    A = (P.T @ sp.csr_matrix(P.multiply(w[:, None]))).tocsr()
    return (0.5 * (A + A.T)).tocsr()


class InverseCovariance:
    """Inverse covariance N = PᵀWP of an LSQ cube: the cube's covariance (PᵀWP)⁻¹ is block diagonal
    over the slices (pixels shared between slices are left out of the fit), so N is one sparse
    (nλ·ncol)² block per cube row.

    ``matrix(row)``: CSR block of cube row ``row``, cells λ-major, column-minor (index
    λ·ncol + column: ``cube[:, row, :].ravel()``), block tridiagonal over λ bins; a cell no usable
    pixel sees has a zero row and column (NaN in the cube).  N x̂ = PᵀW d: fits to the cube weighted
    by N are fits to the detector pixels (:func:`slicersim.reduction.gls_extraction.extract_gls`).
    Built on demand from the projection tables and the weights 1/var of the usable pixels (held:
    the tables, 12 bytes per usable pixel), or kept (``keep``: rectify's own matrices, about
    12 bytes × nλ·ncol·(2·bandwidth + 1) per slice, bandwidth ≈ ncol × (1 + spot width / bin
    width); ``nbytes()``).  Valid for every image of a stack (one variance)."""

    def __init__(self, tables, weight, slices, shape, keep=False):
        flat = np.asarray(weight, np.float64)
        self.image_shape = flat.shape                     # the detector's (H, W): the weights' image
        flat = flat.ravel()
        usable = np.flatnonzero(flat > 0)
        self._pix = usable.astype(np.int32 if flat.size < 2**31 else np.int64)
        self._w = flat[usable]
        self._tables = tables
        self.slices = tuple(int(v) for v in slices)       # gather order: cube row r ↔ slices[S − 1 − r]
        self.shape = tuple(int(v) for v in shape)         # (nλ, n_rows, ncol)
        self.keep = bool(keep)
        self._kept = {}
        self.weights_of = None                             # noise_information: the N this B goes with

    def _weight_of(self, pix):
        if self._pix.size == 0:
            return np.zeros(np.shape(pix))
        i = np.minimum(np.searchsorted(self._pix, pix), self._pix.size - 1)
        return np.where(self._pix[i] == pix, self._w[i], 0.0)

    def _store(self, s, A):
        if self.keep:
            self._kept[s] = A

    def matrix(self, row):
        """N of cube row ``row`` (CSR, (nλ·ncol)²) [unit⁻²]."""
        nrow = self.shape[1]
        row = validation.integer("row (cube row)", row, low=0, high=nrow - 1)
        s = nrow - 1 - row
        if s in self._kept:
            return self._kept[s]
        P, _, w, _ = _slice_matrix(self._tables, s, self._weight_of)
        A = _normal_matrix(P, w)
        self._store(s, A)
        return A

    def nbytes(self):
        """Bytes held: the pixel weights and the kept matrices (not the shared projection tables)."""
        kept = sum(A.data.nbytes + A.indices.nbytes + A.indptr.nbytes for A in self._kept.values())
        return int(self._pix.nbytes + self._w.nbytes + kept)


def noise_information(info, variance):
    """B = PᵀW Σ W P for an LSQ cube whose inverse covariance is ``info`` (N = PᵀWP, W the weights
    it was rectified with) and pixels of true variance Σ = diag(``variance``) [unit²]: the cube's
    covariance is then N⁻¹ B N⁻¹ (the sandwich), N⁻¹ only when W = Σ⁻¹.  Pixels used by the cube
    whose ``variance`` is not finite and > 0 keep 1/W.  An :class:`InverseCovariance` of the same
    tables (``matrix(row)`` gives B's blocks), for :func:`~slicersim.reduction.gls_extraction.extract_gls`'s
    ``noise_information``.  ``variance`` must have the shape of the image the cube was rectified
    from (the detector's)."""
    if not isinstance(info, InverseCovariance):
        raise ParameterError(f"info must be a cube's InverseCovariance (CubeProduct.inverse_covariance), "
                             f"got {type(info).__name__}")
    if np.iscomplexobj(variance):
        raise ParameterError("variance must be real numbers, got complex values")
    try:
        var = np.asarray(variance, np.float64)
    except (TypeError, ValueError):
        raise ParameterError("variance must be a numeric array") from None
    if var.shape != info.image_shape:
        raise ParameterError(f"variance has shape {var.shape}: the cube was rectified from {info.image_shape} "
                             "pixels (one variance per detector pixel)")
    s2 = var.ravel()[info._pix]
    w = info._w
    s2 = np.where(np.isfinite(s2) & (s2 > 0), s2, 1.0 / w)
    flat = np.zeros(var.size)
    flat[info._pix] = w * w * s2
    out = InverseCovariance(info._tables, flat.reshape(info.image_shape), info.slices, info.shape)
    out.weights_of = info
    return out


#: fraction of a slice's pixels without weight (saturated, flagged) above which an unmeasured cell is blamed on
#: them rather than on the grid
FLAGGED_SHARE = 0.05


def _why_unmeasured(share):
    """Why some cells of a slice are not measured: its pixels without weight (saturated or flagged: the
    source, not the grid) when they hold more than :data:`FLAGGED_SHARE` of the slice's light (``share``),
    else a grid finer than the pixels."""
    if share > FLAGGED_SHARE:
        return (f"{100 * share:.0f} % of its pixels carry no weight (saturated or flagged: a saturated source "
                "leaves its cells unmeasured); a shorter readout (fewer groups) or --rectify drizzle, whose cells "
                "take what the good pixels give, avoids it")
    return ("the grid is finer than the detector samples it (cells smaller than pixel and spot); use fewer "
            "columns (ncol), wider λ bins or method='drizzle'")


#: a field with more than 1/UNSOLVED_SHARE of its slices unsolvable (or more than one) is refused (the grid asked
#: for is finer than the detector samples it); fewer are a few damaged slices (cosmic rays, bad pixels around a
#: cell): their cells are NaN, with a warning
UNSOLVED_SHARE = 10


class _UnsolvedSlice(Exception):
    """A slice whose normal matrix cannot be solved (singular or too ill-conditioned); its message says why."""


def _solve_slice(P, w, rhs, data, want_variance, max_bytes, sid, A, excluded=0.0):
    """Weighted LSQ of one slice (A = PᵀWP): (x (nc, N), variance (nc,) or None, κ₁(A)); ``excluded``: the
    share of the slice's projection on pixels without weight (named when the matrix cannot be solved)."""
    nc = P.shape[1]
    seen = A.diagonal() > 0
    x = np.full((nc, rhs.shape[1]), np.nan)
    var = np.full(nc, np.nan) if want_variance else None
    if not seen.any():
        return x, var, 1.0
    idx = np.flatnonzero(seen)
    if idx.size < nc:
        A = A[idx][:, idx].tocsr()
    coo = A.tocoo()
    band = int(np.abs(coo.row - coo.col).max()) if coo.nnz else 0
    block = max(band, 1)
    need = 4 * (-(-idx.size // block) + 1) * block * block * 8      # blocks of A, of L⁻¹ and of L
    if need > max_bytes:
        raise ParameterError(f"slice {sid}: the normal matrix needs {need / 2**20:.0f} MiB (bandwidth {band}) "
                             f"> max_bytes {max_bytes / 2**20:.0f} MiB: use fewer columns, wider λ bins "
                             "or method='drizzle'")
    try:
        fac = BlockCholesky(A, block)
    except LinAlgError:
        raise _UnsolvedSlice(f"slice {sid}: the normal matrix PᵀWP is singular — "
                             + _why_unmeasured(excluded)) from None
    # the solve, its refinement with the data residual (corrected semi-normal equations) and the first
    # two solves of Hager's estimate of ‖A⁻¹‖₁ go together (one pass of the recursion for both)
    n, k = idx.size, rhs.shape[1]
    Pk = P[:, idx]
    sol = fac.solve(np.column_stack([rhs[idx], np.full(n, 1.0 / n)]))
    xs, y = sol[:, :k], sol[:, k]
    resid = data - Pk @ xs
    sol = fac.solve(np.column_stack([Pk.T @ (w[:, None] * resid), np.where(y >= 0, 1.0, -1.0)]))
    xs += sol[:, :k]
    cond = float(abs(A).sum(axis=0).max() * fac.inverse_norm1(y, sol[:, k]))
    if not cond < MAX_CONDITION:
        raise _UnsolvedSlice(f"slice {sid}: the normal matrix PᵀWP has condition {cond:.2g} > "
                             f"{MAX_CONDITION:.0e}: " + _why_unmeasured(excluded))
    x[idx] = xs
    if want_variance:
        var[idx] = fac.inverse_diagonal()
    return x, var, cond


# --------------------------------------------------------------------------- fields
def _cube_axes(values):
    """(…, S, nλ, ncol) gather order → (…, nλ, n_rows, ncol) cube order (row r ↔ slices[S − 1 − r])."""
    return np.ascontiguousarray(np.swapaxes(values, -3, -2)[..., ::-1, :])


def _field_lsq(images, weight, tables, slices, want_variance, max_bytes, backend, info):
    """Weighted LSQ of one field: ((N, S, nλ, ncol) flux, (S, nλ, ncol) variance or None, diagnostics);
    the slices' normal matrices go to ``info`` (an :class:`InverseCovariance`, kept if it keeps them)."""
    S, E, Q = tables.grid
    ne, nq = tables.oversample
    shape = (S, E // ne, Q // nq)
    nc = shape[1] * shape[2]
    N = images.shape[0]
    usable = weight > 0
    rhs = np.stack([gather(np.where(usable, img, 0.0) * weight, tables, backend=backend)    # Pᵀ W d
                    for img in images]).reshape(N, S, nc)
    flat_w, flat_d = weight.ravel(), images.reshape(N, -1)
    flux = np.empty((N, S, nc))
    var = np.empty((S, nc)) if want_variance else None
    cond, lost, unsolved = 0.0, 0.0, []
    for s in range(S):
        P, upix, w, lost_s = _slice_matrix(tables, s, flat_w.__getitem__)
        A = _normal_matrix(P, w)
        info._store(s, A)
        total = float(lost_s.sum() + P.sum())
        try:
            x, v, c = _solve_slice(P, w, rhs[:, s].T, flat_d[:, upix].T, want_variance, max_bytes, slices[s], A,
                                   excluded=float(lost_s.sum()) / total if total > 0 else 0.0)
        except _UnsolvedSlice as exc:             # one bad slice (cosmic rays, bad pixels): its cells NaN, said
            unsolved.append(str(exc))
            flux[:, s] = np.nan
            if want_variance:
                var[s] = np.nan
            continue
        flux[:, s] = x.T
        if want_variance:
            var[s] = v
        cond, lost = max(cond, c), max(lost, float(lost_s.max()))
    if len(unsolved) > max(1, S // UNSOLVED_SHARE):       # the request, not a few damaged slices: refused
        raise ParameterError(f"{unsolved[0]} ({len(unsolved)} of {S} slices)")
    if unsolved:
        warnings.warn(f"{len(unsolved)} of {S} slices not rectified, their cells NaN: {unsolved[0]}", RuntimeWarning,
                      stacklevel=3)
    flux = flux.reshape((N,) + shape)
    chi2, grad = [], []
    for n in range(N):                                                  # model image P x̂ on the device
        resid = np.where(usable, images[n] - deposit(np.nan_to_num(flux[n]), tables, **float64_kwargs(backend)), 0.0)
        chi2.append(float((weight * resid * resid).sum()))
        g = gather(weight * resid, tables, backend=backend)
        grad.append(float(np.linalg.norm(g) / max(np.linalg.norm(rhs[n]), 1e-300)))
    diag = {"cond1_normal_max": cond, "chi2": np.array(chi2), "dof": int(usable.sum()) - int(np.isfinite(
        flux[0]).sum()), "gradient_rel": np.array(grad), "excluded_flux_max": lost,
            "unsolved_slices": len(unsolved)}
    return flux, None if var is None else var.reshape(shape), diag


def _field_drizzle(images, usable, variance, cover, tables, backend):
    """Pixel-to-cell estimate of one field (``cover`` = P·1): ((N, S, nλ, ncol) flux, variance or
    None, diagnostics)."""
    inside = usable & (cover > 0)
    safe = np.where(inside, cover, 1.0)
    seen = gather(inside.astype(np.float64), tables, backend=backend)          # Σ_p P_pc m_p
    ok = seen > 0
    den = np.where(ok, seen, 1.0)
    num = np.stack([gather(np.where(inside, img, 0.0) / safe, tables, backend=backend) for img in images])
    flux = np.where(ok, num / den, np.nan)
    var = None
    if variance is not None:
        vq = gather(np.where(inside, variance, 0.0) / (safe * safe), tables, power=2, backend=backend)
        var = np.where(ok, vq / (den * den), np.nan)
    diag = {"flux_image": np.array([float(img[inside].sum()) for img in images]),
            "flux_cube": np.nansum(flux, axis=(1, 2, 3)), "coverage_min": float(seen[ok].min()) if ok.any()
            else 0.0}
    return flux, var, diag


def _usable_pixels(images, variance, owner_ok, field_name, weighted):
    """Usable pixels of a field and the LSQ weights: finite variance (> 0 when ``weighted``) and rate."""
    usable = owner_ok.copy()
    if variance is not None:
        usable &= np.isfinite(variance)
        if weighted and (variance[usable] == 0).any():
            raise ParameterError(f"variance must be > 0 on the pixels the {field_name} field reaches "
                                 "(+inf leaves a pixel out)")
    bad = np.zeros(usable.shape, bool)
    for img in images:
        bad |= usable & ~np.isfinite(img)
    if bad.any():
        raise ParameterError(f"rate_image is not finite on {int(bad.sum())} pixel(s) the {field_name} field "
                             "reaches: give them variance=+inf to leave them out")
    weight = np.zeros(usable.shape)
    weight[usable] = 1.0 if variance is None else 1.0 / variance[usable]
    return usable, weight


def _field_tables(mapper, name, edges, ncol, ov, truncate, weights_dtype, backend):
    """(slices in gather order, projection tables, P·1 image) of a field."""
    slices = [int(s) for s in FIELDS[name]]
    tables = mapper.projection_tables(slices, ncol, edges, oversample=ov, truncate=truncate,
                                      weights_dtype=weights_dtype, backend=backend)
    cover = deposit(np.ones((len(slices), edges.size - 1, ncol)), tables, **float64_kwargs(backend))
    return slices, tables, cover


def rectify(rate_image, variance=None, options=None, **keywords):
    """Rectify a detector rate image into the cube(s) of a field: see the module docstring.

    ``options`` is a :class:`~slicersim.reduction.rectify_checks.RectifyOptions` (None: its defaults); its
    fields, given as keywords, replace those of ``options`` (the keyword form of earlier releases):

    Parameters
    ----------
    rate_image : (H, W) or (N, H, W) float [``unit`` per pixel, e.g. e-/s]
        the mapper's detector; a stack shares one variance (one factorisation for all).
    variance : (H, W) float, optional
        per-pixel variance [unit²]; +inf leaves a pixel out (its rate may then be NaN).
        Without it ``lsq`` is unweighted and no variance is returned.
    mapper : SlicerMapper (default ``SlicerMapper.default()``)
    field : "narrow" (slices 1–58), "wide" (59–116) or "both"
    lbda, lbda_edges : (nλ,), (nλ+1,) [Å]
        output bin centres and/or edges (edges from midpoints when only centres are given).
    ncol : columns per slice (cells along the slice, fieldpos −1 … +1).
    method : "lsq" (exact weighted least squares) or "drizzle" (pixel-to-cell).
    oversample, truncate, weights_dtype : the projection's options (as ``project_cube``: the
        same values give the same P, hence exact recovery of a cube projected with them).
    max_bytes : memory allowed for one slice's factorisation (``lsq``) [bytes].
    unit : the image's unit;  backend : "auto", "numpy" or "opencl".
    keep_information : ``lsq`` with a variance: keep every slice's normal matrix PᵀWP (the cube's
        inverse covariance, :class:`InverseCovariance`) instead of rebuilding it when asked.

    Returns a :class:`CubeProduct` (``field="both"``: a dict of two); ``lsq`` with a variance:
    its ``inverse_covariance``.  ``diagnostics``:
    lsq: ``cond1_normal_max`` (largest κ₁(PᵀWP) of a slice), ``chi2`` per image over the used
    pixels, ``dof``, ``gradient_rel`` (‖Pᵀ W (d − P x̂)‖ / ‖Pᵀ W d‖, 0 at the optimum),
    ``excluded_flux_max`` (largest fraction of a cell's flux on pixels shared with another
    slice, left out), ``pixels_shared``; drizzle: ``flux_image`` and ``flux_cube`` (equal:
    flux conserved), ``coverage_min``; both: ``pixels_used``, ``time_s``.
    """
    opts = build_options(RectifyOptions, options, keywords, "rectify")
    mapper = _default_mapper() if opts.mapper is None else opts.mapper
    names = _check_options(opts.field, opts.method, opts.ncol, opts.backend, mapper)
    if opts.method == "drizzle" and variance is not None and opts.oversample != (1, 1):
        raise ParameterError("drizzle variances need oversample (1, 1)")
    centres, edges = _check_grid(opts.lbda, opts.lbda_edges, mapper)
    images, var = _check_images(rate_image, variance, mapper.detector_shape)
    if images.size == 0:
        raise ParameterError(f"rate_image is an empty stack {images.shape}: give at least one image")
    stack = images.ndim == 3
    images = images if stack else images[None]
    lsq = opts.method == "lsq"
    count = _slice_coverage(mapper, opts.ncol, edges, opts.oversample, opts.truncate) if lsq else None
    out = {}
    for name in names:
        flux, fvar, slices, diag, info = _rectify_field(images, var, mapper, name, edges, count, opts)
        wcs = {"axes": ("lbda", "slice", "fieldpos"), "lbda": centres, "lbda_edges": edges, "lbda_unit": "Angstrom",
               "slice_of_row": tuple(slices[::-1]), "fieldpos_edges": np.linspace(-1.0, 1.0, opts.ncol + 1),
               "unit": f"{opts.unit} per cell per bin"}
        out[name] = CubeProduct(name, opts.method, flux if stack else flux[0], fvar, centres, edges,
                                tuple(slices[::-1]), opts.unit, wcs, diag, info)
    return out if opts.field == "both" else out[opts.field]


def _rectify_field(images, var, mapper, name, edges, count, opts):
    """One field: (flux, variance or None in cube order, slices, diagnostics, InverseCovariance or None)."""
    t0 = time.perf_counter()
    ncol = opts.ncol
    slices, tables, cover = _field_tables(mapper, name, edges, ncol, opts.oversample, opts.truncate,
                                          opts.weights_dtype, opts.backend)
    reach = cover > 0
    info = None
    if opts.method == "lsq":
        usable, weight = _usable_pixels(images, var, reach & (count == 1), name, True)
        shape = (edges.size - 1, len(slices), ncol)
        info = InverseCovariance(tables, weight, slices, shape, opts.keep_information and var is not None)
        flux, fvar, diag = _field_lsq(images, weight, tables, slices, var is not None, opts.max_bytes,
                                      opts.backend, info)
        diag["pixels_shared"] = int((reach & (count > 1)).sum())
        info = info if var is not None else None
    else:
        usable, _ = _usable_pixels(images, var, reach, name, False)
        flux, fvar, diag = _field_drizzle(images, usable, var, cover, tables, opts.backend)
    diag.update(pixels_used=int(usable.sum()), time_s=time.perf_counter() - t0)
    return _cube_axes(flux), None if fvar is None else _cube_axes(fvar), slices, diag, info


def inverse_covariance(variance, *, mapper=None, field="narrow", lbda_edges, ncol, oversample=(1, 1), truncate=4.0,
                       weights_dtype=np.float32, backend="auto", keep=False):
    """The :class:`InverseCovariance` that ``rectify(…, variance, method="lsq")`` with the same
    options attaches to its cube (same usable pixels: unshared, finite variance > 0), without
    rectifying anything (e.g. for a cube read back from a file).  ``field="both"``: a dict of two."""
    mapper = _default_mapper() if mapper is None else mapper
    names = _check_options(field, "lsq", ncol, "auto" if backend is None else backend, mapper)
    ov = _check_projection(oversample, truncate, weights_dtype)
    _, edges = _check_grid(None, lbda_edges, mapper)
    _, var = _check_images(np.zeros((0,) + tuple(mapper.detector_shape)), variance, mapper.detector_shape)
    if var is None:
        raise ParameterError("inverse_covariance needs the per-pixel variance the cube was rectified with")
    count = _slice_coverage(mapper, int(ncol), edges, ov, truncate)
    out = {}
    for name in names:
        slices, tables, cover = _field_tables(mapper, name, edges, int(ncol), ov, truncate, weights_dtype, backend)
        _, weight = _usable_pixels((), var, (cover > 0) & (count == 1), name, True)
        out[name] = InverseCovariance(tables, weight, slices, (edges.size - 1, len(slices), int(ncol)), keep)
    return out if field == "both" else out[field]
