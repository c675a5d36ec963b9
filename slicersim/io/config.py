"""Instrument configuration: TOML files (reference format) merged in order.

``load_config("cbe")`` returns the built-in Lazuli current-best-estimate
configuration; ``"eol"`` is CBE with the end-of-life overrides applied; a path
(or a list of paths / names) loads TOML files in the reference's format, later
files overriding earlier ones.  Curve file names are resolved next to the TOML
that names them and stored as absolute paths.
"""
from __future__ import annotations

import copy
import difflib
import os
from functools import lru_cache
from importlib import resources

import numpy as np

from slicersim import validation
from slicersim.errors import ConfigError  # noqa: F401  (re-exported)
from slicersim.io.tables import parse_toml, read_file_bytes

__all__ = ["load_config", "validate_config", "ConfigError", "builtin_config_dir", "complete_config_hint",
           "tables_of", "SCHEMA", "PROFILES"]




#: allowed keys per TOML table (reference format plus a few slicersim extensions)
SCHEMA = {
    "telescope": {"diameter_ext", "diameter_int", "temperature", "emissivity", "nelements"},
    "spectrograph": {"spectral_range", "dispersion_law", "dispersion_scale", "dispersion_resolution",
                     "resolving_power", "spatial_scale", "spatial_shape", "anamorphosis", "kind"},
    "spectrograph.throughput": {"throughput", "components", "noptics"},
    "spectrograph.optics": {"temperature", "emissivity", "nelements", "fratio", "geometry", "dispersed"},
    "spectrograph.psf.spatial": {"psf_profile", "psf_sigma_spectral", "guiding_profile", "guiding_sigma"},
    "spectrograph.psf.detector": {"xdisp_profile", "xdisp_sigma_spectral", "xdisp_sigma"},
    "detector": {"shape", "QE", "qe", "gain", "saturation", "ron", "readout_noise", "tframe",
                 "pixel_size", "readout_mode", "max_group", "min_group", "variance_model", "dark",
                 "roic_glow", "thermal_dark_range"},
    "extraction": {"nramps", "xdisp_width_insigma", "aperture_radius_insigma"},
    "scene.background": {"name", "model", "scale"},
    "scene.pointsource": {"name", "source", "temperature", "position", "mag", "band", "magsys",
                          "redshift", "phase", "MBmax", "c", "x1"},
    "scene.host": {"name", "sersic_index", "r_eff", "axis_ratio", "position_angle", "offset", "mag", "band"},
}
#: every key of every table
_ALL_KEYS = sorted(set().union(*SCHEMA.values()))
#: keys whose (string) value names a curve file to resolve next to the TOML
FILE_KEYS = {("spectrograph", "dispersion_law"), ("spectrograph.throughput", "throughput"),
             ("detector", "QE"), ("detector", "qe")}
#: aliases accepted for reference compatibility: (table, alias) -> key
ALIASES = {("detector", "readout_noise"): "ron", ("detector", "qe"): "QE"}

BUILTIN = {"cbe": ["lazuli_cbe.toml"], "bol": ["lazuli_cbe.toml"],
           "eol": ["lazuli_cbe.toml", "lazuli_eol.toml"]}


def builtin_config_dir():
    """Directory of the built-in Lazuli configuration files."""
    return str(resources.files("slicersim.data") / "lazuli")


def complete_config_hint():
    """Where the complete default configuration is, and how to change only a few of its keys (the
    end of a message about a key missing or in the wrong table)."""
    return (f"start from the complete default configuration, the built-in 'cbe' ({builtin_config_dir()}/"
            "lazuli_cbe.toml, every key commented, with its curve files beside it), or layer your file on it: "
            "--config cbe --config FILE (Python: config=['cbe', FILE])")


def tables_of(key):
    """The configuration tables (of :data:`SCHEMA`) that have ``key``, sorted."""
    return sorted(table for table, keys in SCHEMA.items() if key in keys)


def _belongs(key):
    """"'gain' belongs in [detector]" when some table has ``key``, else ""."""
    homes = tables_of(key)
    return f"{key!r} belongs in {' or '.join(f'[{t}]' for t in homes)}" if homes else ""


def _elsewhere(names):
    """" (did you mean 'gain' of [detector]?)" for the first of ``names`` close to a key of any table."""
    for name in names:
        close = difflib.get_close_matches(name, _ALL_KEYS, n=1, cutoff=0.6)
        if close:
            return f" (did you mean {close[0]!r} of {' or '.join(f'[{t}]' for t in tables_of(close[0]))}?)"
    return ""


def _flatten_tables(doc, prefix=""):
    """{'a': {'b': {'k': v}}} -> {'a.b': {'k': v}} (tables only; leaves stay)."""
    out = {}
    for key, val in doc.items():
        name = f"{prefix}{key}"
        if isinstance(val, dict):
            leaves = {k: v for k, v in val.items() if not isinstance(v, dict)}
            if leaves or name in SCHEMA:
                out[name] = leaves
            out.update(_flatten_tables({k: v for k, v in val.items() if isinstance(v, dict)}, name + "."))
        elif tables_of(key):
            raise ConfigError(f"top-level key {name!r} must live in its table: {_belongs(key)}; "
                              f"{complete_config_hint()}")
        else:
            raise ConfigError(f"unknown top-level key {name!r}{_elsewhere([key])}: keys live in "
                              f"tables ({', '.join(f'[{t}]' for t in sorted(SCHEMA))}); {complete_config_hint()}")
    return out


def _did_you_mean(names, valid):
    """" (did you mean 'x'?)" for the first of ``names`` close to a ``valid`` one, else ""."""
    for name in names:
        close = difflib.get_close_matches(name, sorted(valid), n=1, cutoff=0.6)
        if close:
            return f" (did you mean {close[0]!r}?)"
    return ""


def _read_toml(path):
    if not os.path.lexists(path):
        raise ConfigError(f"configuration file not found: {path}")
    raw = read_file_bytes(path, ConfigError, "configuration file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:                              # a binary file: not UTF-8
        raise ConfigError(f"cannot parse TOML {path}: not UTF-8 text (byte {exc.start})") from None
    doc = parse_toml(text, f"configuration file {path}", ConfigError)
    try:
        tables = _flatten_tables(doc)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    here = os.path.dirname(os.path.abspath(path))
    for table, entries in tables.items():
        if table not in SCHEMA:
            raise ConfigError(f"{path}: unknown configuration table [{table}]{_did_you_mean([table], SCHEMA)}; "
                              f"known tables: {sorted(SCHEMA)}")
        unknown = set(entries) - SCHEMA[table]
        if unknown:
            if any(tables_of(k) for k in unknown):
                where = "; ".join(_belongs(k) or f"{k!r} is unknown{_elsewhere([k])}"
                                  for k in sorted(unknown))
                raise ConfigError(f"{path}: [{table}] has no key(s) {', '.join(map(repr, sorted(unknown)))}: "
                                  f"{where}; {complete_config_hint()}")
            hint = _did_you_mean(sorted(unknown), SCHEMA[table]) or _elsewhere(sorted(unknown))
            raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)} in [{table}]{hint}; allowed: "
                              f"{sorted(SCHEMA[table])}")
        for key in list(entries):
            if (table, key) in FILE_KEYS and isinstance(entries[key], str):
                fpath = entries[key] if os.path.isabs(entries[key]) else os.path.join(here, entries[key])
                where = f"{path}: [{table}] {key} = {entries[key]!r}: curve file"
                if not os.path.lexists(fpath):
                    raise ConfigError(f"{where} not found at {fpath}")
                entries[key] = validation.regular_file(where, fpath, error=ConfigError)   # a FIFO, device: refused
            if (table, key) in ALIASES:
                entries[ALIASES[(table, key)]] = entries.pop(key)
    return tables


def expand_config(config):
    if isinstance(config, (str, os.PathLike)):
        config = [config]
    paths = []
    for item in config:
        item = os.fspath(item)
        if item.lower() in BUILTIN:
            paths += [os.path.join(builtin_config_dir(), f) for f in BUILTIN[item.lower()]]
        elif item.lower().endswith(".toml") or os.path.sep in item:
            paths.append(item)
        else:
            raise ConfigError(f"unknown configuration {item!r}: use 'cbe', 'eol', a TOML path "
                              "or a list of TOML paths")
    if not paths:
        raise ConfigError("empty configuration list")
    return paths


def load_config(config="cbe"):
    """Load and merge configuration files.

    Parameters
    ----------
    config : str, path-like or list
        ``"cbe"``, ``"eol"``, a TOML path, or a list of names/paths applied in order.

    Returns
    -------
    dict
        Table name (e.g. ``"detector"``, ``"spectrograph.optics"``) -> {key: value};
        the ``"_sources"`` entry lists the files read.
    """
    if isinstance(config, dict):
        return validate_config(copy.deepcopy(config))
    merged = {}
    paths = expand_config(config)
    for path in paths:
        for table, entries in _read_toml(path).items():
            merged.setdefault(table, {}).update(entries)
    merged["_sources"] = [os.path.abspath(p) for p in paths]
    return validate_config(merged)


# --------------------------------------------------------------------------- #
#  physical validation of the merged configuration                            #
# --------------------------------------------------------------------------- #
def _bad(table, key, value, reason):
    shown = repr(os.fspath(value)) if isinstance(value, (str, os.PathLike)) else validation.short_repr(value)
    return ConfigError(f"[{table}] {key} = {shown}: {reason}")      # a curve path in full, arrays summarised


def _numbers(table, key, value):
    """Flat float array of a scalar or (nested) list value; ConfigError if not numeric."""
    try:
        arr = validation.array(f"[{table}] {key}", value, finite=False, error=ConfigError).ravel()
    except ConfigError:
        raise _bad(table, key, value, "must be a number or a list of numbers") from None
    if arr.size == 0:
        raise _bad(table, key, value, "must not be empty")
    return arr


def _check_range(cfg, table, key, lo=None, hi=None, lo_open=False, finite=True, integer=False):
    entries = cfg.get(table, {})
    if not isinstance(entries, dict) or key not in entries or entries[key] is None:
        return
    value = entries[key]
    if isinstance(value, bool):
        raise _bad(table, key, value, "must be a number")
    arr = _numbers(table, key, value)
    if np.any(np.isnan(arr)) or (finite and not np.all(np.isfinite(arr))):
        raise _bad(table, key, value, "must be finite")
    if integer and np.any(arr != np.round(arr)):
        raise _bad(table, key, value, "must be an integer")
    if lo is not None:
        if lo_open and np.any(arr <= lo):
            raise _bad(table, key, value, f"must be > {lo:g}")
        if not lo_open and np.any(arr < lo):
            raise _bad(table, key, value, f"must be ≥ {lo:g}")
    if hi is not None and np.any(arr > hi):
        raise _bad(table, key, value, f"must be ≤ {hi:g}")


@lru_cache(maxsize=64)
def _curve_values(path, mtime):
    from slicersim.io.curves import CurveError, read_curve
    try:
        _, cols = read_curve(path)
    except CurveError as exc:
        raise ConfigError(str(exc)) from exc
    return {name: (float(np.min(v)), float(np.max(v)), bool(np.all(np.isfinite(v))))
            for name, v in cols.items()}


def _check_fraction(cfg, table, key, what):
    """Scalar in [0, 1], or a curve file whose every value column lies in [0, 1]."""
    entries = cfg.get(table, {})
    if not isinstance(entries, dict) or key not in entries or entries[key] is None:
        return
    value = entries[key]
    if isinstance(value, (str, os.PathLike)):
        path = os.fspath(value)
        if not os.path.lexists(path):
            raise _bad(table, key, value, "curve file not found")
        validation.regular_file(f"[{table}] {key} = {path!r}: curve file", path, error=ConfigError)
        for col, (vmin, vmax, finite) in _curve_values(path, os.path.getmtime(path)).items():
            if not finite:
                raise _bad(table, key, value, f"{what} column {col!r} of the curve file has NaN/inf values")
            if vmin < 0 or vmax > 1:
                raise _bad(table, key, value, f"{what} column {col!r} of the curve file spans "
                                              f"{vmin:g}–{vmax:g}, must lie in [0, 1]")
        return
    if isinstance(value, (list, tuple)) and len(value) == 2 and np.ndim(value[0]) == 1:
        arr = _numbers(table, key, value[1])          # (lbda, values) pair
    else:
        arr = _numbers(table, key, value)
    if not np.all(np.isfinite(arr)):
        raise _bad(table, key, value, f"{what} must be finite")
    if np.any(arr < 0) or np.any(arr > 1):
        raise _bad(table, key, value, f"{what} must lie in [0, 1]")


#: the PSF / guiding profiles a configuration may name: the simulator's chromatic PSF and guiding
#: are Gaussian ("normal"); the Airy profile of cubes is chosen per product (``psf_profile=`` of
#: ``get_cube``, the campaign's ``observation.psf_profile``), not in the instrument configuration
PROFILES = ("normal", "gaussian")


def _check_spectrograph_keys(cfg):
    """spatial_shape, anamorphosis and the PSF profiles: used as written or refused."""
    spc = cfg.get("spectrograph", {})
    if isinstance(spc, dict) and spc.get("spatial_shape") is not None:
        validation.shape("[spectrograph] spatial_shape", spc["spatial_shape"], error=ConfigError)
    if isinstance(spc, dict) and spc.get("anamorphosis") is not None:
        value = spc["anamorphosis"]
        arr = _numbers("spectrograph", "anamorphosis", value)
        if arr.size not in (1, 2) or not np.all(np.isfinite(arr)) or np.any(arr < 1) or np.any(arr != np.round(arr)):
            raise _bad("spectrograph", "anamorphosis", value, "must be one or two integers ≥ 1 (y, x)")
    if isinstance(spc, dict) and spc.get("spectral_range") is not None:
        value = spc["spectral_range"]
        arr = _numbers("spectrograph", "spectral_range", value)
        if arr.size != 2 or not np.all(np.isfinite(arr)) or not 0 < arr[0] < arr[1]:
            raise _bad("spectrograph", "spectral_range", value, "must be [min, max] with 0 < min < max")
    psf = cfg.get("spectrograph.psf.spatial", {})
    for key in ("psf_profile", "guiding_profile"):
        if isinstance(psf, dict) and psf.get(key) is not None:
            validation.choice(f"[spectrograph.psf.spatial] {key}", psf[key], PROFILES, error=ConfigError)


def validate_config(cfg):
    """Refuse physically invalid values of a merged configuration (returned unchanged).

    Raises :class:`ConfigError` ``"[table] key = value: reason"`` for: emissivities
    outside [0, 1]; negative temperatures; throughput or QE outside [0, 1] (scalars and
    every value of their curve files); saturation ≤ 0; tframe ≤ 0 or not finite; a
    detector shape that is not two integers ≥ 1; negative dark, ron, roic_glow (or
    full_well, when given); gain ≤ 0; bias ≥ saturation (when given); diameter_ext ≤ 0;
    diameter_int < 0 or ≥ diameter_ext; aperture_radius_insigma ≤ 0; nramps < 1;
    min_group < 2, max_group < min_group, max_group or min_group > :data:`~slicersim.validation.MAX_GROUPS`,
    readout_mode out of :func:`~slicersim.validation.readout`'s bounds or n > max_group;
    spatial_shape not two integers ≥ 1, anamorphosis not two numbers ≥ 1, a PSF or guiding
    profile other than "normal" (see :data:`PROFILES`); ``dispersed`` entries that are not TOML
    booleans; negative ``xdisp_sigma`` / ``xdisp_sigma_spectral``, ``xdisp_width_insigma`` ≤ 0.
    """
    for table, key in (("telescope", "emissivity"), ("spectrograph.optics", "emissivity")):
        _check_range(cfg, table, key, 0.0, 1.0)
    for table in ("telescope", "spectrograph.optics"):
        _check_range(cfg, table, "temperature", 0.0)
        _check_range(cfg, table, "nelements", 0.0, integer=True)
    tel = cfg.get("telescope", {})
    _check_range(cfg, "telescope", "diameter_ext", 0.0, lo_open=True)
    _check_range(cfg, "telescope", "diameter_int", 0.0)
    if "diameter_int" in tel and tel.get("diameter_int") is not None:
        dext = tel.get("diameter_ext", 3.0)
        if float(tel["diameter_int"]) >= float(dext):
            raise _bad("telescope", "diameter_int", tel["diameter_int"],
                       f"must be smaller than diameter_ext = {dext!r}")
    _check_fraction(cfg, "spectrograph.throughput", "throughput", "throughput")
    _check_fraction(cfg, "detector", "QE", "QE")
    _check_range(cfg, "spectrograph", "spatial_scale", 0.0, lo_open=True)
    _check_range(cfg, "spectrograph", "dispersion_resolution", 0.0, lo_open=True)
    _check_range(cfg, "spectrograph", "dispersion_scale", 0.0, lo_open=True)
    _check_range(cfg, "spectrograph.psf.spatial", "guiding_sigma", 0.0)
    det = cfg.get("detector", {})
    _check_range(cfg, "detector", "saturation", 0.0, lo_open=True, finite=False)
    top = validation.DETECTOR_MAX
    _check_range(cfg, "detector", "tframe", 0.0, top["tframe"], lo_open=True)
    _check_range(cfg, "detector", "gain", 0.0, top["gain"], lo_open=True)
    _check_range(cfg, "detector", "pixel_size", 0.0, lo_open=True)
    for key in ("dark", "ron", "roic_glow", "full_well"):
        _check_range(cfg, "detector", key, 0.0, top.get(key))
    if "shape" in det:
        shape = det["shape"]
        if (not isinstance(shape, (list, tuple)) or len(shape) != 2
                or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 1 <= v <= 65536
                           for v in shape)):
            raise _bad("detector", "shape", shape, "must be two integers in [1, 65536] (ny, nx)")
    _check_range(cfg, "detector", "bias")
    if det.get("bias") is not None:
        sat = det.get("saturation", 65535)
        if float(det["bias"]) >= float(sat):
            raise _bad("detector", "bias", det["bias"], f"must be below saturation = {sat!r}")
    _check_range(cfg, "detector", "min_group", 2.0, validation.MAX_GROUPS, integer=True)
    _check_range(cfg, "detector", "max_group", 2.0, validation.MAX_GROUPS, integer=True)
    _check_spectrograph_keys(cfg)
    min_group, max_group = det.get("min_group", 2), det.get("max_group", 64)
    if max_group and min_group and max_group < min_group:
        raise _bad("detector", "max_group", max_group, f"must be ≥ min_group = {min_group!r}")
    mode = det.get("readout_mode")
    if mode is not None and max_group:
        try:
            n, _, _ = validation.readout(mode, name="[detector] readout_mode", error=ConfigError)
        except ConfigError as exc:
            raise _bad("detector", "readout_mode", mode, f"must be (n, m, d) integers ({exc})") from None
        if n > max_group:
            raise _bad("detector", "readout_mode", mode, f"n = {n} exceeds max_group = {max_group!r}")
    _check_range(cfg, "extraction", "aperture_radius_insigma", 0.0, lo_open=True)
    _check_range(cfg, "extraction", "nramps", 1.0, integer=True)
    _check_range(cfg, "extraction", "xdisp_width_insigma", 0.0, lo_open=True)
    _check_range(cfg, "spectrograph.psf.detector", "xdisp_sigma", 0.0)
    _check_range(cfg, "spectrograph.psf.detector", "xdisp_sigma_spectral", 0.0)
    _check_booleans(cfg, "spectrograph.optics", "dispersed")
    return cfg


def _check_booleans(cfg, table, key):
    """A TOML boolean or list of them (``true``/``false``): ``"no"``, 0 or 1 are refused, not read as truth values."""
    entries = cfg.get(table, {})
    if not isinstance(entries, dict) or entries.get(key) is None:
        return
    value = entries[key]
    values = value if isinstance(value, (list, tuple)) else [value]
    bad = [v for v in values if not isinstance(v, (bool, np.bool_))]
    if bad:
        raise _bad(table, key, value, f"must be booleans (true / false), got {validation.short_repr(bad[0])}")
