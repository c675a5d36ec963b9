"""A :class:`~slicersim.simulation.Simulation` assembled from a configuration and a field.

``build_simulation("cbe", "narrow", pointsource)`` reads the (layered) TOML
configuration and builds the telescope, the slicer spectrograph of the chosen
Lazuli field, the detector and the scene.  Targets and the batch ETC both start
here.
"""
from __future__ import annotations

import os
import warnings

from slicersim import validation
from slicersim.errors import ConfigError
from slicersim.instrument.detector import Detector
from slicersim.instrument.mapper import SlicerMapper
from slicersim.instrument.spectrograph import MLASpectrograph, SlicerSpectrograph, wavelength_grid_from_dispersion
from slicersim.instrument.telescope import Telescope
from slicersim.io.config import complete_config_hint, expand_config, load_config
from slicersim.io.curves import read_curve
from slicersim.physics.conventions import DEFAULT_CONVENTIONS
from slicersim.simulation import Simulation
from slicersim.sources.scene import Background, Scene

__all__ = ["LAZULI_FIELDS", "build_simulation", "check_field", "default_mapper"]

#: Lazuli slicer fields: cell size [arcsec], throughput column, IFU optics count (optics group 1)
LAZULI_FIELDS = {"narrow": {"spatial_scale": 0.04, "throughput_column": "narrow", "ifu_nelements": 4},
                 "wide": {"spatial_scale": 0.08, "throughput_column": "wide", "ifu_nelements": 6}}
#: index of the IFU / slicer group in [spectrograph.optics]
IFU_OPTICS_INDEX = 1


def check_field(field):
    """A Lazuli field name ("narrow", "wide") or None (the configuration as written); ConfigError
    listing the valid ones (with a did-you-mean) otherwise."""
    return validation.choice("field", field, (*LAZULI_FIELDS, None), error=ConfigError)


#: keys whose absence makes an ideal instrument (QE 1, no noise, no losses): warned, as a partial file
#: meant to amend the built-in configuration replaces it
IDEAL_DEFAULTS = {("detector", "QE"): "1", ("detector", "ron"): "0 electron", ("detector", "dark"): "0",
                  ("detector", "gain"): "1", ("spectrograph.throughput", "throughput"): "1",
                  ("telescope", "diameter_ext"): "3 m"}


class IdealDefaultsWarning(UserWarning):
    """A configuration leaves key instrument properties unset: ideal values are used."""


def _warn_ideal_defaults(cfg):
    missing = [f"[{t}] {k} ({v})" for (t, k), v in IDEAL_DEFAULTS.items() if k not in (cfg.get(t) or {})]
    if missing:
        files = ", ".join(os.path.basename(p) for p in cfg.get("_sources", ())) or "given as a dict"
        warnings.warn(f"the configuration ({files}) leaves {', '.join(missing)} unset: these ideal values are "
                      "used (a configuration file replaces the built-in one, it does not amend it); "
                      f"{complete_config_hint()}", IdealDefaultsWarning, stacklevel=3)


def build_simulation(config="cbe", field="narrow", pointsource=None, background="zodi",
                     position=(0.0, 0.0), conventions=DEFAULT_CONVENTIONS):
    """Simulation from a configuration (see :func:`~slicersim.load_config`) and a field.

    Parameters
    ----------
    config : str, path-like, list or dict, optional
        "cbe", "eol", TOML path(s) or a configuration dict, as :func:`~slicersim.load_config`.
    field : {"narrow", "wide"} or None, optional
        The Lazuli field; None uses the configuration as written (single-channel
        instruments).
    pointsource : PointSource, optional
        The point source of the scene.
    background : str, Background or None, optional
        The background of the scene ("zodi" by default).
    position : tuple of float, optional
        (x, y) of the point source relative to the field centre [cells].
    conventions : {"physical", "slicersim-1.0"}, optional
        Physics conventions ("physical" by default; ``slicersim.physics.conventions``).

    Returns
    -------
    Simulation
        The simulation (telescope, spectrograph, detector and scene).
    """
    check_field(field)
    cfg = load_config(config)
    tel, spc, det = cfg.get("telescope", {}), cfg.get("spectrograph", {}), cfg.get("detector", {})
    optics = dict(cfg.get("spectrograph.optics", {}))
    psf = cfg.get("spectrograph.psf.spatial", {})
    ext = cfg.get("extraction", {})
    thr = cfg.get("spectrograph.throughput", {})
    fieldpar = LAZULI_FIELDS[field] if field else {}
    if fieldpar and "nelements" in optics and len(optics["nelements"]) > IFU_OPTICS_INDEX:
        optics["nelements"] = list(optics["nelements"])
        optics["nelements"][IFU_OPTICS_INDEX] = fieldpar["ifu_nelements"]
    telescope = Telescope(diameter_ext=tel.get("diameter_ext", 3.0), diameter_int=tel.get("diameter_int", 0.0),
                          temperature=tel.get("temperature", 0.0),
                          emissivity=tel.get("emissivity", [0.0]), nelements=tel.get("nelements", [1]),
                          guiding_sigma=psf.get("guiding_sigma", 0.0))
    if psf.get("psf_sigma_spectral", "default") not in ("default", None):
        raise ConfigError("psf_sigma_spectral other than 'default' is not supported yet")
    kind = validation.choice("kind", spc.get("kind", "slicer"), ("slicer", "mla"), error=ConfigError,
                             what="spectrograph kind")
    cls = SlicerSpectrograph if kind == "slicer" else MLASpectrograph
    _check_anamorphosis(spc, cls, kind)
    extra = _mla_options(cfg.get("spectrograph.psf.detector", {}), ext)
    if kind == "slicer":
        _check_slicer_ignores(extra)
        extra = {}
    if "dispersion_law" not in spc and "resolving_power" not in spc:
        files = ", ".join(os.path.basename(p) for p in cfg.get("_sources", ())) or "given as a dict"
        raise ConfigError(f"the configuration ({files}) sets neither [spectrograph] dispersion_law nor "
                          "resolving_power, one of which the model needs (a configuration file replaces the built-in "
                          f"one, it does not amend it); {complete_config_hint()}")
    _warn_ideal_defaults(cfg)
    spectrograph = cls(spectral_range=spc.get("spectral_range", (4000.0, 17000.0)),
                       dispersion_law=spc.get("dispersion_law"), resolving_power=spc.get("resolving_power"),
                       dispersion_scale=spc.get("dispersion_scale", 1.0),
                       dispersion_resolution=spc.get("dispersion_resolution", 2.0),
                       throughput=thr.get("throughput", 1.0), noptics=thr.get("noptics"),
                       throughput_column=fieldpar.get("throughput_column"),
                       spatial_scale=_spatial_scale(spc, field, fieldpar),
                       spatial_shape=spc.get("spatial_shape", (58, 58)), optics=optics, **extra)
    detector = Detector(qe=det.get("QE", 1.0), gain=det.get("gain", 1.0), dark=det.get("dark", 0.0),
                        roic_glow=det.get("roic_glow", 0.0), ron=det.get("ron", 0.0),
                        tframe=det.get("tframe", 2.83), pixel_size=det.get("pixel_size", 10.0),
                        saturation=det.get("saturation", 65535), nmd=det.get("readout_mode", (16, 8, 0)),
                        min_group=det.get("min_group", 2), max_group=det.get("max_group", 64),
                        variance_model=det.get("variance_model", "Rauscher07"),
                        shape=det.get("shape", (4096, 4096)),
                        thermal_dark_range=None)
    thermal_dark_range = det.get("thermal_dark_range")
    if thermal_dark_range is None:
        thermal_dark_range = _base_grid_range(config)
    if isinstance(background, str):
        background = Background(model="zodi", scale=2.0) if background == "zodi" else None
    scene = Scene(pointsource=pointsource, background=background)
    detector.thermal_dark_range = thermal_dark_range
    sim = Simulation(scene, telescope, spectrograph, detector, nramps=ext.get("nramps", 1),
                     aperture_radius_insigma=ext.get("aperture_radius_insigma", 10.0), conventions=conventions)
    sim.config, sim.field = config, field
    return sim


#: [spectrograph] spatial_scale of the built-in configurations [arcsec]: a field replaces it
_BUILTIN_SPATIAL_SCALE = 0.04


def _spatial_scale(spc, field, fieldpar):
    """The cell size [arcsec]: the field's, or the configuration's with ``field=None``.  A
    configuration value other than the built-in default and the field's own would be silently
    replaced: refused (ConfigError naming the key)."""
    given = spc.get("spatial_scale")
    if not fieldpar:
        return 0.04 if given is None else given
    if given is not None and not any(abs(float(given) - v) <= 1e-9 * v
                                     for v in (_BUILTIN_SPATIAL_SCALE, fieldpar["spatial_scale"])):
        raise ConfigError(f"[spectrograph] spatial_scale = {validation.short_repr(given)}: the {field} field's cells "
                          f"are {fieldpar['spatial_scale']:g} arcsec and replace it; build with field=None to use "
                          "the configuration's spatial_scale, or remove the key")
    return fieldpar["spatial_scale"]


def _check_anamorphosis(spc, cls, kind):
    """[spectrograph] anamorphosis is fixed by the spectrograph kind (slicer 1×2, micro-lens array
    1×1): a different value is refused (ConfigError naming the key), not ignored."""
    value = spc.get("anamorphosis")
    if value is None:
        return
    fixed = tuple(cls.anamorphosis)
    given = (1, value) if not isinstance(value, (list, tuple)) else tuple(value)
    if len(given) == 1:
        given = (1, given[0])
    if tuple(float(v) for v in given) != tuple(float(v) for v in fixed):
        raise ConfigError(f"[spectrograph] anamorphosis = {validation.short_repr(value)}: the {kind} spectrograph's "
                          f"anamorphosis is {list(fixed)} (y, x); remove the key or give {list(fixed)}")


def _mla_options(xdisp, ext):
    """The micro-lens-array spectrograph's cross-dispersion options of a configuration
    (``[spectrograph.psf.detector]`` xdisp_sigma_spectral, xdisp_sigma [px]; ``[extraction]``
    xdisp_width_insigma): they set the pixels a spaxel's spectrum spans (its read noise, dark and
    full well, :func:`slicersim.physics.conventions.detector_pixels_per_cell`)."""
    if xdisp.get("xdisp_profile", "normal") not in ("normal", None):
        raise ConfigError(f"xdisp_profile {xdisp['xdisp_profile']!r}: only 'normal' is supported")
    out = {}
    for key, val, positive in (("xdisp_sigma_spectral", xdisp.get("xdisp_sigma_spectral"), False),
                               ("xdisp_sigma", xdisp.get("xdisp_sigma"), False),
                               ("xdisp_width_insigma", ext.get("xdisp_width_insigma"), True)):
        if val is not None:
            out[key] = validation.number(key, val, low=0.0, low_open=positive, error=ConfigError)
    return out


#: the micro-lens-array cross-dispersion defaults (:class:`~slicersim.instrument.spectrograph.MLASpectrograph`):
#: the built-in Lazuli files carry them, unused by the slicer
_MLA_DEFAULTS = {"xdisp_sigma_spectral": 0.9, "xdisp_sigma": 0.3, "xdisp_width_insigma": 10.0}


def _check_slicer_ignores(options):
    """The cross-dispersion keys set the micro-lens array's pixels per spaxel; the slicer's are fixed by its
    1×2 anamorphosis.  A value other than the MLA default would be ignored: refused, naming the key."""
    for key, value in options.items():
        if abs(value - _MLA_DEFAULTS[key]) > 1e-12 * _MLA_DEFAULTS[key]:
            table = "extraction" if key == "xdisp_width_insigma" else "spectrograph.psf.detector"
            raise ConfigError(f"[{table}] {key} = {value:g} is used only by the micro-lens-array spectrograph "
                              f"([spectrograph] kind = \"mla\"); the slicer's cross-dispersion is fixed by its 1×2 "
                              f"anamorphosis: remove the key (or give {_MLA_DEFAULTS[key]:g})")


def _base_grid_range(config):
    """Thermal-dark integration range of a layered configuration (slicersim 1.0 convention).

    The undispersed thermal light is integrated over the wavelength grid of the
    *base* instrument: when later files (e.g. end-of-life) change the dispersion,
    the detector keeps the base grid, as ``change_configuration`` does in
    slicersim 1.0.  Returns None for a single configuration (use its own grid).
    """
    if isinstance(config, dict):
        return None
    paths = expand_config(config)
    if len(paths) < 2:
        return None
    base = load_config(paths[0]).get("spectrograph", {})
    if "dispersion_law" not in base:
        return None
    llbda, cols = read_curve(base["dispersion_law"])
    lbda, _ = wavelength_grid_from_dispersion(llbda, next(iter(cols.values())),
                                              base.get("spectral_range", (4000.0, 17000.0)),
                                              base.get("dispersion_scale", 1.0),
                                              base.get("dispersion_resolution", 2.0))
    return float(lbda[0]), float(lbda[-1])


_DEFAULT_MAPPER = []


def default_mapper():
    """The built-in Lazuli detector layout, built once per process (its projection tables
    are cached inside it, so later detector images are fast)."""
    if not _DEFAULT_MAPPER:
        _DEFAULT_MAPPER.append(SlicerMapper.default())
    return _DEFAULT_MAPPER[0]
