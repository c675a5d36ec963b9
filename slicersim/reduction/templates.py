"""Forward-modelled templates of a point source for the GLS extraction.

An LSQ cube x̂ = (PᵀWP)⁻¹PᵀW d on a coarse grid (e.g. 2 native λ bins × 58 columns) is linear in
the detector image d.  The detector image of a point source is made at the NATIVE resolution
(the spot is sharp within a coarse cell), so E[x̂] is not F·P_coarse, and the GLS with a per-bin
PSF on the coarse cells is biased (a model error).  By linearity it is exactly

    E[x̂] = Σ_b F_b T_b,        T_b = rectify(project(C_b)),

where C_b is the native cube of the point source restricted to the native bins of coarse bin b,
per unit flux of that bin, projected with the native λ grid (as the simulation) and rectified
with the SAME mapper, coarse grid, projection options and variance as the data.  Using T
(:func:`point_source_template`) as the model of
:func:`~slicersim.reduction.gls_extraction.extract_gls` (``psf=T``) makes the GLS unbiased; F̂_b
is the source's flux in the native bins of coarse bin b (over the field's cells).

Rule: a native bin belongs to the coarse bin holding its centre; every coarse edge must be a
native edge (to 1e-6 of a native bin width), so each coarse bin is a whole number of native
bins and no native bin straddles two.  Native bins outside the coarse range are not modelled
(their light on the detector is a model error: choose the coarse range to cover the source's
light on the field, or leave those pixels out with variance +inf).  The spectral shape within a
coarse bin is the native cube's: a source of another shape within a bin gives a second-order
difference.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.backends.precision import float64_kwargs
from slicersim.reduction.rectify import rectify

__all__ = ["point_source_template"]

_EDGE_TOLERANCE = 1e-6          # of a native bin width


def _native_groups(native_shape, native_lbda_edges, lbda_edges):
    """Coarse bin of every native bin (−1: outside), checked edges."""
    ne = np.asarray(native_lbda_edges, float)
    ce = np.asarray(lbda_edges, float)
    if ne.ndim != 1 or ne.size != native_shape[0] + 1 or not np.all(np.isfinite(ne)) or np.any(np.diff(ne) <= 0):
        raise ParameterError(f"native_lbda_edges must be {native_shape[0] + 1} finite increasing edges [Å] "
                             f"(the native cube has {native_shape[0]} bins), got shape {ne.shape}")
    if ce.ndim != 1 or ce.size < 2 or not np.all(np.isfinite(ce)) or np.any(np.diff(ce) <= 0):
        raise ParameterError(f"lbda_edges must be at least 2 finite increasing edges [Å], got "
                             f"{validation.short_repr(ce)}")
    if ce[0] < ne[0] or ce[-1] > ne[-1]:
        raise ParameterError(f"the coarse grid {ce[0]:.6g}–{ce[-1]:.6g} Å must lie within the native grid "
                             f"{ne[0]:.6g}–{ne[-1]:.6g} Å")
    idx = np.clip(np.searchsorted(ne, ce), 1, ne.size - 1)
    nearest = np.where(np.abs(ne[idx] - ce) < np.abs(ne[idx - 1] - ce), idx, idx - 1)
    width = np.diff(ne)[np.clip(nearest, 0, ne.size - 2)]
    off = np.abs(ne[nearest] - ce) / width
    if off.max() > _EDGE_TOLERANCE:
        k = int(np.argmax(off))
        raise ParameterError(f"every coarse edge must be a native edge: lbda_edges[{k}] = {ce[k]:.6g} Å is "
                             f"{off[k]:.3g} native bin from the nearest ({ne[nearest[k]]:.6g} Å)")
    centres = 0.5 * (ne[1:] + ne[:-1])
    group = np.searchsorted(ce, centres, side="right") - 1
    group[(centres < ce[0]) | (centres >= ce[-1])] = -1
    return group


def point_source_template(native_cube, native_lbda_edges, lbda_edges, *, mapper, field, ncol, variance=None,
                          oversample=(1, 1), truncate=4.0):
    """Expected LSQ cube per unit flux of each coarse bin of a point source given at native resolution.

    Parameters
    ----------
    native_cube : (nλ_native, ny, nx_native) float
        the point source's cube on the native grid (any normalisation: only its shape within each
        coarse bin matters), as the simulation projects it (cube row r ↔ the field's slice
        ``slices[ny − 1 − r]``, ``nx_native`` columns).
    native_lbda_edges : (nλ_native + 1,) [Å]
    lbda_edges : (nλ + 1,) [Å]
        the coarse grid of the data's cube; each edge a native edge (module docstring).
    mapper, field, ncol, variance, oversample, truncate :
        as the data's :func:`~slicersim.reduction.rectify.rectify` (``field`` "narrow" or "wide";
        ``oversample`` / ``truncate`` are used for the native projection too: give the simulation's).

    Returns T (nλ, nλ, ny, ncol): T[b] the rectified cube of the light of coarse bin b per unit
    of its flux; ``extract_gls(cube, psf=T)`` returns F̂_b = the source's flux in bin b.
    """
    if mapper is None:
        raise ParameterError("point_source_template needs the mapper the data were rectified with")
    validation.choice("field", field, ("narrow", "wide"), what="field (one cube per template)")
    if isinstance(ncol, (float, np.floating)):
        raise ParameterError(f"ncol (columns of the coarse cube) must be an integer ≥ 1, got {ncol!r}")
    ncol = validation.integer("ncol (columns of the coarse cube)", ncol, low=1)
    try:
        cube = np.asarray(native_cube, float)
    except (TypeError, ValueError):
        raise ParameterError("native_cube must be a numeric (nλ_native, ny, nx_native) array") from None
    if cube.ndim != 3 or min(cube.shape) < 1 or not np.all(np.isfinite(cube)):
        raise ParameterError(f"native_cube must be a finite (nλ_native, ny, nx_native) array, got shape {cube.shape}")
    group = _native_groups(cube.shape, native_lbda_edges, lbda_edges)
    ne = np.asarray(native_lbda_edges, float)
    ce = np.asarray(lbda_edges, float)
    nl = ce.size - 1
    totals = np.array([cube[group == b].sum() for b in range(nl)])
    if not np.all(totals > 0):
        b = int(np.argmin(totals))
        raise ParameterError(f"the native cube has no positive flux in coarse bin {b} "
                             f"({ce[b]:.6g}–{ce[b + 1]:.6g} Å, total {totals[b]:.3g}): no template per unit flux")
    nlbda = 0.5 * (ne[1:] + ne[:-1])
    images = np.empty((nl,) + tuple(mapper.detector_shape))
    for b in range(nl):
        cb = np.where((group == b)[:, None, None], cube / totals[b], 0.0)
        images[b] = 0.0
        try:
            mapper.project_cube(cb, nlbda, ne, field, out=images[b], oversample=oversample, truncate=truncate,
                                **float64_kwargs())
        except ValueError as err:
            raise ParameterError(f"native_cube cannot be projected on the {field} field: {err}") from None
    cp = rectify(images, variance, mapper=mapper, field=field, lbda_edges=ce, ncol=ncol, oversample=oversample,
                 truncate=truncate)
    return np.asarray(cp.flux, float)


def background_template(native_shape, native_lbda_edges, lbda_edges, *, mapper, field, ncol, variance=None,
                        oversample=(1, 1), truncate=4.0):
    """Expected LSQ cube of a background uniform at native resolution, per unit of the coarse cell
    value B_b of each coarse bin (e-/s per coarse cell per coarse bin, as the GLS's uniform B_λ).

    A uniform native sky is not exactly uniform once projected and rectified on a coarse grid
    (the coarse cells' boxes do not reproduce the native footprint at the slice ends and band
    edges), so fitting it with a uniform B_λ biases the point source's flux; this template,
    ``extract_gls(cube, psf=T, background_template=Tb)``, removes that model error.

    native_shape : (ny, nx_native) of the native cube (the field's slices × native columns);
    other arguments as :func:`point_source_template`.  Returns (nλ, nλ, ny, ncol).
    """
    ny, nxn = validation.shape("native_shape (ny, nx_native)", native_shape)
    n_native = np.asarray(native_lbda_edges, float).size - 1
    uniform = np.ones((max(n_native, 1), ny, nxn))
    T = point_source_template(uniform, native_lbda_edges, lbda_edges, mapper=mapper, field=field, ncol=ncol,
                              variance=variance, oversample=oversample, truncate=truncate)
    return T * float(ny * ncol)            # per unit flux of the bin → per unit value of a coarse cell
