"""Source spectra: validated (λ, F) tables, point sources, SNe Ia (sncosmo), black bodies.

Flux densities F(λ) are in erg/s/cm²/Å, wavelengths in Å.
"""
from __future__ import annotations

import numpy as np

from slicersim.constants import C_LIGHT, H_PLANCK, K_BOLTZMANN
from slicersim.errors import ParameterError, SpectrumError
from slicersim.versioning import Versioned

__all__ = ["PointSource", "validate_spectrum", "snia_spectrum", "blackbody_flambda", "normalise_to_mag",
           "SNCOSMO_SNIA_MODELS"]

#: sncosmo SN Ia sources and whether they work offline (built into sncosmo)
SNCOSMO_SNIA_MODELS = {"hsiao-subsampled": True, "hsiao": False, "salt2": False,
                       "salt2-extended": False, "salt3": False, "salt3-nir": False}




def validate_spectrum(lbda, flux, name="spectrum"):
    """Check and return (λ, F) as float arrays; λ strictly increasing, F finite and ≥ 0."""
    lbda = np.asarray(lbda, dtype=float)
    flux = np.asarray(flux, dtype=float)
    if lbda.ndim != 1 or lbda.size == 0:
        raise SpectrumError(f"{name}: empty wavelength array")
    if flux.shape != lbda.shape:
        raise SpectrumError(f"{name}: flux shape {flux.shape} differs from wavelength shape {lbda.shape}")
    if lbda.size < 2:
        raise SpectrumError(f"{name}: need at least 2 samples to interpolate")
    if not np.all(np.isfinite(lbda)) or np.any(np.diff(lbda) <= 0):
        raise SpectrumError(f"{name}: wavelengths must be finite and strictly increasing")
    if not np.all(np.isfinite(flux)):
        raise SpectrumError(f"{name}: flux contains {np.count_nonzero(~np.isfinite(flux))} NaN/inf value(s)")
    if np.any(flux < 0):
        raise SpectrumError(f"{name}: flux contains {np.count_nonzero(flux < 0)} negative value(s)")
    return lbda, flux


def blackbody_flambda(lbda, temperature):
    """Black-body spectral shape B_λ(T) [erg/s/cm²/Å/sr] at λ [Å]."""
    if not temperature > 0:
        raise SpectrumError(f"blackbody temperature must be > 0 K, got {temperature}")
    lbda_m = np.asarray(lbda, dtype=float) * 1e-10
    x = H_PLANCK * C_LIGHT / (lbda_m * K_BOLTZMANN * temperature)
    blam = 2 * H_PLANCK * C_LIGHT**2 / lbda_m**5 / np.expm1(x)  # W/m²/m/sr
    return blam * 1e3 * 1e-10  # erg/s/cm²/Å/sr  (W/m²/m = 1e3 erg/s/cm²/cm ... = 1e-7 erg/s/cm²/Å)


def snia_spectrum(redshift, phase=0.0, source="hsiao-subsampled", peak_absmag=-19.3,
                  band="bessellb", magsys="ab", lbda=None, x1=None, c=None, cosmology=None):
    """SN Ia spectrum from sncosmo at ``phase`` days (observer frame) after peak.

    Returns (λ[Å], F[erg/s/cm²/Å]) on ``lbda`` (default 3000–19990 Å, 10 Å step).
    ``hsiao-subsampled`` is built into sncosmo and works offline; SALT2/3 need
    sncosmo's data download and raise a clear error when unavailable.
    ``x1`` and ``c`` (default 0) exist only for SALT sources: given with any other
    source (e.g. Hsiao) they would be ignored, so they raise :class:`ParameterError`.
    """
    from slicersim.errors import ParameterError
    if "salt" not in str(source).lower() and (x1 is not None or c is not None):
        raise ParameterError(f"x1 / c are SALT parameters: sncosmo source {source!r} has none "
                             "(use source='salt2' or 'salt3', or drop them)")
    import sncosmo
    from astropy.cosmology import Planck18
    if not redshift > 0:
        raise SpectrumError(f"redshift must be > 0, got {redshift}")
    if lbda is None:
        lbda = np.arange(3000.0, 20000.0, 10.0)
    try:
        model = sncosmo.Model(source)
    except Exception as exc:
        raise SpectrumError(f'sncosmo source "{source}" could not be loaded (needs download; offline?) '
                            f"— available offline: {', '.join(k for k, v in SNCOSMO_SNIA_MODELS.items() if v)} "
                            f"({type(exc).__name__}: {exc})") from exc
    params = {"z": redshift, "t0": 0.0}
    if "salt" in str(source).lower():
        params.update(x1=0.0 if x1 is None else x1, c=0.0 if c is None else c)
    model.set(**params)
    model.set_source_peakabsmag(peak_absmag, band, magsys, cosmo=cosmology or Planck18)
    lo, hi = model.minwave(), model.maxwave()
    lbda = np.asarray(lbda, dtype=float)
    keep = (lbda >= lo) & (lbda <= hi)
    if np.count_nonzero(keep) < 2:
        raise SpectrumError(f"redshift {redshift}: the sncosmo model {source!r} covers {lo:.0f}–{hi:.0f} Å "
                            f"(observer frame) at this redshift, outside the wavelength range "
                            f"{lbda[0]:.0f}–{lbda[-1]:.0f} Å: the redshift is outside the model's range")
    return lbda[keep], model.flux(phase, lbda[keep])


def normalise_to_mag(lbda, flux, mag, band="bessellb", magsys="ab"):
    """Scale factor 10^(−0.4 (mag − m_in)) with m_in the synthetic magnitude of (λ, F)."""
    import sncosmo
    try:
        m_in = sncosmo.Spectrum(lbda, flux).bandmag(band, magsys)
    except Exception as exc:
        raise SpectrumError(f"cannot compute the {band} {magsys} magnitude of the spectrum: {exc}") from exc
    if not np.isfinite(m_in):
        raise SpectrumError(f"spectrum has no flux in band {band!r}: cannot normalise to mag {mag}")
    return 10 ** (-0.4 * (mag - m_in)), m_in


class PointSource(Versioned):
    """A point source: spectrum (linear interpolation, NaN outside) at a position [cells]."""

    def __init__(self, lbda, flux, position=(0.0, 0.0), mag=None, band="bessellb", magsys="ab",
                 name="pointsource"):
        self.lbda_in, self.flux_in = validate_spectrum(lbda, flux, name)
        self.position = position
        self.name = name
        if mag is not None and (isinstance(mag, (bool, np.bool_)) or not isinstance(mag, (int, float, np.number))
                                or not np.isfinite(mag)):
            raise SpectrumError(f"mag must be a finite AB magnitude or None, got {mag!r}")
        self.mag, self.band = mag, band
        self.flux_ratio, self.native_mag = 1.0, None
        if mag is not None:
            self.flux_ratio, self.native_mag = normalise_to_mag(self.lbda_in, self.flux_in, mag, band, magsys)

    @classmethod
    def from_snia(cls, redshift, phase=0.0, source="hsiao-subsampled", position=(0.0, 0.0), **kwargs):
        lbda, flux = snia_spectrum(redshift, phase, source, **kwargs)
        obj = cls(lbda, flux, position=position, name=f"SN Ia z={redshift}")
        obj.redshift = redshift
        return obj

    @classmethod
    def from_blackbody(cls, temperature, mag, band="bessellb", lbda=None, position=(0.0, 0.0)):
        lbda = np.arange(3000.0, 20000.0, 10.0) if lbda is None else np.asarray(lbda, float)
        return cls(lbda, blackbody_flambda(lbda, temperature), position=position, mag=mag,
                   band=band, name=f"blackbody {temperature} K")

    def set_spectrum(self, lbda, flux, flux_ratio=None, native_mag=None):
        """Replace the spectrum in place (validated first; renormalised to ``mag`` when set,
        unless ``flux_ratio`` is given)."""
        lbda, flux = validate_spectrum(lbda, flux, self.name)
        if flux_ratio is None:
            flux_ratio, native_mag = (1.0, None) if self.mag is None else \
                normalise_to_mag(lbda, flux, self.mag, self.band)
        self.lbda_in, self.flux_in = lbda, flux
        self.flux_ratio, self.native_mag = flux_ratio, native_mag

    @property
    def position(self):
        """(x, y) [cells] relative to the field centre."""
        return self._position

    @position.setter
    def position(self, position):
        try:
            pos = tuple(float(p) for p in position)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"position must be (x, y) [cells], got {position!r}") from exc
        if len(pos) != 2 or not all(np.isfinite(pos)):
            raise ParameterError(f"position must be finite: two numbers (x, y) [cells], got {position!r}")
        self._position = pos

    def flambda(self, lbda):
        """F(λ) [erg/s/cm²/Å] at λ [Å]."""
        out = np.interp(lbda, self.lbda_in, self.flux_in, left=np.nan, right=np.nan)
        return out * self.flux_ratio

    def overlap(self, lo, hi):
        """True when the input spectrum overlaps [lo, hi] Å."""
        return self.lbda_in[0] < hi and self.lbda_in[-1] > lo
