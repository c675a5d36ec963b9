"""Where the light is, from the rates alone: the white light of the native cells (the transpose of the
projection, no rectification) without the detector's isolated outliers, and the brightest compact
source in it.  The forward fit (:mod:`slicersim.reduction.forward_extraction`) starts from it, and the
reduction's fit-quality check looks for light left in the fit's residual with it.
"""
from __future__ import annotations

import numpy as np

from slicersim.errors import ParameterError

__all__ = ["white_light_start", "isolated_outliers", "locate_source"]


def white_light_start(rate, variance, tables, rows=None, noise_floor=False):
    """Where the light is, from the pixels alone: the native cells' white light Σ_λ Pᵀd / Σ_λ Pᵀ1
    (transpose of the projection, no rectification), then :func:`locate_source` (over the cube
    ``rows`` only, when given).  ``noise_floor``: the scatter the significance is measured against is
    at least that of white noise of ``variance`` through the same statistic (for residual images,
    whose own scatter can be far below the noise).  Returns ((x, y) [native cells from the field
    centre], significance [σ])."""
    from slicersim.backends.projection_transpose import gather
    r0, r1 = tables.row_range                                 # the field's rows: the rest plays no part
    variance = np.asarray(variance)[r0:r1]
    rate = np.asarray(rate)[r0:r1]
    floor = 0.0
    usable = np.isfinite(variance) & (variance > 0) & np.isfinite(rate)
    usable &= ~isolated_outliers(rate, variance, usable)
    den = gather(usable.astype(float), tables, band=True)    # Σ_λ Pᵀ1: shared by both cubes
    if noise_floor:
        noise = np.sqrt(np.where(usable, variance, 0.0))
        noise *= np.random.default_rng(0).standard_normal(noise.shape)
        floor = locate_source(_white_light_cube(noise, usable, den, tables, rows), scatter=True)
    return locate_source(_white_light_cube(rate, usable, den, tables, rows), floor=floor)


#: running-median window [pixels] and threshold [σ] of :func:`isolated_outliers`
_OUTLIER_WINDOW = 7
_OUTLIER_SIGMA = 5.0
#: candidates whose running medians are taken at once (~350 B each): a variance far below the noise
#: makes most pixels candidates, and a 4096² image then took ~3 GB
_OUTLIER_CHUNK = 1 << 17


def isolated_outliers(rate, variance, usable):
    """Pixels brighter than their neighbours along both detector axes (those longer than one pixel):
    above the running median of ``_OUTLIER_WINDOW`` pixels of their row and of their column by more
    than ``_OUTLIER_SIGMA`` σ (σ² = ``variance``) and by more than half that median.  Hot and warm pixels and the unflagged
    neighbours of cosmic rays are such points; a spectrum is smooth along the dispersion and a slice's
    image along the slices, so a source's pixels stand out along one axis at most.  In a wide-field
    Lazuli ramp with ``effects = "lazuli"`` warm pixels (0.6 % of them, median 0.3 e-/s against a
    faint source's 0.05 e-/s per pixel) dominated the white light's scatter: sources of 8 σ were found
    at 4.8 σ.

    Parameters
    ----------
    rate : numpy.ndarray of shape (ny, nx)
        Rates [e-/s].
    variance : numpy.ndarray of shape (ny, nx)
        Their variance [(e-/s)²].
    usable : numpy.ndarray of shape (ny, nx), bool
        Pixels with a rate; the others are never outliers.

    Returns
    -------
    numpy.ndarray of shape (ny, nx), bool
        The isolated outliers (none in a 1 × 1 image: no neighbour says anything).

    Raises
    ------
    ParameterError
        Arrays that are not 2-D real numbers of one shape, or ``usable`` not boolean.
    """
    rate, variance, usable = _outlier_inputs(rate, variance, usable)
    d = np.where(usable, rate, 0.0)
    ny, nx = d.shape
    if ny == 1 and nx == 1:                              # no neighbour along either axis: nothing to say
        return np.zeros(d.shape, bool)
    # candidates (cheap, whole image): above the fainter of the two neighbours along the column (pairs of
    # outliers pass too; rows mirrored at the ends); the running medians are then taken at the
    # candidates only (the whole-image filters cost ~3 CPU-s per reduction)
    if ny > 1:
        excess = np.empty_like(d)
        np.minimum(d[:-2], d[2:], out=excess[1:-1])
        excess[0], excess[-1] = d[1], d[-2]
        np.subtract(d, excess, out=excess)
        cand = excess > 0
        cand &= usable
        np.square(excess, out=excess)
        with np.errstate(invalid="ignore"):
            cand &= excess > _OUTLIER_SIGMA ** 2 * np.where(cand, variance, np.inf)
        ys, xs = np.nonzero(cand)
    else:                                                # one row: the columns say nothing
        ys, xs = np.nonzero(usable)
    offsets = np.arange(-(_OUTLIER_WINDOW // 2), _OUTLIER_WINDOW // 2 + 1)
    out = np.zeros(d.shape, bool)
    for c in range(0, ys.size, _OUTLIER_CHUNK):       # bounded memory when most pixels are candidates
        cy, cx = ys[c:c + _OUTLIER_CHUNK], xs[c:c + _OUTLIER_CHUNK]
        keep = np.ones(cy.size, bool)
        with np.errstate(invalid="ignore"):              # a negative variance: NaN, never an outlier
            value, thr = d[cy, cx], _OUTLIER_SIGMA * np.sqrt(variance[cy, cx])
        for n, rows in ((ny, True), (nx, False)):
            if n == 1:                                           # an axis of one pixel says nothing
                continue
            at = np.abs((cy if rows else cx)[:, None] + offsets[None, :])   # mirrored at both ends ("mirror")
            at = np.where(at > n - 1, 2 * (n - 1) - at, at)
            at = np.clip(at, 0, n - 1)                           # windows longer than the axis
            window = d[at, cx[:, None]] if rows else d[cy[:, None], at]
            med = np.median(window, axis=1)
            keep &= (value - med > thr) & (value - med > 0.5 * np.abs(med))
        out[cy[keep], cx[keep]] = True
    return out


def _outlier_inputs(rate, variance, usable):
    """The arguments of :func:`isolated_outliers` checked: 2-D real rates, variances of their shape and a
    boolean ``usable`` of their shape (ParameterError otherwise)."""
    from slicersim import validation
    rate = validation.array("rate", rate, ndim=2, finite=False)
    variance = validation.array("variance", variance, ndim=2, finite=False)
    usable = np.asarray(usable)
    if variance.shape != rate.shape:
        raise ParameterError(f"variance must have the rates' shape {rate.shape}, got {variance.shape}")
    if usable.dtype != bool or usable.shape != rate.shape:
        raise ParameterError(f"usable must be a boolean array of the rates' shape {rate.shape}, got "
                             f"{usable.dtype} of shape {usable.shape}")
    return rate, variance, usable


def _white_light_cube(rate, usable, den, tables, rows):
    from slicersim.backends.projection_transpose import gather
    d = np.where(usable, rate, 0.0)
    num = gather(d, tables, band=True)                       # (S, E, Q)
    with np.errstate(invalid="ignore", divide="ignore"):
        cells = np.where(den > 0.5 * np.median(den[den > 0]) if (den > 0).any() else den > 0, num / den, np.nan)
    cube = np.swapaxes(cells, 0, 1)[:, ::-1, :]              # (E, rows, Q): row r ↔ slice S − 1 − r
    if rows is not None:
        keep = np.zeros(cube.shape[1], bool)
        keep[np.asarray(rows, int)] = True
        cube = np.where(keep[None, :, None], cube, np.nan)
    return cube


def locate_source(cube_flux, floor=0.0, scatter=False):
    """Centre of the brightest compact light in a cube (nλ, ny, nx): white light (each plane minus its
    median), 3×3 box smoothing, peak cell, centroid over the 5×5 cells around it.

    Returns ((x, y) [cube cells from the field centre], significance of the peak [σ]: over the robust
    scatter of the smoothed white light, at least ``floor``); ``scatter=True``: that scatter only.
    """
    from scipy.ndimage import uniform_filter
    flux = np.asarray(cube_flux, float)
    if flux.ndim != 3:
        raise ParameterError(f"cube must be (nλ, ny, nx), got shape {flux.shape}")
    good = np.isfinite(flux)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(good, flux, np.nan), axis=(1, 2))
    white = np.where(good, flux - np.nan_to_num(med)[:, None, None], 0.0).sum(axis=0)
    seen = good.any(axis=0)                                  # cells with data: the statistics' sample
    if not seen.any():
        return 0.0 if scatter else ((0.0, 0.0), 0.0)
    smooth = uniform_filter(white, 3, mode="constant")
    ny, nx = white.shape
    iy, ix = np.unravel_index(int(np.argmax(np.where(seen, smooth, -np.inf))), smooth.shape)
    level = np.median(smooth[seen])
    mad = np.median(np.abs(smooth[seen] - level)) * 1.4826
    if scatter:
        return float(mad)
    mad = max(mad, float(floor))
    signif = float((smooth[iy, ix] - level) / mad) if mad > 0 else 0.0
    y0, y1, x0, x1 = max(iy - 2, 0), min(iy + 3, ny), max(ix - 2, 0), min(ix + 3, nx)
    w = np.clip(white[y0:y1, x0:x1], 0, None)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    tot = w.sum()
    cy, cx = ((yy * w).sum() / tot, (xx * w).sum() / tot) if tot > 0 else (iy, ix)
    return (float(cx - (nx - 1) / 2), float(cy - (ny - 1) / 2)), signif
