"""Distances and redshift scalings of sources (astropy cosmology; Planck18 by default).

A galaxy of proper size R [kpc] and luminosity density L_λ at redshift z is seen with

* angular size θ = R / D_A(z)                                     (:func:`arcsec_per_kpc`);
* observed flux density F_λ(λ) = L_λ(λ / (1+z)) / (4π D_L(z)² (1+z))
  (:func:`restframe_to_observed`), at λ = (1+z) λ_rest;

so, with D_L = (1+z)² D_A, its bolometric surface brightness F / θ² falls as (1+z)⁻⁴
(Tolman dimming, :func:`surface_brightness_dimming`) and F_λ per arcsec² at a fixed
rest-frame wavelength as (1+z)⁻⁵.  Moving a source from z₀ to z (:func:`redshift_scalings`)
multiplies its angles by D_A(z₀)/D_A(z), its wavelengths by (1+z)/(1+z₀) and F_λ by
(D_L(z₀)/D_L(z))² (1+z₀)/(1+z).
"""
from __future__ import annotations

import math

from slicersim import validation
from slicersim.errors import ParameterError, SpectrumError

__all__ = ["get_cosmology", "check_source_redshift", "angular_diameter_distance_kpc", "luminosity_distance_cm",
           "arcsec_per_kpc", "surface_brightness_dimming", "redshift_scalings", "restframe_to_observed",
           "ARCSEC_PER_RADIAN", "PC10_CM"]

ARCSEC_PER_RADIAN = 180.0 * 3600.0 / math.pi
PC10_CM = 10.0 * 3.0856775814913673e18          #: 10 pc [cm] (absolute magnitudes)


def get_cosmology(cosmology=None):
    """An astropy cosmology: None → Planck18, a realisation name ("Planck18", "WMAP9", ...)
    or a Cosmology instance (ParameterError otherwise)."""
    from astropy.cosmology import Cosmology, realizations
    if cosmology is None:
        return realizations.Planck18
    if isinstance(cosmology, Cosmology):
        return cosmology
    if isinstance(cosmology, str) and cosmology in realizations.available:
        return getattr(realizations, cosmology)
    raise ParameterError(f"cosmology must be an astropy Cosmology or one of "
                         f"{', '.join(realizations.available)}, got {cosmology!r}")


def check_source_redshift(redshift, name="redshift"):
    """A redshift in (0, :data:`~slicersim.validation.MAX_REDSHIFT`] as float (ParameterError naming
    ``name`` otherwise)."""
    return validation.redshift(name, redshift)


def angular_diameter_distance_kpc(redshift, cosmology=None):
    """D_A(z) [kpc]."""
    return float(get_cosmology(cosmology).angular_diameter_distance(redshift).to_value("kpc"))


def luminosity_distance_cm(redshift, cosmology=None):
    """D_L(z) [cm]."""
    return float(get_cosmology(cosmology).luminosity_distance(redshift).to_value("cm"))


def arcsec_per_kpc(redshift, cosmology=None):
    """Angle [arcsec] subtended by 1 proper kpc at z: 206264.8″ / D_A [kpc]."""
    return ARCSEC_PER_RADIAN / angular_diameter_distance_kpc(redshift, cosmology)


def surface_brightness_dimming(redshift):
    """(1+z)⁻⁴: bolometric surface brightness at z over that of the same source at rest."""
    return (1.0 + float(redshift)) ** -4


def redshift_scalings(from_redshift, to_redshift, cosmology=None):
    """(angle, wavelength, F_λ) factors moving a source from ``from_redshift`` to ``to_redshift``
    at fixed proper size and luminosity (see the module docstring)."""
    z0 = validation.redshift("from_redshift", from_redshift)
    z1 = validation.redshift("to_redshift", to_redshift)
    if z0 == z1:
        return 1.0, 1.0, 1.0
    cosmo = get_cosmology(cosmology)
    angle = angular_diameter_distance_kpc(z0, cosmo) / angular_diameter_distance_kpc(z1, cosmo)
    flux = (luminosity_distance_cm(z0, cosmo) / luminosity_distance_cm(z1, cosmo)) ** 2 * (1 + z0) / (1 + z1)
    return angle, (1 + z1) / (1 + z0), flux


def restframe_to_observed(rest_lbda, rest_flux, redshift, cosmology=None, absmag=None, mag=None,
                          band="bessellr", magsys="ab"):
    """Observed spectrum (λ [Å], F_λ [erg/s/cm²/Å]) of a rest-frame SED at ``redshift``.

    The table is the SED itself stretched, λ = (1+z) λ_rest (no interpolation), scaled

    * ``absmag``: so that the SED at 10 pc has AB magnitude ``absmag`` in the rest-frame
      ``band``, then F = F_10pc (10 pc / D_L)² / (1+z) (sncosmo's ``set_source_peakabsmag``
      convention: the K-correction is in the SED);
    * ``mag``: so that the observed spectrum has AB magnitude ``mag`` in ``band``
      (observer frame) at this redshift.

    Exactly one of ``absmag`` / ``mag`` must be given."""
    from slicersim.sources.spectra import normalise_to_mag, validate_spectrum
    z = check_source_redshift(redshift)
    lbda, flux = validate_spectrum(rest_lbda, rest_flux, "rest-frame spectrum")
    if (absmag is None) == (mag is None):
        raise ParameterError("give exactly one of absmag (rest-frame) or mag (observed), "
                             f"got absmag={absmag!r}, mag={mag!r}")
    for name, value in (("absmag", absmag), ("mag", mag)):
        if value is not None:
            validation.number(f"{name} [AB mag]", value)
    lbda_obs = lbda * (1.0 + z)
    try:
        if absmag is not None:
            ratio, _ = normalise_to_mag(lbda, flux, absmag, band, magsys)
            dilution = (PC10_CM / luminosity_distance_cm(z, cosmology)) ** 2 / (1.0 + z)
            return lbda_obs, flux * ratio * dilution
        ratio, _ = normalise_to_mag(lbda_obs, flux, mag, band, magsys)
    except SpectrumError as exc:
        raise SpectrumError(f"cannot normalise the host/galaxy spectrum in band {band!r}: {exc}") from None
    return lbda_obs, flux * ratio
