"""SN Ia spectra of a population: sncosmo's model, vectorised over targets.

The observer-frame F_λ [erg/s/cm²/Å] follows sncosmo's model exactly (``Model._flux``)::

    F_obs(t, λ) = A · a · F_src(t_rest, a λ) · 10^(−0.4 A_host(a λ)) · 10^(−0.4 A_MW(λ)),  a = 1/(1+z)

with ``phase`` = t_rest the *rest-frame* days from B-band peak, and the amplitude A set
from the rest-frame peak magnitude in ``band``: m = M + μ(z) with μ the distance modulus of
``cosmology`` (``set_source_peakabsmag``); for SALT sources the Tripp relation M − α x1 + β c
(x0 from the standardised m_B, the SALT convention; x1, c only exist for SALT).  Dust (sncosmo
effects): host CCM89 in the rest frame, Milky Way F99 in the observer frame, each with E(B−V)
and R_V.  :func:`restframe_to_observed` moves a host's rest-frame SED to redshift z.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim.errors import ConfigError, ParameterError, SpectrumError
from slicersim.validation import MAX_REDSHIFT
from slicersim.sources.spectra import SNCOSMO_SNIA_MODELS, offline_names

__all__ = ["SNIaModel", "snia_fluxes", "model_fluxes", "cosmology", "restframe_to_observed"]

PC10_CM = 10 * 3.0856775814913673e18          # 10 pc [cm]


def cosmology(name):
    """The astropy cosmology realisation ``name`` (e.g. "Planck18")."""
    from astropy.cosmology import realizations
    if not isinstance(name, str) or name not in realizations.available:
        raise ConfigError(f"population.cosmology: unknown cosmology {name!r}; known: "
                          f"{', '.join(realizations.available)}")
    return getattr(realizations, name)


_SOURCES = {}


def _source(name):
    """The sncosmo source ``name`` (loaded once per process; SALT needs sncosmo's data)."""
    if name not in _SOURCES:
        from slicersim.sources.spectra import load_sncosmo_source
        try:
            _SOURCES[name] = load_sncosmo_source(name)
        except SpectrumError as exc:
            offline = ", ".join(k for k in SNCOSMO_SNIA_MODELS if k in offline_names())
            raise SpectrumError(f"{exc} — available offline: {offline}") from None
    return _SOURCES[name]


def _rest_peak_mag(source, band, magsys, x1=0.0, c=0.0):
    """Rest-frame peak magnitude of ``source`` at unit amplitude (x0 = 1, x1, c for SALT)."""
    src = source.__class__.__new__(source.__class__)
    src.__dict__.update(source.__dict__)
    src._parameters = source._parameters.copy()
    src._parameters[0] = 1.0
    if "x1" in src.param_names:
        src.set(x1=x1, c=c)
    return src.peakmag(band, magsys)


def _dust_curve(law, wave, r_v):
    """A_λ / E(B−V) of a sncosmo dust law at ``wave`` [Å] (linear in E(B−V) at fixed R_V)."""
    import sncosmo
    effect = {"ccm89": sncosmo.CCM89Dust, "f99": sncosmo.F99Dust}[law]()
    effect.set(ebv=1.0, r_v=r_v) if "r_v" in effect.param_names else effect.set(ebv=1.0)
    ok = (wave >= effect.minwave()) & (wave <= effect.maxwave())
    out = np.full(wave.shape, np.nan)
    out[ok] = -2.5 * np.log10(effect.propagate(wave[ok], np.ones(np.count_nonzero(ok))))
    return out


@dataclass(frozen=True)
class SNIaModel:
    """The SN Ia model shared by a population: sncosmo ``source``, the rest-frame ``band`` and
    ``magsys`` of the peak magnitude, the SALT standardisation ``alpha``, ``beta``, the
    ``cosmology`` (astropy name) and R_V of the Milky-Way (``mw_rv``, F99) and host (``host_rv``,
    CCM89) dust laws."""
    source: str = "hsiao-subsampled"
    band: str = "bessellb"
    magsys: str = "ab"
    alpha: float = 0.14
    beta: float = 3.1
    cosmology: str = "Planck18"
    mw_rv: float = 3.1
    host_rv: float = 3.1


def snia_fluxes(lbda, redshift, phase, peak_absmag, source="hsiao-subsampled", band="bessellb", magsys="ab",
                x1=None, c=None, mwebv=None, hostebv=None, **model):
    """Observer-frame SN Ia F_λ [erg/s/cm²/Å] (N, k) on ``lbda`` [Å]; NaN outside the model.

    redshift, phase (rest-frame days), peak_absmag: (N,) arrays; x1, c for SALT sources;
    mwebv / hostebv: E(B−V) of the Milky-Way (F99, observer frame) and host (CCM89, rest
    frame) dust; ``source``, ``band``, ``magsys`` and ``model`` (alpha, beta, cosmology, mw_rv,
    host_rv): the fields of :class:`SNIaModel`.  Equal to sncosmo.Model(source, effects).flux to
    rounding (tested)."""
    unknown = sorted(set(model) - set(SNIaModel.__dataclass_fields__))
    if unknown:
        raise ParameterError(f"snia_fluxes: unknown keyword(s) {', '.join(map(repr, unknown))}; valid: "
                             f"{', '.join(SNIaModel.__dataclass_fields__)}")
    return model_fluxes(lbda, SNIaModel(source, band, magsys, **model), redshift, phase, peak_absmag,
                        x1=x1, c=c, mwebv=mwebv, hostebv=hostebv)


def _amplitudes(src, model, z, absmag, x1, c):
    """Model amplitude per target (x0 for SALT sources): the peak magnitude, standardised
    (M − α x1 + β c) for SALT, moved to redshift z by the distance modulus."""
    mu = np.asarray(cosmology(model.cosmology).distmod(z).value, dtype=float)
    m0 = _rest_peak_mag(src, model.band, model.magsys)
    standardised = absmag - model.alpha * x1 + model.beta * c if "x1" in src.param_names else absmag
    return 10.0 ** (-0.4 * (standardised + mu - m0))


def _per_target(value, n, default=0.0):
    """(n,) float array of a per-target value (scalar broadcast; None → ``default``)."""
    return np.broadcast_to(np.asarray(default if value is None else value, dtype=float), (n,))


def _target_fluxes(src, lbda, z, phase, amplitude, salt_params, host_dust):
    """F_λ of each target in the observer frame on ``lbda`` (NaN outside the model's wavelengths
    or phases), before Milky-Way dust; ``host_dust`` = (E(B−V) per target or None, R_V)."""
    x1, c = salt_params
    hostebv, host_rv = host_dust
    a = 1.0 / (1.0 + z)
    out = np.full((z.size, lbda.size), np.nan)
    salt = "x1" in src.param_names
    params = src._parameters.copy()
    try:
        for i in range(z.size):
            rest = lbda * a[i]
            ok = (rest >= src.minwave()) & (rest <= src.maxwave())
            if not (src.minphase() <= phase[i] <= src.maxphase()) or np.count_nonzero(ok) < 2:
                continue
            src._parameters[0] = 1.0
            if salt:
                src.set(x1=x1[i], c=c[i])
            f = amplitude[i] * a[i] * src._flux(np.array([phase[i]]), rest[ok])[0]
            if hostebv is not None and hostebv[i] != 0:
                f = f * 10.0 ** (-0.4 * hostebv[i] * _dust_curve("ccm89", rest[ok], host_rv))
            out[i, ok] = f
    finally:
        src._parameters[:] = params
    return out


def model_fluxes(lbda, model, redshift, phase, peak_absmag, x1=None, c=None, mwebv=None, hostebv=None):
    """:func:`snia_fluxes` of an :class:`SNIaModel`: observer-frame F_λ [erg/s/cm²/Å] (N, k)."""
    lbda = np.asarray(lbda, dtype=float)
    z = np.atleast_1d(np.asarray(redshift, dtype=float))
    n = z.size
    if np.any(~(z > 0)):
        raise SpectrumError("redshift: SN Ia redshifts must be > 0")
    if np.any(z > MAX_REDSHIFT):
        raise SpectrumError(f"redshift: SN Ia redshifts must be ≤ {MAX_REDSHIFT:g}, the largest is {z.max():g}")
    src = _source(model.source)
    if "x1" not in src.param_names and (x1 is not None or c is not None):
        raise ConfigError(f"x1 / c are SALT parameters: sncosmo source {model.source!r} has none")
    x1, c = _per_target(x1, n), _per_target(c, n)
    amplitude = _amplitudes(src, model, z, _per_target(peak_absmag, n), x1, c)
    out = _target_fluxes(src, lbda, z, _per_target(phase, n), amplitude, (x1, c), (hostebv, model.host_rv))
    if mwebv is not None and np.any(np.asarray(mwebv) != 0):
        mw = _dust_curve("f99", lbda, model.mw_rv)[None, :] * _per_target(mwebv, n)[:, None]
        out *= 10.0 ** (-0.4 * mw)
    return out


def restframe_to_observed(lbda, rest_lbda, rest_flux, absmag, z, band, cosmo):
    """F_λ on ``lbda`` of a rest-frame SED scaled to ``absmag`` (AB) in rest-frame ``band``
    at redshift z: F_obs(λ) = F_10pc(λ/(1+z)) (10 pc / D_L)² / (1+z)."""
    import sncosmo
    m_in = sncosmo.Spectrum(rest_lbda, rest_flux).bandmag(band, "ab")
    scale = 10 ** (-0.4 * (absmag - m_in))
    dl_cm = cosmo.luminosity_distance(z).to_value("cm")
    flux = np.interp(lbda / (1 + z), rest_lbda, rest_flux * scale, left=np.nan, right=np.nan)
    return flux * (PC10_CM / dl_cm) ** 2 / (1 + z)
