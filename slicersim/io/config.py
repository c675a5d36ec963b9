"""Instrument configuration: TOML files (reference format) merged in order.

``load_config("cbe")`` returns the built-in Lazuli current-best-estimate
configuration; ``"eol"`` is CBE with the end-of-life overrides applied; a path
(or a list of paths / names) loads TOML files in the reference's format, later
files overriding earlier ones.  Curve file names are resolved next to the TOML
that names them and stored as absolute paths.
"""
from __future__ import annotations

from slicersim.errors import ConfigError  # noqa: F401  (re-exported)

import copy
import os
import tomllib
from importlib import resources

__all__ = ["load_config", "ConfigError", "builtin_config_dir", "SCHEMA"]




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
        else:
            raise ConfigError(f"top-level key {name!r} must live in a table such as [detector]")
    return out


def _read_toml(path):
    if not os.path.isfile(path):
        raise ConfigError(f"configuration file not found: {path}")
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"cannot parse TOML {path}: {exc}") from exc
    tables = _flatten_tables(doc)
    here = os.path.dirname(os.path.abspath(path))
    for table, entries in tables.items():
        if table not in SCHEMA:
            raise ConfigError(f"{path}: unknown configuration table [{table}]; "
                              f"known tables: {sorted(SCHEMA)}")
        unknown = set(entries) - SCHEMA[table]
        if unknown:
            raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)} in [{table}]; "
                              f"allowed: {sorted(SCHEMA[table])}")
        for key in list(entries):
            if (table, key) in FILE_KEYS and isinstance(entries[key], str):
                fpath = entries[key] if os.path.isabs(entries[key]) else os.path.join(here, entries[key])
                if not os.path.isfile(fpath):
                    raise ConfigError(f"{path}: [{table}] {key} = {entries[key]!r}: "
                                      f"curve file not found at {fpath}")
                entries[key] = fpath
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
    config : str, path or list
        ``"cbe"``, ``"eol"``, a TOML path, or a list of names/paths applied in order.

    Returns
    -------
    dict  table name (e.g. ``"detector"``, ``"spectrograph.optics"``) -> {key: value};
    the ``"_sources"`` entry lists the files read.
    """
    if isinstance(config, dict):
        return copy.deepcopy(config)
    merged = {}
    paths = expand_config(config)
    for path in paths:
        for table, entries in _read_toml(path).items():
            merged.setdefault(table, {}).update(entries)
    merged["_sources"] = [os.path.abspath(p) for p in paths]
    return merged
