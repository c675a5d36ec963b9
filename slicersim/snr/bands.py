"""Coverage of an SNR band by the instrument grid and by the source spectrum.

A band is never silently clipped.  The rule (the same for the grid and the spectrum):

* a band entirely inside the instrument grid (its bin edges) and entirely covered by
  the source spectrum is used as is;
* a band only partly covered raises :class:`~slicersim.errors.SpectrumError` naming the
  covered fraction (the SNR would otherwise be that of a narrower band: bins outside
  the spectrum are NaN and the band means would ignore them) — unless the caller passes
  ``allow_partial=True``: then a :class:`BandCoverageWarning` names the covered fraction
  and the SNR is computed on the covered part;
* a band less than :data:`MIN_GRID_COVERAGE` inside the grid, or with no bin at all, is
  refused even with ``allow_partial=True``.

Single-target calls (``Target.get_band_snr`` / ``setup_to_snr``,
``Simulation.get_band_snr`` / ``fetch_snr`` / ``band_mask`` /
``get_band_variance_contribution``) default to ``allow_partial=False``;
:func:`slicersim.etc.solve.solve_many` defaults to ``allow_partial=True`` (a batch of
survey targets whose rest-frame bands straddle the grid edge, e.g. SN Ia 4000–6800 Å rest
at z > 1.5, is answered with one warning naming the targets instead of failing).
"""
from __future__ import annotations

import warnings

import numpy as np

from slicersim import validation
from slicersim.errors import SpectrumError

__all__ = ["ALLOW_PARTIAL_HINT", "MIN_GRID_COVERAGE", "BandCoverageWarning", "covered_fraction", "check_band_in_grid", "warn_partial_spectrum",
           "check_band_coverage"]


#: how a message names the switch that accepts a partly covered band (Python keyword and CLI flag)
ALLOW_PARTIAL_HINT = "allow_partial=True in Python, --allow-partial on the command line"

#: smallest fraction of a band that must lie inside the instrument grid (else SpectrumError)
MIN_GRID_COVERAGE = 0.5


def _allow_partial_hint():
    """``--allow-partial`` within the CLI (:func:`slicersim.validation.flag_names`), else both spellings."""
    flag = validation.shown("allow_partial")
    return flag if flag != "allow_partial" else ALLOW_PARTIAL_HINT


class BandCoverageWarning(UserWarning):
    """The source spectrum covers only part of an SNR band."""


def covered_fraction(lo, hi, cover_lo, cover_hi):
    """Fraction of [lo, hi] inside [cover_lo, cover_hi] (arrays broadcast)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    inside = np.clip(np.minimum(hi, cover_hi) - np.maximum(lo, cover_lo), 0.0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(hi > lo, inside / (hi - lo), 0.0)


def check_band_in_grid(ranges, grid_edges, who=None, allow_partial=True):
    """Bands (N, 2) [Å] against the instrument grid [grid_edges[0], grid_edges[-1]]: raise
    SpectrumError when less than :data:`MIN_GRID_COVERAGE` of a band is inside, warn
    (BandCoverageWarning) naming the covered fraction when it is not 100 %.  Returns the
    covered fractions.  ``allow_partial=False``: SpectrumError below 100 %."""
    ranges = np.atleast_2d(np.asarray(ranges, dtype=float))
    g0, g1 = float(grid_edges[0]), float(grid_edges[-1])
    frac = covered_fraction(ranges[:, 0], ranges[:, 1], g0, g1)

    def head(idx):
        lo, hi = ranges[int(idx[0])]
        return f"band {lo:g}–{hi:g} Å" if who is None else \
            f"band of target(s) {idx[:10].tolist()} (first: {lo:g}–{hi:g} Å)"
    bad = np.nonzero(frac < MIN_GRID_COVERAGE)[0]
    if bad.size:
        raise SpectrumError(f"{head(bad)} is only {100 * frac[bad[0]]:.1f} % inside the instrument grid "
                            f"{g0:.0f}–{g1:.0f} Å (at least {100 * MIN_GRID_COVERAGE:.0f} % needed, even with "
                            f"{_allow_partial_hint()}): choose a band inside the grid")
    part = np.nonzero(frac < 1.0)[0]
    if part.size and not allow_partial:
        raise SpectrumError(f"{head(part)} is only {100 * frac[part[0]]:.1f} % inside the instrument grid "
                            f"{g0:.0f}–{g1:.0f} Å: the SNR would be that of a narrower band; choose a band "
                            f"inside the grid or use the covered part ({_allow_partial_hint()})")
    if part.size:
        warnings.warn(f"{head(part)} is only {100 * frac[part[0]]:.1f} % inside the instrument grid "
                      f"{g0:.0f}–{g1:.0f} Å: the SNR is computed on the covered part",
                      BandCoverageWarning, stacklevel=3)
    return frac


def warn_partial_spectrum(ranges, spec_lo, spec_hi, who=None, allow_partial=True):
    """Warn (BandCoverageWarning) when the source spectrum [spec_lo, spec_hi] covers only
    part of a band (``allow_partial=False``: raise SpectrumError); returns the covered
    fractions."""
    ranges = np.atleast_2d(np.asarray(ranges, dtype=float))
    frac = covered_fraction(ranges[:, 0], ranges[:, 1], spec_lo, spec_hi)
    part = np.nonzero(frac < 1.0)[0]
    if part.size:
        i = int(part[0])
        lo, hi = ranges[i]
        head = f"band {lo:g}–{hi:g} Å" if who is None else \
            f"band of target(s) {part[:10].tolist()} (first: {lo:g}–{hi:g} Å)"
        msg = (f"the source spectrum ({float(spec_lo):g}–{float(spec_hi):g} Å) covers only "
               f"{100 * frac[i]:.1f} % of the {head}")
        if not allow_partial:
            raise SpectrumError(f"{msg}: the SNR would be that of a narrower band; choose a band the "
                                f"spectrum covers or use the covered part ({_allow_partial_hint()})")
        warnings.warn(f"the source spectrum ({float(spec_lo):g}–{float(spec_hi):g} Å) covers only "
                      f"{100 * frac[i]:.1f} % of the {head}: the SNR is computed on the covered part",
                      BandCoverageWarning, stacklevel=3)
    return frac


def check_band_coverage(sim, lbda_range, allow_partial=False):
    """Single-target check (called by ``Simulation.band_mask``): see
    :func:`check_band_in_grid` and :func:`warn_partial_spectrum` (module docstring: the rule)."""
    check_band_in_grid([lbda_range], sim.spectrograph.lbda_edges, allow_partial=allow_partial)
    ps = sim.scene.pointsource
    if ps is not None:
        warn_partial_spectrum([lbda_range], ps.lbda_in[0], ps.lbda_in[-1], allow_partial=allow_partial)
