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

from dataclasses import dataclass, field

import numpy as np

from slicersim.errors import ParameterError
from slicersim.physics.psf import cell_centres, gaussian_psf_cells
from slicersim.products.extraction import EXTRACTION_METHODS, extract_aperture, extract_optimal

__all__ = ["extract_spectrum", "SpectrumProduct", "fit_gaussian_psf", "psf_from_cube", "propagate_variance",
           "METHODS"]

#: extraction methods: the cube's cells weighted by the diagonal of its covariance ("optimal",
#: "aperture") or the GLS fit with its full inverse covariance ("gls", LSQ cubes)
METHODS = (*EXTRACTION_METHODS, "gls")
_MAX_CHUNKS = 512
_MIN_SIGMA = 0.25


@dataclass
class SpectrumProduct:
    """Extracted spectrum: ``flux`` (nλ,) or (N, nλ) for a stack [cube unit per bin, e.g. e-/s],
    ``variance`` (nλ,) [unit²] (None without a cube variance); ``lbda`` centres, ``lbda_edges``
    [Å]; ``position`` (x, y) [cells]; ``psf_sigma`` (nλ, 2) (σ_x, σ_y) [cells] of the Gaussian
    model (None for a given PSF); ``background`` (nλ,) or (N, nλ) [unit per cell] and
    ``background_variance``; ``enclosed_energy`` (nλ,) Σ_aperture P; ``cell_weights`` (nλ, ny, nx):
    the linear estimator, F̂_λ = Σ u_λc C_λc (for :func:`propagate_variance`); ``diagnostics``."""

    lbda: np.ndarray
    lbda_edges: np.ndarray
    flux: np.ndarray
    variance: np.ndarray | None
    method: str
    unit: str
    position: tuple
    aperture: float
    psf_sigma: np.ndarray | None = None
    background: np.ndarray | None = None
    background_variance: np.ndarray | None = None
    enclosed_energy: np.ndarray | None = None
    cell_weights: np.ndarray | None = None
    diagnostics: dict = field(default_factory=dict)

    @property
    def snr(self):
        """flux / √variance per bin."""
        return None if self.variance is None else self.flux / np.sqrt(self.variance)

    def arrays(self):
        """Name → array for writing (None entries left out)."""
        out = {"LBDA": self.lbda, "LBDA_EDGES": self.lbda_edges, "FLUX": self.flux, "VAR": self.variance,
               "PSF_SIGMA": self.psf_sigma, "BACKGROUND": self.background,
               "BACKGROUND_VAR": self.background_variance, "ENCLOSED_ENERGY": self.enclosed_energy}
        return {k: np.asarray(v) for k, v in out.items() if v is not None}


# --------------------------------------------------------------------------- PSF
def _gaussian_field(shape, sig_x, sig_y, position):
    """(nλ, ny, nx) erf cell fractions of a Gaussian of σ (nλ,) [cells] at ``position``."""
    ny, nx = shape
    iy, ix = np.indices(shape).reshape(2, -1)
    p = gaussian_psf_cells(np.atleast_1d(sig_y), np.atleast_1d(sig_x), shape, position, (iy, ix))
    return p.reshape(-1, ny, nx)


def _fit_image(image, weight, shape, start, fix_position=None):
    """Least-squares fit of A·G(x0, y0, σx, σy) + B to a 2-D image: (x0, y0, σx, σy, A, B)."""
    from scipy.optimize import least_squares
    good = weight > 0
    sw = np.sqrt(weight[good])

    def model(par):
        if fix_position is None:
            x0, y0, sx, sy = par[:4]
        else:
            (x0, y0), (sx, sy) = fix_position, par[:2]
        g = _gaussian_field(shape, sx, sy, (x0, y0))[0]
        design = np.stack([g[good], np.ones(good.sum())], axis=1) * sw[:, None]
        coef, *_ = np.linalg.lstsq(design, image[good] * sw, rcond=None)    # A, B linear
        return design @ coef - image[good] * sw, coef

    x0 = np.asarray(start if fix_position is None else start[2:4], float)
    lo = np.full(x0.size, -np.inf)
    lo[-2:] = _MIN_SIGMA                                    # σ ≥ 0.25 cell: no collapse onto one cell
    x0[-2:] = np.maximum(x0[-2:], 2 * _MIN_SIGMA)
    res = least_squares(lambda p: model(p)[0], x0, x_scale="jac", method="trf", bounds=(lo, np.inf),
                        max_nfev=400)
    coef = model(res.x)[1]
    if fix_position is None:
        x, y, sx, sy = res.x
    else:
        (x, y), (sx, sy) = fix_position, res.x
    return np.array([x, y, sx, sy, coef[0], coef[1]]), bool(res.success)


def fit_gaussian_psf(flux, variance=None, lbda=None, position=None, nchunks=_MAX_CHUNKS, degree=2):
    """Gaussian PSF of a point source in a cube (nλ, ny, nx): centre (x, y) [cells] and σ_x(λ),
    σ_y(λ) [cells]: white-light fit, then a fit in each of ``nchunks`` λ chunks (default every
    bin) with the centre fixed, smoothed by a polynomial of ``degree`` in λ weighted by the
    chunk's SNR.  Returns (position, sig_x (nλ,), sig_y (nλ,), diagnostics)."""
    nl, ny, nx = flux.shape
    good = np.isfinite(flux) & (np.isfinite(variance) & (variance > 0) if variance is not None else True)
    data = np.where(good, flux, 0.0)
    white = data.sum(axis=0)
    if variance is not None:
        wvar = np.where(good, variance, 0.0).sum(axis=0)
        weight = np.where(wvar > 0, 1.0 / np.where(wvar > 0, wvar, 1.0), 0.0)
    else:
        weight = np.ones((ny, nx))
    weight = np.where(good.any(axis=0), weight, 0.0)
    if not (weight > 0).sum() > 6:
        raise ParameterError("PSF fit: fewer than 7 usable cells in the white-light image")
    bg = np.median(white[weight > 0])
    peak = np.unravel_index(np.argmax(np.where(weight > 0, white - bg, -np.inf)), white.shape)
    yc, xc = cell_centres((ny, nx))
    start = [xc[peak], yc[peak], 1.0, 1.0] if position is None else [*position, 1.0, 1.0]
    par, ok = _fit_image(white, weight, (ny, nx), start, fix_position=None if position is None else position)
    if not par[4] > 0:
        raise ParameterError("PSF fit: no point source found in the white-light image (fitted amplitude ≤ 0)")
    pos = (float(par[0]), float(par[1]))
    lbda = np.arange(nl, dtype=float) if lbda is None else np.asarray(lbda, float)
    n = int(max(1, min(nchunks, nl)))
    bounds = np.linspace(0, nl, n + 1).astype(int)
    mids, sx, sy, amp = [], [], [], []
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        img = data[i0:i1].sum(axis=0)
        if variance is not None:
            v = np.where(good[i0:i1], variance[i0:i1], 0.0).sum(axis=0)
            w = np.where((v > 0) & good[i0:i1].any(axis=0), 1.0 / np.where(v > 0, v, 1.0), 0.0)
        else:
            w = good[i0:i1].any(axis=0).astype(float)
        if (w > 0).sum() < 7:
            continue
        p, ok_c = _fit_image(img, w, (ny, nx), [*pos, par[2], par[3]], fix_position=pos)
        if ok_c and p[4] > 0:
            mids.append(lbda[i0:i1].mean())
            sx.append(p[2])
            sy.append(p[3])
            amp.append(p[4] * np.sqrt(w.max()))
    mids, sx, sy, amp = (np.asarray(a) for a in (mids, sx, sy, amp))
    deg = int(min(degree, mids.size - 1))
    if deg >= 0:                                    # smooth σ(λ): weighted polynomial (weights ∝ SNR)
        t = (lbda - lbda.mean()) / max(np.ptp(lbda), 1e-300)
        tm = (mids - lbda.mean()) / max(np.ptp(lbda), 1e-300)
        sig_x = np.polyval(np.polyfit(tm, sx, deg, w=amp), t)
        sig_y = np.polyval(np.polyfit(tm, sy, deg, w=amp), t)
    else:
        sig_x, sig_y = np.full(nl, par[2]), np.full(nl, par[3])
    sig_x, sig_y = np.clip(sig_x, 0.05, None), np.clip(sig_y, 0.05, None)
    diag = {"white_sigma": (float(par[2]), float(par[3])), "white_amplitude": float(par[4]),
            "white_background": float(par[5]), "white_fit_converged": ok, "chunks_fitted": len(mids)}
    return pos, sig_x, sig_y, diag


def psf_from_cube(point_source_cube):
    """PSF fractions (nλ, ny, nx) from a noiseless point-source cube (e.g. the simulation's own
    point-source light on the rectified grid): each bin divided by its total."""
    c = np.asarray(point_source_cube, float)
    if c.ndim != 3:
        raise ParameterError(f"point_source_cube must be (nλ, ny, nx), got shape {c.shape}")
    tot = c.sum(axis=(1, 2), keepdims=True)
    if not np.all(tot > 0):
        raise ParameterError("point_source_cube has a bin with no light: its PSF is undefined")
    return c / tot


# --------------------------------------------------------------------------- extraction
def _check(cube_product, method, psf, aperture, background_radius, position):
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    flux = getattr(cube_product, "flux", None)
    if flux is None:
        raise ParameterError("cube_product must be a CubeProduct (from slicersim.reduction.rectify)")
    flux = np.asarray(flux, float)
    if flux.ndim not in (3, 4):
        raise ParameterError(f"cube flux must be (nλ, ny, nx) or (N, nλ, ny, nx), got shape {flux.shape}")
    shape = flux.shape[-3:]
    var = cube_product.variance
    if var is not None:
        var = np.asarray(var, float)
        if var.shape != shape:
            raise ParameterError(f"cube variance must have shape {shape}, got {var.shape}")
    for name, val in (("aperture", aperture), ("background_radius", background_radius)):
        if not (isinstance(val, (int, float, np.number)) and np.isfinite(val) and val > 0):
            raise ParameterError(f"{name} must be a positive number of PSF σ, got {val!r}")
    if background_radius <= aperture:
        raise ParameterError(f"background_radius ({background_radius}) must exceed aperture ({aperture})")
    if isinstance(psf, str) and psf != "fit":
        raise ParameterError(f"psf must be None, 'fit' or an (nλ, ny, nx) array, got {psf!r}")
    if psf is not None and not isinstance(psf, str):
        psf = np.asarray(psf, float)
        if psf.shape != shape or not np.all(np.isfinite(psf)) or (psf < 0).any():
            raise ParameterError(f"psf array must be finite, ≥ 0, of shape {shape}, got {psf.shape}")
    if position is not None:
        try:
            position = tuple(float(v) for v in position)
        except (TypeError, ValueError):
            position = ()
        if len(position) != 2 or not np.all(np.isfinite(position)):
            raise ParameterError("position must be (x, y) [cells from the field centre]")
    return flux, var, psf, position


def _moments(p):
    """Centre (x, y) and σ (x, y) [cells] of the white-light PSF fractions (nλ, ny, nx)."""
    w = p.sum(axis=0)
    yc, xc = cell_centres(w.shape)
    t = w.sum()
    x0, y0 = (w * xc).sum() / t, (w * yc).sum() / t
    sx = np.sqrt(max((w * (xc - x0) ** 2).sum() / t, 1e-6))
    sy = np.sqrt(max((w * (yc - y0) ** 2).sum() / t, 1e-6))
    return (float(x0), float(y0)), (float(sx), float(sy))


def extract_spectrum(cube_product, *, method="optimal", psf=None, position=None, aperture=3.0,
                     background=True, background_radius=6.0, nchunks=_MAX_CHUNKS):
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

    Returns a :class:`SpectrumProduct` in the cube's unit per bin.
    """
    if method == "gls":
        from slicersim.reduction.gls_extraction import extract_gls
        return extract_gls(cube_product, psf=psf, position=position, background=background, nchunks=nchunks)
    flux, var, psf, position = _check(cube_product, method, psf, aperture, background_radius, position)
    shape = flux.shape[-3:]
    stack = flux.ndim == 4
    images = flux if stack else flux[None]
    diag, sigma = {}, None
    if psf is None or isinstance(psf, str):
        mean = np.nanmean(images, axis=0) if stack else images[0]
        position, sx, sy, diag = fit_gaussian_psf(mean, var, cube_product.lbda, position, nchunks)
        P = _gaussian_field(shape[1:], sx, sy, position)
        sigma = np.stack([sx, sy], axis=1)
        white_sigma = diag["white_sigma"]
    else:
        P = psf
        centroid, white_sigma = _moments(P)
        position = centroid if position is None else position
    # cells: aperture and outer (background) ellipses in white-light σ
    yc, xc = cell_centres(shape[1:])
    r = np.hypot((xc - position[0]) / white_sigma[0], (yc - position[1]) / white_sigma[1])
    iy, ix = np.nonzero(r <= aperture)
    if iy.size == 0:
        raise ParameterError(f"the aperture ({aperture} σ around {position}) contains no cell centre")
    outer = r >= background_radius
    if background and outer.sum() < 4:
        raise ParameterError(f"fewer than 4 cells lie beyond background_radius={background_radius} σ: lower it "
                             "or use background=False")
    v0 = np.ones(shape) if var is None else var
    nl = shape[0]
    out_f, out_b, out_bv = [], [], []
    for img in images:
        good = np.isfinite(img) & np.isfinite(v0) & (v0 > 0)
        c = np.where(good, img, 0.0)
        v = np.where(good, v0, np.inf)
        if background:
            wo = np.where(outer[None] & good, 1.0 / np.where(good, v, 1.0), 0.0)
            norm = wo.sum(axis=(1, 2))
            with np.errstate(invalid="ignore", divide="ignore"):
                b = (wo * c).sum(axis=(1, 2)) / norm
                bvar = 1.0 / norm
                pbar = (wo * P).sum(axis=(1, 2)) / norm
        else:
            b, bvar, pbar = np.zeros(nl), np.zeros(nl), np.zeros(nl)
        sub = c - b[:, None, None]
        u = np.zeros(shape)                          # F̂_λ = Σ_c u_λc C_c (cells of bin λ)
        if method == "optimal":
            weights = P[:, iy, ix]
            s0, var0 = extract_optimal(sub, v, weights, (iy, ix))
            with np.errstate(invalid="ignore", divide="ignore"):
                a = weights / v[:, iy, ix] * var0[:, None]                 # optimal weights a_c
                suma = a.sum(axis=1)
                k = 1.0 - pbar * suma
                f = s0 / k
                fv = (var0 + suma ** 2 * bvar) / k ** 2
                u[:, iy, ix] = a / k[:, None]
                if background:
                    u -= (suma / k / norm)[:, None, None] * wo
        else:
            gsel = good[:, iy, ix]
            s0, var0 = extract_aperture(np.where(good, sub, 0.0), np.where(good, v, 0.0), (iy, ix))
            ee_full = P[:, iy, ix].sum(axis=1)
            ee_used = (P[:, iy, ix] * gsel).sum(axis=1)
            nused = gsel.sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                k = (ee_used - nused * pbar) / ee_full
                f = s0 / k
                fv = (var0 + nused ** 2 * bvar) / k ** 2
                u[:, iy, ix] = gsel / k[:, None]
                if background:
                    u -= (nused / k / norm)[:, None, None] * wo
        if not out_f:
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


# --------------------------------------------------------------------------- exact variance
def propagate_variance(spectrum, cube_product, rate_variance=None, *, mapper=None, oversample=(1, 1),
                       truncate=4.0, weights_dtype=np.float32, backend="auto"):
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
        total += (rhs * z).sum(axis=0)
    return total
