"""Named galaxy models: Sersic profiles, black bodies and real nearby galaxies.

A model is named ``"spatial:spectral"`` as in slicersim 1.4.2:

* spatial: ``"sersic"`` (analytic, :class:`~slicersim.sources.extended.SersicProfile`) or
  an NGC name (its r-band image, :class:`~slicersim.sources.extended.ImageProfile`);
* spectral: ``"bb"`` / ``"blackbody"`` with an optional temperature ``"bb-6000"`` [K], or an
  NGC name (its rest-frame spectral template);
* a bare NGC name ``"ngc0628"`` means ``"ngc0628:ngc0628"``, a bare ``"sersic"`` means
  ``"sersic:bb-5000"``.

Real galaxies come from the optional package ``lazuli-astrosim-data`` (``pip install
'slicersim[galaxies]'``; offline): 90 NGC spectra (Brown et al. 2014 atlas, treated as
rest-frame templates) of which 63 have a Legacy Surveys DR10 r-band image (nanomaggy,
``PIXSCALE`` [arcsec], ``REDSHIFT``, ``XCENTER``/``YCENTER``).  We use it rather than GalSim:
GalSim's real-galaxy catalogues (COSMOS) must be downloaded, and its parametric profiles add
nothing to our exact Sersic integration.

:class:`GalaxyModel` holds the physical, redshift-independent description (proper half-light
radius ``r_kpc``, luminosity through ``magabs``); :meth:`GalaxyModel.host` renders it at a
redshift (:mod:`slicersim.sources.cosmology`): angles ∝ 1/D_A, F_λ ∝ 1/(D_L² (1+z)),
λ ∝ (1+z).  An NGC image keeps its physical size: its pixel scale at z is
``PIXSCALE`` · D_A(z_gal)/D_A(z), so z must exceed the galaxy's own redshift.
"""
from __future__ import annotations

import copy
import functools
import math
import numbers
import re

import numpy as np

from slicersim import validation
from slicersim.errors import GalaxyDataUnavailable, ParameterError
from slicersim.sources.cosmology import (angular_diameter_distance_kpc, arcsec_per_kpc, check_source_redshift,
                                         get_cosmology, redshift_scalings, restframe_to_observed)
from slicersim.sources.extended import CubeSource, Host, ImageProfile, SersicProfile, host_field_fraction
from slicersim.sources.spectra import blackbody_flambda, validate_spectrum

__all__ = ["GALAXY_PACKAGE", "GalaxyDataUnavailable", "known_galaxies", "galaxy_name", "load_galaxy_spectrum",
           "load_galaxy_image", "parse_host_model", "GalaxyModel", "HOST_DEFAULTS", "HOST_PARAMETERS", "HostPlacement",
           "check_host_covers", "host_offset", "check_host_in_field", "HOST_MIN_FIELD_FRACTION", "own_copy"]

GALAXY_PACKAGE = "lazuli-astrosim-data"
#: slicersim 1.4.2 defaults (``band`` is Bessell R here: sncosmo's SDSS r needs a download)
HOST_DEFAULTS = {"r_kpc": 5.0, "sersic_index": 2.0, "axis_ratio": 0.7, "position_angle": -30.0,
                 "rotation": 0.0, "magabs": -21.0, "band": "bessellr", "temperature": 5000.0}
#: slicersim 1.4.2 parameter names → ours
ALIASES = {"n": "sersic_index", "theta": "position_angle"}
PARAMETERS = ("refmodel", "redshift", "cosmology", "r_kpc", "r_eff", "sersic_index", "ellip", "axis_ratio",
              "position_angle", "rotation", "magabs", "mag", "band", "temperature", "offset", "position") \
    + tuple(ALIASES)
#: parameter pairs that say the same thing: giving both is refused (never one silently wins)
CONFLICTS = (("mag", "magabs", "mag (observed) or magabs (rest frame)"),
             ("offset", "position", "offset [arcsec, relative to the target] or position [cells]"),
             ("r_kpc", "r_eff", "r_kpc [proper kpc] or r_eff [arcsec]"),
             ("ellip", "axis_ratio", "ellip or axis_ratio"),
             ("n", "sersic_index", "n or sersic_index (the same parameter)"),
             ("theta", "position_angle", "theta or position_angle (the same parameter)"))
#: a host putting less than this fraction of its light in the field is refused
HOST_MIN_FIELD_FRACTION = 1e-6
_NGC = re.compile(r"^ngc[\s_]*0*(\d{1,4})(?:[\s_]*([a-z]))?$")
_REST_BB_LBDA = np.geomspace(100.0, 1.0e5, 8000)          # rest-frame black-body grid [Å]


def _data_dir():
    try:
        from lazuli_astrosim_data.io import PACKAGE_PATH
    except ImportError:
        raise GalaxyDataUnavailable(f"named real galaxies (NGC images and spectra) need the optional package "
                                    f"{GALAXY_PACKAGE}: pip install 'slicersim[galaxies]' (or pip install "
                                    f"{GALAXY_PACKAGE}); 'sersic' and 'bb-<T>' models need nothing") from None
    return PACKAGE_PATH.joinpath("data", "ngc")


def _file_stem(name):
    return "ngc_" + name[3:]


@functools.lru_cache(maxsize=2)
def known_galaxies(with_image=False):
    """Sorted names ("ngc0628", ...) of the galaxies with a spectrum (and an image).

    Parameters
    ----------
    with_image : bool, optional
        Only the galaxies that also have an image.

    Returns
    -------
    tuple of str
        The galaxy names, sorted.
    """
    suffix = "_thumbnails.fits.gz" if with_image else "_spec.fits"
    names = [p.name[:-len(suffix)].replace("ngc_", "ngc") for p in _data_dir().iterdir() if p.name.endswith(suffix)]
    return tuple(sorted(names))


def is_galaxy_name(name):
    """True when ``name`` reads as an NGC name (whether or not the data has it)."""
    return isinstance(name, str) and _NGC.match(name.strip().lower()) is not None


def galaxy_name(name, with_image=False):
    """Canonical name ``"ngc0628"`` of ``"NGC628"``, ``"ngc_0628"``, ``"NGC 0628"`` ...; ParameterError
    naming the known galaxies when the data has no such galaxy (or no image of it)."""
    m = _NGC.match(name.strip().lower()) if isinstance(name, str) else None
    canon = None if m is None else f"ngc{int(m.group(1)):04d}" + (f"_{m.group(2)}" if m.group(2) else "")
    known = known_galaxies(with_image)
    if canon in known:
        return canon
    what = "galaxy image" if with_image else "galaxy"
    extra = ""
    if with_image and canon in known_galaxies(False):
        extra = f" ({canon} has a spectrum only: use it as the spectral part, e.g. 'sersic:{canon}')"
    raise ParameterError(f"unknown {what} {name!r}{extra}; known: {', '.join(known)}")


@functools.lru_cache(maxsize=16)
def load_galaxy_spectrum(name):
    """Rest-frame template (λ [Å], F_λ [erg/s/cm²/Å], arbitrary scale) of a named galaxy."""
    from astropy.io import fits
    name = galaxy_name(name)
    with fits.open(_data_dir().joinpath(_file_stem(name) + "_spec.fits")) as hdul:
        data = hdul[1].data
        lbda, flux = np.array(data["WAVELENGTH"], float), np.array(data["FLUX"], float)
    lbda, flux = validate_spectrum(lbda, np.clip(flux, 0.0, None), f"{name} spectrum")
    lbda.setflags(write=False)
    flux.setflags(write=False)
    return lbda, flux


@functools.lru_cache(maxsize=8)
def load_galaxy_image(name):
    """(image normalised to 1, pixel scale [arcsec], galaxy redshift, centre (x, y) 0-based pixel,
    header dict) of a named galaxy's r-band image."""
    from astropy.io import fits
    name = galaxy_name(name, with_image=True)
    with fits.open(_data_dir().joinpath(_file_stem(name) + "_thumbnails.fits.gz")) as hdul:
        image, header = np.array(hdul[0].data, dtype=np.float64), dict(hdul[0].header)
    image = np.clip(np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    image /= image.sum()
    image.setflags(write=False)
    return (image, float(header["PIXSCALE"]), float(header["REDSHIFT"]),
            (float(header["XCENTER"]) - 1.0, float(header["YCENTER"]) - 1.0), header)


def _blackbody_temperature(part):
    head, _, tail = part.partition("-")
    if head not in ("bb", "blackbody"):
        return None
    if not tail:
        return "default"
    try:
        t = float(tail)
    except ValueError:
        raise ParameterError(f"black-body model {part!r}: the temperature must be a number [K], "
                             "e.g. 'bb-5000'") from None
    if not (math.isfinite(t) and t > 0):
        raise ParameterError(f"black-body temperature must be > 0 K, got {part!r}")
    return t


def parse_host_model(model):
    """(spatial, spectral) of a model name; spatial "sersic" or an NGC name, spectral
    "bb-<T>" (T may be "default") or an NGC name.  ParameterError for anything else."""
    if not isinstance(model, str) or not model.strip():
        raise ParameterError(f"host model must be a name 'spatial:spectral', got {model!r}")
    text = model.strip().lower()
    if ":" not in text:
        if text == "sersic":
            text = "sersic:bb"
        elif is_galaxy_name(text):
            text = f"{text}:{text}"
        else:
            raise ParameterError(f"host model {model!r} not understood: use 'spatial:spectral' with spatial "
                                 "'sersic' or an NGC name and spectral 'bb[-T]' or an NGC name "
                                 "(e.g. 'sersic:bb-5000', 'ngc0628', 'sersic:ngc2403')")
    spatial, spectral = (p.strip() for p in text.split(":", 1))
    if spatial != "sersic" and not is_galaxy_name(spatial):
        raise ParameterError(f"spatial model {spatial!r} not understood: 'sersic' or an NGC name")
    temperature = _blackbody_temperature(spectral)
    if temperature is None and not is_galaxy_name(spectral):
        raise ParameterError(f"spectral model {spectral!r} not understood: 'bb[-<T K>]' or an NGC name")
    return spatial, (f"bb-{temperature}" if temperature is not None else spectral)


def _check_conflicts(params):
    """ParameterError for an unknown parameter name (with the valid ones and a "did you mean"), or
    when two given parameters name the same thing (:data:`CONFLICTS`)."""
    for key in sorted(set(params) - set(PARAMETERS)):
        validation.choice(key, key, PARAMETERS, what="host parameter")
    for a, b, what in CONFLICTS:
        if a in params and b in params:
            raise ParameterError(f"give {what}, not both (got {a}={params[a]!r} and {b}={params[b]!r})")


def _positive(value, name, upper=None):
    """A finite number in (0, upper] (upper None: > 0), else ParameterError naming it."""
    return validation.number(name, value, low=0.0, high=math.inf if upper is None else upper, low_open=True)


class GalaxyModel:
    """A galaxy independent of its redshift: a named model and its physical parameters.

    The keyword parameters accept slicersim 1.4.2 names too: ``n``, ``theta``, ``ellip``,
    ``refmodel``.  Pairs naming the same thing (``mag``/``magabs``, ``offset``/``position``,
    ``r_kpc``/``r_eff``, ``ellip``/``axis_ratio``, ``n``/``sersic_index``,
    ``theta``/``position_angle``, a temperature in the name and ``temperature``) are refused
    when both are given.

    Parameters
    ----------
    model : str, optional
        Model name (module docstring), default ``"sersic:bb-5000"``.
    r_kpc : float, optional
        Proper half-light radius [kpc] (Sersic; default 5).
    r_eff : float, optional
        Instead of ``r_kpc``: half-light radius [arcsec] at the redshift a target first
        renders it at (the target then keeps that proper size when its redshift changes; the
        model itself is never changed: :meth:`pinned`).
    sersic_index : float, optional
        Sersic index ``n``, in [0.1, 20] (default 2).
    axis_ratio : float, optional
        b/a (default 0.7), or ``ellip`` = 1 − b/a.
    position_angle : float, optional
        Major axis counter-clockwise from +x [deg] (``theta``; default −30).
    rotation : float, optional
        NGC image rotation counter-clockwise [deg] (default 0).
    magabs : float, optional
        AB magnitude in the rest-frame ``band`` [mag] (default −21).
    mag : float, optional
        Instead of ``magabs``: observed AB magnitude in ``band`` at the redshift the model is
        rendered at [mag].
    band : str, optional
        sncosmo band (default "bessellr").
    temperature : float, optional
        Black-body temperature [K] (default 5000).
    offset : tuple of float, optional
        (x, y) relative to the target [arcsec]; resolved by the target.
    position : tuple of float, optional
        Instead of ``offset``: (x, y) from the field centre [cells] (1.4.2).
    cosmology : astropy.cosmology.Cosmology or str, optional
        Astropy cosmology or realisation name (default Planck18).
    redshift : float, optional
        1.4.2 dicts only: a target with another redshift refuses the model.
    """

    def __init__(self, model="sersic:bb-5000", **params):
        _check_conflicts(params)
        params = {ALIASES.get(k, k): v for k, v in params.items()}
        if "refmodel" in params:
            model = params.pop("refmodel")
        self.spatial, self.spectral = parse_host_model(model)
        z = params.pop("redshift", None)
        #: redshift the model was given with (None: its target's); a target refuses a different one
        self.redshift = None if z is None else check_source_redshift(z, "host redshift")
        if "ellip" in params:
            ellip = validation.number("ellip (= 1 − b/a)", params.pop("ellip"), low=0.0, high=1.0, high_open=True)
            params["axis_ratio"] = 1.0 - ellip
        p = dict(HOST_DEFAULTS)
        if "mag" in params:
            p.pop("magabs")
        if "r_eff" in params:
            p.pop("r_kpc")
        p.update(params)
        if self.spectral.startswith("bb-"):
            if self.spectral != "bb-default":         # a temperature in the name: it must agree
                named = float(self.spectral[3:])
                given = params.get("temperature")
                if given is not None and not (isinstance(given, numbers.Real) and float(given) == named):
                    raise ParameterError(f"host model {model!r} names a {named:g} K black body but "
                                         f"temperature={given!r}: give the temperature once")
                p["temperature"] = named
            self.spectral = "bb"
        if "sersic_index" in p:
            n = p["sersic_index"]
            if isinstance(n, numbers.Real) and not isinstance(n, bool) and math.isfinite(n) and n <= 0:
                raise ParameterError(f"Sersic index must be > 0 (0.5 Gaussian, 1 exponential, "
                                     f"4 de Vaucouleurs; allowed [0.1, 20]), got {n!r}")
            p["sersic_index"] = _positive(n, "Sersic index", 20.0)
            if p["sersic_index"] < 0.1:
                raise ParameterError(f"Sersic index must be in [0.1, 20], got {n!r}")
        for key in ("r_kpc", "r_eff"):
            if key in p:
                p[key] = _positive(p[key], f"Sersic half-light radius {key}")
        p["axis_ratio"] = _positive(p["axis_ratio"], "axis ratio b/a", 1.0)
        for key in ("position_angle", "rotation", "magabs", "mag"):
            if key in p:
                p[key] = validation.number(f"host {key}", p[key])
        p["temperature"] = _positive(p["temperature"], "black-body temperature [K]")
        if not isinstance(p["band"], str):
            raise ParameterError(f"band must be an sncosmo band name, got {p['band']!r}")
        for key in ("offset", "position"):
            if key in p:
                xy = p[key]
                if isinstance(xy, (str, bytes)) or not hasattr(xy, "__len__") or len(xy) != 2:
                    raise ParameterError(f"host {key} must be (x, y), got {validation.short_repr(xy)}")
                p[key] = (validation.number(f"host {key}[0] (x)", xy[0]),
                          validation.number(f"host {key}[1] (y)", xy[1]))
        p["cosmology"] = get_cosmology(p.get("cosmology"))
        self.params = p
        # real-galaxy data checked now (unknown names and a missing package fail at once)
        if self.spatial != "sersic":
            self.spatial = galaxy_name(self.spatial, with_image=True)
        if self.spectral != "bb":
            self.spectral = galaxy_name(self.spectral)

    @property
    def name(self):
        """Model name, e.g. "sersic:bb-5000" or "ngc0628:ngc0628"."""
        spectral = f"bb-{self.params['temperature']:g}" if self.spectral == "bb" else self.spectral
        return f"{self.spatial}:{spectral}"

    def __repr__(self):
        return f"GalaxyModel({self.name!r})"

    def config(self):
        """Parameters as a dict (``refmodel`` and our parameter names).

        Returns
        -------
        dict
            ``{"refmodel": name, **params}``.
        """
        return {"refmodel": self.name, **self.params}

    def updated(self, **params):
        """A new model with some parameters changed (validated; conflicting pairs such as
        ``mag`` + ``magabs`` given together raise ParameterError).

        Parameters
        ----------
        **params
            The parameters changed (as :class:`GalaxyModel`).

        Returns
        -------
        GalaxyModel
            The new model.
        """
        _check_conflicts(params)
        params = {ALIASES.get(k, k): v for k, v in params.items()}
        current = {**self.params, **params}
        if self.redshift is not None and "redshift" not in params:
            current["redshift"] = self.redshift
        current["refmodel"] = params.get("refmodel", f"{self.spatial}:{'bb' if self.spectral == 'bb' else self.spectral}")
        if "refmodel" in params and "temperature" not in params:
            try:
                named = parse_host_model(params["refmodel"])[1]
            except ParameterError:
                named = None                      # reported by the constructor below
            if named is not None and named.startswith("bb-") and named != "bb-default":
                current.pop("temperature", None)  # the new name's temperature replaces the old one
        if "mag" in params or "magabs" in params:
            current.pop("magabs" if "mag" in params else "mag", None)
        if "r_eff" in params or "r_kpc" in params:
            current.pop("r_kpc" if "r_eff" in params else "r_eff", None)
        if "offset" in params or "position" in params:
            current.pop("position" if "offset" in params else "offset", None)
        if "ellip" in params:
            current.pop("axis_ratio", None)
        model = current.pop("refmodel", self.name)
        return GalaxyModel(model, **current)

    def rest_spectrum(self):
        """Rest-frame SED (arbitrary scale).

        Returns
        -------
        lbda : numpy.ndarray
            Wavelengths [Å].
        flux : numpy.ndarray
            F_λ (arbitrary scale).
        """
        if self.spectral == "bb":
            return _REST_BB_LBDA, blackbody_flambda(_REST_BB_LBDA, self.params["temperature"])
        return load_galaxy_spectrum(self.spectral)

    def host(self, redshift):
        """The :class:`~slicersim.Host` seen at ``redshift``, centred at (0, 0) (the target places
        it); ``host.model`` is this model.

        Parameters
        ----------
        redshift : float
            Redshift z.

        Returns
        -------
        Host
            The host.
        """
        z = check_source_redshift(redshift, "host redshift")
        p, cosmo = self.params, self.params["cosmology"]
        if self.spatial == "sersic":
            r_eff = p["r_eff"] if "r_eff" in p else p["r_kpc"] * arcsec_per_kpc(z, cosmo)
            profile = SersicProfile(p["sersic_index"], r_eff, p["axis_ratio"], p["position_angle"])
        else:
            image, pixscale, z_gal, centre, _ = load_galaxy_image(self.spatial)
            if not z > z_gal:
                raise ParameterError(f"{self.spatial} is at z = {z_gal:g}: it can be placed only at a larger "
                                     f"redshift (its image has no finer detail), got {z:g}")
            scale = pixscale * angular_diameter_distance_kpc(z_gal, cosmo) / angular_diameter_distance_kpc(z, cosmo)
            profile = ImageProfile(image, scale, rotation=p["rotation"], centre_pixel=centre)
        lbda, flux = restframe_to_observed(*self.rest_spectrum(), z, cosmo, absmag=p.get("magabs"),
                                           mag=p.get("mag"), band=p["band"])
        host = Host(profile, lbda, flux, redshift=z, cosmology=cosmo)
        host.model = self
        return host

    def copy(self):
        """An independent copy (its ``params`` dict is its own).

        Returns
        -------
        GalaxyModel
            The copy.
        """
        new = copy.copy(self)
        new.params = dict(self.params)
        return new

    def pinned(self, redshift):
        """A copy fixed to the target that renders it at ``redshift``: an angular ``r_eff`` becomes
        the proper ``r_kpc`` it has there, and the model's own ``redshift`` is dropped (the
        target's rules from then on).  The model itself is never changed.

        Parameters
        ----------
        redshift : float
            The target's redshift.

        Returns
        -------
        GalaxyModel
            The pinned copy.
        """
        new = self.copy()
        new.redshift = None
        p = new.params
        if "r_eff" in p:
            z = check_source_redshift(redshift, "host redshift")
            p["r_kpc"] = p.pop("r_eff") / arcsec_per_kpc(z, p["cosmology"])
        return new

    @classmethod
    def from_spec(cls, spec):
        """A model from a name, a dict (``refmodel`` + parameters) or a GalaxyModel.

        Parameters
        ----------
        spec : str, dict or GalaxyModel
            The model (a GalaxyModel is returned as it is).

        Returns
        -------
        GalaxyModel
            The model.
        """
        if isinstance(spec, GalaxyModel):
            return spec
        if isinstance(spec, str):
            return cls(spec)
        if isinstance(spec, dict):
            bad = [k for k in spec if not isinstance(k, str)]
            if bad:
                raise ParameterError(f"host dict keys must be parameter names, got {bad}")
            return cls(**{"refmodel": "sersic:bb-5000", **spec})
        raise ParameterError(f"host must be a model name, a dict with 'refmodel', a GalaxyModel, a Host or a "
                             f"CubeSource, got {type(spec).__name__}")


#: ``host__<name>`` parameters of a host given by name (slicersim 1.4.2 names included)
HOST_PARAMETERS = ("refmodel", "r_kpc", "r_eff", "sersic_index", "n", "axis_ratio", "ellip", "position_angle",
                   "theta", "rotation", "magabs", "mag", "band", "temperature", "offset", "position")


class HostPlacement:
    """How a target holds its host: the origin object (Host / CubeSource) and its redshift, the
    GalaxyModel it was rendered from (or None), its offset [arcsec] at the origin redshift and
    whether that offset is relative to the target."""

    def __init__(self, origin, origin_z, model, offset, relative):
        self.origin, self.origin_z, self.model = origin, origin_z, model
        self.offset, self.relative = (float(offset[0]), float(offset[1])), bool(relative)

    @classmethod
    def resolve(cls, host, redshift, relative, spatial_scale):
        """Validated state of a ``set_host`` argument (nothing applied; the argument itself is
        never changed: models and Host / CubeSource objects are copied)."""
        if isinstance(host, (str, dict, GalaxyModel)):
            model = GalaxyModel.from_spec(dict(host) if isinstance(host, dict) else host)
            z = redshift
            if model.redshift is not None:
                if z is None:
                    z = model.redshift
                elif model.redshift != z:
                    raise ParameterError(f"the host is given at redshift {model.redshift:g} but the target is at "
                                         f"{z:g}: a host is at its target's redshift (drop the host's 'redshift')")
            if z is None:
                raise ParameterError("a host given by name needs a redshift: give the target a redshift "
                                     "(or the host dict a 'redshift')")
            origin = model.host(z)
            model = origin.model = model.pinned(z)
            p = model.params
            if "position" in p:      # 1.4.2: cells from the field centre, absolute
                return cls(origin, float(z), model, (p["position"][0] * spatial_scale,
                                                     p["position"][1] * spatial_scale), False)
            return cls(origin, float(z), model, p.get("offset", (0.0, 0.0)), relative)
        if not callable(getattr(host, "flux_cube", None)):
            raise ParameterError("host must be a model name, a dict with 'refmodel', a GalaxyModel or provide "
                                 "flux_cube(lbda, shape, spatial_scale) (slicersim.Host or slicersim.CubeSource)")
        origin_z = getattr(host, "redshift", None)
        return cls(own_copy(host), redshift if origin_z is None else origin_z, None, host_offset(host), relative)

    def _angle(self, redshift):
        if redshift is None or self.origin_z is None or redshift == self.origin_z:
            return 1.0
        return redshift_scalings(self.origin_z, redshift, getattr(self.origin, "cosmology", None))[0]

    def at(self, redshift):
        """The host seen at ``redshift`` (the origin itself when it is already there)."""
        if redshift is None or self.origin_z is None or redshift == self.origin_z:
            return self.origin
        if not callable(getattr(self.origin, "at_redshift", None)):
            raise ParameterError(f"the host ({type(self.origin).__name__}) cannot be moved to another redshift")
        return self.origin.at_redshift(redshift, from_redshift=self.origin_z)

    def offset_at(self, redshift):
        """Offset [arcsec] at ``redshift``: a relative offset keeps its proper length."""
        a = self._angle(redshift) if self.relative else 1.0
        return (self.offset[0] * a, self.offset[1] * a)

    def updated(self, host_params, redshift, spatial_scale):
        """State after ``host__<name>`` changes (validated; model hosts only)."""
        if self.model is None:
            raise ParameterError("host__<name> needs a host given by name (set_host('sersic:bb-5000', ...))")
        model = self.model.updated(**host_params)
        z = redshift if redshift is not None else self.origin_z
        new = HostPlacement.resolve(model, z, self.relative, spatial_scale)
        if "offset" not in host_params and "position" not in host_params:
            new.offset, new.relative = self.offset_at(z), self.relative
        return new


def own_copy(host):
    """A copy of a Host / CubeSource the target may place (profile copied; arrays shared)."""
    if not isinstance(host, (Host, CubeSource)):
        return host                     # a user object with flux_cube: used as given
    new = copy.copy(host)
    if isinstance(host, Host):
        new.profile = copy.copy(host.profile)
        new.profile.touch()
    new.touch()
    return new


def check_host_in_field(host, centre, shape, spatial_scale):
    """ParameterError when a host centred at ``centre`` (x, y) [arcsec] puts less than
    :data:`HOST_MIN_FIELD_FRACTION` of its light in the (ny, nx) field (its light would be lost)."""
    frac = host_field_fraction(host, centre, shape, spatial_scale)
    if frac is None or frac >= HOST_MIN_FIELD_FRACTION:
        return
    ny, nx = shape
    amount = "none" if frac == 0 else f"less than {frac:.1e}"
    raise ParameterError(f"the host centred at ({centre[0]:.4g}″, {centre[1]:.4g}″) from the field centre puts "
                         f"{amount} of its light in the field ({nx * spatial_scale:.4g}″ × {ny * spatial_scale:.4g}″): "
                         "its light would be lost; move it (offset [arcsec] / position [cells]) or drop it")


def check_host_covers(host, lbda):
    """ParameterError unless the host spectrum covers the instrument grid ``lbda`` [Å]."""
    lbda_in = getattr(host, "lbda_in", None)
    if lbda_in is not None and (lbda_in[0] > lbda[0] or lbda_in[-1] < lbda[-1]):
        z = getattr(host, "redshift", None)
        at = "" if z is None else f" at z = {z:g}"
        raise ParameterError(f"the host spectrum{at} covers {lbda_in[0]:.0f}–{lbda_in[-1]:.0f} Å (observer frame), "
                             f"not the instrument range {lbda[0]:.0f}–{lbda[-1]:.0f} Å")


def host_offset(host):
    """(x, y) [arcsec] of a host: its profile offset or its cube centre."""
    if hasattr(host, "profile") and hasattr(host.profile, "offset"):
        return tuple(float(v) for v in host.profile.offset)
    if hasattr(host, "centre"):
        return tuple(float(v) for v in host.centre)
    return (0.0, 0.0)
