"""Parameter distributions of populations, drawn by inverse CDF from Philox uniforms.

A spec value is a number (fixed) or a table ``{distribution = ..., ...}``:

=================  ==========================================================
fixed              ``value``
uniform            ``min``, ``max``
normal             ``mean``, ``sigma`` [, ``min``, ``max``: truncation]
exponential        ``scale`` [, ``max``: truncation]   (E(B−V) of host dust)
=================  ==========================================================

Redshifts (:class:`RedshiftDistribution`) also take ``volumetric`` (``min``, ``max``,
``rate_index`` α, default 1.5: a volumetric rate ∝ (1+z)^α times dV/dz/(1+z) of the
population's cosmology, the observed-frame time dilation included) and ``table``
(``file`` with columns ``z`` and ``weight``: a piecewise-linear density).
"""
from __future__ import annotations

import os

import numpy as np

from slicersim.errors import ConfigError
from slicersim.validation import number, shown

__all__ = ["Distribution", "RedshiftDistribution"]

_KEYS = {"fixed": {"value"}, "uniform": {"min", "max"}, "normal": {"mean", "sigma", "min", "max"},
         "exponential": {"scale", "max"}}
_REQUIRED = {"fixed": {"value"}, "uniform": {"min", "max"}, "normal": {"mean", "sigma"}, "exponential": {"scale"}}


def _first(u):
    u = np.asarray(u, dtype=float)
    return u[:, 0] if u.ndim == 2 else u


class Distribution:
    """One scalar parameter's distribution (see the module docstring)."""

    def __init__(self, kind, params, name):
        self.kind, self.params, self.name = kind, params, name

    @classmethod
    def parse(cls, spec, name, lo=None, hi=None):
        """From a number or a ``{distribution = ...}`` table; values outside [lo, hi] are refused."""
        if not isinstance(spec, dict):
            spec = {"distribution": "fixed", "value": spec}
        spec = dict(spec)
        kind = spec.pop("distribution", None)
        if not isinstance(kind, str) or kind not in _KEYS:
            raise ConfigError(f"{name}.distribution must be one of {', '.join(map(repr, _KEYS))}, got {kind!r}")
        for key in spec:
            if key not in _KEYS[kind]:
                raise ConfigError(f"unknown key {name}.{key!r} for a {kind} distribution; known: "
                                  f"{', '.join(sorted(_KEYS[kind]))}")
        missing = _REQUIRED[kind] - set(spec)
        if missing:
            raise ConfigError(f"{name}: a {kind} distribution needs {', '.join(sorted(missing))}")
        p = {k: number(f"{name}.{k}", v, error=ConfigError) for k, v in spec.items()}
        if kind in ("normal", "exponential") and p.get("sigma", p.get("scale", 1)) <= 0:
            raise ConfigError(f"{name}: sigma / scale must be > 0")
        if "min" in p and "max" in p and not p["min"] <= p["max"]:
            raise ConfigError(f"{name}: min ({p['min']}) must be ≤ max ({p['max']})")
        dist = cls(kind, p, name)
        lo_v, hi_v = dist.support()
        if (lo is not None and lo_v < lo) or (hi is not None and hi_v > hi):
            how = {"normal": "min / max", "exponential": "max", "uniform": "min / max"}.get(kind, "value")
            raise ConfigError(f"{name} must lie in [{lo}, {hi}]; the {kind} distribution {p} reaches "
                              f"[{lo_v:.6g}, {hi_v:.6g}] (set its {how} within the range)")
        return dist

    def support(self):
        """Smallest and largest value a draw can take (uniforms lie in [2⁻⁵³, 1 − 2⁻⁵³])."""
        lo, hi = self.draw(np.array([2.0**-53, 1 - 2.0**-53]))
        return float(lo), float(hi)

    def draw(self, u):
        """Values from uniforms ``u`` in (0, 1) ((N,) or (N, 2): the first column is used)."""
        from scipy.special import ndtr, ndtri
        u = _first(u)
        p, k = self.params, self.kind
        if k == "fixed":
            return np.full(u.shape, p["value"])
        if k == "uniform":
            return p["min"] + u * (p["max"] - p["min"])
        if k == "normal":
            a = ndtr((p.get("min", -np.inf) - p["mean"]) / p["sigma"])
            b = ndtr((p.get("max", np.inf) - p["mean"]) / p["sigma"])
            x = p["mean"] + p["sigma"] * ndtri(a + u * (b - a))
            return np.clip(x, p.get("min", -np.inf), p.get("max", np.inf))
        fmax = -np.expm1(-p["max"] / p["scale"]) if "max" in p else 1.0
        return -p["scale"] * np.log1p(-u * fmax)

    def to_spec(self):
        return {"distribution": self.kind, **self.params}


class RedshiftDistribution:
    """Redshift distribution of a population (see the module docstring)."""

    KINDS = {"uniform": {"min", "max"}, "volumetric": {"min", "max", "rate_index"}, "table": {"file"},
             "fixed": {"value"}}
    MAX_Z = 10.0

    def __init__(self, kind, params, table=None, digest=None):
        self.kind, self.params, self.table, self.digest = kind, params, table, digest

    @classmethod
    def parse(cls, spec, base_dir="."):
        name = "population.redshift"
        if not isinstance(spec, dict):
            spec = {"distribution": "fixed", "value": spec}
        spec = dict(spec)
        kind = spec.pop("distribution", "uniform")
        if not isinstance(kind, str) or kind not in cls.KINDS:
            raise ConfigError(f"{name}.distribution must be one of {', '.join(map(repr, cls.KINDS))}, got {kind!r}")
        for key in spec:
            if key not in cls.KINDS[kind]:
                raise ConfigError(f"unknown key {name}.{key!r} for a {kind} redshift distribution; known: "
                                  f"{', '.join(sorted(cls.KINDS[kind]))}")
        if kind == "table":
            return cls._from_table(spec, base_dir)
        need = cls.KINDS[kind] - {"rate_index"}
        if need - set(spec):
            raise ConfigError(f"{name}: a {kind} distribution needs {', '.join(sorted(need - set(spec)))}")
        p = {k: number(f"{name}.{k}", v, error=ConfigError) for k, v in spec.items()}
        for key in ("min", "max", "value"):
            if key in p and not 0 <= p[key] <= cls.MAX_Z:
                why = "redshifts cannot be negative" if p[key] < 0 else \
                    f"redshifts above {cls.MAX_Z:g} are outside any SN Ia model"
                raise ConfigError(f"{shown(f'{name}.{key}')} must be in [0, {cls.MAX_Z:g}] ({why}), got {p[key]:g}")
        if kind == "fixed" and p["value"] == 0:
            raise ConfigError(f"{shown(f'{name}.value')}: a SN Ia needs a redshift > 0")
        if kind != "fixed" and not p["min"] < p["max"]:
            raise ConfigError(f"{shown(f'{name}.min')} ({p['min']:g}) must be < {shown(f'{name}.max')} "
                              f"({p['max']:g})")
        if kind == "volumetric":
            p.setdefault("rate_index", 1.5)
            if not -5 <= p["rate_index"] <= 10:
                raise ConfigError(f"{name}.rate_index must be in [-5, 10], got {p['rate_index']}")
        return cls(kind, p)

    @classmethod
    def _from_table(cls, spec, base_dir):
        from slicersim.io.tables import file_digest, numeric_column, read_table, resolve_path
        path = resolve_path(spec.get("file"), base_dir, "population.redshift.file")
        tab = read_table(path, "population.redshift.file")
        if not {"z", "weight"} <= set(tab.colnames):
            raise ConfigError(f"population.redshift.file {path} needs columns z and weight, has {tab.colnames}")
        z, w = (numeric_column(tab, col, path, "population.redshift.file") for col in ("z", "weight"))
        if (z.size < 2 or not np.all(np.isfinite(z)) or np.any(np.diff(z) <= 0) or z[0] < 0
                or z[-1] > cls.MAX_Z):
            raise ConfigError(f"population.redshift.file: z must increase strictly within [0, {cls.MAX_Z}] "
                              "(redshifts cannot be negative), with ≥ 2 rows")
        if not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
            raise ConfigError("population.redshift.file: weights must be finite, ≥ 0 and not all 0")
        return cls("table", {"file": os.path.abspath(path)}, table=(z, w), digest=file_digest(path))

    def density(self, cosmology, npts=4097):
        """(z grid, unnormalised density) of the distribution."""
        p = self.params
        if self.kind == "table":
            return self.table
        z = np.linspace(p["min"], p["max"], npts)
        if self.kind == "uniform":
            return z, np.ones_like(z)
        dvdz = cosmology.differential_comoving_volume(z).value          # Mpc³/sr per unit z
        return z, (1 + z) ** p["rate_index"] * dvdz / (1 + z)

    def draw(self, u, cosmology=None):
        """Redshifts from uniforms ``u`` (inverse CDF; exact for uniform, the trapezoid-rule
        CDF of a 4097-point grid for volumetric / table)."""
        u = _first(u)
        p = self.params
        if self.kind == "fixed":
            return np.full(u.shape, p["value"])
        if self.kind == "uniform":
            return p["min"] + u * (p["max"] - p["min"])
        z, w = self.density(cosmology)
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(z))])
        cdf /= cdf[-1]
        # inverse of a piecewise-linear density: solve the quadratic in each interval
        k = np.clip(np.searchsorted(cdf, u, side="right") - 1, 0, z.size - 2)
        dz = z[k + 1] - z[k]
        slope = (w[k + 1] - w[k]) / dz
        need = (u - cdf[k]) * cdf_norm(z, w)
        with np.errstate(invalid="ignore", divide="ignore"):
            x = np.where(np.abs(slope) * dz > 1e-12 * np.maximum(w[k], 1e-300),
                         (-w[k] + np.sqrt(np.maximum(w[k] ** 2 + 2 * slope * need, 0))) / slope,
                         need / np.where(w[k] > 0, w[k], 1))
        out = z[k] + np.clip(x, 0, dz)
        return np.maximum(out, np.nextafter(0, 1)) if out.min() <= 0 else out

    def to_spec(self):
        out = {"distribution": self.kind, **self.params}
        if self.digest:
            out["file_sha256"] = self.digest
        return out


def cdf_norm(z, w):
    """∫ w dz (trapezoid) of a tabulated density."""
    return float(np.sum(0.5 * (w[1:] + w[:-1]) * np.diff(z)))
