"""Calibration values of the simulated detector in the JWST reference-file conventions (no I/O).

What a JWST pipeline (stcal / jwst) needs to calibrate slicersim ramps, derived from the same
parameters as the ramps (:class:`~slicersim.physics.ramp.RampParameters`), in JWST units
(DN = ADU; ``gain`` below is slicersim's, in ADU/e-):

* gain [e-/DN] = 1 / gain;
* read noise [DN]: that of a correlated double sample (CDS: the difference of two single-frame
  reads), √2 · √(gain² σ² + 1/12), σ the white read noise of one frame [e-] and 1/12 DN² the
  rounding of each read to an integer DN (the JWST read-noise files are measured on CDS pairs,
  which carry it);
* dark [DN]: the charge a pixel collects in the dark, read frame by frame: frame k (0-based,
  the first read one frame time after the reset) holds (k + 1) · μ_dark · gain, with
  μ_dark = (dark + thermal dark) · t_frame + ROIC glow [e-/frame] (linear DN: the JWST dark step
  runs after the linearity correction);
* saturation [DN]: the lowest raw value a pixel may read once its charge has reached the full
  well (:func:`saturation_level`).
"""
from __future__ import annotations

import math

import numpy as np

from slicersim import validation
from slicersim.errors import EffectsError
from slicersim.physics.nonlinearity import measured_charge

__all__ = ["ADC_MAX", "SATURATION_MARGIN_SIGMA", "gain_e_per_dn", "cds_read_noise", "frame_read_noise_dn",
           "saturation_level", "dark_frames"]

ADC_MAX = 65535.0                     # the 16-bit ADC's largest value [DN]
SATURATION_MARGIN_SIGMA = 5.0         # saturation level: this many single-frame read noises below the full well


def gain_e_per_dn(gain):
    """JWST gain [e-/DN] of slicersim's ``gain`` [ADU/e-] (DN = ADU)."""
    return 1.0 / validation.number("gain [ADU/e-]", gain, low=0.0, low_open=True, error=EffectsError)


def frame_read_noise_dn(ron, gain):
    """Noise of one read [DN]: √(gain² σ² + 1/12), σ = ``ron`` [e-] (white, per frame) and the
    1/12 DN² of the rounding to an integer DN."""
    ron = validation.number("ron [e-]", ron, low=0.0, error=EffectsError)
    gain = validation.number("gain [ADU/e-]", gain, low=0.0, low_open=True, error=EffectsError)
    return math.sqrt((gain * ron) ** 2 + 1.0 / 12.0)


def cds_read_noise(ron, gain):
    """JWST read noise [DN]: that of a CDS of two single-frame reads, √2 × :func:`frame_read_noise_dn`."""
    return math.sqrt(2.0) * frame_read_noise_dn(ron, gain)


def saturation_level(bias, gain, full_well, a2=None, a3=None, ipc_centre=1.0, read_noise_dn=0.0,
                     margin_sigma=SATURATION_MARGIN_SIGMA):
    """Per-pixel saturation level [DN] in the JWST convention (a raw group at or above it is flagged
    SATURATED), consistent with the nonlinearity and the full well.

    A pixel whose charge has reached the full well Q_fw reads bias + gain · c · M(Q_fw), with M the
    pixel's nonlinear response (M(Q) = Q + a₂Q² + a₃Q³; Q without nonlinearity) and c the IPC
    kernel's centre (the least the pixel keeps of its own signal: neighbours add to it, never
    subtract), or the ADC's 65535 if lower; the level is that value less ``margin_sigma`` read
    noises, so that read noise does not hide a saturated read.  Below the level the linearity
    correction holds (it is fitted up to the full well).

    Parameters
    ----------
    bias : float or ndarray (ny, nx)
        Raw value of an empty pixel [DN] (the superbias).
    gain : float
        [ADU/e-] (slicersim's convention).
    full_well : float
        [e-].
    a2, a3 : ndarray (ny, nx) or None
        Nonlinearity coefficients [e-⁻¹, e-⁻²] (None: linear pixels).
    ipc_centre : float
        Centre of the IPC kernel (1 without IPC).
    read_noise_dn : float
        Noise of one read [DN] (:func:`frame_read_noise_dn`).
    margin_sigma : float
        Margin below the full-well value, in read noises.

    Returns
    -------
    ndarray (ny, nx) float32
        Saturation level [DN].
    """
    full_well = validation.number("full_well [e-]", full_well, low=0.0, low_open=True, error=EffectsError)
    ipc_centre = validation.number("ipc_centre", ipc_centre, low=0.0, high=1.0, low_open=True, error=EffectsError)
    measured = full_well if a2 is None else measured_charge(full_well, np.asarray(a2), np.asarray(a3))
    raw = np.minimum(np.asarray(bias, np.float64) + gain * ipc_centre * measured, ADC_MAX)
    return np.asarray(raw - margin_sigma * read_noise_dn, np.float32)


def dark_frames(dark_per_frame, gain, nframes):
    """Dark ramp [DN], frame by frame (NFRAMES = 1, GROUPGAP = 0): float32 (nframes, ny, nx),
    frame k = (k + 1) · gain · μ_dark.

    Parameters
    ----------
    dark_per_frame : ndarray (ny, nx)
        μ_dark [e-/frame]: dark current, thermal dark and ROIC glow of one frame (0 for pixels that
        collect no charge).
    gain : float
        [ADU/e-].
    nframes : int
        Frames of the dark ramp (the JWST dark step extends it linearly to longer ramps).

    Returns
    -------
    ndarray (nframes, ny, nx) float32
    """
    nframes = validation.integer("dark frames", nframes, low=2, high=1 << 16, error=EffectsError)
    mu = np.asarray(dark_per_frame, np.float64) * gain
    return np.asarray(np.arange(1, nframes + 1)[:, None, None] * mu[None], np.float32)
