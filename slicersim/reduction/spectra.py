"""Rectified cubes → point-source spectra with variance (optimal or aperture extraction).

Input: a :class:`~slicersim.reduction.rectify.CubeProduct` C (nλ, ny, nx) [e.g. e-/s per cell per
bin], rows = slices, columns = cells along the slice, with variance V.  Cell coordinates
(x, y) are centred on the field (:func:`slicersim.physics.psf.cell_edges`), in the cube's own
cells (a column may be longer than a slice is wide: σ_x and σ_y are separate).

PSF P (fractions of the point source's light per cell, per bin; Σ over the field ≤ 1):

* ``psf=array`` (nλ, ny, nx): given (e.g. the simulation's own, :func:`psf_from_cube`);
* ``psf="fit"`` (or None): a Gaussian integrated over the cells (erf fractions, the
  simulation's PSF model) — centre and (σ_x, σ_y) fitted on the white-light image (Σ_λ C,
  with a constant background), then (σ_x, σ_y) refitted in every bin (up to 512 chunks) with
  the centre fixed and smoothed by a quadratic in λ (weights ∝ the bin's SNR).

Background B(λ) (uniform over the field: sky, zodiacal and thermal light): inverse-variance
mean over the *outer* cells (elliptical radius ≥ ``background_radius`` σ of the white-light
PSF), B̂ = Σ_o C/V / Σ_o 1/V, Var B̂ = 1/Σ_o 1/V.  The point-source light in the outer cells
(p̄ = Σ_o P/V / Σ_o 1/V) is corrected exactly, so that for C = F P + B both estimators are
unbiased:

* optimal (Horne 1986, :func:`slicersim.products.extraction.extract_optimal`, aperture cells
  within ``aperture`` σ): S₀ = Σ a (C − B̂), a = (P/V)/Σ P²/V; F̂ = S₀ / (1 − p̄ Σa),
  Var F̂ = (1/Σ P²/V + (Σa)² Var B̂) / (1 − p̄ Σa)².  F̂ estimates the *total* flux F.
* aperture (:func:`slicersim.products.extraction.extract_aperture`): S₀ = Σ_ap (C − B̂);
  F̂_ap = S₀ · EE / (EE − N p̄) estimates F·EE, the light in the aperture (EE = Σ_ap P, as the
  ETC's aperture spectrum: no aperture correction; ``enclosed_energy`` is returned).

Cells with non-finite flux or variance get zero weight (bin by bin).  Both weight cells with the
diagonal of the cube covariance only: on an LSQ cube, whose cells are strongly correlated, use
``method="gls"`` (:mod:`slicersim.reduction.gls_extraction`: the full inverse covariance, minimum
variance) or at least :func:`propagate_variance` for the exact variance of these estimators.
"""
from __future__ import annotations

import numpy as np

from slicersim.errors import ParameterError
from slicersim.physics.psf import cell_centres
from slicersim.products.extraction import extract_aperture, extract_optimal
from slicersim.reduction.gls_extraction import extract_gls
from slicersim.reduction.spectrum_product import (_MAX_CHUNKS, METHODS, SpectrumProduct,  # noqa: F401 (re-exported)
                                                  _check, _gaussian_field, _moments, fit_gaussian_psf,
                                                  psf_from_cube)

__all__ = ["extract_spectrum", "SpectrumProduct", "fit_gaussian_psf", "psf_from_cube", "propagate_variance",
           "METHODS"]



def extract_spectrum(cube_product, *, method="optimal", psf=None, position=None, aperture=3.0,
                     background=True, background_radius=6.0, nchunks=_MAX_CHUNKS, background_template=None,
                     noise_information=None):
    """Spectrum of a point source in a rectified cube (see the module docstring).

    method : "optimal" (PSF-weighted: total flux), "aperture" (sum: light in the aperture) — cells
        weighted with the diagonal of the cube covariance — or "gls" (total flux: the
        generalised-least-squares fit F_λ P + B_λ over every cell with the cube's full inverse
        covariance, :func:`slicersim.reduction.gls_extraction.extract_gls`: minimum variance,
        exact variance; LSQ cubes rectified with a variance; ``aperture`` and
        ``background_radius`` unused)
    psf : None / "fit" (Gaussian fitted on the cube) or an (nλ, ny, nx) array of PSF fractions
    position : (x, y) [cells from the field centre]; None: fitted (or the given PSF's centroid)
    aperture : radius of the elliptical aperture [white-light PSF σ along each axis]
    background : estimate B(λ) from the cells beyond ``background_radius`` σ and subtract it
        (with its variance and the exact correction for the PSF light there)
    noise_information : "gls" only: the sandwich variance for weights that are not the pixels'
        inverse variance (:func:`~slicersim.reduction.gls_extraction.extract_gls`)

    Returns a :class:`SpectrumProduct` in the cube's unit per bin.
    """
    if method == "gls":
        return extract_gls(cube_product, psf=psf, position=position, background=background, nchunks=nchunks,
                           background_template=background_template, noise_information=noise_information)
    if noise_information is not None:
        raise ParameterError("noise_information is for method='gls' only")
    if background_template is not None:
        raise ParameterError("background_template is for method='gls' only")
    flux, var, psf, position = _check(cube_product, method, psf, aperture, background_radius, position, background,
                                      nchunks)
    shape = flux.shape[-3:]
    stack = flux.ndim == 4
    images = flux if stack else flux[None]
    P, position, white_sigma, sigma, diag = _psf_model(images, var, psf, position, cube_product.lbda, nchunks)
    iy, ix, outer = _cells(shape, position, white_sigma, aperture, background_radius, background)
    v0 = np.ones(shape) if var is None else var
    out_f, out_b, out_bv, cell_weights = [], [], [], None
    for img in images:
        f, fv, b, bvar, u = _extract_image(img, v0, P, (iy, ix), outer if background else None, method)
        if cell_weights is None:
            cell_weights = np.nan_to_num(u)
        out_f.append(f)
        out_b.append(b)
        out_bv.append(bvar)
        variance = fv
    ee = P[:, iy, ix].sum(axis=1)
    diag.update(aperture_cells=int(iy.size), background_cells=int(outer.sum()) if background else 0,
                variance_model="cells independent (diagonal of the cube covariance)")
    return SpectrumProduct(
        lbda=np.asarray(cube_product.lbda), lbda_edges=np.asarray(cube_product.lbda_edges),
        flux=np.array(out_f) if stack else out_f[0], variance=None if var is None else variance,
        method=method, unit=getattr(cube_product, "unit", "e-/s"), position=tuple(position),
        aperture=float(aperture), psf_sigma=sigma,
        background=(np.array(out_b) if stack else out_b[0]) if background else None,
        background_variance=(out_bv[0] if var is not None else None) if background else None,
        enclosed_energy=ee, cell_weights=cell_weights, diagnostics=diag)


def _psf_model(images, var, psf, position, lbda, nchunks):
    """(P (nλ, ny, nx), position, white-light σ (x, y) [cells], σ per bin or None, diagnostics): the
    given PSF (position: its centroid unless given) or a Gaussian fitted on the (mean) cube."""
    if psf is None or isinstance(psf, str):
        mean = np.nanmean(images, axis=0) if images.shape[0] > 1 else images[0]
        position, sx, sy, diag = fit_gaussian_psf(mean, var, lbda, position, nchunks)
        P = _gaussian_field(images.shape[-2:], sx, sy, position)
        return P, position, diag["white_sigma"], np.stack([sx, sy], axis=1), diag
    centroid, white_sigma = _moments(psf)
    return psf, centroid if position is None else position, white_sigma, None, {}


def _cells(shape, position, white_sigma, aperture, background_radius, background):
    """(iy, ix) of the aperture cells (within ``aperture`` white-light σ) and the outer (background)
    cells mask (beyond ``background_radius`` σ; at least 4 when ``background``)."""
    yc, xc = cell_centres(shape[1:])
    r = np.hypot((xc - position[0]) / white_sigma[0], (yc - position[1]) / white_sigma[1])
    iy, ix = np.nonzero(r <= aperture)
    if iy.size == 0:
        raise ParameterError(f"aperture: the aperture ({aperture} σ around {position}) contains no cell centre")
    outer = r >= background_radius
    if background and outer.sum() < 4:
        raise ParameterError(f"fewer than 4 cells lie beyond background_radius={background_radius} σ: lower it "
                             "or use background=False")
    return iy, ix, outer


def _extract_image(img, v0, P, cells, outer, method):
    """One cube image: (F̂, Var F̂, B̂, Var B̂ per bin, the weights u with F̂_λ = Σ_c u_λc C_c) of the
    optimal or aperture estimator, the background (``outer`` cells; None: no background) subtracted
    with the exact correction for the PSF light there (module docstring)."""
    iy, ix = cells
    nl = P.shape[0]
    good = np.isfinite(img) & np.isfinite(v0) & (v0 > 0)
    c = np.where(good, img, 0.0)
    v = np.where(good, v0, np.inf)
    if outer is not None:
        wo = np.where(outer[None] & good, 1.0 / np.where(good, v, 1.0), 0.0)
        norm = wo.sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            b = (wo * c).sum(axis=(1, 2)) / norm
            bvar = 1.0 / norm
            pbar = (wo * P).sum(axis=(1, 2)) / norm
    else:
        b, bvar, pbar = np.zeros(nl), np.zeros(nl), np.zeros(nl)
    sub = c - b[:, None, None]
    u = np.zeros(P.shape)                            # F̂_λ = Σ_c u_λc C_c (cells of bin λ)
    with np.errstate(invalid="ignore", divide="ignore"):
        if method == "optimal":
            weights = P[:, iy, ix]
            s0, var0 = extract_optimal(sub, v, weights, (iy, ix))
            a = weights / v[:, iy, ix] * var0[:, None]                     # optimal weights a_c
            n_used = a.sum(axis=1)
            k = 1.0 - pbar * n_used
            u[:, iy, ix] = a / k[:, None]
        else:
            gsel = good[:, iy, ix]
            s0, var0 = extract_aperture(np.where(good, sub, 0.0), np.where(good, v, 0.0), (iy, ix))
            n_used = gsel.sum(axis=1)
            k = ((P[:, iy, ix] * gsel).sum(axis=1) - n_used * pbar) / P[:, iy, ix].sum(axis=1)
            u[:, iy, ix] = gsel / k[:, None]
        f = s0 / k
        fv = (var0 + n_used ** 2 * bvar) / k ** 2
        if outer is not None:
            u -= (n_used / k / norm)[:, None, None] * wo
    return f, fv, b, bvar, u


# --------------------------------------------------------------------------- exact variance
def propagate_variance(spectrum, cube_product, rate_variance=None, *, mapper=None, oversample=(1, 1),
                       truncate=4.0, weights_dtype=np.float32, backend="auto", noise_information=None):
    """Variance [unit²] of an extracted spectrum with the full covariance of an LSQ cube.

    The ``variance`` of :func:`extract_spectrum` ("optimal", "aperture") treats cells as
    independent (the cube carries only diag((PᵀWP)⁻¹)); neighbouring LSQ cells are
    anti-correlated, so that sum is too large.  Here Var F̂_λ = Σ_slices u_λᵀ N_s⁻¹ u_λ exactly,
    N_s = P_sᵀ W P_s the cube's inverse covariance per slice (``cube_product.inverse_covariance``,
    :class:`~slicersim.reduction.rectify.InverseCovariance`), for every slice the extraction
    weights ``u`` reach with more than 1e-3 of their largest weight (the background's tiny
    weights on the other slices keep their diagonal term).  A "gls" spectrum's variance is
    already exact: returned as is.

    ``rate_variance`` (H, W) [unit²/px]: optional; given, N is rebuilt from it
    (:func:`~slicersim.reduction.rectify.inverse_covariance`, with ``mapper`` and the projection
    options, which must be those given to ``rectify``) — for a cube without its own.

    ``noise_information``: B = PᵀWΣWP (:func:`~slicersim.reduction.rectify.noise_information` of the
    cube's own inverse covariance) when the cube's weights W are not the pixels' inverse variance
    (model weights): the cube's covariance is then N⁻¹BN⁻¹ and Var F̂_λ = Σ_slices zᵀ B_s z,
    z = N_s⁻¹ u_λ (the sandwich; N⁻¹ alone under-reports as for ``method="gls"``).
    """
    from scipy.sparse.linalg import splu

    from slicersim.reduction.rectify import inverse_covariance
    if getattr(cube_product, "method", None) != "lsq":
        raise ParameterError("propagate_variance needs an LSQ cube (rectify(method='lsq'))")
    if getattr(spectrum, "method", None) == "gls":
        return np.array(spectrum.variance, float)
    u = getattr(spectrum, "cell_weights", None)
    if u is None or u.shape != np.shape(cube_product.flux)[-3:]:
        raise ParameterError("spectrum must come from extract_spectrum on this cube")
    nl, nrow, ncol = u.shape
    if noise_information is not None:
        from slicersim.reduction.gls_extraction import _check_noise_information
        if rate_variance is not None:
            raise ParameterError("noise_information goes with the cube's own inverse covariance, "
                                 "not with rate_variance")
        _check_noise_information(noise_information, getattr(cube_product, "inverse_covariance", None))
    if rate_variance is not None:
        info = inverse_covariance(rate_variance, mapper=mapper, field=cube_product.field,
                                  lbda_edges=cube_product.lbda_edges, ncol=ncol, oversample=oversample,
                                  truncate=truncate, weights_dtype=weights_dtype, backend=backend)
    else:
        info = getattr(cube_product, "inverse_covariance", None)
        if info is None:
            raise ParameterError("the cube carries no inverse covariance: give rate_variance (rectify's variance)")
    cvar = np.nan_to_num(np.asarray(cube_product.variance, float)) if cube_product.variance is not None else None
    total = np.zeros(nl)
    reach = np.abs(u).max(axis=(0, 2))
    for row in range(nrow):
        us = u[:, row, :]                                    # (nλ, ncol)
        if reach[row] <= 1e-3 * reach.max() and cvar is not None:
            total += (us ** 2 * cvar[:, row, :]).sum(axis=1)
            continue
        A = info.matrix(row)
        idx = np.flatnonzero(A.diagonal() > 0)
        rhs = np.zeros((nl * ncol, nl))
        rhs[np.arange(nl * ncol), np.repeat(np.arange(nl), ncol)] = us.ravel()    # λ-major cells
        rhs = rhs[idx]
        z = splu(A[idx][:, idx].tocsc()).solve(rhs)
        if noise_information is not None:                    # sandwich: zᵀ B z
            Bs = noise_information.matrix(row)[idx][:, idx]
            total += (z * (Bs @ z)).sum(axis=0)
        else:
            total += (rhs * z).sum(axis=0)
    return total
