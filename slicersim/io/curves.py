"""Reading tabulated instrument curves (ECSV / CSV) and turning them into callables.

File I/O only: no physics here.  Wavelengths are returned in Angstrom.
"""
from __future__ import annotations

import os

import numpy as np

from slicersim.errors import ConfigError

__all__ = ["read_curve", "CurveError"]

_UNIT_TO_AA = {"angstrom": 1.0, "aa": 1.0, "a": 1.0, "nm": 10.0, "nanometer": 10.0,
               "micron": 1e4, "um": 1e4, "µm": 1e4, "micrometer": 1e4, "m": 1e10}


class CurveError(ConfigError):
    """A curve file is missing, unreadable or malformed (a :class:`ConfigError`, hence a
    ``ValueError`` and a :class:`~slicersim.errors.SlicersimError`)."""


def _to_angstrom(values, unit, default_unit):
    unit = (str(unit) if unit is not None else default_unit).strip().lower()
    if unit not in _UNIT_TO_AA:
        raise CurveError(f"unknown wavelength unit {unit!r}")
    return np.asarray(values, dtype=float) * _UNIT_TO_AA[unit]


def read_curve(path, columns=None, wavelength_unit=None):
    """Read a tabulated curve.

    Parameters
    ----------
    path : str
        ECSV (astropy, units read from the header) or CSV/whitespace text file
        with a header line; the first column is the wavelength.
    columns : list of str, optional
        value columns to return (default: every column after the wavelength).
    wavelength_unit : str, optional
        unit of the wavelength column when the file does not say; default
        micron for ECSV and Angstrom for CSV.

    Returns
    -------
    lbda : ndarray  [AA], strictly increasing
    values : dict  column name -> ndarray
    """
    if not os.path.isfile(path):
        raise CurveError(f"curve file not found: {path}")
    try:
        if path.lower().endswith(".ecsv"):
            from astropy.table import Table
            tab = Table.read(path, format="ascii.ecsv")
            names = tab.colnames
            wcol = tab[names[0]]
            unit = wavelength_unit or (str(wcol.unit) if wcol.unit is not None else "micron")
            lbda = _to_angstrom(np.asarray(wcol), unit, "micron")
            data = {n: np.asarray(tab[n], dtype=float) for n in names[1:]}
        else:
            with open(path) as fh:
                first = fh.readline()
            delim = "," if "," in first else None
            raw = np.genfromtxt(path, delimiter=delim, names=True, dtype=float, comments="#")
            names = list(raw.dtype.names)
            lbda = _to_angstrom(raw[names[0]], wavelength_unit, "angstrom")
            data = {n: np.asarray(raw[n], dtype=float) for n in names[1:]}
    except CurveError:
        raise
    except Exception as exc:  # pragma: no cover - message path
        raise CurveError(f"cannot read curve file {path}: {exc}") from exc
    if columns is not None:
        missing = [c for c in columns if c not in data]
        if missing:
            raise CurveError(f"curve file {path} has no column(s) {missing}; it has {list(data)}")
        data = {c: data[c] for c in columns}
    if lbda.size < 2 or np.any(~np.isfinite(lbda)) or np.any(np.diff(lbda) <= 0):
        raise CurveError(f"curve file {path}: wavelengths must be finite and strictly increasing")
    return lbda, data
