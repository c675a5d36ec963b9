"""The extracted-spectrum product, the checks of extraction inputs and the cube PSF model
shared by the cell-weighted extractions (:mod:`slicersim.reduction.spectra`) and the GLS one
(:mod:`slicersim.reduction.gls_extraction`).

PSF P (fractions of the point source's light per cell, per bin; Σ over the field ≤ 1): given
(e.g. :func:`psf_from_cube`) or a Gaussian integrated over the cells, fitted on the cube
(:func:`fit_gaussian_psf`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.physics.psf import cell_centres, gaussian_psf_cells
from slicersim.products.extraction import EXTRACTION_METHODS

__all__ = ["SpectrumProduct", "fit_gaussian_psf", "psf_from_cube", "METHODS"]

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
    # start at the peak of the matched-filtered image (smoothed by a PSF-sized Gaussian, σ = 1 cell),
    # not of single cells: a faint source on a fine grid (e.g. a z = 0.8 SN Ia at 116 columns per slice)
    # loses to a noise cell, from which the fit ends at a negative amplitude
    excess = np.where(weight > 0, (white - bg) * weight, 0.0)
    norm = np.sqrt(gaussian_filter(weight, 1.0, mode="constant"))                # > 0 at every used cell
    score = gaussian_filter(excess, 1.0, mode="constant") / np.where(weight > 0, norm, 1.0)
    peak = np.unravel_index(np.argmax(np.where(weight > 0, score, -np.inf)), white.shape)
    yc, xc = cell_centres((ny, nx))
    start = [xc[peak], yc[peak], 1.0, 1.0] if position is None else [*position, 1.0, 1.0]
    par, ok = _fit_image(white, weight, (ny, nx), start, fix_position=None if position is None else position)
    # a noise-led fit can end on a broad blob outside the field (a z = 0.8 SN Ia at 116 columns: centre
    # 10 rows beyond the edge, σ_y = 14 cells, then σ_y(λ) = 7e4 cells and a singular GLS): no source
    # was found, and a PSF from such a fit would give a wrong spectrum without a word
    sigma_max = max(1.0, 0.25 * max(ny, nx))
    inside = xc.min() - 0.5 <= par[0] <= xc.max() + 0.5 and yc.min() - 0.5 <= par[1] <= yc.max() + 0.5
    if (position is None and not inside) or max(par[2], par[3]) > sigma_max:
        raise ParameterError(f"PSF fit: no point source found in the white-light image (the fit ended at "
                             f"x, y = {par[0]:.1f}, {par[1]:.1f} cells with σ = {par[2]:.1f}, {par[3]:.1f} cells, "
                             f"{'outside the field' if not inside else 'wider than a quarter of it'}); give "
                             "position= or psf=")
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
        if ok_c and p[4] > 0 and max(p[2], p[3]) <= sigma_max:
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
    sig_x, sig_y = np.clip(sig_x, 0.05, sigma_max), np.clip(sig_y, 0.05, sigma_max)
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
#: tolerance on Σ_field P ≤ 1 per bin (PSF fractions)
_PSF_SUM_TOLERANCE = 1e-6


def _check_psf_sum(psf):
    """PSF fractions: the light of a bin in the field cannot exceed the source's (Σ_field P ≤ 1)."""
    total = psf.reshape(psf.shape[0], -1).sum(axis=1)
    if total.size and total.max() > 1.0 + _PSF_SUM_TOLERANCE:
        raise ParameterError(f"psf must hold fractions of the point source's light per cell (Σ over the field "
                             f"≤ 1 in every bin), got a bin summing to {total.max():.6g}: normalise it "
                             "(psf_from_cube)")


def _check(cube_product, method, psf, aperture, background_radius, position, background=True,
           nchunks=_MAX_CHUNKS):
    validation.choice("method", method, METHODS)
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
    aperture = validation.number("aperture [PSF σ]", aperture, low=0.0, low_open=True)
    background_radius = validation.number("background_radius [PSF σ]", background_radius, low=0.0, low_open=True)
    if background_radius <= aperture:
        raise ParameterError(f"background_radius ({background_radius}) must exceed aperture ({aperture})")
    if isinstance(psf, str):
        validation.choice("psf", psf, ("fit",))
    if psf is not None and not isinstance(psf, str):
        psf = np.asarray(psf, float)
        if psf.shape != shape or not np.all(np.isfinite(psf)) or (psf < 0).any():
            raise ParameterError(f"psf array must be finite, ≥ 0, of shape {shape}, got {psf.shape}")
        _check_psf_sum(psf)
    validation.flag("background", background)
    if isinstance(nchunks, (float, np.floating)):                 # 2.0 is not a count of chunks either
        raise ParameterError(f"nchunks (λ chunks of the PSF fit) must be an integer ≥ 1, got {nchunks!r}")
    validation.integer("nchunks (λ chunks of the PSF fit)", nchunks, low=1)
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
