"""The instrument keywords of slicersim's level-1b files: one table, one meaning per name.

A pipeline dispatches on INSTRUME, DETECTOR, EXP_TYPE and READPATT; a calibration database
(CRDS-like) selects its reference files (gain, read noise, saturation, ...) by the same values.
They are defined here only, so the raw files and the reference files agree:

==========  ======================  =========================================================
keyword     value                   meaning
==========  ======================  =========================================================
TELESCOP    ``Lazuli``              the observatory
INSTRUME    ``LAZULI_IFS``          :data:`INSTRUMENT`, the Lazuli image-slicer IFS
DETECTOR    ``H4RG-1``              :data:`DETECTOR`, its (single) H4RG-10 detector
EXP_TYPE    ``LZ_IFU``              :data:`EXP_TYPE`, an IFU science (or dark) exposure
READPATT    ``MACC_<m>_<d>``        :func:`readout_pattern`: m frames averaged per group, d
                                    frames dropped between groups (NGROUPS gives n); e.g.
                                    MACC(16, 8, 0) → ``MACC_8_0``
GAINEDN     gain [e-/DN]            as JWST gain reference files: 1 / slicersim's GAIN
RDNCDSDN    read noise [DN]         of a CDS difference of two single frames, √2·σ_frame·GAIN
                                    (as JWST read-noise reference files)
SUBARRAY    ``FULL`` / ``GENERIC``  with SUBSTRT1/2 (1-based x/y of the first pixel on the
                                    detector) and SUBSIZE1/2
==========  ======================  =========================================================

Two names, two meanings, both kept: ``HIERARCH SLICERSIM GAIN`` is slicersim's conversion gain
[ADU/e-] and ``HIERARCH SLICERSIM READNOISE`` its per-frame read noise [e-] (the simulation's
parameters, read back by slicersim); GAINEDN and RDNCDSDN are the same quantities in the units
pipelines use.  ``HIERARCH SLICERSIM READPATT`` keeps the full pattern ``MACC(n,m,d)``.

JWST's schema (stdatamodels ``core.schema.yaml``) enumerates INSTRUME, DETECTOR, EXP_TYPE and
READPATT with JWST names only, so a Lazuli file opens in ``Level1bModel`` / ``RampModel`` and
passes every other schema check, but a *strict* validation names these four keywords; to feed
JWST pipeline code that dispatches on them, pass ``keywords=JWST_STAND_IN`` (NIRSpec IFU names,
also an image slicer; the file is then as honest as that choice), which validates strictly.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["TELESCOPE", "INSTRUMENT", "DETECTOR", "EXP_TYPE", "JWST_STAND_IN", "GROUPDQ_FLAGS", "readout_pattern",
           "pipeline_units", "instrument_keywords", "SATURATION_MARGIN", "saturation_reference", "group_sigma_dn",
           "observed_saturation"]

TELESCOPE = "Lazuli"
#: INSTRUME of every slicersim level-1b file (and of the matching reference files)
INSTRUMENT = "LAZULI_IFS"
#: DETECTOR of the Lazuli IFS's H4RG-10
DETECTOR = "H4RG-1"
#: EXP_TYPE of an IFU exposure
EXP_TYPE = "LZ_IFU"
#: JWST names a caller may put in place of ours (``keywords=``) to run JWST pipeline code
JWST_STAND_IN = {"INSTRUME": "NIRSPEC", "DETECTOR": "NRS1", "EXP_TYPE": "NRS_IFU", "READPATT": "NRSRAPID"}

#: what the GROUPDQ extension holds: "none" (no GROUPDQ, as in flight level-1b files: flags are the
#: pipeline's to set), "observed" (SATURATED where the observed DN reaches SATURATION, as a
#: pipeline's saturation step flags it, and every later group), "truth" (the simulator's flags,
#: from the true charge: the truth, not an observable)
GROUPDQ_FLAGS = ("none", "observed", "truth")

#: the saturation reference level sits this many σ (white noise of one group) below the plateau
SATURATION_MARGIN = 5.0


def group_sigma_dn(gain_adu_per_e, ron_e, nframes, ktc_e=0.0):
    """White noise of one group's DN about its plateau [DN]: gain·√(ron²/nframes + kTC²)."""
    return float(gain_adu_per_e) * math.sqrt(float(ron_e) ** 2 / int(nframes) + float(ktc_e) ** 2)


def saturation_reference(plateau_dn, saturation_dn, sigma_dn):
    """The saturation level a pipeline flags against [DN] (as a JWST saturation reference file):
    ``min(plateau, saturation) − SATURATION_MARGIN·σ``.

    Parameters
    ----------
    plateau_dn : float or (rows, nx) array [DN], bias + gain·R(full well): where a full pixel reads
    saturation_dn : float [DN], the ADC / SATURATION level (a ramp never reads above it)
    sigma_dn : float [DN], the white noise of one group about the plateau (:func:`group_sigma_dn`)

    Returns
    -------
    float or array [DN] : a group at or above it is SATURATED (and every later one)
    """
    return np.minimum(np.asarray(plateau_dn, np.float64), float(saturation_dn)) - SATURATION_MARGIN * float(sigma_dn)


def readout_pattern(nframes, groupgap):
    """READPATT of a MACC pattern: ``MACC_<nframes>_<groupgap>`` (str; NGROUPS is its own keyword)."""
    return f"MACC_{int(nframes)}_{int(groupgap)}"


def pipeline_units(gain_adu_per_e, ron_e):
    """(gain [e-/DN], CDS read noise [DN]) from slicersim's gain [ADU/e-] and per-frame read noise [e-].

    Parameters
    ----------
    gain_adu_per_e : float, conversion gain [ADU/e-] (> 0)
    ron_e : float, read noise of one frame [e-]

    Returns
    -------
    (float, float) : 1/gain [e-/DN] and √2·ron·gain [DN], the noise of a difference of two frames
    """
    g = float(gain_adu_per_e)
    return 1.0 / g, math.sqrt(2.0) * float(ron_e) * g


def instrument_keywords(attrs):
    """Primary-header cards [(key, value, comment)] of the instrument for root attributes ``attrs``
    (NFRAMES, GROUPGAP; GAIN [ADU/e-] and READNOISE [e-] when present)."""
    cards = [("TELESCOP", TELESCOPE, "observatory"), ("INSTRUME", INSTRUMENT, "Lazuli image-slicer IFS"),
             ("DETECTOR", DETECTOR, "H4RG-10 of the IFS"), ("EXP_TYPE", EXP_TYPE, "IFU exposure")]
    if "NFRAMES" in attrs and "GROUPGAP" in attrs:
        cards.append(("READPATT", readout_pattern(attrs["NFRAMES"], attrs["GROUPGAP"]),
                      "MACC_<frames per group>_<dropped frames>"))
    if "GAIN" in attrs and "READNOISE" in attrs and float(attrs["GAIN"]) > 0:
        gain, rdn = pipeline_units(attrs["GAIN"], attrs["READNOISE"])
        cards += [("GAINEDN", gain, "[e-/DN] gain as pipelines use it"),
                  ("RDNCDSDN", rdn, "[DN] CDS read noise of two frames")]
    return cards


def observed_saturation(sci, level):
    """GROUPDQ of saturation seen in the data: SATURATED (2) from the first group whose DN reaches
    ``level`` on, as a pipeline's saturation step flags it from what it reads.

    Parameters
    ----------
    sci : (ngroups, ...) integer array [DN], the groups of one integration
    level : float or array broadcasting to ``sci.shape[1:]`` [DN], the saturation level

    Returns
    -------
    (ngroups, ...) uint8 : 2 where saturated, else 0
    """
    reached = np.asarray(sci) >= np.asarray(level, dtype=np.float64)
    return np.where(np.logical_or.accumulate(reached, axis=0), np.uint8(2), np.uint8(0)).astype(np.uint8)
