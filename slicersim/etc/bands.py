"""Coverage of an SNR band by the instrument grid and by the source spectrum.

A band is never silently clipped: when part of it lies outside the instrument
wavelength grid (its bin edges) the request is refused with a
:class:`~slicersim.errors.SpectrumError` naming the covered fraction; when the
*source spectrum* covers only part of the band (the rest is NaN and ignored by
the band means) a :class:`BandCoverageWarning` names the covered fraction.
"""
from __future__ import annotations

import warnings

import numpy as np

from slicersim.errors import SpectrumError

__all__ = ["BandCoverageWarning", "covered_fraction", "check_band_in_grid", "warn_partial_spectrum",
           "check_band_coverage"]


class BandCoverageWarning(UserWarning):
    """The source spectrum covers only part of an SNR band."""


def covered_fraction(lo, hi, cover_lo, cover_hi):
    """Fraction of [lo, hi] inside [cover_lo, cover_hi] (arrays broadcast)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    inside = np.clip(np.minimum(hi, cover_hi) - np.maximum(lo, cover_lo), 0.0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(hi > lo, inside / (hi - lo), 0.0)


def check_band_in_grid(ranges, grid_edges, who=None):
    """Raise SpectrumError when any band (N, 2) [Å] is not 100 % inside the instrument
    grid [grid_edges[0], grid_edges[-1]]."""
    ranges = np.atleast_2d(np.asarray(ranges, dtype=float))
    g0, g1 = float(grid_edges[0]), float(grid_edges[-1])
    frac = covered_fraction(ranges[:, 0], ranges[:, 1], g0, g1)
    bad = np.nonzero(frac < 1.0)[0]
    if bad.size:
        i = int(bad[0])
        lo, hi = ranges[i]
        head = f"band {lo:.0f}–{hi:.0f} Å" if who is None else \
            f"band of target(s) {bad[:10].tolist()} (first: {lo:.0f}–{hi:.0f} Å)"
        raise SpectrumError(f"{head} is only {100 * frac[i]:.1f} % inside the instrument grid "
                            f"{g0:.0f}–{g1:.0f} Å: the band is not clipped, choose a band inside the grid")
    return ranges


def warn_partial_spectrum(ranges, spec_lo, spec_hi, who=None):
    """Warn (BandCoverageWarning) when the source spectrum [spec_lo, spec_hi] covers only
    part of a band; returns the covered fractions."""
    ranges = np.atleast_2d(np.asarray(ranges, dtype=float))
    frac = covered_fraction(ranges[:, 0], ranges[:, 1], spec_lo, spec_hi)
    part = np.nonzero(frac < 1.0)[0]
    if part.size:
        i = int(part[0])
        lo, hi = ranges[i]
        head = f"band {lo:.0f}–{hi:.0f} Å" if who is None else \
            f"band of target(s) {part[:10].tolist()} (first: {lo:.0f}–{hi:.0f} Å)"
        warnings.warn(f"the source spectrum ({float(spec_lo):.0f}–{float(spec_hi):.0f} Å) covers only "
                      f"{100 * frac[i]:.1f} % of the {head}: the SNR is computed on the covered part",
                      BandCoverageWarning, stacklevel=3)
    return frac


def check_band_coverage(sim, lbda_range):
    """Single-target check (called by ``Simulation.band_mask``): band 100 % inside the
    instrument grid (else SpectrumError), warn when the point-source spectrum covers
    only part of it."""
    check_band_in_grid([lbda_range], sim.spectrograph.lbda_edges)
    ps = sim.scene.pointsource
    if ps is not None:
        warn_partial_spectrum([lbda_range], ps.lbda_in[0], ps.lbda_in[-1])
