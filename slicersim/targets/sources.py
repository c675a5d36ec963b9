"""More target kinds: power laws, any sncosmo source by name, kilonovae and CALSPEC stars from files.

Every spectrum is in the observer frame [erg/s/cm²/Å] and normalised when the target is
built; offline, sncosmo serves ``hsiao-subsampled`` and the Bessell bands only (a source or
band that needs a download raises SpectrumError saying how to provide its files).

* :class:`PowerLaw` — F_λ ∝ (λ / 5500 Å)^α (slicersim 1.4.2's convention), ``mag`` in ``band``;
* :class:`SncosmoTarget` — ``sncosmo.Model(source)`` at a redshift and phase;
* :class:`Kilonova` — a POSSIS model file (``slicersim.sources.kilonova``) through sncosmo;
* :class:`CalSpec` — a CALSPEC FITS file (absolute flux; optional renormalisation).

Each has a ``Lazuli*`` variant (Lazuli IFS, CBE configuration, narrow field by default).
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.names import check_parameter_names
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, phase_frame
from slicersim.sources.spectra import (find_calspec_file, load_sncosmo_source, normalise_to_mag,
                                       powerlaw_flambda, read_calspec, sncosmo_spectrum, validate_spectrum)
from slicersim.targets.base import Target, _Lazuli, lazuli_doc
from slicersim.targets.state import check_redshift

__all__ = ["PowerLaw", "SncosmoTarget", "Kilonova", "CalSpec", "LazuliPowerLaw", "LazuliSncosmoTarget",
           "LazuliKilonova", "LazuliCalSpec", "powerlaw_grid", "check_mag", "TARGET_OPTIONS"]


def powerlaw_grid():
    """Default wavelength grid of a power law [Å]: 1000–30000 Å in 5 Å steps."""
    return np.arange(1000.0, 30000.0 + 2.5, 5.0)


def check_mag(mag, name="mag", required=False):
    """A magnitude: a finite number (None allowed unless ``required``); ParameterError naming ``name``."""
    if mag is None and not required:
        return None
    return validation.number(name, mag)


#: the keywords every target passes on to :class:`~slicersim.targets.base.Target` (``**target``)
TARGET_OPTIONS = ("config", "field", "position", "conventions", "host")


def _target_options(target):
    """``**target`` of a source constructor, checked: only :data:`TARGET_OPTIONS` (ParameterError
    naming the unknown keyword otherwise), with the Target defaults for the missing ones."""
    check_parameter_names("target", target, TARGET_OPTIONS)
    return {"config": None, "field": "default", "position": (0.0, 0.0), "conventions": DEFAULT_CONVENTIONS,
            "host": None, **target}


class PowerLaw(Target):
    """F_λ = F_0 (λ / 5500 Å)^α [erg/s/cm²/Å] (F_ν ∝ λ^(α+2)), F_0 such that the spectrum has
    magnitude ``mag`` in ``band`` / ``magsys`` (sncosmo synthetic photometry on ``lbda``).

    Parameters
    ----------
    alpha : float
        Power-law index α of F_λ.
    mag : float
        Magnitude of the spectrum in ``band`` / ``magsys`` [mag].
    band : str, optional
        sncosmo band (default ``"bessellr"``; slicersim 1.4.2's ``"sdssr"`` needs a download).
    magsys : str, optional
        sncosmo magnitude system.
    lbda : array_like of shape (n,), optional
        Wavelength grid [Å]; defaults to ``powerlaw_grid()`` and must cover the band.
    config, field, position, conventions, host
        As :class:`~slicersim.Target`.
    redshift : float, optional
        Only a label for ``frame="rest"`` bands.
    """

    def __init__(self, alpha, mag, band="bessellr", magsys="ab", lbda=None, config=None, field="default",
                 position=(0.0, 0.0), redshift=None, conventions=DEFAULT_CONVENTIONS, host=None):
        mag = check_mag(mag, required=True)
        lbda = powerlaw_grid() if lbda is None else lbda
        lbda, shape = validate_spectrum(lbda, powerlaw_flambda(lbda, alpha), "power law")
        ratio, _ = normalise_to_mag(lbda, shape, mag, band, magsys)
        self.alpha, self.mag, self.band, self.magsys = float(alpha), mag, band, magsys
        super().__init__(lbda, shape * ratio, config=config, field=field, position=position,
                         redshift=redshift, conventions=conventions, host=host)


class SncosmoTarget(Target):
    """Any sncosmo source at ``redshift`` and ``phase`` [rest-frame days from t0 = 0]:
    F_λ = ``sncosmo.Model(source).flux(phase (1 + z), λ)`` (``slicersim.sources.spectra.sncosmo_spectrum``;
    under ``conventions="slicersim-1.0"`` ``phase`` is observer-frame days, as in slicersim 1.0).

    ``update(redshift=...)`` recomputes the spectrum with the same normalisation rule.

    Parameters
    ----------
    source : str, tuple or sncosmo.Source
        A registry name (e.g. ``"hsiao-subsampled"``, ``"salt3"`` when its files are here),
        a (name, version) pair, or a ``sncosmo.Source`` built from your own files.
    redshift : float
        Redshift z.
    phase : float, optional
        Rest-frame days from t0 = 0 [d].
    peak_absmag : float, optional
        Peak absolute magnitude in rest-frame ``band`` [AB mag] (``set_source_peakabsmag``,
        ``cosmology`` default Planck18); exactly one of ``peak_absmag`` and ``mag``.
    mag : float, optional
        Apparent magnitude of the observed spectrum at ``phase`` in observer-frame ``band``.
    band : str, optional
        sncosmo band of the normalisation.
    magsys : str, optional
        sncosmo magnitude system of the normalisation.
    params : dict, optional
        The source's parameters, e.g. {"x1": 1, "c": 0.1} for SALT (finite numbers).
    cosmology : astropy.cosmology.Cosmology, optional
        Cosmology of ``peak_absmag`` (default Planck18).
    **target
        ``config``, ``field``, ``position``, ``conventions``, ``host`` as
        :class:`~slicersim.Target` (keywords).
    """

    def __init__(self, source, redshift, phase=0.0, peak_absmag=None, mag=None, band="bessellb", magsys="ab",
                 params=None, cosmology=None, **target):
        peak_absmag, mag = check_mag(peak_absmag, "peak_absmag"), check_mag(mag)
        if (peak_absmag is None) == (mag is None):
            raise ParameterError("give exactly one normalisation: peak_absmag (rest-frame peak absolute "
                                 f"magnitude) or mag (observed magnitude at this phase), got {peak_absmag=}, {mag=}")
        redshift = check_redshift(redshift)
        if redshift is None:
            raise ParameterError("an sncosmo source needs a redshift > 0")
        if params is not None and not isinstance(params, dict):
            raise ParameterError(f"params must be a dict of source parameters, got {validation.short_repr(params)}")
        self.source = load_sncosmo_source(source)
        self.phase, self.peak_absmag, self.mag, self.band, self.magsys = phase, peak_absmag, mag, band, magsys
        self.params, self.cosmology = dict(params or {}), cosmology
        self.phase_frame = phase_frame(_target_options(target)["conventions"])
        lbda, flux = self._spectrum_at(redshift)
        super().__init__(lbda, flux, redshift=redshift, **_target_options(target))

    def _spectrum_at(self, redshift):
        lbda, flux = sncosmo_spectrum(self.source, redshift, self.phase, peak_absmag=self.peak_absmag,
                                      band=self.band, magsys=self.magsys, params=self.params,
                                      cosmology=self.cosmology, phase_frame=self.phase_frame)
        if self.mag is not None:
            flux = flux * normalise_to_mag(lbda, flux, self.mag, self.band, self.magsys)[0]
        return lbda, flux


class Kilonova(SncosmoTarget):
    """Kilonova from a POSSIS model file (``.txt`` or ``.fits``; ``slicersim.sources.kilonova``)
    at ``redshift``, ``phase`` [rest-frame days since merger; observer-frame under
    ``conventions="slicersim-1.0"``] and viewing angle ``theta``
    [deg, 0 pole-on … 90 edge-on].

    Normalised to ``peak_absmag`` (default −15.8, slicersim 1.4.2's) in rest-frame ``band``
    (default ``"bessellr"``; 1.4.2's ``"sdssr"`` needs a download), or to the observed ``mag``
    at ``phase`` when given (1.4.2's ``mag`` is instead a rest-frame peak magnitude).
    No model ships with slicersim: a missing file raises SpectrumError saying where to get one.

    Parameters
    ----------
    model : str or path-like
        The POSSIS model file (``.txt`` or ``.fits``).
    redshift : float, optional
        Redshift z.
    phase : float, optional
        Rest-frame days since merger [d] (observer frame under
        ``conventions="slicersim-1.0"``).
    theta : float or astropy.units.Quantity, optional
        Viewing angle [deg, 0 pole-on … 90 edge-on] (a Quantity is converted to degrees).
    peak_absmag : float, optional
        Peak absolute magnitude in rest-frame ``band`` [AB mag].
    mag : float, optional
        Instead: observed magnitude at ``phase`` in ``band`` [AB mag].
    band : str, optional
        sncosmo band of the normalisation.
    magsys : str, optional
        sncosmo magnitude system of the normalisation.
    cosmology : astropy.cosmology.Cosmology, optional
        Cosmology of the distance (default Planck18).
    **target
        ``config``, ``field``, ``position``, ``conventions``, ``host`` as
        :class:`~slicersim.Target` (keywords).
    """

    def __init__(self, model, redshift=0.2, phase=1.4, theta=0.0, peak_absmag=-15.8, mag=None, band="bessellr",
                 magsys="ab", cosmology=None, **target):
        theta = validation.number("theta", theta, low=0.0, high=180.0, unit="deg")
        from slicersim.sources.kilonova import kilonova_source
        self.model, self.theta = model, theta
        super().__init__(kilonova_source(model), redshift, phase, peak_absmag=None if mag is not None else peak_absmag,
                         mag=mag, band=band, magsys=magsys, params={"theta": theta}, cosmology=cosmology,
                         **_target_options(target))


class CalSpec(Target):
    """CALSPEC spectrophotometric standard from a FITS file (absolute F_λ, no redshift).

    Parameters
    ----------
    name : str or path-like
        A FITS path, or a star name (file-name prefix, e.g. ``"bd_17d4708"``) looked up in
        ``calspec_dir`` or $SLICERSIM_CALSPEC_DIR (latest version wins;
        ``slicersim.sources.spectra.find_calspec_file``).
    calspec_dir : str or path-like, optional
        Directory of the CALSPEC FITS files.
    mag : float, optional
        AB magnitude in ``band`` the spectrum is renormalised to (none by default).
    band : str, optional
        sncosmo band of that renormalisation.
    config, field, position, conventions
        As :class:`~slicersim.Target`.
    redshift, host
        ``host`` (and the ``redshift`` a host by name needs) as for every target
        (:meth:`Target.set_host <slicersim.Target.set_host>`)."""

    def __init__(self, name, calspec_dir=None, mag=None, band="bessellb", config=None, field="default",
                 position=(0.0, 0.0), conventions=DEFAULT_CONVENTIONS, redshift=None, host=None):
        self.path = find_calspec_file(name, calspec_dir)
        lbda, flux = read_calspec(self.path)
        self.star = str(name)
        super().__init__(lbda, flux, mag=check_mag(mag), band=band, config=config, field=field,
                         position=position, conventions=conventions, redshift=redshift, host=host)


class LazuliPowerLaw(_Lazuli, PowerLaw):
    __doc__ = lazuli_doc(PowerLaw, "Power law observed with the Lazuli IFS.")


class LazuliSncosmoTarget(_Lazuli, SncosmoTarget):
    __doc__ = lazuli_doc(SncosmoTarget, "sncosmo source observed with the Lazuli IFS.")


class LazuliKilonova(_Lazuli, Kilonova):
    __doc__ = lazuli_doc(Kilonova, "Kilonova observed with the Lazuli IFS.")


class LazuliCalSpec(_Lazuli, CalSpec):
    __doc__ = lazuli_doc(CalSpec, "CALSPEC standard star observed with the Lazuli IFS.")
