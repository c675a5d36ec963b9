"""Source spectra: validated (λ, F) tables, point sources, any sncosmo source (SNe Ia),
black bodies, power laws and CALSPEC files.

Flux densities F(λ) are in erg/s/cm²/Å, wavelengths in Å.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from slicersim import validation
from slicersim.constants import C_LIGHT, H_PLANCK, K_BOLTZMANN
from slicersim.errors import ParameterError, SpectrumError
from slicersim.io.tables import check_increasing
from slicersim.physics.conventions import observer_days
from slicersim.sources.salt_files import SALT_PACKAGE, offline_salt_names, offline_salt_source
from slicersim.versioning import Versioned

__all__ = ["PointSource", "validate_spectrum", "snia_spectrum", "sncosmo_spectrum", "load_sncosmo_source",
           "blackbody_flambda", "powerlaw_flambda", "normalise_to_mag", "find_calspec_file", "read_calspec",
           "SNCOSMO_SNIA_MODELS", "SNCOSMO_OFFLINE", "offline_names", "POWERLAW_LAMBDA_REF", "CALSPEC_URL", "default_lbda",
           "MAX_FLAMBDA", "MIN_MAG", "check_flambda"]

#: the brightest point-source F_λ accepted [erg/s/cm²/Å]: 5× the Sun's at Earth (≈ 2e2 near 5000 Å),
#: so above any astronomical source; an H4RG pixel behind a 1-m telescope would fill its well
#: (~1e5 e-) within a microsecond of a 2.83 s frame, the samplers' range ends far below
MAX_FLAMBDA = 1e3
#: the brightest AB magnitude accepted (the Sun is about −26.7 AB at Earth)
MIN_MAG = -30.0

#: sncosmo SN Ia sources and whether they work offline without extra files (built into sncosmo);
#: the SALT ones do where ``jax-bandflux`` is installed (:func:`offline_names`)
SNCOSMO_SNIA_MODELS = {"hsiao-subsampled": True, "hsiao": False, "salt2": False,
                       "salt2-extended": False, "salt3": False, "salt3-nir": False}
#: sncosmo sources whose files ship inside the sncosmo package (every other one needs its data files)
SNCOSMO_OFFLINE = ("hsiao-subsampled",)
#: reference wavelength of the power law [Å] (slicersim 1.4.2's; it cancels in the normalisation)
POWERLAW_LAMBDA_REF = 5500.0
#: the CALSPEC archive (STScI): ``<star>_<instruments>_<version>.fits`` files
CALSPEC_URL = "https://archive.stsci.edu/hlsps/reference-atlases/cdbs/current_calspec/"


def offline_names():
    """sncosmo sources that load without a download here.

    Returns
    -------
    tuple of str
        :data:`SNCOSMO_OFFLINE` plus the SALT models whose template files are installed
        (:func:`slicersim.sources.salt_files.offline_salt_names`).
    """
    return SNCOSMO_OFFLINE + offline_salt_names()


def default_lbda():
    """Default wavelength grid of model spectra: 3000–19990 Å, 10 Å steps."""
    return np.arange(3000.0, 20000.0, 10.0)



def validate_spectrum(lbda, flux, name="spectrum"):
    """Check and return (λ, F) as float arrays; λ strictly increasing (else an error naming the first
    two samples out of order and their indices), F finite and ≥ 0."""
    lbda = validation.array(f"{name}: wavelengths", lbda, finite=False, error=SpectrumError)
    flux = validation.array(f"{name}: flux", flux, finite=False, error=SpectrumError)
    if lbda.ndim != 1 or lbda.size == 0:
        raise SpectrumError(f"{name}: wavelengths must be a non-empty 1-D array, got shape {lbda.shape}")
    if flux.shape != lbda.shape:
        raise SpectrumError(f"{name}: flux shape {flux.shape} differs from wavelength shape {lbda.shape}")
    if lbda.size < 2:
        raise SpectrumError(f"{name}: need at least 2 samples to interpolate")
    check_increasing(lbda, name, error=SpectrumError, label="index", first=0)
    if not np.all(np.isfinite(lbda)):
        raise SpectrumError(f"{name}: wavelengths must be finite and strictly increasing")
    if not np.all(np.isfinite(flux)):
        raise SpectrumError(f"{name}: flux contains {np.count_nonzero(~np.isfinite(flux))} NaN/inf value(s)")
    if np.any(flux < 0):
        raise SpectrumError(f"{name}: flux contains {np.count_nonzero(flux < 0)} negative value(s)")
    return lbda, flux


def check_flambda(name, flux):
    """SpectrumError naming ``name`` when the F_λ [erg/s/cm²/Å] ``flux`` exceeds :data:`MAX_FLAMBDA`."""
    peak = float(np.max(flux, initial=0.0))
    if peak > MAX_FLAMBDA:
        raise SpectrumError(f"{name}: F_λ reaches {peak:g} erg/s/cm²/Å, above {MAX_FLAMBDA:g} (5× the Sun's "
                            "F_λ at Earth: no astronomical source is brighter); give F_λ in erg/s/cm²/Å or "
                            "normalise the spectrum with mag=")
    return flux


def blackbody_flambda(lbda, temperature):
    """Black-body spectral shape B_λ(T) [erg/s/cm²/Å/sr] at λ [Å]."""
    temperature = validation.number("blackbody temperature", temperature, low=0.0, low_open=True, unit="K",
                                    error=SpectrumError)
    lbda_m = np.asarray(lbda, dtype=float) * 1e-10
    x = H_PLANCK * C_LIGHT / (lbda_m * K_BOLTZMANN * temperature)
    with np.errstate(over="ignore"):            # x ≫ 700 (cold body, short λ): exp overflows to inf → B = 0
        blam = 2 * H_PLANCK * C_LIGHT**2 / lbda_m**5 / np.expm1(x)  # W/m²/m/sr
    return blam * 1e3 * 1e-10  # erg/s/cm²/Å/sr  (W/m²/m = 1e3 erg/s/cm²/cm ... = 1e-7 erg/s/cm²/Å)


def powerlaw_flambda(lbda, alpha, lambda_ref=POWERLAW_LAMBDA_REF):
    """Power-law shape (λ / λ_ref)^α at λ [Å] (dimensionless): F_λ ∝ λ^α, i.e. F_ν ∝ λ^(α+2)
    (slicersim 1.4.2's convention: α is the F_λ index)."""
    alpha = validation.number("power-law index alpha", alpha, error=SpectrumError)
    with np.errstate(over="ignore", under="ignore", divide="ignore"):
        return (np.asarray(lbda, dtype=float) / lambda_ref) ** float(alpha)   # overflow: inf, refused by callers


def snia_spectrum(redshift, phase=0.0, source="hsiao-subsampled", peak_absmag=-19.3,
                  band="bessellb", magsys="ab", lbda=None, x1=None, c=None, cosmology=None, phase_frame="rest"):
    """SN Ia spectrum from sncosmo at ``phase`` days from B-band maximum.

    :func:`sncosmo_spectrum` with the peak absolute magnitude ``peak_absmag`` in rest-frame
    ``band``.  ``hsiao-subsampled`` is built into sncosmo and works offline; ``salt2``/``salt3``
    work offline where their template files are installed
    (:func:`~slicersim.sources.salt_files.offline_salt_source`), else raise a clear error.

    Parameters
    ----------
    redshift : float
        Redshift z, 0 < z ≤ 50.
    phase : float
        Days from B-band maximum [d], in ``phase_frame`` (default rest frame: the model is read
        at t = phase (1 + z) observer days).
    source : str, tuple or sncosmo.Source
        sncosmo SN Ia source (:func:`load_sncosmo_source`).
    peak_absmag : float
        Peak absolute magnitude in rest-frame ``band`` / ``magsys`` [mag].
    band, magsys : str
        sncosmo bandpass and magnitude system of ``peak_absmag``.
    lbda : array_like of shape (k,), optional
        Wavelengths [Å] (default 3000–19990 Å, 10 Å step).
    x1, c : float, optional
        SALT stretch and colour (default 0); only for SALT sources (ParameterError otherwise).
    cosmology : astropy.cosmology.Cosmology, optional
        For the distance modulus (default Planck18).
    phase_frame : {"rest", "obs"}
        Frame of ``phase`` (``slicersim.physics.conventions.phase_frame``: "rest" by default,
        "obs" under ``conventions="slicersim-1.0"``).

    Returns
    -------
    lbda : numpy.ndarray of shape (k',)
        The part of ``lbda`` the model covers at this redshift [Å].
    flux : numpy.ndarray of shape (k',)
        Observer-frame F_λ [erg/s/cm²/Å].
    """
    salt = "salt" in str(getattr(source, "name", source)).lower()
    if not salt and (x1 is not None or c is not None):
        raise ParameterError(f"x1 / c are SALT parameters: sncosmo source {source!r} has none "
                             "(use source='salt2' or 'salt3', or drop them)")
    params = {"x1": 0.0 if x1 is None else x1, "c": 0.0 if c is None else c} if salt else None
    return sncosmo_spectrum(source, redshift, phase, peak_absmag=peak_absmag, band=band, magsys=magsys,
                            params=params, cosmology=cosmology, lbda=lbda, phase_frame=phase_frame)


def sncosmo_spectrum(source, redshift, phase=0.0, peak_absmag=None, band="bessellb", magsys="ab",
                     params=None, cosmology=None, lbda=None, phase_frame="rest"):
    """Observer-frame spectrum of any sncosmo source at ``redshift`` and ``phase``.

    ``sncosmo.Model(source)`` with t0 = 0, read at t = phase (1 + z) observer days for a
    rest-frame ``phase`` (the default; t = phase for ``phase_frame="obs"``, slicersim 1.0's
    reading), on the part of ``lbda`` the model covers.

    Parameters
    ----------
    source : str, tuple or sncosmo.Source
        A registry name, a (name, version) pair or a ``sncosmo.Source`` (your own files, e.g.
        ``sncosmo.TimeSeriesSource``); see :func:`load_sncosmo_source`.
    redshift : float
        Redshift z, 0 < z ≤ 50.
    phase : float
        Days from the model's t0 (maximum light for SNe, merger for kilonovae) [d], in ``phase_frame``.
    peak_absmag : float, optional
        Peak absolute magnitude in rest-frame ``band`` / ``magsys`` (``Model.set_source_peakabsmag``,
        distance modulus of ``cosmology``, default Planck18); None keeps the source's own amplitude.
    band, magsys : str
        sncosmo bandpass and magnitude system of ``peak_absmag``.
    params : dict, optional
        The source's own parameters, e.g. {"x1": 1.0, "c": 0.1} (SALT), {"theta": 30} (kilonova).
    cosmology : astropy.cosmology.Cosmology, optional
        Default Planck18.
    lbda : array_like of shape (k,), optional
        Wavelengths [Å] (default 3000–19990 Å, 10 Å).
    phase_frame : {"rest", "obs"}
        Frame of ``phase`` (``slicersim.physics.conventions.phase_frame``).

    Returns
    -------
    lbda : numpy.ndarray of shape (k',)
        The covered part of ``lbda`` [Å].
    flux : numpy.ndarray of shape (k',)
        F_λ [erg/s/cm²/Å].
    """
    import sncosmo
    from astropy.cosmology import Planck18
    redshift = validation.redshift("redshift", redshift, error=SpectrumError)
    if isinstance(phase, (bool, np.bool_)) or not isinstance(phase, (int, float, np.number)) \
            or not np.isfinite(phase):
        raise SpectrumError(f"phase must be a finite number of days, got {phase!r}")
    if peak_absmag is not None and (isinstance(peak_absmag, (bool, np.bool_)) or not isinstance(
            peak_absmag, (int, float, np.number)) or not np.isfinite(peak_absmag)):
        raise SpectrumError(f"peak_absmag must be a finite magnitude or None, got {peak_absmag!r}")
    lbda = default_lbda() if lbda is None else np.asarray(lbda, dtype=float)
    model = sncosmo.Model(load_sncosmo_source(source))
    params = dict(params or {})
    settable = [p for p in model.param_names if p not in ("z", "t0")]
    bad = [k for k, v in params.items() if k not in settable or isinstance(v, (bool, np.bool_))
           or not isinstance(v, (int, float, np.number)) or not np.isfinite(v)]
    if bad:
        raise ParameterError(f"invalid parameter(s) {bad} of sncosmo source {_source_label(source)!r}: "
                             f"its parameters are {', '.join(settable)} (finite numbers)")
    model.set(z=redshift, t0=0.0, **params)
    if peak_absmag is not None:
        try:
            model.set_source_peakabsmag(peak_absmag, band, magsys, cosmo=cosmology or Planck18)
        except Exception as exc:
            raise SpectrumError(f"cannot normalise {_source_label(source)!r} to peak absolute magnitude "
                                f"{peak_absmag} in {band!r} ({magsys}): {type(exc).__name__}: {exc}") from exc
    time = observer_days(float(phase), redshift, phase_frame)     # [observer-frame days from t0]
    if not model.mintime() <= time <= model.maxtime():        # sncosmo would repeat its first or last epoch
        scale, where = (1.0 + redshift, "rest frame") if phase_frame == "rest" else \
            (1.0, f"observer frame at redshift {redshift:g}")
        raise SpectrumError(f"phase {validation.short_repr(phase)} days is outside the range {model.mintime() / scale:g} "
                            f"to {model.maxtime() / scale:g} days ({where}) of the sncosmo model "
                            f"{_source_label(source)!r}")
    lo, hi = model.minwave(), model.maxwave()
    keep = (lbda >= lo) & (lbda <= hi)
    if np.count_nonzero(keep) < 2:
        raise SpectrumError(f"redshift {redshift:g}: the sncosmo model {_source_label(source)!r} covers "
                            f"{lo:g}–{hi:g} Å (observer frame) at this redshift, outside the wavelength "
                            f"range {lbda[0]:g}–{lbda[-1]:g} Å: the redshift is outside the model's range")
    return lbda[keep], model.flux(time, lbda[keep])


def _source_label(source):
    name = getattr(source, "name", None) if not isinstance(source, (str, tuple)) else source
    return name if isinstance(name, str) else str(source)


def load_sncosmo_source(source):
    """A ``sncosmo.Source`` from a registry name, a (name, version) pair or a Source (returned as is).

    Only the sources in :data:`SNCOSMO_OFFLINE` ship inside sncosmo; ``salt2``, ``salt3`` and
    ``salt3-nir`` load offline from the template files of the ``jax-bandflux`` package where it is
    installed (:mod:`slicersim.sources.salt_files`); the others load from sncosmo's data
    directory, which sncosmo fills by downloading.  When that fails, or the
    name is unknown, SpectrumError says (in one line) which source and how to provide it."""
    import sncosmo
    if isinstance(source, sncosmo.Source):
        return source
    name, version = source if isinstance(source, tuple) and len(source) == 2 else (source, None)
    if not isinstance(name, str) or not name.strip() or not (version is None or isinstance(version, str)):
        raise SpectrumError(f"an sncosmo source is a name, a (name, version) pair or a sncosmo.Source, "
                            f"got {source!r}")
    offline = offline_salt_source(name, version)      # SALT templates installed as package data
    if offline is not None:
        return offline
    try:
        return sncosmo.get_source(name, version=version)
    except Exception as exc:
        raise SpectrumError(_missing_source_message(name, version, exc)) from exc


def _missing_source_message(name, version, exc):
    """One line: the source, why it failed and how to provide its files."""
    label = name if version is None else f"{name}, version {version}"
    cause = " ".join(f"{type(exc).__name__}: {exc}".split())[:160]
    own = "pass a sncosmo.Source built from your own files (e.g. sncosmo.TimeSeriesSource(phase, wave, flux))"
    known, relpath = _sncosmo_registry_entry(name, version)
    if known is False:
        return (f'sncosmo source "{label}" is not a name sncosmo knows (its list of built-in sources) — '
                f"available offline: {', '.join(offline_names())}; for a model of your own, {own}")
    where = relpath or "its files"
    try:
        from sncosmo.builtins import DATADIR
        datadir, remote = DATADIR.rootdir(), DATADIR._remote_root
    except Exception:  # noqa: BLE001  (sncosmo internals differ between versions)
        datadir, remote = "sncosmo's data directory", "https://sncosmo.github.io/data/"
    salt = (f"; for SALT2/SALT3 offline, `pip install --no-deps {SALT_PACKAGE}` (its template files)"
            if name.lower().startswith("salt") else "")
    return (f'sncosmo source "{label}" could not be loaded (needs download; offline?) — available offline: '
            f"{', '.join(offline_names())}{salt}.  To provide it, put sncosmo's {where!r} (downloaded from "
            f"{remote}, a folder comes as .tar.gz) under {datadir} or set SNCOSMO_DATA_DIR to a folder "
            f"holding it, or {own} ({cause})")


def _sncosmo_registry_entry(name, version):
    """(known, relative data path) of a source in sncosmo's registry; (None, None) if unknown here."""
    try:
        from sncosmo.models import _SOURCES
        loaders = dict(_SOURCES._loaders)
    except Exception:  # noqa: BLE001  (private registry layout)
        return None, None
    keys = [k for k in loaders if k[0] == name.lower() and (version is None or k[1] == version)]
    if not keys:
        return False, None
    args = loaders[max(keys, key=lambda k: str(k[1]))][1]
    return True, next((a for a in args if isinstance(a, str) and "/" in a), None)


def find_calspec_file(name, calspec_dir=None):
    """Path of a CALSPEC FITS file: ``name`` itself when it is a file, else the last (latest
    version) ``<name>*.fits`` in ``calspec_dir`` or $SLICERSIM_CALSPEC_DIR (case-insensitive
    prefix, e.g. ``"bd_17d4708"``).  SpectrumError, saying where to download it, when absent."""
    if not isinstance(name, (str, os.PathLike)) or not str(name).strip():
        raise SpectrumError(f"a CALSPEC star is a name (e.g. 'bd_17d4708') or a FITS path, got {name!r}")
    if os.path.lexists(name) and not os.path.isdir(name):
        return Path(validation.regular_file("CALSPEC file", name, error=SpectrumError))   # no FIFO, device
    folder = calspec_dir if calspec_dir is not None else os.environ.get("SLICERSIM_CALSPEC_DIR")
    how = (f"download it from {CALSPEC_URL} and pass its path, or calspec_dir= (or $SLICERSIM_CALSPEC_DIR) "
           "naming the folder that holds it")
    if folder is None:
        raise SpectrumError(f"CALSPEC star {str(name)!r}: no such file and no CALSPEC folder given; {how}")
    if not Path(folder).is_dir():
        raise SpectrumError(f"CALSPEC star {str(name)!r}: the CALSPEC folder {str(folder)!r} does not exist; {how}")
    prefix = Path(name).name.lower()
    found = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.name.lower().startswith(prefix)
                   and p.name.lower().endswith((".fits", ".fits.gz")))
    if not found:
        raise SpectrumError(f"CALSPEC star {str(name)!r}: no file {prefix}*.fits in {str(folder)!r}; {how}")
    return found[-1]


def read_calspec(path):
    """(λ [Å], F_λ [erg/s/cm²/Å]) of a CALSPEC FITS file: the first table with WAVELENGTH
    (Å) and FLUX (FLAM) columns; units other than those raise SpectrumError."""
    from astropy.io import fits
    try:
        with fits.open(path) as hdus:
            for hdu in hdus:
                cols = getattr(hdu, "columns", None)
                names = [c.name.upper() for c in cols] if cols is not None else []
                if "WAVELENGTH" in names and "FLUX" in names:
                    units = {c.name.upper(): (c.unit or "").strip().lower() for c in cols}
                    lbda = np.array(hdu.data.field(names.index("WAVELENGTH")), dtype=float)
                    flux = np.array(hdu.data.field(names.index("FLUX")), dtype=float)
                    break
            else:
                raise SpectrumError(f"{path}: no table with WAVELENGTH and FLUX columns (CALSPEC layout)")
    except OSError as exc:
        raise SpectrumError(f"{path}: not a readable FITS file ({exc})") from exc
    if units["WAVELENGTH"] not in ("", "angstroms", "angstrom", "a"):
        raise SpectrumError(f"{path}: WAVELENGTH in {units['WAVELENGTH']!r}, expected Angstroms (CALSPEC)")
    if units["FLUX"] not in ("", "flam", "erg/s/cm2/a", "erg/(s cm2 angstrom)", "erg s-1 cm-2 angstrom-1"):
        raise SpectrumError(f"{path}: FLUX in {units['FLUX']!r}, expected FLAM = erg/s/cm²/Å (CALSPEC)")
    return validate_spectrum(lbda, flux, name=str(path))


def normalise_to_mag(lbda, flux, mag, band="bessellb", magsys="ab"):
    """Scale factor 10^(−0.4 (mag − m_in)) with m_in the synthetic magnitude of (λ, F).

    ``band`` / ``magsys`` are sncosmo names (strings; ParameterError otherwise)."""
    import sncosmo
    if not isinstance(band, str) or not isinstance(magsys, str):
        raise ParameterError(f"band and magsys must be sncosmo names (strings), got band={band!r}, magsys={magsys!r}")
    try:
        with np.errstate(divide="ignore"):      # no flux in the band: log10(0) = −inf, reported below
            m_in = sncosmo.Spectrum(lbda, flux).bandmag(band, magsys)
    except Exception as exc:
        raise SpectrumError(f"cannot compute the {band} {magsys} magnitude of the spectrum: {exc}") from exc
    if not np.isfinite(m_in):
        found = (f"its flux overflows the integral (F_λ up to {float(np.max(flux)):g})" if m_in < 0 else
                 "its flux in the band is 0")
        raise SpectrumError(f"spectrum has no usable flux in band {band!r} ({found}): cannot normalise to mag "
                            f"{mag:g}")
    exponent = -0.4 * (mag - m_in)
    if exponent > 300:
        raise SpectrumError(f"normalising the spectrum (magnitude {m_in:g} in {band!r}) to mag {mag:g} needs a "
                            f"factor 1e{exponent:.0f}: give F_λ in erg/s/cm²/Å")
    return 10 ** exponent, m_in


class PointSource(Versioned):
    """A point source: spectrum (linear interpolation, NaN outside) at a position [cells].

    Parameters
    ----------
    lbda : array_like of shape (n,)
        Wavelengths of the spectrum [Å].
    flux : array_like of shape (n,)
        F_λ [erg/s/cm²/Å].
    position : tuple of float, optional
        (x, y) of the source in the field [cells].
    mag : float, optional
        Magnitude the spectrum is normalised to in ``band`` (``magsys``); the spectrum is
        used as given when None.
    band : str, optional
        sncosmo bandpass of that normalisation.
    magsys : str, optional
        sncosmo magnitude system of that normalisation.
    name : str, optional
        Label of the source in messages and figures.
    """

    def __init__(self, lbda, flux, position=(0.0, 0.0), mag=None, band="bessellb", magsys="ab",
                 name="pointsource"):
        self.lbda_in, self.flux_in = validate_spectrum(lbda, flux, name)
        self.position = position
        self.name = name
        if mag is not None:
            mag = validation.number("mag [AB]", mag, error=SpectrumError)
            if mag < MIN_MAG:
                raise SpectrumError(f"mag [AB] must be ≥ {MIN_MAG:g} (the Sun is about −26.7 AB), got {mag:g}")
        self.mag, self.band = mag, band
        self.flux_ratio, self.native_mag = 1.0, None
        if mag is not None:
            self.flux_ratio, self.native_mag = normalise_to_mag(self.lbda_in, self.flux_in, mag, band, magsys)
        check_flambda(f"{name} spectrum", self.flux_in * self.flux_ratio)

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
        unless ``flux_ratio`` is given).

        Parameters
        ----------
        lbda : array_like of shape (n,)
            Wavelengths [Å].
        flux : array_like of shape (n,)
            F_λ [erg/s/cm²/Å].
        flux_ratio : float, optional
            Factor applied to ``flux`` (≥ 0) instead of the renormalisation.
        native_mag : float, optional
            Magnitude of the spectrum before that factor (recorded).

        Returns
        -------
        None
            Changed in place.
        """
        lbda, flux = validate_spectrum(lbda, flux, self.name)
        if flux_ratio is not None:
            flux_ratio = validation.number("flux_ratio", flux_ratio, low=0.0, error=SpectrumError)
        if flux_ratio is None:
            flux_ratio, native_mag = (1.0, None) if self.mag is None else \
                normalise_to_mag(lbda, flux, self.mag, self.band)
        check_flambda(f"{self.name} spectrum", flux * flux_ratio)
        self.lbda_in, self.flux_in = lbda, flux
        self.flux_ratio, self.native_mag = flux_ratio, native_mag

    @property
    def position(self):
        """(x, y) [cells] relative to the field centre."""
        return self._position

    @position.setter
    def position(self, position):
        if isinstance(position, (str, bytes)) or not hasattr(position, "__len__") or len(position) != 2:
            raise ParameterError(f"position must be (x, y) [cells], got {validation.short_repr(position)}")
        self._position = (validation.number("position", position[0]),     # x [cells]
                          validation.number("position", position[1]))     # y [cells]

    def flambda(self, lbda):
        """F(λ) [erg/s/cm²/Å] at λ [Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            F_λ [erg/s/cm²/Å] (NaN outside the input spectrum).
        """
        out = np.interp(lbda, self.lbda_in, self.flux_in, left=np.nan, right=np.nan)
        return out * self.flux_ratio

    def overlap(self, lo, hi):
        """True when the input spectrum overlaps [lo, hi] Å.

        Parameters
        ----------
        lo, hi : float
            The band [Å].

        Returns
        -------
        bool
            Whether they overlap.
        """
        return self.lbda_in[0] < hi and self.lbda_in[-1] > lo
