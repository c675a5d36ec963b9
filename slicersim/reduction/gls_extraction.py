"""Generalised-least-squares extraction of a point source from an LSQ cube and its inverse covariance.

An LSQ cube x̂ = (PᵀWP)⁻¹PᵀW d (:func:`~slicersim.reduction.rectify.rectify`) has the covariance
C = (PᵀWP)⁻¹: neighbouring cells are strongly (anti-)correlated and the noise of single cells is
amplified by the conditioning of P, so that any extraction weighting cells by the diagonal of C
alone (:func:`~slicersim.reduction.spectra.extract_spectrum`, ``method="optimal"``) loses most of
the SNR.  Its inverse N = PᵀWP is sparse, block diagonal over slices
(:class:`~slicersim.reduction.rectify.InverseCovariance`), and the GLS fit of a linear model cube
M θ to x̂ weighted by it,

    θ̂ = (Mᵀ N M)⁻¹ Mᵀ N x̂,        Cov θ̂ = (Mᵀ N M)⁻¹,

is the minimum-variance linear unbiased estimator of θ given the cube; as N x̂ = PᵀW d it is
also the weighted fit of P M θ to the detector pixels the cube was rectified from: nothing is
lost by going through the cube.

Model (per λ bin, all cells of the field): C_λ(row, col) = F_λ P_λ(row, col) + B_λ, with P the
point source's fractions per cell (a given array, or the Gaussian fitted on the cube,
:func:`~slicersim.reduction.spectra.fit_gaussian_psf`) and B_λ a uniform background (sky,
zodiacal and thermal light; ``background=False`` leaves it out).  N couples neighbouring bins of
a slice (the spot spreads a cell's light along λ), so all 2 nλ unknowns are fitted jointly:
Mᵀ N M is accumulated row by row of the cube (slice by slice) and solved densely (Cholesky).

The returned ``variance`` is diag(Mᵀ N M)⁻¹ (exact for Gaussian pixel noise of the variance the
cube was rectified with); ``diagnostics["covariance"]`` holds the full (nλ × nλ) covariance of
F̂ (neighbouring bins are correlated), ``chi2`` / ``dof`` the fit's χ² = (x̂ − Mθ̂)ᵀ N (x̂ − Mθ̂)
per image and its degrees of freedom (cells seen − unknowns).

Forward-modelled templates: ``psf`` may also be a 4-D array T (K, nλ, ny, nx), the expected LSQ
cube per unit flux of each of K unknowns (:func:`~slicersim.reduction.templates.point_source_template`:
a native-resolution point source projected and rectified exactly as the data), so that
M[cell(λ, row, col), k] = T[k, λ, row, col] (one column spans every bin the light of unknown k
reaches) and E[x̂] = Σ_k F_k T_k + B exactly: no model error from the coarse grid.  The flux,
variance and covariance are then those of the K unknowns.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from slicersim.errors import ParameterError
from slicersim.reduction.spectrum_product import SpectrumProduct, _check, _gaussian_field, _moments, fit_gaussian_psf

__all__ = ["extract_gls", "gls_normal_equations"]


def _inverse_covariance(cube_product):
    info = getattr(cube_product, "inverse_covariance", None)
    if info is None:
        method = getattr(cube_product, "method", "?")
        raise ParameterError(f"method='gls' needs the cube's inverse covariance (rectify(method='lsq') with a "
                             f"variance); this {method} cube has none: use method='optimal' or 'aperture'")
    return info


def gls_normal_equations(cube_product, psf, background=True, background_template=None):
    """(G = Mᵀ N M (K, K), b = Mᵀ N x̂ (K, N), xᵀNx (N,), number of cells seen) of the model
    F_λ P + B_λ (K = 2 nλ unknowns, F first; nλ without ``background``) for the cube's images
    (N = 1 for a single cube).  ``psf``: (nλ, ny, nx) cell fractions, or a template
    (K_F, nλ, ny, nx): the model Σ_k F_k T_k + B_λ (K = K_F + nλ unknowns, F first).
    ``background_template`` (nλ, nλ, ny, nx): the background's expected cube per unit B_b
    (:func:`~slicersim.reduction.templates.background_template`) instead of a uniform B_λ."""
    info = _inverse_covariance(cube_product)
    flux = np.asarray(cube_product.flux, float)
    images = flux if flux.ndim == 4 else flux[None]
    nl, ny, nx = images.shape[1:]
    if info.shape != (nl, ny, nx):
        raise ParameterError(f"the inverse covariance is for cubes {info.shape}, the cube is {(nl, ny, nx)}")
    nc = nl * nx
    psf = np.asarray(psf, float)
    template = psf.ndim == 4
    if template:
        if psf.shape[1:] != (nl, ny, nx) or psf.shape[0] < 1:
            raise ParameterError(f"a template psf must have shape (K, {nl}, {ny}, {nx}), got {psf.shape}")
    elif psf.shape != (nl, ny, nx):
        raise ParameterError(f"psf must have shape {(nl, ny, nx)} or (K, {nl}, {ny}, {nx}), got {psf.shape}")
    if background_template is not None:
        background_template = np.asarray(background_template, float)
        if not background:
            raise ParameterError("background_template needs background=True")
        if background_template.shape != (nl, nl, ny, nx) or not np.all(np.isfinite(background_template)):
            raise ParameterError(f"background_template must be a finite ({nl}, {nl}, {ny}, {nx}) array, "
                                 f"got shape {background_template.shape}")
    nk = psf.shape[0] if template else nl                  # flux unknowns
    K = nk + nl if background else nk
    lam = np.repeat(np.arange(nl), nx)                     # cell λ·ncol + col → its bin
    cells = np.arange(nc)
    G = np.zeros((K, K))
    b = np.zeros((K, images.shape[0]))
    q = np.zeros(images.shape[0])
    seen_total = 0
    for row in range(ny):
        N = info.matrix(row)
        if N.nnz == 0:
            continue
        seen = N.diagonal() > 0
        seen_total += int(seen.sum())
        if template or background_template is not None:
            if template:
                T = psf[:, :, row, :].reshape(nk, nc).T                 # (cells, K) dense
            else:
                T = (lam[:, None] == np.arange(nl)[None]) * psf[:, row, :].ravel()[:, None]
            if background_template is not None:
                T = np.concatenate([T, background_template[:, :, row, :].reshape(nl, nc).T], axis=1)
            elif background:
                T = np.concatenate([T, (lam[:, None] == np.arange(nl)[None]).astype(float)], axis=1)
            M = sp.csr_matrix(T)
        elif background:
            p = psf[:, row, :].ravel()
            M = sp.csr_matrix((np.concatenate([p, np.ones(nc)]), (np.concatenate([cells, cells]),
                                                                  np.concatenate([lam, nl + lam]))), shape=(nc, K))
        else:
            M = sp.csr_matrix((psf[:, row, :].ravel(), (cells, lam)), shape=(nc, K))
        x = images[:, :, row, :].reshape(images.shape[0], nc).T
        x = np.where(seen[:, None], np.nan_to_num(x), 0.0)           # unseen cells: zero rows of N
        Nx = N @ x
        G += (M.T @ (N @ M)).toarray()
        b += M.T @ Nx
        q += np.einsum("ck,ck->k", x, Nx)
    return 0.5 * (G + G.T), b, q, seen_total


def extract_gls(cube_product, *, psf=None, position=None, background=True, nchunks=512,
                background_template=None, noise_information=None):
    """GLS spectrum of a point source in an LSQ cube with its inverse covariance (module docstring).

    psf : None / "fit" (Gaussian fitted on the cube, as ``extract_spectrum``), an (nλ, ny, nx)
        array of the point source's fractions per cell, or an (nλ, nλ, ny, nx) template: the
        expected cube per unit flux of each bin
        (:func:`~slicersim.reduction.templates.point_source_template`, module docstring)
    position : (x, y) [cells] for the PSF fit (None: fitted)
    background : fit a uniform B_λ per bin jointly with F_λ
    background_template : (nλ, nλ, ny, nx) the background's expected cube per unit B_b
        (:func:`~slicersim.reduction.templates.background_template`: a sky uniform at native
        resolution) instead of a uniform B_λ

    noise_information : B = PᵀWΣWP (:func:`~slicersim.reduction.rectify.noise_information`) when the
        cube's weights W are not the pixels' inverse variance Σ⁻¹ (e.g. weights from a model image
        that misses the point source's sharp core): the variance is then the sandwich
        (MᵀNM)⁻¹ MᵀBM (MᵀNM)⁻¹, exact for the estimator used (with Σ estimated from the data, whose
        expectation is the truth); None: (MᵀNM)⁻¹

    Returns a :class:`~slicersim.reduction.spectra.SpectrumProduct` (``method="gls"``): ``flux``
    F̂_λ (total flux), ``variance`` from (Mᵀ N M)⁻¹, ``background`` B̂_λ and its variance;
    ``cell_weights`` None (F̂_λ uses the cells of neighbouring bins too); ``aperture`` NaN (every
    cell of the field is used); ``enclosed_energy``
    Σ_field P (a template: Σ over the cube of T_k); ``diagnostics``: ``covariance`` (nλ, nλ) of F̂,
    ``chi2`` (per image), ``dof``.
    """
    _inverse_covariance(cube_product)
    template = None
    if psf is not None and not isinstance(psf, str) and np.ndim(psf) == 4:
        template, psf = _check_template(cube_product, psf), None
    flux, var, psf, position = _check(cube_product, "optimal", psf, 3.0, 6.0, position, background, nchunks)
    shape = flux.shape[-3:]
    stack = flux.ndim == 4
    diag, sigma = {}, None
    if template is not None:
        P = template
        position = _moments(np.clip(P.sum(axis=0), 0, None))[0] if position is None else position
    elif psf is None or isinstance(psf, str):
        mean = np.nanmean(flux, axis=0) if stack else flux
        position, sx, sy, diag = fit_gaussian_psf(mean, var, cube_product.lbda, position, nchunks)
        P = _gaussian_field(shape[1:], sx, sy, position)
        sigma = np.stack([sx, sy], axis=1)
    else:
        P = psf
        position = _moments(P)[0] if position is None else position
    G, b, q, seen = gls_normal_equations(cube_product, P, background, background_template)
    nl = shape[0]                                           # F unknowns (= K of a template, checked)
    try:
        fac = cho_factor(G, lower=True, check_finite=True)
        cov = cho_solve(fac, np.eye(G.shape[0]))
    except (LinAlgError, ValueError):
        raise ParameterError("GLS extraction: Mᵀ N M is singular — a λ bin has no PSF light on the cells seen "
                             "(or no cell at all)") from None
    theta = cov @ b                                         # (K, N)
    chi2 = q - np.einsum("kn,kn->n", theta, b)              # (x̂ − Mθ̂)ᵀN(x̂ − Mθ̂) = x̂ᵀNx̂ − θ̂ᵀb
    variance_model = "GLS: (Mᵀ N M)⁻¹ with the full inverse covariance N = PᵀWP of the LSQ cube"
    if noise_information is not None:
        _check_noise_information(noise_information, cube_product.inverse_covariance)
        from types import SimpleNamespace
        H, *_ = gls_normal_equations(SimpleNamespace(flux=cube_product.flux, inverse_covariance=noise_information),
                                     P, background, background_template)
        cov = cov @ H @ cov
        variance_model = "GLS sandwich: (MᵀNM)⁻¹ MᵀBM (MᵀNM)⁻¹, B = PᵀWΣWP with the pixels' variance Σ"
    cov = 0.5 * (cov + cov.T)
    f = theta[:nl].T
    bg = theta[nl:].T if background else None
    diag.update(covariance=cov[:nl, :nl], chi2=chi2, dof=int(seen - G.shape[0]), cells_seen=int(seen),
                variance_model=variance_model)
    return SpectrumProduct(
        lbda=np.asarray(cube_product.lbda), lbda_edges=np.asarray(cube_product.lbda_edges),
        flux=f if stack else f[0], variance=np.diag(cov)[:nl].copy(), method="gls",
        unit=getattr(cube_product, "unit", "e-/s"), position=tuple(float(v) for v in position), aperture=float("nan"),
        psf_sigma=sigma, background=None if bg is None else (bg if stack else bg[0]),
        background_variance=np.diag(cov)[nl:].copy() if background else None,
        enclosed_energy=P.reshape(nl, -1).sum(axis=1), cell_weights=None, diagnostics=diag)


def _check_noise_information(noise, info):
    """``noise`` must be B = PᵀWΣWP built for this cube's N = PᵀWP (same field, grid, pixels and weights W):
    one of another field or λ grid of the same shape would give a wrong variance silently."""
    from slicersim.reduction.rectify import InverseCovariance
    if not isinstance(noise, InverseCovariance) or noise.weights_of is None:
        raise ParameterError("noise_information must be rectify.noise_information(cube.inverse_covariance, variance), "
                             f"got {type(noise).__name__}")
    if noise.weights_of is not info:
        shape = "" if noise.shape == info.shape else f" (cube {noise.shape}, this one {info.shape})"
        raise ParameterError("noise_information is not for this cube: build it from this cube's inverse covariance, "
                             f"noise_information(cube.inverse_covariance, variance){shape}")


def _check_template(cube_product, psf):
    """A (K = nλ, nλ, ny, nx) finite template for the cube."""
    flux = getattr(cube_product, "flux", None)
    if flux is None:
        raise ParameterError("cube_product must be a CubeProduct (from slicersim.reduction.rectify)")
    shape = np.shape(flux)[-3:]
    try:
        t = np.asarray(psf, float)
    except (TypeError, ValueError):
        raise ParameterError("a template psf must be a numeric (K, nλ, ny, nx) array") from None
    if t.shape != (shape[0],) + tuple(shape) or not np.all(np.isfinite(t)):
        want = (shape[0],) + tuple(shape)
        raise ParameterError(f"a template psf must be finite, of shape (nλ, nλ, ny, nx) = {want} (one unknown "
                             f"flux per bin of the cube), got {t.shape}")
    return t
