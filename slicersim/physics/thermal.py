"""Thermal (black-body) emission of optics, in photon units."""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.constants import C_LIGHT, H_PLANCK, K_BOLTZMANN
from slicersim.errors import ParameterError

__all__ = ["photon_radiance", "solid_angle_from_fratio", "thermal_dark_rate"]


def photon_radiance(lbda, temperature):
    """Black-body photon radiance [ph / s / m² / sr / Å].

    Parameters
    ----------
    lbda : array_like  wavelength [Å]
    temperature : float  [K]; 0 gives no emission.
    """
    lbda_m = np.asarray(lbda, dtype=float) * 1e-10
    if temperature <= 0:
        return np.zeros_like(lbda_m)
    x = H_PLANCK * C_LIGHT / (lbda_m * K_BOLTZMANN * temperature)
    return 2 * C_LIGHT / lbda_m**4 / np.expm1(x) * 1e-10


def solid_angle_from_fratio(fratio, geometry="square"):
    """Solid angle [sr] of a beam of focal ratio ``fratio`` = f or (f_y, f_x).

    ``square`` gives 1/(f_y f_x); ``circular`` gives π/4/(f_y f_x) (small-angle limit).
    """
    validation.choice("geometry", geometry, ("square", "circular"), what="optics geometry")
    f = validation.array("fratio", np.atleast_1d(fratio), ndim=1, low=0.0)
    if f.size not in (1, 2) or np.any(f == 0):
        raise ParameterError(f"fratio must be f or (f_y, f_x), each > 0, got {validation.short_repr(fratio)}")
    fy, fx = (f[0], f[0]) if f.size == 1 else (f[0], f[1])
    if geometry == "square":
        return 1.0 / (fy * fx)
    return np.pi / 4.0 / (fy * fx)                   # circular


def thermal_dark_rate(temperatures, emissivities, nelements, solid_angles, pixel_area_m2,
                      qe, lbda_range, breakpoints=None, order=24):
    """Undispersed thermal emission seen by one pixel [e-/s/px].

    D = Σ_i ε_i n_i Ω_i A_pix ∫ B_ph(λ, T_i) QE(λ) dλ over ``lbda_range`` [Å].

    The integral is done with Gauss–Legendre quadrature (``order`` nodes) on
    sub-intervals split at ``breakpoints`` (the QE table nodes, where the
    piecewise-linear QE has kinks) and at most 250 Å long: the integrand is then
    smooth on each piece and the result agrees with adaptive quadrature to ~1e-12.

    Parameters
    ----------
    qe : callable  λ[Å] -> QE [e-/ph]
    """
    lo, hi = (float(v) for v in lbda_range)
    knots = [lo, hi] + [b for b in (breakpoints if breakpoints is not None else []) if lo < b < hi]
    knots = np.unique(knots)
    # pieces longer than 250 Å split evenly (np.linspace); the others (dense QE tables: thousands)
    # are just their two knots, taken as they are
    nsub = np.maximum(1, np.ceil(np.diff(knots) / 250.0).astype(int))
    pieces = [knots] + [np.linspace(knots[i], knots[i + 1], nsub[i] + 1) for i in np.flatnonzero(nsub > 1)]
    edges = np.unique(np.concatenate(pieces))
    x, w = np.polynomial.legendre.leggauss(order)
    half = 0.5 * np.diff(edges)[:, None]
    mid = 0.5 * (edges[1:] + edges[:-1])[:, None]
    lbda = (mid + half * x[None, :]).ravel()
    weights = (half * w[None, :]).ravel()
    qe_val = qe(lbda)
    total = 0.0
    for temp, eps, n, omega in zip(temperatures, emissivities, nelements, solid_angles):
        if eps * n == 0 or temp <= 0:
            continue
        integral = float(np.sum(weights * photon_radiance(lbda, temp) * qe_val))
        total += eps * n * omega * pixel_area_m2 * integral
    return total
