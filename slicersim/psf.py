"""Spatial PSF models: fraction of a point source's flux falling in each cell.

Cell coordinates are in cell units relative to the field centre: cell edges
X_k = k − nx/2, Y_j = j − ny/2; a source at (0, 0) sits on the corner shared
by the four central cells.  Flux falling outside the field is lost.
"""
from __future__ import annotations

import numpy as np
from scipy.special import erf

__all__ = ["gaussian_psf_sigmas", "gaussian_psf_fractions", "cell_centres", "aperture_cells"]


def cell_edges(n):
    """Cell edges [cells] of an axis of n cells, centred on 0."""
    return np.arange(n + 1, dtype=float) - n / 2.0


def cell_centres(shape):
    """(y, x) 2-D arrays of cell-centre coordinates [cells]."""
    ny, nx = shape
    return np.meshgrid(cell_edges(ny)[:-1] + 0.5, cell_edges(nx)[:-1] + 0.5, indexing="ij")


def gaussian_psf_sigmas(lbda, sigma_ref_arcsec, spatial_scale, guiding_sigma, instrumental_sigma,
                        lbda_ref=1e4):
    """Gaussian PSF widths (σ_y, σ_x) [cells] at λ [Å].

    σ_t = σ_ref (λ/λ_ref) / s (diffraction, Airy-equivalent), γ = guiding / s (jitter),
    σ_y = √(σ_t² + γ²), σ_x = √(σ_t² + γ² + σ_inst²) (instrumental blur along the slice).
    """
    sig_t = sigma_ref_arcsec * (np.asarray(lbda, dtype=float) / lbda_ref) / spatial_scale
    gam = guiding_sigma / spatial_scale
    sig_y = np.sqrt(sig_t**2 + gam**2)
    sig_x = np.sqrt(sig_t**2 + gam**2 + instrumental_sigma**2)
    return sig_y, sig_x


def _erf_cell_fractions(edges, centre, sigma):
    """(nλ, ncell) fraction of a 1-D Gaussian in each cell: ½[erf((e_{k+1}−c)/√2σ) − erf((e_k−c)/√2σ)]."""
    z = (edges[None, :] - centre) / (np.sqrt(2.0) * np.asarray(sigma, dtype=float)[:, None])
    cdf = erf(z)
    return 0.5 * (cdf[:, 1:] - cdf[:, :-1])


def gaussian_psf_fractions(sig_y, sig_x, shape, position=(0.0, 0.0)):
    """PSF cube P[λ, y, x]: Gaussian integrated exactly over each cell (no renormalisation).

    Parameters
    ----------
    sig_y, sig_x : (nλ,) arrays [cells]
    shape : (ny, nx)
    position : (x0, y0) source position [cells] relative to the field centre
    """
    ny, nx = shape
    x0, y0 = position
    fy = _erf_cell_fractions(cell_edges(ny), y0, sig_y)
    fx = _erf_cell_fractions(cell_edges(nx), x0, sig_x)
    return fy[:, :, None] * fx[:, None, :]


def gaussian_psf_cells(sig_y, sig_x, shape, position, cells):
    """P restricted to a list of cells: (nλ, ncell) for ``cells`` = (iy, ix) index arrays."""
    ny, nx = shape
    x0, y0 = position
    fy = _erf_cell_fractions(cell_edges(ny), y0, sig_y)
    fx = _erf_cell_fractions(cell_edges(nx), x0, sig_x)
    iy, ix = cells
    return fy[:, iy] * fx[:, ix]


def aperture_cells(shape, position, radius):
    """(iy, ix) indices of the cells whose centre lies within ``radius`` [cells] of ``position``."""
    yc, xc = cell_centres(shape)
    x0, y0 = position
    inside = np.sqrt((xc - x0) ** 2 + (yc - y0) ** 2) <= radius
    return np.nonzero(inside)
