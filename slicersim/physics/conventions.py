"""Conventions: the physical default, or every slicersim 1.0 behaviour that differs from it.

``conventions="physical"`` (default) and ``conventions="slicersim-1.0"`` are
accepted by every target, :func:`~slicersim.assembly.build_simulation` and
:class:`~slicersim.simulation.Simulation`.  What differs:

=====================  ===================================  =====================================
quantity               physical                             slicersim-1.0
=====================  ===================================  =====================================
variance in ADU²       V_e [e-²] × g²  (ADU = g · e-)       V_e [e-²] / g²  (SNR ∝ g² for g ≠ 1)
instrumental blur σ_x  √(dr² − 2²)/2 cells                 √(dr² − 2²) cells (a full width used
                       (:func:`physical_blur_sigma`)        as σ: 2× too large)
detector pixels per    the pixel rows of one bin:           ``pixels_per_cell`` (2 for the slicer):
cell (read noise,      1 for the slicer — consecutive bins  each bin's 2-px slit image counted
dark, saturation)      share the slit image's rows          again for every bin (read noise and
                       (:func:`detector_pixels_per_cell`)   dark counted twice)
``phase`` of SNe and   rest-frame days from the time of     observer-frame days: the sncosmo
every sncosmo source   maximum (t0): the model is read at   model read at t = phase (1.0's
                       t = phase (1 + z) observer days,     ``LazuliSupernova``); a campaign
                       as SN light curves are fitted and    population at the same number was
                       as populations, campaigns, survey    another epoch at every z > 0
                       plans and the CLI read it            (:func:`phase_frame`)
=====================  ===================================  =====================================
"""
from __future__ import annotations

import math

from slicersim import validation

__all__ = ["CONVENTIONS", "DEFAULT_CONVENTIONS", "check_conventions", "variance_gain_factor",
           "instrumental_blur_sigma", "physical_blur_sigma", "detector_pixels_per_cell", "phase_frame",
           "PHASE_FRAMES", "observer_days"]

#: frames a transient's ``phase`` can be counted in
PHASE_FRAMES = ("rest", "obs")

DEFAULT_CONVENTIONS = "physical"
CONVENTIONS = ("physical", "slicersim-1.0")


def check_conventions(conventions):
    """The validated convention name (ParameterError listing the known ones, with a "did you mean")."""
    return validation.choice("conventions", conventions, CONVENTIONS)


def variance_gain_factor(gain, conventions=DEFAULT_CONVENTIONS):
    """ADU² per e-² of a variance: g² (physical: a signal of N e- reads g·N ADU, so its
    variance is g² Var[N]); 1/g² under slicersim 1.0 (exact for g = 1 only)."""
    return gain**2 if check_conventions(conventions) == "physical" else 1.0 / gain**2


def instrumental_blur_sigma(dispersion_resolution, anamorphosis=(1, 1), conventions=DEFAULT_CONVENTIONS):
    """Gaussian σ [cells] of the spectrograph aberrations along the slice (x axis of the cube).

    See :func:`slicersim.physics.conventions.physical_blur_sigma` for the derivation of
    the physical default; slicersim 1.0 used √(dr² − 2²) with dr in pixels, read as cells.
    """
    dr = float(dispersion_resolution)
    if check_conventions(conventions) == "slicersim-1.0":
        return math.sqrt(dr**2 - 4.0) if dr > 2 else 0.0
    return physical_blur_sigma(dr, anamorphosis)


def physical_blur_sigma(dispersion_resolution, anamorphosis=(1, 1)):
    """Aberration blur σ_x [cells] along the slice, from the resolution element.

    ``dispersion_resolution`` dr [px] is the full width of a monochromatic slice image
    on the detector along the dispersion.  Of it, 2 px is the geometric image of the
    slice width (the 1×2 anamorphosis images one cell on 2 pixels); the spectrograph
    aberrations add, in quadrature, a full width w = √(dr² − 2²) [px] (1.136 px for
    dr = 2.3: the paper's "typical 1 pixel extra scatter").  The code's own width
    convention is width = 2σ (the LSF has σ = dr/2 bins), so σ_ab = w / 2 [px].
    Along the slice one detector pixel spans one cell (the anamorphosis stretches the
    other axis), so σ_x = √(dr² − 4) / 2 cells (0.568 for dr = 2.3, 0.75 for 2.5);
    across slices the aberrations act after the slicer and add nothing (σ_y = 0).
    slicersim 1.0 used w as σ (2× too large); 1.4.2 also divided by the anamorphosis
    (2× too small).  ``anamorphosis`` is accepted for MLA/other spectrographs, whose
    cells map to one pixel along the slice too; it does not enter the formula.
    """
    dr = float(dispersion_resolution)
    return 0.5 * math.sqrt(dr**2 - 4.0) if dr > 2 else 0.0


def detector_pixels_per_cell(spectrograph, conventions=DEFAULT_CONVENTIONS):
    """Detector pixels whose read noise, dark and full well one cell (spaxel × native bin) carries.

    A native bin is one pixel row along the dispersion (the grid sits on the pixel lattice).
    The slicer's 1×2 anamorphosis images a cell on 2 px *across the slice width*, i.e. along the
    dispersion: that 2-px slit image is part of the LSF (σ = dr/2 bins), which already spreads
    each line over the neighbouring bins, so consecutive bins of a spaxel share their rows and a
    cell owns ``spectrograph.pixels_per_bin`` pixels (1 for the slicer; an MLA spaxel's spectrum
    spans its cross-dispersion strip).  slicersim 1.0 counted ``pixels_per_cell`` (2) per cell
    with cells independent: read noise and dark twice, a band SNR 6–22 % low for Lazuli SNe Ia
    where read noise matters (``benchmarks/etc_snr_bound.py``: the pixel-level bound agrees with
    the physical count to 2 %), and a pixel rate (saturation) half the true one.
    """
    if check_conventions(conventions) == "slicersim-1.0":
        return spectrograph.pixels_per_cell
    return spectrograph.pixels_per_bin


def phase_frame(conventions=DEFAULT_CONVENTIONS):
    """Frame of a transient's ``phase`` under ``conventions``.

    Parameters
    ----------
    conventions : {"physical", "slicersim-1.0"}
        The convention set (:data:`CONVENTIONS`).

    Returns
    -------
    str
        ``"rest"`` (physical: rest-frame days from maximum, the frame of SN light-curve fits,
        populations, campaigns and survey plans) or ``"obs"`` (slicersim 1.0's
        ``LazuliSupernova``: observer-frame days).
    """
    return "rest" if check_conventions(conventions) == "physical" else "obs"


def observer_days(phase, redshift, frame="rest"):
    """Observer-frame days since maximum of a ``phase`` counted in ``frame``.

    Parameters
    ----------
    phase : float or array_like
        Days since maximum light [d], in ``frame``.
    redshift : float or array_like
        Redshift z > 0 (broadcast against ``phase``).
    frame : {"rest", "obs"}
        The frame ``phase`` is counted in.

    Returns
    -------
    float or numpy.ndarray
        t_obs = phase (1 + z) for a rest-frame phase (cosmological time dilation), ``phase``
        itself for an observer-frame one [d].
    """
    frame = validation.choice("phase frame", frame, PHASE_FRAMES)
    return phase * (1.0 + redshift) if frame == "rest" else phase
