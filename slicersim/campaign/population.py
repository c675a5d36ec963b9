"""Target populations: SNe Ia drawn from distributions, or a user catalog.

A population draws its targets' parameters as an astropy Table (:meth:`draw`) and gives
their observer-frame spectra F_λ [erg/s/cm²/Å] (:meth:`spectra` for many, :meth:`spectrum`
for one catalog row: the same numbers, one implementation).  Every random parameter is
drawn from its own Philox stream keyed by (population seed, target id), so a target's
parameters depend on nothing else: not on ``n``, the order, nor on which other parameters
are switched on.

SN Ia spectra: :mod:`slicersim.campaign.snia_model` (sncosmo's model exactly), with
M = ``peak_absmag`` + N(0, ``mag_scatter``) drawn here.

Hosts (optional): an elliptical Sersic profile whose effective radius follows the
Shen et al. (2003, MNRAS 343, 978, eq. 18, late types, SDSS r, h = 0.7) size–luminosity
relation with its luminosity-dependent log-normal scatter; the SN is placed on the host's
light distribution (inverse of the Sersic enclosed-light fraction, uniform azimuth).
The host spectrum is a two-temperature stellar continuum (old 4000 K + young 12000 K
black bodies, ``young_fraction`` of the flux at 5500 Å) normalised to the host's absolute
magnitude in rest-frame ``bessellr`` (AB) — a smooth continuum, no lines or 4000 Å break —
or a user rest-frame spectrum file.
"""
from __future__ import annotations

import os
import numpy as np

from slicersim import rng
from slicersim.campaign.distributions import Distribution, RedshiftDistribution
from slicersim.campaign.snia_model import SNIaModel, cosmology, model_fluxes, restframe_to_observed
from slicersim.campaign.snia_model import snia_fluxes  # noqa: F401  (documented path: docs/guide/campaigns.md)
from slicersim import validation
from slicersim.errors import ConfigError, SpectrumError
from slicersim.validation import number, shown
from slicersim.io.tables import file_digest, read_spectrum_table as _read_spectrum_table, read_table, resolve_path
from slicersim.sources.spectra import blackbody_flambda

__all__ = ["SNIaPopulation", "CatalogPopulation", "population_from_spec", "POPULATIONS", "snia_fluxes"]

#: Philox streams of the population parameters (one per parameter)
STREAMS = {"redshift": 0x5A01, "phase": 0x5A02, "x1": 0x5A03, "c": 0x5A04, "mag": 0x5A05,
           "mwebv": 0x5A06, "hostebv": 0x5A07, "host_absmag": 0x5A08, "host_size": 0x5A09,
           "host_shape": 0x5A0A, "host_position": 0x5A0B}
MAX_TARGETS = 10_000_000

_SN_KEYS = {"source": "hsiao-subsampled", "phase": 0.0, "peak_absmag": -19.3, "mag_scatter": 0.0,
            "band": "bessellb", "magsys": "ab", "x1": None, "c": None, "alpha": 0.14, "beta": 3.1,
            "cosmology": "Planck18", "mw_dust": None, "host_dust": None, "hosts": None, "cadence": None}
#: most visits of one SN (``cadence``)
MAX_VISITS = 1000
_DUST_KEYS = {"ebv": 0.0, "r_v": 3.1}
_HOST_KEYS = {"absmag": {"distribution": "normal", "mean": -20.5, "sigma": 1.0, "min": -23.5, "max": -17.0},
              "sersic_index": 1.0, "axis_ratio": {"distribution": "uniform", "min": 0.3, "max": 1.0},
              "young_fraction": 0.5, "spectrum": None, "max_radius": 4.0}


# ---------------------------------------------------------------------------- helpers
def _unknown(section, allowed, where):
    for key in section:
        if key not in allowed:
            raise ConfigError(f"unknown key {where}{key!r} in the campaign spec; known: {', '.join(sorted(allowed))}")


# ---------------------------------------------------------------------------- hosts
def shen03_radius_kpc(absmag, u):
    """Shen et al. (2003) late-type R_50 [kpc] at SDSS r absolute magnitude ``absmag``
    (h = 0.7), with its log-normal scatter drawn from the uniform ``u`` (eq. 16, 18)."""
    from scipy.special import ndtri
    alpha, beta, gamma, m0, s1, s2 = 0.21, 0.53, -1.31, -20.52, 0.48, 0.25
    absmag = np.asarray(absmag, float)
    log_r = -0.4 * alpha * absmag + (beta - alpha) * np.log10(1 + 10 ** (-0.4 * (absmag - m0))) + gamma
    sigma_ln = s2 + (s1 - s2) / (1 + 10 ** (-0.8 * (absmag - m0)))
    return 10 ** log_r * np.exp(sigma_ln * ndtri(u))


class HostModel:
    """Sersic hosts from a size–luminosity relation (see the module docstring).

    Catalog columns: host_absmag (rest-frame bessellr AB), host_r_eff [arcsec],
    host_sersic_index, host_axis_ratio, host_position_angle [deg], host_offset_x/y
    [arcsec]: the host centre relative to the SN."""

    COLUMNS = ("host_absmag", "host_r_eff", "host_sersic_index", "host_axis_ratio", "host_position_angle",
               "host_offset_x", "host_offset_y")

    def __init__(self, section, base_dir="."):
        if section is True:
            section = {}
        if not isinstance(section, dict):
            raise ConfigError(f"population.hosts must be a table (hosts = {{}} for the defaults), got {section!r}")
        section = dict(section)
        _unknown(section, _HOST_KEYS, "population.hosts.")
        cfg = {**_HOST_KEYS, **section}
        self.absmag = Distribution.parse(cfg["absmag"], "population.hosts.absmag")
        self.sersic_index = Distribution.parse(cfg["sersic_index"], "population.hosts.sersic_index", lo=0.3, hi=8)
        self.axis_ratio = Distribution.parse(cfg["axis_ratio"], "population.hosts.axis_ratio", lo=0.05, hi=1)
        self.young_fraction = number("population.hosts.young_fraction", cfg["young_fraction"], low=0, high=1,
                                     error=ConfigError)
        self.max_radius = number("population.hosts.max_radius", cfg["max_radius"], low=0.5, high=20,
                                 error=ConfigError)
        self.spectrum_file = cfg["spectrum"]
        self.spectrum_digest = None
        if self.spectrum_file is not None:
            path = resolve_path(self.spectrum_file, base_dir, "population.hosts.spectrum")
            self.spectrum_file = path
            self.rest_lbda, self.rest_flux = read_spectrum_table(path, "population.hosts.spectrum")
            self.spectrum_digest = file_digest(path)
        else:
            self.rest_lbda = np.arange(900.0, 30000.0, 10.0)
            old, young = blackbody_flambda(self.rest_lbda, 4000.0), blackbody_flambda(self.rest_lbda, 12000.0)
            i55 = np.searchsorted(self.rest_lbda, 5500.0)
            self.rest_flux = ((1 - self.young_fraction) * old / old[i55]
                              + self.young_fraction * young / young[i55])
        self.section = cfg

    def to_spec(self):
        out = {"absmag": self.absmag.to_spec(), "sersic_index": self.sersic_index.to_spec(),
               "axis_ratio": self.axis_ratio.to_spec(), "young_fraction": self.young_fraction,
               "max_radius": self.max_radius, "spectrum": self.spectrum_file}
        if self.spectrum_digest:
            out["spectrum_sha256"] = self.spectrum_digest
        return out

    def draw(self, seed, ids, z, cosmo):
        from scipy.special import gammaincinv

        from slicersim.sources.extended import sersic_bn
        absmag = self.absmag.draw(rng.uniform(seed, ids, STREAMS["host_absmag"]))
        size_u = rng.uniform(seed, ids, STREAMS["host_size"])
        shape_u = rng.uniform(seed, ids, STREAMS["host_shape"])
        pos_u = rng.uniform(seed, ids, STREAMS["host_position"])
        n_s = self.sersic_index.draw(size_u[:, 1:])
        q = self.axis_ratio.draw(shape_u[:, :1] if shape_u.ndim == 2 else shape_u)
        pa = 180.0 * shape_u[:, 1]
        r_kpc = shen03_radius_kpc(absmag, size_u[:, 0])
        arcsec_per_kpc = cosmo.arcsec_per_kpc_proper(z).value
        r_eff = r_kpc * arcsec_per_kpc
        # the SN on the host's light: L(<r)/L = P(2n, b_n (r/r_e)^(1/n)), truncated at max_radius r_e
        bn = np.array([sersic_bn(v) for v in n_s])
        from scipy.special import gammainc
        fmax = gammainc(2 * n_s, bn * self.max_radius ** (1 / n_s))
        r_sn = r_eff * (gammaincinv(2 * n_s, pos_u[:, 0] * fmax) / bn) ** n_s
        theta = 2 * np.pi * pos_u[:, 1]
        u, v = r_sn * np.cos(theta), q * r_sn * np.sin(theta)          # host frame (major, minor axes)
        phi = np.deg2rad(pa)
        dx, dy = u * np.cos(phi) - v * np.sin(phi), u * np.sin(phi) + v * np.cos(phi)
        return {"host_absmag": absmag, "host_r_eff": r_eff, "host_sersic_index": n_s, "host_axis_ratio": q,
                "host_position_angle": pa, "host_offset_x": -dx, "host_offset_y": -dy}

    def build(self, row, cosmo):
        """The :class:`~slicersim.sources.extended.Host` of one row (offset relative to the SN)."""
        from slicersim.sources.extended import Host, SersicProfile
        z = float(row["redshift"])
        lbda = np.arange(3000.0, 20001.0, 10.0)
        flux = restframe_to_observed(lbda, self.rest_lbda, self.rest_flux, float(row["host_absmag"]), z,
                                      "bessellr", cosmo)
        ok = np.isfinite(flux)
        profile = SersicProfile(float(row["host_sersic_index"]), float(row["host_r_eff"]),
                                float(row["host_axis_ratio"]), float(row["host_position_angle"]),
                                offset=(float(row["host_offset_x"]), float(row["host_offset_y"])))
        return Host(profile, lbda[ok], flux[ok])


def read_spectrum_table(path, name):
    """Validated (λ [Å], F_λ) of a user spectrum file (one ConfigError naming ``name``)."""
    from slicersim.sources.spectra import validate_spectrum
    try:
        return validate_spectrum(*_read_spectrum_table(path, name), f"{name} {path}")
    except SpectrumError as exc:
        raise ConfigError(str(exc)) from None


# ---------------------------------------------------------------------------- cadence
def _cadence(value):
    """The validated ``population.cadence``: None, or increasing observer-frame days ≥ 0 starting at 0."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or not 1 <= len(value) <= MAX_VISITS:
        raise ConfigError(f"population.cadence must be a list of 1 to {MAX_VISITS} observer-frame days of the visits "
                          f"after the first (e.g. [0, 10, 20]), got {validation.short_repr(value)}")
    days = [number(f"population.cadence[{i}] [observer-frame days]", v, low=0, high=3650, error=ConfigError)
            for i, v in enumerate(value)]
    if days[0] != 0 or any(b <= a for a, b in zip(days, days[1:])):
        raise ConfigError(f"population.cadence must start at 0 (the first visit, at the drawn phase) and increase "
                          f"strictly, got {days}")
    return tuple(days)


def visits(table, cadence):
    """One row per visit of each SN of ``table``: the SN's parameters repeated, its phase advanced.

    Parameters
    ----------
    table : astropy.table.Table
        One row per SN, with ``target_id`` (unique integers ≥ 0), ``redshift`` and ``phase``
        [rest-frame days at the first visit].
    cadence : sequence of float
        Observer-frame days of the visits after the first (starting at 0, increasing).

    Returns
    -------
    astropy.table.Table
        ``len(table) * len(cadence)`` rows, SN by SN: ``sn_id`` (the SN's ``target_id``),
        ``visit`` (0, 1, …), ``visit_day`` [observer-frame days since the first visit],
        ``phase`` = phase + visit_day / (1 + z) [rest-frame days] and a new unique
        ``target_id`` = sn_id × len(cadence) + visit (each visit its own exposure and noise).
    """
    k = len(cadence)
    clash = [c for c in ("sn_id", "visit", "visit_day") if c in table.colnames]
    if clash:
        raise ConfigError(f"population.cadence makes the columns {clash}: the catalog may not have them")
    sn_id = np.asarray(table["target_id"]).astype(np.int64)
    if sn_id.size and int(sn_id.max()) > (2**62) // k:
        raise ConfigError(f"population.cadence: target_id up to {int(sn_id.max())} × {k} visits overflows the ids")
    out = table[np.repeat(np.arange(len(table)), k)]
    day = np.tile(np.asarray(cadence, dtype=float), len(table))
    z = np.asarray(out["redshift"], dtype=float)
    out["target_id"] = np.repeat(sn_id, k) * k + np.tile(np.arange(k), len(table))
    out["phase"] = np.asarray(out["phase"], dtype=float) + day / (1.0 + z)
    out.add_column(np.repeat(sn_id, k), name="sn_id", index=1)
    out.add_column(np.tile(np.arange(k, dtype=np.int64), len(table)), name="visit", index=2)
    out.add_column(day, name="visit_day", index=3)
    return out


# ---------------------------------------------------------------------------- populations
class _SNParameters:
    """SN Ia parameters shared by the drawn and the catalog populations."""

    def _parse_sn(self, cfg, base_dir):
        src = cfg["source"]
        if not isinstance(src, str) or not src:
            raise ConfigError(f"population.source must be an sncosmo SN Ia source name, got {src!r}")
        self.source = src
        self.salt = "salt" in src.lower()
        for key in ("x1", "c"):
            if cfg[key] is not None and not self.salt:
                raise ConfigError(f"population.{key}: x1 / c are SALT parameters; source {src!r} has none "
                                  "(use source = \"salt2\" or \"salt3\", with sncosmo's data available)")
        self.phase = Distribution.parse(cfg["phase"], "population.phase", lo=-20, hi=85)
        self.peak_absmag = number("population.peak_absmag", cfg["peak_absmag"], low=-25, high=-10,
                                  error=ConfigError)
        self.mag_scatter = number("population.mag_scatter", cfg["mag_scatter"], low=0, high=2, error=ConfigError)
        self.x1 = Distribution.parse(cfg["x1"] if cfg["x1"] is not None else
                                     ({"distribution": "normal", "mean": 0.0, "sigma": 1.0, "min": -3, "max": 3}
                                      if self.salt else 0.0), "population.x1", lo=-5, hi=5)
        self.c = Distribution.parse(cfg["c"] if cfg["c"] is not None else
                                    ({"distribution": "normal", "mean": 0.0, "sigma": 0.1, "min": -0.3, "max": 0.5}
                                     if self.salt else 0.0), "population.c", lo=-1, hi=2)
        self.alpha = number("population.alpha", cfg["alpha"], low=-5, high=5, error=ConfigError)
        self.beta = number("population.beta", cfg["beta"], low=-10, high=10, error=ConfigError)
        import sncosmo
        for key, reg in (("band", sncosmo.get_bandpass), ("magsys", sncosmo.get_magsystem)):
            try:
                reg(cfg[key])
            except Exception:
                raise ConfigError(f"population.{key}: unknown sncosmo {key} {cfg[key]!r}") from None
        self.band, self.magsys = cfg["band"], cfg["magsys"]
        self.cosmology_name = cfg["cosmology"]
        cosmology(self.cosmology_name)
        self.mw_dust = self._dust(cfg["mw_dust"], "population.mw_dust")
        self.host_dust = self._dust(cfg["host_dust"], "population.host_dust")
        self.hosts = None if cfg["hosts"] in (None, False) else HostModel(cfg["hosts"], base_dir)
        self.cadence = _cadence(cfg["cadence"])

    @staticmethod
    def _dust(section, name):
        if section is None:
            return None
        if not isinstance(section, dict):
            raise ConfigError(f"{name} must be a table {{ebv = ..., r_v = 3.1}}, got {section!r}")
        _unknown(section, _DUST_KEYS, f"{name}.")
        cfg = {**_DUST_KEYS, **section}
        return {"ebv": Distribution.parse(cfg["ebv"], f"{name}.ebv", lo=0, hi=5),
                "r_v": number(f"{name}.r_v", cfg["r_v"], low=1, high=8, error=ConfigError)}

    @property
    def cosmology(self):
        return cosmology(self.cosmology_name)

    def _sn_spec(self):
        dust = {k: (None if d is None else {"ebv": d["ebv"].to_spec(), "r_v": d["r_v"]})
                for k, d in (("mw_dust", self.mw_dust), ("host_dust", self.host_dust))}
        return {"source": self.source, "phase": self.phase.to_spec(), "peak_absmag": self.peak_absmag,
                "mag_scatter": self.mag_scatter, "x1": self.x1.to_spec(), "c": self.c.to_spec(),
                "alpha": self.alpha, "beta": self.beta, "band": self.band, "magsys": self.magsys,
                "cosmology": self.cosmology_name, **dust,
                "hosts": None if self.hosts is None else self.hosts.to_spec(),
                **({} if self.cadence is None else {"cadence": list(self.cadence)})}

    def _draw_sn(self, seed, ids, table):
        """Fill the SN columns of ``table`` that it does not have (catalog columns win)."""
        from scipy.special import ndtri
        n = len(ids)

        def put(name, values):
            if name not in table.colnames:
                table[name] = np.broadcast_to(values, (n,)).astype(float)
        put("phase", self.phase.draw(rng.uniform(seed, ids, STREAMS["phase"])))
        if self.salt:
            put("x1", self.x1.draw(rng.uniform(seed, ids, STREAMS["x1"])))
            put("c", self.c.draw(rng.uniform(seed, ids, STREAMS["c"])))
        scatter = self.mag_scatter * ndtri(rng.uniform(seed, ids, STREAMS["mag"])[:, 0]) if self.mag_scatter \
            else 0.0
        put("peak_absmag", self.peak_absmag + scatter)
        if self.mw_dust is not None:
            put("mwebv", self.mw_dust["ebv"].draw(rng.uniform(seed, ids, STREAMS["mwebv"])))
        if self.host_dust is not None:
            put("hostebv", self.host_dust["ebv"].draw(rng.uniform(seed, ids, STREAMS["hostebv"])))
        if self.hosts is not None:
            for name, col in self.hosts.draw(seed, ids, np.asarray(table["redshift"], float),
                                             self.cosmology).items():
                put(name, col)
        return table if self.cadence is None else visits(table, self.cadence)

    def _sn_fluxes(self, table, lbda):
        def col(name):
            return np.asarray(table[name], dtype=float) if name in table.colnames else None
        model = SNIaModel(self.source, self.band, self.magsys, alpha=self.alpha, beta=self.beta,
                          cosmology=self.cosmology_name, mw_rv=(self.mw_dust or _DUST_KEYS)["r_v"],
                          host_rv=(self.host_dust or _DUST_KEYS)["r_v"])
        return model_fluxes(lbda, model, col("redshift"), col("phase"), col("peak_absmag"), x1=col("x1"), c=col("c"),
                            mwebv=col("mwebv"), hostebv=col("hostebv"))

    def host(self, row):
        """The host of a catalog row, or None."""
        if self.hosts is None or "host_r_eff" not in row:
            return None
        return self.hosts.build(row, self.cosmology)

    def spectrum(self, row, lbda):
        """(λ, F_λ) of one catalog row: the covered part of :meth:`spectra` on ``lbda``."""
        from astropy.table import Table
        table = Table({k: [v] for k, v in dict(row).items() if np.ndim(v) == 0})
        flux = self.spectra(table, lbda)[0]
        ok = np.isfinite(flux)
        if np.count_nonzero(ok) < 2:
            raise SpectrumError(f"target {row.get('target_id')}: no model flux on {lbda[0]:.0f}–{lbda[-1]:.0f} Å")
        return np.asarray(lbda, float)[ok], flux[ok]


class SNIaPopulation(_SNParameters):
    """``n`` SNe Ia with redshifts from ``redshift`` (see :class:`RedshiftDistribution`)
    and the SN parameters of the module docstring."""

    kind = "snia"

    def __init__(self, n, redshift=None, base_dir=".", **sn):
        self.n = validation.integer("population.n (an empty population has nothing to simulate)", n, low=1,
                                    high=MAX_TARGETS, error=ConfigError)
        self.redshift = RedshiftDistribution.parse(
            redshift if redshift is not None else {"distribution": "uniform", "min": 0.05, "max": 1.5},
            base_dir=base_dir)
        _unknown(sn, _SN_KEYS, "population.")
        self._parse_sn({**_SN_KEYS, **sn}, base_dir)

    def draw(self, seed):
        """Table of the targets: target_id, redshift, phase, peak_absmag [, x1, c, mwebv, hostebv, host_*]."""
        from astropy.table import Table
        ids = np.arange(self.n, dtype=np.int64)
        z = self.redshift.draw(rng.uniform(seed, ids.astype(np.uint64), STREAMS["redshift"]),
                               cosmology=self.cosmology)
        table = Table({"target_id": ids, "redshift": z})
        return self._draw_sn(seed, ids.astype(np.uint64), table)

    def spectra(self, table, lbda):
        return self._sn_fluxes(table, lbda)

    def to_spec(self):
        return {"kind": self.kind, "n": self.n, "redshift": self.redshift.to_spec(), **self._sn_spec()}


class CatalogPopulation(_SNParameters):
    """Targets from a user table (ECSV, CSV or Parquet).

    Required column: ``redshift`` (> 0).  Optional: ``target_id`` (unique integers ≥ 0;
    default the row number), SN Ia parameters (``phase``, ``peak_absmag``, ``x1``, ``c``,
    ``mwebv``, ``hostebv``, ``host_*``; missing ones are drawn as for ``kind = "snia"``),
    and ``spectrum_file``: a table (lbda [Å], flux [erg/s/cm²/Å], observer frame, relative
    to the catalog) used as the target's spectrum instead of the SN Ia model.  Other
    columns are carried to the dataset catalog."""

    kind = "catalog"
    RESERVED = ("sn_id", "visit", "visit_day", "field", "n", "m", "d", "nramps", "exposure_time", "snr", "data_volume", "data_volume_compressed",
                "status", "error", "seed", "ramp_seed",
                *(f"{p}_{s}" for p in ("spectrum", "cube", "detector_image", "ramps") for s in ("product", "sha256")))
    #: bounds of the catalog's parameter columns (the spec's bounds for the same parameters)
    BOUNDS = {"redshift": (0, 10), "phase": (-20, 85), "peak_absmag": (-25, -10), "x1": (-5, 5), "c": (-1, 2),
              "mwebv": (0, 5), "hostebv": (0, 5), "host_absmag": (-26, -10), "host_r_eff": (1e-3, 600),
              "host_sersic_index": (0.3, 8), "host_axis_ratio": (0.05, 1), "host_position_angle": (-360, 360),
              "host_offset_x": (-600, 600), "host_offset_y": (-600, 600)}

    def __init__(self, file, base_dir=".", **sn):
        self.file = resolve_path(file, base_dir, shown("population.file"))
        self.digest = file_digest(self.file)
        _unknown(sn, _SN_KEYS, "population.")
        self._parse_sn({**_SN_KEYS, **sn}, base_dir)
        self.base_dir = os.path.dirname(self.file)
        self._check(self._read())

    SN_COLUMNS = ("redshift", "target_id", "phase", "peak_absmag", "x1", "c", "mwebv", "hostebv")

    @property
    def _where(self):
        """The table as messages name it: its key (or the flag, :func:`slicersim.validation.flag_names`)
        and its path."""
        return f"{shown('population.file')} {self.file}"

    def _read(self):
        """The user table with its empty cells filled: "" in text columns, NaN in other
        numeric columns; an empty redshift or SN parameter is an error naming the row."""
        from astropy.table import Table
        tab = read_table(self.file, shown("population.file"))
        for name in tab.colnames:
            col = tab[name]
            mask = np.asarray(getattr(col, "mask", np.zeros(len(col), bool)))
            if not mask.any():
                continue
            if name in self.SN_COLUMNS or name.startswith("host_"):
                raise ConfigError(f"{self._where}: column {name!r} is empty in row {int(np.nonzero(mask)[0][0])}")
            kind = np.asarray(col).dtype.kind
            if kind in "US":
                tab[name] = col.filled("")
            elif kind in "iufcb":                 # integers become floats: an empty cell is NaN, not 0
                tab[name] = np.where(mask, np.nan, np.asarray(col.filled(0), dtype=float))
            else:
                raise ConfigError(f"{self._where}: column {name!r} has empty cells (row "
                                  f"{int(np.nonzero(mask)[0][0])}) of an unsupported type")
        return Table(tab, masked=False)

    def _check(self, tab):
        if len(tab) == 0:
            raise ConfigError(f"{self._where} has no rows: an empty population has nothing to simulate")
        if "redshift" not in tab.colnames:
            raise ConfigError(f"{self._where} has no 'redshift' column (columns: {tab.colnames})")
        clash = [c for c in tab.colnames if c in self.RESERVED]
        if clash:
            raise ConfigError(f"{self._where}: columns {clash} are computed by the campaign and the ETC; rename them")
        salt_cols = [c for c in ("x1", "c") if c in tab.colnames]
        if salt_cols and not self.salt:
            raise ConfigError(f"{self._where}: columns {salt_cols} are SALT parameters; source {self.source!r} has "
                              "none (use the source salt2 or salt3, with sncosmo's data available)")
        for name, (lo, hi) in self.BOUNDS.items():
            if name not in tab.colnames:
                continue
            try:
                values = np.asarray(tab[name], dtype=float)
            except (TypeError, ValueError):
                raise ConfigError(f"{self._where}: column {name!r} is not numeric{_first_not_number(tab[name])}") \
                    from None
            bad = ~((values >= lo) & (values <= hi))
            if bad.any():
                i = int(np.nonzero(bad)[0][0])
                raise ConfigError(f"{self._where}: {name} = {values[i]:g} in row {i} is outside [{lo}, {hi}]"
                                  + (" (redshifts cannot be negative)" if name == "redshift" and values[i] < 0 else ""))
        host_cols = [c for c in tab.colnames if c.startswith("host_")]
        if host_cols and self.hosts is not None and set(host_cols) != set(HostModel.COLUMNS):
            raise ConfigError(f"{self._where}: give all host columns {list(HostModel.COLUMNS)} or none "
                              f"(has {host_cols})")
        z = np.asarray(tab["redshift"], dtype=float)
        if np.any(~np.isfinite(z)) or np.any(z < 0):
            raise ConfigError(f"{self._where}: redshifts must be finite and not negative (row "
                              f"{int(np.nonzero(~(z >= 0))[0][0])})")
        if "spectrum_file" not in tab.colnames and np.any(z == 0):
            raise ConfigError(f"{self._where}: SN Ia redshifts must be > 0 (row {int(np.nonzero(z == 0)[0][0])}; "
                              "give a spectrum_file for z = 0)")
        if "target_id" in tab.colnames:
            ids = np.asarray(tab["target_id"])
            if ids.dtype.kind not in "iu" or np.any(ids < 0) or len(np.unique(ids)) != len(ids):
                raise ConfigError(f"{self._where}: target_id must be unique integers ≥ 0{_first_bad_id(ids)}")
        return tab

    def draw(self, seed):
        tab = self._read()
        if "target_id" not in tab.colnames:
            tab.add_column(np.arange(len(tab), dtype=np.int64), name="target_id", index=0)
        ids = np.asarray(tab["target_id"]).astype(np.uint64)
        tab["redshift"] = np.asarray(tab["redshift"], dtype=float)
        return self._draw_sn(seed, ids, tab)

    def spectra(self, table, lbda):
        lbda = np.asarray(lbda, float)
        if "spectrum_file" not in table.colnames:
            return self._sn_fluxes(table, lbda)
        col = table["spectrum_file"]
        files = np.asarray(col.filled("") if hasattr(col, "filled") else col).astype(str)
        user = np.char.str_len(np.char.strip(files)) > 0
        out = np.full((len(table), lbda.size), np.nan)
        if (~user).any():
            out[~user] = self._sn_fluxes(table[~user], lbda)
        for i in np.nonzero(user)[0]:
            path = resolve_path(files[i], self.base_dir, f"population.file row {i} spectrum_file")
            sl, sf = read_spectrum_table(path, "spectrum_file")
            out[i] = np.interp(lbda, sl, sf, left=np.nan, right=np.nan)
        return out

    def spectrum_files_digest(self):
        """sha256 over the (name, sha256) of every spectrum_file the catalog names ('' if none):
        editing a user spectrum changes the dataset's identity."""
        import hashlib
        tab = self._read()
        if "spectrum_file" not in tab.colnames:
            return ""
        names = sorted({str(v).strip() for v in tab["spectrum_file"] if str(v).strip()})
        h = hashlib.sha256()
        for name in names:
            path = resolve_path(name, self.base_dir, "population.file spectrum_file")
            h.update(f"{name}\0{file_digest(path)}\n".encode())
        return h.hexdigest() if names else ""

    def to_spec(self):
        return {"kind": self.kind, "file": self.file, "file_sha256": self.digest,
                "spectrum_files_sha256": self.spectrum_files_digest(), **self._sn_spec()}


def _first_not_number(column):
    """" (row i: 'value')" naming the first cell of ``column`` that is not a number."""
    for i, value in enumerate(column):
        try:
            float(value)
        except (TypeError, ValueError):
            return f" (row {i}: {validation.short_repr(str(value))})"
    return ""


def _first_bad_id(ids):
    """" (row i: ...)" naming the first target_id that is not an integer ≥ 0 or repeats an earlier one."""
    if ids.dtype.kind not in "iu":
        return f" (the column holds {ids.dtype.name} values, e.g. {validation.short_repr(ids[0])} in row 0)"
    seen = {}
    for i, v in enumerate(ids.tolist()):
        if v < 0:
            return f" (row {i}: {v})"
        if v in seen:
            return f" (row {i}: {v}, as row {seen[v]})"
        seen[v] = i
    return ""


POPULATIONS = {"snia": SNIaPopulation, "catalog": CatalogPopulation}


def population_from_spec(section, base_dir="."):
    """The population of a ``[population]`` table (unknown keys and kinds are errors)."""
    if not isinstance(section, dict):
        raise ConfigError(f"[population] must be a TOML table, got {section!r}")
    section = dict(section)
    kind = section.pop("kind", "snia")
    if not isinstance(kind, str) or kind not in POPULATIONS:
        raise ConfigError(f"population.kind {kind!r} unknown; known: {', '.join(POPULATIONS)}")
    if kind == "snia":
        _unknown(section, {"n", "redshift", *_SN_KEYS}, "population.")
        if "n" not in section:
            raise ConfigError("population.n (the number of targets) is required for kind = \"snia\"")
        return SNIaPopulation(section.pop("n"), section.pop("redshift", None), base_dir=base_dir, **section)
    _unknown(section, {"file", *_SN_KEYS}, "population.")
    if "file" not in section:
        raise ConfigError("population.file (ECSV, CSV or Parquet table of targets) is required for kind = \"catalog\"")
    return CatalogPopulation(section.pop("file"), base_dir=base_dir, **section)
